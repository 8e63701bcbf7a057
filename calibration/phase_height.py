"""The reference-plane phase-to-height model (paper 000, Eq. 17) from a plate on a stage.

    h = l·Δφ / (Δφ + 2π·d/λ0),   Δφ = φ_reference − φ_object

A flat plate is scanned at known stage heights h_k (h_0 = 0 is the reference plane). Only
l and K = 2π·d/λ0 shape the curve, so they are fitted to every pixel of every height
(linear least squares on h·Δφ = l·Δφ − K·h, then refined on the height error); λ0, the
fringe pitch on the reference plane, is measured from the reference phase over the plane's
metric coordinates (the calibrated camera and the plate's triangulated plane), which
separates d = K·λ0/2π. Eq. 17 assumes one pitch and one geometry for the whole field; with
a tilted projector the pitch varies across it, so l and K are also fitted per pixel (the
per-pixel refinement) where every height was decoded.

Accuracy is judged per height against the stage, beside full triangulation of the same
scans: heights left out of the fit (every other one) measure the model between its
calibration heights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from calibration.errors import CalibrationError, NotEnoughData
from scanner.geometry import PhaseToHeight, Pinhole

FIT_SUBSAMPLE = 4  # every n-th pixel in each direction for the global fit


@dataclass(frozen=True)
class HeightError:
    """RMS height errors (mm) of one plate scan against its stage height."""

    height_mm: float
    held_out: bool
    eq17_mm: float
    per_pixel_mm: float
    triangulation_mm: float
    pixels: int


@dataclass(frozen=True, eq=False)
class PhaseHeightFit:
    """The fitted Eq. 17 model, with its per-pixel refinement, and its accuracy per height."""

    model: PhaseToHeight
    errors: list[HeightError]
    pitch_range_mm: tuple[float, float]  # 5th and 95th percentile of the local fringe pitch on the plate

    def rms(self, held_out: bool) -> tuple[float, float, float]:
        """RMS over the (held-out or fitted) heights: (Eq. 17, per-pixel, triangulation)."""
        sel = [e for e in self.errors if e.held_out == held_out and e.height_mm != 0.0]
        if not sel:
            return (float("nan"),) * 3
        w = np.array([e.pixels for e in sel], dtype=np.float64)

        def pooled(vals: list[float]) -> float:
            return float(np.sqrt(np.sum(w * np.square(vals)) / w.sum()))

        return (pooled([e.eq17_mm for e in sel]), pooled([e.per_pixel_mm for e in sel]),
                pooled([e.triangulation_mm for e in sel]))

    def to_dict(self) -> dict[str, object]:
        m = self.model
        return {"l_mm": m.l_mm, "d_mm": m.d_mm, "pitch_mm": m.pitch_mm, "plane": m.plane.tolist(),
                "plate_distance_mm": float(m.plane[3]), "local_pitch_range_mm": list(self.pitch_range_mm),
                "errors": [e.__dict__ for e in self.errors],
                "rms_held_out_mm": dict(zip(("eq17", "per_pixel", "triangulation"), self.rms(True))),
                "rms_fitted_mm": dict(zip(("eq17", "per_pixel", "triangulation"), self.rms(False)))}

    def lines(self) -> list[str]:
        out = ["height (mm)   Eq.17 RMS   per-pixel RMS   triangulation RMS   pixels"]
        for e in self.errors:
            tag = " (held out)" if e.held_out else ""
            out.append(f"{e.height_mm:9.3f}   {e.eq17_mm * 1e3:8.1f} um   {e.per_pixel_mm * 1e3:10.1f} um   "
                       f"{e.triangulation_mm * 1e3:13.1f} um   {e.pixels:8d}{tag}")
        return out


def reference_pitch_mm(phase: np.ndarray, plane: np.ndarray, camera: Pinhole) -> float:
    """λ0: the fringe pitch on the reference plane, from the phase gradient over the plane's
    metric coordinates (least-squares linear fit of the phase)."""
    rays = camera.ray_grid[::FIT_SUBSAMPLE, ::FIT_SUBSAMPLE].reshape(-1, 3).astype(np.float64)
    phi = phase[::FIT_SUBSAMPLE, ::FIT_SUBSAMPLE].ravel().astype(np.float64)
    ok = np.isfinite(phi)
    n, c = plane[:3], plane[3]
    X = rays[ok] * (-c / (rays[ok] @ n))[:, None]
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    A = np.stack([X @ e1, X @ e2, np.ones(len(X))], axis=1)
    g, *_ = np.linalg.lstsq(A, phi[ok], rcond=None)
    return float(2.0 * np.pi / np.hypot(g[0], g[1]))


def local_pitch_range_mm(phase: np.ndarray, plane: np.ndarray, camera: Pinhole) -> tuple[float, float]:
    """5th and 95th percentile of the local fringe pitch on the plane (mm): one fringe over
    the phase gradient in pixels, times the plane's size of a pixel there (a measure of how
    far the field is from Eq. 17's single pitch)."""
    gy, gx = np.gradient(phase.astype(np.float64))
    rays = camera.ray_grid.astype(np.float64)
    z = -plane[3] / (rays @ plane[:3])
    pitch = 2.0 * np.pi / np.hypot(gx, gy) * z / np.sqrt(camera.K[0, 0] * camera.K[1, 1])
    lo, hi = np.nanpercentile(pitch[::FIT_SUBSAMPLE, ::FIT_SUBSAMPLE], [5, 95])
    return float(lo), float(hi)


def fit_phase_to_height(heights_mm: list[float], phases: list[np.ndarray], plane: np.ndarray, camera: Pinhole,
                        fit_mask: list[bool]) -> PhaseToHeight:
    """Eq. 17 (global) with its per-pixel (l, K) maps from plate phases (H, W, NaN invalid)
    at `heights_mm` (the first is the reference, 0); only heights with `fit_mask` are fitted."""
    if heights_mm[0] != 0.0:
        raise CalibrationError(f"phase-to-height: the first stage height is the reference plane and must be 0, "
                               f"got {heights_mm[0]}")
    used = [k for k in range(1, len(heights_mm)) if fit_mask[k]]
    if len(used) < 2:
        raise NotEnoughData(f"phase-to-height: {len(used)} non-zero stage height(s) to fit, at least 2 are needed")
    ref = phases[0]
    s = FIT_SUBSAMPLE
    dphi = np.concatenate([(ref - phases[k])[::s, ::s].ravel() for k in used]).astype(np.float64)
    h = np.concatenate([np.full(ref[::s, ::s].size, heights_mm[k]) for k in used])
    ok = np.isfinite(dphi)
    dphi, h = dphi[ok], h[ok]
    if len(h) < 100:
        raise NotEnoughData(f"phase-to-height: only {len(h)} decoded plate pixels")
    (l0, k0), *_ = np.linalg.lstsq(np.stack([dphi, -h], axis=1), h * dphi, rcond=None)
    sol = least_squares(lambda p: p[0] * dphi / (dphi + p[1]) - h, [l0, k0], x_scale="jac")
    l_mm, K = (float(v) for v in sol.x)
    pitch = reference_pitch_mm(ref, plane, camera)
    # per pixel: the same linear system, summed over the fitted heights
    a11 = np.zeros(ref.shape)
    a12 = np.zeros(ref.shape)
    a22 = np.zeros(ref.shape)
    b1 = np.zeros(ref.shape)
    b2 = np.zeros(ref.shape)
    count = np.zeros(ref.shape, dtype=np.int32)
    for k in used:
        d = (ref - phases[k]).astype(np.float64)
        good = np.isfinite(d)
        d = np.where(good, d, 0.0)
        hk = np.where(good, heights_mm[k], 0.0)
        a11 += d * d
        a12 -= hk * d
        a22 += hk * hk
        b1 += hk * d * d
        b2 -= hk * hk * d
        count += good
    det = a11 * a22 - a12 * a12
    with np.errstate(divide="ignore", invalid="ignore"):
        l_map = np.where(count == len(used), (a22 * b1 - a12 * b2) / det, np.nan)
        k_map = np.where(count == len(used), (a11 * b2 - a12 * b1) / det, np.nan)
    return PhaseToHeight(l_mm, K * pitch / (2.0 * np.pi), pitch, ref.astype(np.float32), plane,
                         l_map.astype(np.float32), k_map.astype(np.float32))


def evaluate(heights_mm: list[float], fit_mask: list[bool], phases: list[np.ndarray],
             triangulated: list[np.ndarray], model: PhaseToHeight) -> list[HeightError]:
    """RMS height errors per plate scan against the stage heights: Eq. 17, its per-pixel
    refinement, and triangulation (`triangulated` (H, W, 3) camera-frame points per scan),
    all over the pixels where all three have a value."""
    n, c = model.plane[:3], model.plane[3]
    out = []
    for h, fitted, phi, pts in zip(heights_mm, fit_mask, phases, triangulated):
        eq17 = model.height(phi, per_pixel=False)
        pp = model.height(phi)
        tri = pts @ n + c
        ok = np.isfinite(eq17) & np.isfinite(pp) & np.isfinite(tri)
        if not ok.any():
            raise CalibrationError(f"phase-to-height: nothing decoded on the plate at {h} mm")
        eq17_rms, pp_rms, tri_rms = (float(np.sqrt(np.mean((x[ok].astype(np.float64) - h) ** 2)))
                                     for x in (eq17, pp, tri))
        out.append(HeightError(float(h), not fitted, eq17_rms, pp_rms, tri_rms, int(ok.sum())))
    return out


def scan_height_errors(model: PhaseToHeight, camera: Pinhole, depths: dict[str, np.ndarray], true_depth: np.ndarray,
                       region: np.ndarray, top_mm: float) -> tuple[dict[str, tuple[float, float]], int]:
    """How well each method measured a scan, judged over the measuring volume: the pixels of
    `region` whose true height above the reference plane lies within the calibrated heights
    0 .. `top_mm`. `depths`: method -> depth map (H, W, mm along `camera`'s rays, NaN where
    none). Returns method -> (RMS height error (mm), fraction of the volume's pixels it
    measured), and the number of pixels in the volume. A depth error along a ray is a height
    error of that times the ray's height change per mm of depth."""
    rays = camera.ray_grid.astype(np.float64)
    per_mm = rays @ model.plane[:3]
    height = per_mm * true_depth + model.plane[3]
    volume = region & (height >= -0.01 * top_mm) & (height <= top_mm)
    n = int(volume.sum())
    if n == 0:
        raise CalibrationError(f"phase-to-height check: no pixel of the scan lies between the reference plane and "
                               f"{top_mm} mm above it")
    out = {}
    for name, z in depths.items():
        ok = volume & np.isfinite(z)
        err = (per_mm * (z - true_depth))[ok]
        out[name] = (float(np.sqrt(np.mean(err ** 2))) if ok.any() else float("nan"), float(ok.sum() / n))
    return out, n
