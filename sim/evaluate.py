"""Scan accuracy against the simulator's ground truth, and the precision the noise allows.

The bound: per frequency the N-step phase noise is σφ = sqrt(2/N)·σI/B (σI from the
sensor model: shot, read and quantisation noise at the pixel's mean level A). Decoding
combines the frequencies by inverse variance, so the finest-fringe phase has
σφ = sqrt(2/N)·σI / sqrt(Σ (B_i f_i/f_max)²) (`OrientationMaps.phase_weight`); the
projector coordinate has σc = σφ·period/(2π) and the depth σz = σc·|dz/dc| from the
triangulation geometry. The reported bound is the RMS of σz over the evaluated pixels.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from scanner.decode import DecodeResult
from scanner.file_checks import ArraySpec, FileRefused, load_npz
from scanner.pointcloud import OrganisedCloud
from scanner.reconstruct import Triangulator
from scanner.session import write_npz
from sim.render import GroundTruth, SensorModel

GROUND_TRUTH_FILE = "ground_truth.npz"
TRUTH_ARRAYS = {"depth": ArraySpec("f", 2), "object_id": ArraySpec("iu", 2, shape_of="depth"),
                "proj_uv": ArraySpec("f", 3, shape_of="depth")}


@dataclass(frozen=True, eq=False)
class Truth:
    """The part of the ground truth a scan is judged by (camera frame, mm): depth (H, W,
    NaN where nothing), object id (0 nothing, 1 reference plane, 2.. objects) and the
    projector coordinates each pixel sees (H, W, 2, NaN where not lit)."""

    depth: np.ndarray
    object_id: np.ndarray
    proj_uv: np.ndarray

    @property
    def lit(self) -> np.ndarray:
        return np.isfinite(self.proj_uv[..., 0])

    @classmethod
    def of(cls, gt: GroundTruth) -> Truth:
        return cls(gt.depth, gt.object_id, gt.proj_uv)

    def save(self, path: Path) -> None:
        """Write beside a session's raw frames; appears complete or not at all
        (`scanner.session.write_npz`, zlib level 1: the demo's 1280 x 1024 truth in 0.33 s
        and 7.5 MB, against 0.64 s and 8.1 MB at np.savez_compressed's level 6)."""
        write_npz(path, {"depth": self.depth.astype(np.float32), "object_id": self.object_id,
                         "proj_uv": self.proj_uv.astype(np.float32)})

    @classmethod
    def load(cls, path: Path) -> Truth:
        """The truth saved beside a session, checked (`scanner.file_checks.load_npz`: kinds,
        shapes, no header that claims more than the file holds); FileRefused when unusable."""
        z = load_npz(path, TRUTH_ARRAYS, what="simulator ground truth")
        if z["proj_uv"].shape[2] != 2:
            raise FileRefused(path, f"not a usable simulator ground truth: 'proj_uv' is {z['proj_uv'].shape}, "
                                    f"expected (H, W, 2)")
        return cls(z["depth"], z["object_id"], z["proj_uv"])


@dataclass(frozen=True)
class Accuracy:
    """Figures in mm unless named otherwise."""

    pixels: int  # evaluated: valid, on smooth lit surfaces away from edges
    rms_mm: float  # depth error against ground truth
    mean_mm: float  # signed mean depth error (systematic part)
    bound_mm: float  # RMS of the predicted per-pixel depth noise
    ratio: float  # rms / bound
    coverage: float  # valid / (lit, unshadowed, unsaturated) pixels
    order_errors: int  # valid pixels off by half a fringe period or more, on smooth surfaces
    order_errors_all: int  # the same over every valid lit pixel

    def as_dict(self) -> dict[str, float | str | None]:
        """The figures for JSON: an undefined one (no pixel to evaluate) is null, and `note`
        says why."""
        d: dict[str, float | str | None] = {k: (v if np.isfinite(v) else None) for k, v in asdict(self).items()}
        if any(v is None for v in d.values()):
            d["note"] = (f"null: undefined over {self.pixels} evaluated pixels (no valid pixel on a smooth lit "
                         f"surface, or no noise bound)")
        return d

    def summary(self) -> str:
        return (f"depth error RMS {self.rms_mm * 1e3:.1f} um (noise bound {self.bound_mm * 1e3:.1f} um, ratio "
                f"{self.ratio:.2f}), mean {self.mean_mm * 1e3:+.2f} um over {self.pixels} px; coverage "
                f"{self.coverage * 100:.2f} %; fringe-order errors {self.order_errors} (smooth) / "
                f"{self.order_errors_all} (all)")


def smooth_region(gt: Truth, margin_px: int = 3, max_step_mm: float = 0.5) -> np.ndarray:
    """Lit pixels at least `margin_px` from object boundaries, shadows and depth steps."""
    depth = np.nan_to_num(gt.depth, nan=0.0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    step = cv2.dilate(depth, kernel) - cv2.erode(depth, kernel) > max_step_mm
    ids = gt.object_id.astype(np.float32)
    boundary = cv2.dilate(ids, kernel) != cv2.erode(ids, kernel)
    bad = (step | boundary | ~gt.lit).astype(np.uint8)
    bad = cv2.dilate(bad, np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)) > 0
    return gt.lit & ~bad


def depth_noise_bound(decoded: DecodeResult, triangulator: Triangulator, sensor: SensorModel) -> np.ndarray:
    """Predicted depth noise σz (mm) per pixel for a single-orientation decode (NaN invalid)."""
    (orientation, m), = decoded.maps.items()
    n = decoded.patterns.steps
    sigma_i = sensor.noise_sigma_dn(m.background, decoded.bit_depth)
    sigma_phi = np.sqrt(2.0 / n) * sigma_i / np.sqrt(np.maximum(m.phase_weight, 1e-12))
    sigma_c = sigma_phi * m.period_px / (2.0 * np.pi)
    _, dz_dc = triangulator.depth_scale(m.coordinate, orientation, sensitivity=True)
    return sigma_c * dz_dc


def evaluate(decoded: DecodeResult, cloud: OrganisedCloud, gt: Truth, sensor: SensorModel,
             triangulator: Triangulator) -> Accuracy:
    """Compare a scan of the simulated scene with its ground truth."""
    valid = cloud.valid
    saturated = np.logical_or.reduce([m.masks["saturated"] for m in decoded.maps.values()])
    eligible = gt.lit & ~saturated
    smooth = smooth_region(gt) & ~saturated & valid
    err = cloud.points[..., 2] - gt.depth
    e = err[smooth].astype(np.float64)
    bound = depth_noise_bound(decoded, triangulator, sensor)[smooth].astype(np.float64)
    rms = float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")
    bound_rms = float(np.sqrt(np.mean(bound ** 2))) if bound.size else float("nan")
    order_all = 0
    order_smooth = 0
    for o, m in decoded.maps.items():
        truth = gt.proj_uv[..., 0 if o == "vertical" else 1]
        off = np.abs(m.coordinate - truth) >= m.period_px / 2.0
        order_all += int((off & valid & gt.lit).sum())
        order_smooth += int((off & smooth).sum())
    return Accuracy(pixels=int(smooth.sum()), rms_mm=rms, mean_mm=float(np.mean(e)) if e.size else float("nan"),
                    bound_mm=bound_rms, ratio=rms / bound_rms if bound_rms > 0 else float("nan"),
                    coverage=float((valid & eligible).sum() / max(eligible.sum(), 1)),
                    order_errors=order_smooth, order_errors_all=order_all)
