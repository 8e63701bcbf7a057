"""How far whole faces of a scan read off their CAD surface at the true pose, against the
model the registration's pose covariance rests on (`evidence._face_offsets`): a face's offset
grows with its points' mean share of light that the camera's blur brings from beyond the
face's outline (`fine.mixing`), tau_f^2 = (kappa x share_f)^2 + floor^2, the floor a few um
that every face may read off.

On the scans of a registration campaign (`python -m studies.registration_bench scan OUT`),
with the simulator's own face labels and pose (the truth, not the registration's):

    python -m studies.face_offsets OUT [--blur-px 0.6] [--json]

prints, per eighth of the faces' shares, how many faces and their RMS mean residual, the kappa
that eighth alone gives (by moments, the noise's share removed); kappa and the floor pooled over
all faces (the Gaussian likelihood of the faces' means); the faces'
mean residuals as z scores against tau_f and the noise: their RMS per eighth (1 if the model's
form holds across the shares; pooled, the likelihood makes it 1) and the fractions beyond 1.96
and 3 of all (5 % and 0.3 % if the offsets are Gaussian); and
per distance of a pixel from its outline (0, 1, 2-3, 4+ px) the median and 90th percentile of
|mean residual| over (face, distance) groups of 10 points or more; and per kind of face (outline
pixels only; the others by share) the RMS of the faces' mean residuals beside the RMS of their
linear trend across the image (`band_effects`). `--blur-px` is the camera
blur assumed in the shares (the bench renders 0.6 px; the registration assumes 1.0 px unless
told): the pooled kappa and the z scores say how either assumption fits.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from inspection.registration.band_effects import image_spread

MIN_POINTS = 10  # points of a face (or of a face's distance class) for its mean to count
INNER_PX = 4  # pixels this far from every outline carry no light from beyond (Phi(-4.5/0.6) ~ 1e-14)
DISTANCES = ((0, 0), (1, 1), (2, 3), (INNER_PX, 10**9))  # px from the nearest outline pixel, inclusive


@dataclass(frozen=True)
class FaceOffset:
    """One face of one scan at the true pose: its points' mean residual (mm), the noise's
    standard error of that mean (mm) and their mean share of light from beyond the outline."""

    scan: str
    face: int
    points: int
    mean_mm: float
    noise_se_mm: float
    share: float
    trend_rms_mm: float = 0.0  # RMS over the face's points of its residuals' linear trend across the image
    outline_only: bool = False  # every point on the outline (0 px from it)


@dataclass(frozen=True)
class Octile:
    """The faces whose share falls in [low, high]: their RMS mean residual, the kappa (mm per
    unit share) they alone give and their z scores' RMS against the pooled model."""

    low: float
    high: float
    faces: int
    rms_mm: float
    kappa_mm: float
    z_rms: float


@dataclass(frozen=True)
class Findings:
    scans: int
    faces: int
    blur_px: float
    octiles: list[Octile]
    kappa_mm: float
    floor_mm: float
    beyond_1_96: float
    beyond_3: float
    by_distance: dict[str, tuple[int, float, float]]  # "0", "1", "2-3", "4+": groups, median, p90 |mean| (mm)
    trends: dict[str, tuple[int, float, float]]  # by kind of face: faces, RMS mean, RMS trend (mm)


def scan_faces(npz: Path, step: str, scale: float, *, blur_px: float,
               groups: dict[str, list[float]]) -> list[FaceOffset]:
    """The faces of one saved scan at its true pose; appends the (face, distance) groups'
    |mean residual| (mm) to `groups`."""
    import cv2

    from inspection.cad import load_cad
    from inspection.measured_cloud import ScanCloud
    from inspection.registration.fine import ASSIGN_VOXELS, mixing, off_outline
    from inspection.registration.settings import RegistrationSettings, TargetSettings
    from inspection.segmentation import project_to_faces

    d = np.load(npz)
    model = load_cad(step, scale=scale)
    T = d["truth"]
    points = d["points"].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    normals = d["normals"].astype(np.float64) @ T[:3, :3].T
    pixels, shape = d["pixels"].astype(np.int64), tuple(int(x) for x in d["shape"])
    scan = ScanCloud(points, normals, npz.stem, np.zeros(3), pixels, shape)  # the model's frame
    face = d["face"].astype(np.int64)
    surface = off_outline(scan, RegistrationSettings.max_incidence_deg, face=face)
    assert surface is not None
    share = mixing(scan, surface, blur_px=blur_px)
    distance = cv2.distanceTransform(surface.astype(np.uint8), cv2.DIST_L2, 5)[pixels[:, 1], pixels[:, 0]]
    px = np.rint(distance).astype(np.int64)
    on = face >= 0
    r = np.full(len(scan), np.nan)
    r[on] = project_to_faces(model, points[on], face[on])[3]
    bound = ASSIGN_VOXELS * model.diagonal_mm / TargetSettings().voxel_fraction  # the fit's assignment bound
    ok = on & (np.abs(r) < bound)
    inner = ok & (px >= INNER_PX)
    noise = 1.4826 * float(np.median(np.abs(r[inner] - np.median(r[inner]))))
    _, f = np.unique(np.where(ok, face, -1), return_inverse=True)
    n = np.bincount(f, weights=ok)
    mean = np.bincount(f, weights=np.where(ok, r, 0.0)) / np.maximum(n, 1)
    mean_share = np.bincount(f, weights=np.where(ok, share, 0.0)) / np.maximum(n, 1)
    ids = np.bincount(f, weights=np.where(ok, face, 0)) / np.maximum(n, 1)
    for label, (lo, hi) in zip(("0", "1", "2-3", "4+"), DISTANCES, strict=True):
        m = ok & (px >= lo) & (px <= hi)
        k = np.bincount(f, weights=m)
        s = np.bincount(f, weights=np.where(m, r, 0.0))
        groups[label].extend(np.abs(s[k >= MIN_POINTS] / k[k >= MIN_POINTS]).tolist())
    trend = _trend_rms(pixels.astype(np.float64), r, f, ok)
    only = np.bincount(f, weights=ok & (px == 0)) == n
    keep = n >= MIN_POINTS
    return [FaceOffset(npz.stem, round(i), int(c), float(a), noise / np.sqrt(c), float(s), float(t), bool(o))
            for i, c, a, s, t, o in zip(ids[keep], n[keep], mean[keep], mean_share[keep], trend[keep], only[keep],
                                        strict=True)]


def _trend_rms(where: np.ndarray, r: np.ndarray, f: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Per face (`f`, the points `ok`), the RMS over its points of the least-squares linear
    trend of its residuals `r` across its image positions `where` (mm): the part of a face's
    offset that tilts it (`band_effects`)."""
    weight = ok.astype(np.float64)
    d, second = image_spread(where, f, weight)
    g = len(second)
    n = np.maximum(np.bincount(f, weights=weight, minlength=g), 1.0)
    dr = np.stack([np.bincount(f, weights=weight * d[:, a] * r, minlength=g) for a in (0, 1)], 1) / n[:, None]
    slope = np.einsum("fab,fb->fa", np.linalg.pinv(second), dr)  # (faces, 2): mm per px
    return np.sqrt(np.bincount(f, weights=np.einsum("na,na->n", d, slope[f]) ** 2, minlength=g) / n)


def _likeliest(mean: np.ndarray, se: np.ndarray, share: np.ndarray) -> tuple[float, float]:
    """kappa^2 and floor^2 (mm^2) of the Gaussian likelihood of the faces' means, mean_f ~
    N(0, (kappa share_f)^2 + floor^2 + se_f^2), from the moments' fit (least squares of the
    excess squares on share^2 and 1, which many faces near the floor's size leave rough)."""
    from scipy.optimize import minimize, nnls

    start, _ = nnls(np.stack([share**2, np.ones_like(share)], axis=1), mean**2 - se**2)
    scale = np.maximum(start, 1e-12 + 1e-3 * float(np.mean(mean**2)))  # a zero start is no scale

    def minus_log_likelihood(x: np.ndarray) -> float:
        v = scale[0] * np.exp(x[0]) * share**2 + scale[1] * np.exp(x[1]) + se**2
        return float(np.sum(np.log(v) + mean**2 / v))

    x = minimize(minus_log_likelihood, np.zeros(2), method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-6}).x
    return float(scale[0] * np.exp(x[0])), float(scale[1] * np.exp(x[1]))


def findings(faces: list[FaceOffset], groups: dict[str, list[float]], *, blur_px: float) -> Findings:
    """The tables of the module docstring from every scan's faces."""
    share = np.array([f.share for f in faces])
    mean = np.array([f.mean_mm for f in faces])
    se = np.array([f.noise_se_mm for f in faces])
    excess = mean**2 - se**2  # E[mean^2] = (kappa share)^2 + se^2 under the model
    kappa2, floor2 = _likeliest(mean, se, share)
    z = mean / np.sqrt(kappa2 * share**2 + floor2 + se**2)
    octiles = []
    for s in np.array_split(np.argsort(share, kind="stable"), 8):  # by rank: many faces share the outline's share
        kappa = np.sqrt(max(float(excess[s].mean()), 0.0) / max(float(np.mean(share[s] ** 2)), 1e-300))
        rms, z_rms = float(np.sqrt(np.mean(mean[s] ** 2))), float(np.sqrt(np.mean(z[s] ** 2)))
        octiles.append(Octile(float(share[s].min()), float(share[s].max()), len(s), rms, float(kappa), z_rms))
    by_distance = {k: (len(v), float(np.median(v)), float(np.quantile(v, 0.9))) for k, v in groups.items() if v}
    only = np.array([f.outline_only for f in faces])
    trend = np.array([f.trend_rms_mm for f in faces])
    kinds = {"outline pixels only": only, "others, share > 0.05": ~only & (share > 0.05),
             "others, share <= 0.05": ~only & (share <= 0.05)}
    trends = {k: (int(m.sum()), float(np.sqrt(np.mean(mean[m] ** 2))), float(np.sqrt(np.mean(trend[m] ** 2))))
              for k, m in kinds.items() if m.any()}
    return Findings(len({f.scan for f in faces}), len(faces), blur_px, octiles, float(np.sqrt(kappa2)),
                    float(np.sqrt(floor2)), float(np.mean(np.abs(z) > 1.96)), float(np.mean(np.abs(z) > 3.0)),
                    by_distance, trends)


def study(out: Path, *, blur_px: float) -> Findings:
    """Every saved scan of the campaign `out` (its cases.json and one npz per scan)."""
    cases = json.loads((out / "cases.json").read_text())
    faces: list[FaceOffset] = []
    groups: dict[str, list[float]] = {"0": [], "1": [], "2-3": [], "4+": []}
    for c in cases:
        npz = out / f"{c['name']}.npz"
        if npz.exists():
            faces += scan_faces(npz, c["step"], c["scale"], blur_px=blur_px, groups=groups)
            print(f"{c['name']}: {len(faces)} faces so far", file=sys.stderr, flush=True)
    if not faces:
        raise SystemExit(f"{out}: no saved scans (run `python -m studies.registration_bench scan {out}` first)")
    return findings(faces, groups, blur_px=blur_px)


def table(f: Findings) -> str:
    lines = [f"{f.faces} faces of {f.scans} scans at the true pose, shares for a blur of {f.blur_px} px",
             "share from  to       faces  RMS mean um  kappa um/share  z RMS"]
    lines += [f"{o.low:9.4f} {o.high:8.4f} {o.faces:6d} {o.rms_mm * 1e3:12.1f} {o.kappa_mm * 1e3:15.1f} {o.z_rms:6.2f}"
              for o in f.octiles]
    lines.append(f"pooled: kappa {f.kappa_mm * 1e3:.0f} um per unit share, floor {f.floor_mm * 1e3:.1f} um; z against "
                 "tau^2 = (kappa x share)^2 + floor^2 with the noise: "
                 f"{100 * f.beyond_1_96:.1f} % beyond 1.96, {100 * f.beyond_3:.1f} % beyond 3")
    lines.append("px from the outline  groups  median |mean| um  90 % um")
    lines += [f"{k:>19} {n:7d} {m * 1e3:17.1f} {p * 1e3:8.1f}" for k, (n, m, p) in f.by_distance.items()]
    lines.append("kind of face            faces  RMS mean um  RMS trend um  trend / mean")
    lines += [f"{k:22} {n:6d} {m * 1e3:12.1f} {t * 1e3:13.1f} {t / max(m, 1e-12):13.2f}"
              for k, (n, m, t) in f.trends.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.face_offsets", description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path, help="a campaign folder of `python -m studies.registration_bench scan`")
    p.add_argument("--blur-px", type=float, default=0.6,
                   help="camera blur sigma for the shares (px; the bench's is 0.6)")
    p.add_argument("--json", action="store_true", help="the findings as JSON on stdout")
    a = p.parse_args(argv)
    f = study(a.out, blur_px=a.blur_px)
    print(json.dumps(asdict(f)) if a.json else table(f))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
