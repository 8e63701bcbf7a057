"""Binocular structured light: two cameras decode the same projected fringes, and a point is
where their absolute projector coordinates agree on an epipolar line.

The projector is only a source of texture here: its lens distortion, gamma and pose never
enter the geometry, which is the two cameras' calibration alone (`StereoModel`).

Method, per scan (millimetres, pixels; OpenCV frames):

1. Rectification (`Rectification`): rotations R_l, R_r (OpenCV's `stereoRectify`) turn both
   cameras so the baseline runs along x; one rectified pinhole (focal f, no distortion) for
   both. Left pixels are not resampled: each keeps its decoded coordinate exactly and gets its
   rectified position (x_l, y_l). The right camera's maps are resampled onto a rectified grid
   by exact bilinear interpolation in float32 (not `cv2.remap`, whose 1/32 px position
   quantisation would add ~0.01 projector px of error), NaN wherever a neighbour is invalid.
2. Matching (`match`): on a rectified right row, consecutive valid samples (x, x+1) span an
   interval of projector coordinate [c(x), c(x+1)). A row's intervals form monotone runs (`_Runs`),
   each of which holds a coordinate in at most one interval; the runs of every row are put on one
   number line (row·span + c), and for each left pixel two `searchsorted` calls count the runs,
   hence the intervals, of a row holding its coordinate. The match is kept only when exactly one
   interval holds it on both rows around y_l (the sub-pixel x on each by linear interpolation
   within the interval, then linearly between the rows: iso-coordinate lines are straight to
   first order), and when each interval's step |c(x+1) − c(x)| exceeds z·σ_step, σ_step the
   step's noise from the decoder's per-pixel coordinate noise, z = Φ⁻¹(1 − α/2) with
   α = GRADIENT_FALSE_ACCEPT: a pair of samples carrying no change of coordinate along the line
   (fringes parallel to it) passes with probability α.
3. With both fringe orientations decoded in both cameras, the orientation whose coordinate
   changes faster along the rectified rows matches; the other checks: at the match the two
   cameras must read the same coordinate within z·sqrt(σ_l² + σ_r² + (g_y·σ_epi)²) (z for
   CHECK_FALSE_REFUSE two-sided, g_y the other coordinate's change across rows, σ_epi the
   calibration's stated epipolar error in px). The offsets it measures, as rectified rows
   (`epipolar_offset_px`), are the scan's check of the stereo calibration.
4. Triangulation: the disparity d = x_l − x_r gives the rectified depth Z = −f·T_x/d
   (T_x: the right camera's x in the rectified frame) and the point on the left pixel's own
   ray; depth noise σ_z from σ_d² = (σ_cl² + σ_cr²)/g_x² (g_x: the right coordinate's change
   per rectified px at the match), σ_Z = Z²/(f·|T_x|)·σ_d.
5. The calibration's term (`calibration_jacobian`): the stereo calibration's error moves every
   point of a scan together (one error for the whole scan, and for every scan made with that
   calibration), so it is kept apart from the noise σ_Z, never in it: a figure averaging many
   points averages noise away, not this. A point satisfies π_l(X; θ) = its left pixel and
   n·π_r(X; θ) = n·(its match), n the normal, in the right camera's pixels, of the line along
   which the right camera reads the matched coordinate (a calibration moved by δθ moves the
   epipolar line, and the match slides along that line: in the rectified frame its slope is the
   difference of the matches on the two rows around the left pixel, `BinocularResult.iso_slope`).
   Implicit differentiation with OpenCV's analytic projection derivatives gives ∂X/∂θ = −A⁻¹B
   per point over the 24 parameters of `StereoModel.covariance`; a model stating no covariance
   (another tool's file, a rig file's nominal geometry) has the term "not included", said so.

The cloud is organised on the left camera's pixels, in the left camera's frame (mm).
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache
from typing import Any

import cv2
import numpy as np

from scanner.decode import DecodeResult
from scanner.decode_checks import normal_isf
from scanner.errors import ConfigError, DecodeError
from scanner.geometry import Pinhole, perturbed_pose
from scanner.pointcloud import OrganisedCloud
from scanner.reconstruct import cloud_from_depth, to_texture8

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")  # px, then OpenCV's distortion (unitless)
EXTRINSIC_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")  # right_from_left: Rodrigues vector (rad), translation (mm)
N_PARAMETERS = 2 * len(INTRINSIC_NAMES) + len(EXTRINSIC_NAMES)
GRADIENT_FALSE_ACCEPT = 1e-3  # α of the gradient gate: a sample pair with no change along the line passes this often
CHECK_FALSE_REFUSE = 1e-4  # of the second orientation's check: a true match is refused this often (Gaussian noise)
JACOBIAN_CHUNK = 100_000  # points per batch of calibration_jacobian (~1.6 KB each while it runs)
CALIBRATION_GRID_PX = 8  # binocular.json's calibration figures: the points of every 8th left pixel each way


def parameter_names(cameras: tuple[str, str]) -> list[str]:
    """The rows of a stereo covariance: each camera's intrinsics by its name ('left.fx', ...), then
    'extrinsic.rx', ... 'extrinsic.tz'."""
    return [f"{c}.{n}" for c in cameras for n in INTRINSIC_NAMES] + [f"extrinsic.{n}" for n in EXTRINSIC_NAMES]


@dataclass(frozen=True, eq=False)
class StereoModel:
    """Two calibrated cameras. `right_from_left` (4x4, mm) maps left-camera points into the
    right camera's frame (OpenCV stereoCalibrate's R, T). `names` are the cameras' names
    (session folders, Rerun). `epipolar_sigma_px`: the calibration's RMS distance (px) of a
    true correspondence from its epipolar line, where the calibration states it (0: none
    stated, the check then allows the phase noise only). `calibration` names the file.
    `covariance` (24, 24): the calibration's covariance of its parameters (`parameter_names`:
    each camera's intrinsics in px and distortion, then right_from_left as a Rodrigues vector
    (rad) and a translation (mm), as `calibration.stereo_cameras` solves them); None where the
    calibration states none (another tool's file, a rig file's nominal geometry): the points'
    calibration term is then not included (module docstring, 5.)."""

    left: Pinhole
    right: Pinhole
    right_from_left: np.ndarray
    names: tuple[str, str] = ("left", "right")
    epipolar_sigma_px: float = 0.0
    calibration: str = ""
    covariance: np.ndarray | None = None

    def __post_init__(self) -> None:
        T = np.asarray(self.right_from_left, dtype=np.float64).reshape(4, 4)
        object.__setattr__(self, "right_from_left", T)
        if not (np.isfinite(T).all() and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
                and np.linalg.det(T[:3, :3]) > 0 and np.allclose(T[3], [0, 0, 0, 1])):
            raise ValueError("right_from_left is not a rigid transform")
        if not np.linalg.norm(T[:3, 3]) > 0:
            raise ValueError("the two cameras sit at one point: no baseline")
        if self.covariance is not None:
            C = np.asarray(self.covariance, dtype=np.float64)
            if C.shape != (N_PARAMETERS, N_PARAMETERS) or not np.isfinite(C).all():
                raise ValueError(f"the covariance is not a finite {N_PARAMETERS} x {N_PARAMETERS} matrix")
            sd = np.sqrt(np.maximum(np.diag(C), 0.0))
            if np.any(np.abs(C - C.T) > 1e-6 * np.outer(sd, sd)) or np.any(np.diag(C) < 0):
                raise ValueError("the covariance is not symmetric with a non-negative diagonal")
            object.__setattr__(self, "covariance", (C + C.T) / 2)  # a solve's B·M·B is symmetric to rounding

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.right_from_left[:3, 3]))

    def parameter_names(self) -> list[str]:
        return parameter_names(self.names)

    def perturbed(self, delta: np.ndarray) -> StereoModel:
        """The model with its parameters moved by `delta` (24,) (order of `parameter_names`; the
        rotation's Rodrigues vector moved additively, as the calibration solves it), no covariance."""
        k = len(INTRINSIC_NAMES)
        return replace(self, left=self.left.perturbed(delta[:k]), right=self.right.perturbed(delta[k:2 * k]),
                       right_from_left=perturbed_pose(self.right_from_left, delta[2 * k:]), covariance=None)

    def to_dict(self) -> dict[str, Any]:
        """The model as manifests hold it; "covariance" only where the calibration states one."""
        out = {"names": list(self.names), "left": self.left.to_dict(), "right": self.right.to_dict(),
               "right_from_left": self.right_from_left.tolist(), "epipolar_sigma_px": self.epipolar_sigma_px,
               "calibration": self.calibration}
        if self.covariance is not None:
            out["covariance"] = {"parameters": self.parameter_names(), "matrix": self.covariance.tolist()}
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "stereo model") -> StereoModel:
        try:
            names = tuple(d.get("names", ("left", "right")))
            cov = d.get("covariance")
            if cov is not None:
                expected = parameter_names(names)
                if list(cov["parameters"]) != expected:
                    raise ValueError(f"covariance parameters {list(cov['parameters'])}, expected {expected}")
                cov = np.array(cov["matrix"], float)
            return cls(Pinhole.from_dict(d["left"], f"{where}: left"), Pinhole.from_dict(d["right"], f"{where}: right"),
                       np.array(d["right_from_left"], float), names, float(d.get("epipolar_sigma_px", 0.0)),
                       str(d.get("calibration", "")), cov)
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(where, None, f"invalid stereo model: {exc!r}") from None


@dataclass(frozen=True, eq=False)
class RectifiedGrid:
    """One camera's maps resampled on the rectified frame: grid pixel (i, j) is the rectified
    position (x0 + i, y0 + j); `source` (Hg, Wg, 2) float32 the original pixel it samples."""

    x0: int
    y0: int
    source: np.ndarray

    @classmethod
    def covering(cls, camera: Pinhole, R: np.ndarray, f: float) -> RectifiedGrid:
        """The grid covering `camera`'s image rotated by R into the rectified frame (focal f)."""
        edge = np.concatenate([np.stack([np.linspace(0, camera.width - 1, 64), np.full(64, y)], 1)
                               for y in (0, camera.height - 1)]
                              + [np.stack([np.full(64, x), np.linspace(0, camera.height - 1, 64)], 1)
                                 for x in (0, camera.width - 1)])
        n = np.column_stack([camera.normalized(edge), np.ones(len(edge))]) @ R.T
        xy = f * n[:, :2] / n[:, 2:3]
        x0, y0 = (int(np.floor(v)) - 1 for v in xy.min(axis=0))
        x1, y1 = (int(np.ceil(v)) + 1 for v in xy.max(axis=0))
        P = np.array([[f, 0.0, -x0], [0.0, f, -y0], [0.0, 0.0, 1.0]])
        mx, my = cv2.initUndistortRectifyMap(camera.K, camera.dist, R, P, (x1 - x0 + 1, y1 - y0 + 1), cv2.CV_32FC1)
        return cls(x0, y0, np.stack([mx, my], axis=-1), (camera.height, camera.width))

    camera_shape: tuple[int, int]

    @property
    def shape(self) -> tuple[int, int]:
        return self.source.shape[:2]

    @cached_property
    def taps(self) -> Taps:
        return Taps.at(self.source[..., 0], self.source[..., 1], self.camera_shape)

    def resample(self, image: np.ndarray) -> np.ndarray:
        """A map of this camera (H, W) on the grid (Hg, Wg), float32, NaN outside the image or
        where any of the four neighbours is NaN."""
        if image.shape != self.camera_shape:
            raise DecodeError(f"a {image.shape[1]} x {image.shape[0]} px map for a {self.camera_shape[1]} x "
                              f"{self.camera_shape[0]} px camera")
        return self.taps(image).reshape(self.shape)


@dataclass(frozen=True, eq=False)
class Rectification:
    """The rectified pair: `R_left`, `R_right` rotate each camera's frame into its rectified
    frame; both rectified cameras have focal `f` px and principal point (0, 0); the right one
    sits at x = `tx_mm` of the left's rectified frame (negative: to the left's right).
    `left_xy` (2, H, W) float64 is every left pixel's rectified position (x plane, y plane), `left_w` (H, W) the
    z of its ray (x/z, y/z, 1) rotated into the rectified frame; `right` is the grid the right
    camera's maps are matched on, `left` the grid the left's are (only) counted on."""

    model: StereoModel
    R_left: np.ndarray
    R_right: np.ndarray
    f: float
    tx_mm: float
    left_xy: np.ndarray
    left_w: np.ndarray
    left: RectifiedGrid
    right: RectifiedGrid

    @classmethod
    def of(cls, model: StereoModel) -> Rectification:
        R1, R2, f, tx = _rectifying(model)
        L = model.left
        rays = L.ray_grid.astype(np.float64) @ R1.T
        w = rays[..., 2]
        return cls(model, R1, R2, f, tx, np.ascontiguousarray(np.moveaxis(f * rays[..., :2] / w[..., None], -1, 0)),
                   w, RectifiedGrid.covering(L, R1, f), RectifiedGrid.covering(model.right, R2, f))

    @cached_property
    def left_ray_planes(self) -> tuple[np.ndarray, np.ndarray]:
        """The left camera's rays (x/z, y/z) as two contiguous (H, W) planes, for `cloud_from_depth`."""
        rays = self.model.left.ray_grid
        return np.ascontiguousarray(rays[..., 0]), np.ascontiguousarray(rays[..., 1])


def _rectifying(model: StereoModel) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The rectification's rotations R_left, R_right, its focal f (px) and tx_mm (`Rectification`)."""
    R, T = model.right_from_left[:3, :3], model.right_from_left[:3, 3]
    L, Rc = model.left, model.right
    R1, R2, *_ = cv2.stereoRectify(L.K, L.dist, Rc.K, Rc.dist, L.size, R, T.reshape(3, 1), flags=0, alpha=-1)
    t = R2 @ T
    if abs(t[0]) < abs(t[1]):
        raise DecodeError(f"the cameras are stacked vertically (baseline {T.round(1).tolist()} mm): binocular "
                          f"matching takes cameras side by side")
    return R1, R2, float(np.mean([L.K[0, 0], L.K[1, 1], Rc.K[0, 0], Rc.K[1, 1]])), float(t[0])


@dataclass(frozen=True, eq=False)
class Taps:
    """Bilinear taps of sample positions in an image of `width` px: the flat index of each
    position's top-left neighbour, its fractional offsets, and whether it lies inside."""

    index: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    inside: np.ndarray
    width: int

    @classmethod
    def at(cls, x: np.ndarray, y: np.ndarray, shape: tuple[int, int]) -> Taps:
        h, w = shape
        x = np.asarray(x, np.float32)
        y = np.asarray(y, np.float32)
        inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
        xi = np.clip(np.floor(np.where(inside, x, 0)), 0, max(w - 2, 0)).astype(np.intp)
        yi = np.clip(np.floor(np.where(inside, y, 0)), 0, max(h - 2, 0)).astype(np.intp)
        return cls(yi * w + xi, np.where(inside, x - xi, 0).astype(np.float32),
                   np.where(inside, y - yi, 0).astype(np.float32), inside, w)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """`image` sampled at the positions (float32; NaN outside or where a neighbour is NaN)."""
        flat = np.asarray(image, np.float32).ravel()
        i, w, fx = self.index, self.width, self.fx
        # the neighbours by taking at offset views (no index arithmetic), the arithmetic in place:
        # top + (bottom - top)·fy, top = a + (b - a)·fx, bottom = c + (d - c)·fx, as written
        out, b, c, d = flat.take(i), flat[1:].take(i), flat[w:].take(i), flat[w + 1:].take(i)
        b -= out
        b *= fx
        out += b
        d -= c
        d *= fx
        c += d
        c -= out
        c *= self.fy
        out += c
        out[~self.inside] = np.nan
        return out


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """`image` (H, W) sampled at (x, y) (pixel centres at integers) by bilinear
    interpolation in float32 with exact weights; NaN outside or where a neighbour is NaN."""
    return Taps.at(x, y, image.shape)(image)


@dataclass(frozen=True, eq=False)
class CameraPhase:
    """One camera's decoded projector coordinates per orientation (H, W) with their predicted
    one-sigma noise (projector px), NaN where invalid, and its texture (DN) and bit depth."""

    coordinate: dict[str, np.ndarray]
    sigma: dict[str, np.ndarray]
    texture: np.ndarray
    bit_depth: int

    @classmethod
    def of(cls, decoded: DecodeResult) -> CameraPhase:
        coords = {o: np.where(m.valid, m.coordinate, np.float32(np.nan)) for o, m in decoded.maps.items()}
        return cls(coords, {o: m.coordinate_sigma for o, m in decoded.maps.items()}, decoded.texture,
                   decoded.bit_depth)


@dataclass(eq=False)
class BinocularResult:
    """A binocular reconstruction. `cloud` is organised on the left camera's pixels, in its
    frame (mm); `depth_sigma_mm` (H, W) the predicted one-sigma noise of each point's depth;
    `model` the stereo model it was made with (`right_pixels`: where the right camera saw each point);
    `masks` why left pixels with a coordinate got no point (first reason counts); `checks`
    the scan's figures (counts; the second orientation's epipolar offsets, px); `iso_slope`
    (H, W) the slope dx/dy, in the rectified frame, of the line along which the right camera
    reads each point's matched coordinate (NaN without a point), for the calibration term.

    `depth_sigma_mm` is noise, independent from point to point. The stereo calibration's
    error is not in it: it is one error common to every point of the scan (module docstring,
    5.), given apart by `calibration_jacobian` (∂X/∂θ per point) and `calibration_depth_sigma_mm`
    (its one-sigma per point), with `calibration_term` saying whether it is included. A figure
    linear in the points (∂x/∂X_i = g_i) gets u_cal² = gᵀ·J·Σ·Jᵀ·g, J stacking every point's
    ∂X/∂θ: the points move together, so their g_i·J_i add before the covariance, never in
    quadrature point by point. That is `inspection.uncertainty`'s rule for a monocular rig
    (u_cal² = Σ_d (Σ_i g_i·J_i·δ_d)², δ_d the covariance's principal directions; the 24
    parameters in the same order, the right camera in the projector's place), and the U it
    belongs in is `slscan verify`'s on a binocular rig (slscan/commands/verify_binocular.py),
    whose ScanUncertainty must take this J in place of the monocular `calibration_jacobian`;
    until it does, that U leaves the term out and says so. outputs/binocular.json states it per
    scan (`calibration_figures`)."""

    cloud: OrganisedCloud
    depth_sigma_mm: np.ndarray
    model: StereoModel
    orientation: str
    iso_slope: np.ndarray
    masks: dict[str, np.ndarray]
    checks: dict[str, float] = field(default_factory=dict)

    @property
    def calibration_term(self) -> str:
        """Where the points' calibration term comes from, or "not included" and why."""
        if self.model.covariance is None:
            return ("not included: the stereo calibration states no covariance (another tool's file or the rig "
                    "file's nominal geometry)")
        return f"the stereo calibration's covariance ({self.model.calibration or 'stated with the model'})"

    def calibration_jacobian(self, idx: np.ndarray) -> np.ndarray:
        """∂X/∂θ (N, 3, 24), mm per unit of each parameter of `model.covariance`, of the points
        at left pixels `idx` (flat indices with a point, as `cloud.valid_indices()`)."""
        return calibration_jacobian(self.model, self.cloud.points.reshape(-1, 3)[idx].astype(np.float64),
                                    self.iso_slope.ravel()[idx])

    def calibration_depth_sigma_mm(self, idx: np.ndarray) -> np.ndarray | None:
        """The calibration's one-sigma (mm) of the depth z of each point at left pixels `idx`
        (the same error in every point of the scan: not noise); None when not included."""
        C = self.model.covariance
        if C is None:
            return None
        out = np.empty(len(idx))
        for part in np.array_split(np.arange(len(idx)), max(1, -(-len(idx) // JACOBIAN_CHUNK))):
            jz = self.calibration_jacobian(idx[part])[:, 2]
            out[part] = np.sqrt(np.maximum(np.einsum("np,pq,nq->n", jz, C, jz), 0.0))
        return out

    def calibration_figures(self, *, grid_px: int = CALIBRATION_GRID_PX) -> dict[str, Any]:
        """The calibration term as binocular.json states it: on the points of a grid of every
        `grid_px`-th left pixel, the median and largest one-sigma of the depth (mm)."""
        if self.model.covariance is None:
            return {"included": False, "term": self.calibration_term}
        h, w = self.iso_slope.shape
        grid = np.zeros((h, w), bool)
        grid[grid_px // 2::grid_px, grid_px // 2::grid_px] = True
        idx = np.flatnonzero(grid.ravel() & self.cloud.valid.ravel())
        sigma = self.calibration_depth_sigma_mm(idx)
        assert sigma is not None
        return {"included": True, "term": self.calibration_term, "grid_px": grid_px, "points": int(idx.size),
                "depth_sigma_median_mm": float(np.median(sigma)) if idx.size else None,
                "depth_sigma_max_mm": float(sigma.max()) if idx.size else None,
                "correlation": "one error common to every point of the scan: not to be averaged over points"}

    def right_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """The left pixels with a point (flat indices) and the right-camera pixel (N, 2) that
        saw each point (its projection: the match, to the triangulation's rounding)."""
        idx = self.cloud.valid_indices()
        T = self.model.right_from_left
        pts = self.cloud.points.reshape(-1, 3)[idx].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        return idx, self.model.right.project(pts)


def _at_most(keys: np.ndarray, q: np.ndarray) -> np.ndarray:
    """How many of the sorted keys (positive float64) are ≤ each q (finite float64):
    `np.searchsorted(keys, q, side="right")` on the numbers' bits as int64. IEEE 754 doubles
    ≥ +0 order as their bits do, and a negative q's bits are a negative integer, below every
    key's as its value is; integer comparisons skip the NaN handling of float ones (~25% faster)."""
    return np.searchsorted(keys.view(np.int64), q.view(np.int64), side="right")


def _last(first: np.ndarray, intervals: int) -> np.ndarray:
    """Each run's last interval (positions in a list of `intervals`) from its first (none without a run)."""
    return np.r_[first[1:], intervals][:len(first)] - 1


@dataclass(frozen=True, eq=False)
class _Runs:
    """The monotone runs of a rectified grid's rows (Hg, Wg) of projector coordinate `c`: a run is
    a stretch of consecutive samples whose coordinate rises at every step, or falls at every step
    (a NaN or a zero step ends it). The intervals [min, max) between a run's neighbouring samples
    tile the run's range [min, max) once, so the intervals of a row holding a coordinate number
    the row's runs whose range holds it: a few runs per row are searched, not ~Wg intervals, and
    the one interval of a run holding it is found among the run's samples, in order by construction.

    `lo`, `hi`: the runs' ranges as keys on one number line of all rows, row·span + (c − base),
    sorted; `lo_sums`, `hi_sums` the running sums of their run numbers in that order. `_line`: every
    run's samples on another line, run·span + (c − base) on a rising run and run·span + (top − c) on
    a falling one (top = base + span), ascending, built from `left` (each interval's left sample, flat
    in the grid) and `first` (each run's first interval, as a position in `left`) only when `find`
    needs it. `gate` (Hg·(Wg − 1),), where the runs are built with the noise
    `sigma`: the interval between horizontal neighbours passes the gradient gate (|step| ≥ z·σ_step)."""

    c: np.ndarray
    sigma: np.ndarray | None
    gate: np.ndarray | None
    lo: np.ndarray
    lo_sums: np.ndarray
    hi: np.ndarray
    hi_sums: np.ndarray
    falling: np.ndarray
    left: np.ndarray
    first: np.ndarray
    base: float
    span: float

    @classmethod
    def of(cls, c: np.ndarray, sigma: np.ndarray | None = None, z: float = 0.0) -> _Runs:
        """The runs of `c` (Hg, Wg); with `sigma` (c's noise, same shape) the gate at `z` too."""
        low, high = np.fmin.reduce(c, axis=None), np.fmax.reduce(c, axis=None)  # NaN: no sample has a coordinate
        base = float(low) - 1.0 if np.isfinite(low) else 0.0
        span = float(high - base) + 2.0 if np.isfinite(low) else 1.0
        width = c.shape[1]
        step = c[:, 1:] - c[:, :-1]
        rising, falling = step > 0, step < 0  # a NaN step: neither
        gate = None
        if sigma is not None:
            s2 = sigma[:, 1:] ** 2
            s2 += sigma[:, :-1] ** 2
            gate = (np.abs(step) >= np.float32(z) * np.sqrt(s2, out=s2)).ravel()
        del step
        # a run starts at an interval going the other way than its left neighbour (or first in its row)
        start = rising.copy()
        start[:, 1:] &= ~rising[:, :-1]
        turn = falling.copy()
        turn[:, 1:] &= ~falling[:, :-1]
        start |= turn
        del turn
        k = np.flatnonzero((rising | falling).ravel())  # interval k joins grid samples p = k + row and p + 1
        first = np.flatnonzero(start.ravel().take(k))  # each run's first interval, as a position in k
        left = k + k // (width - 1)
        k_first = k.take(first)
        del k, start
        run_falling = falling.ravel().take(k_first)
        row = (k_first // (width - 1)).astype(np.float64)
        del rising, falling, k_first
        flat = c.ravel()
        v_first = flat.take(left.take(first)).astype(np.float64)
        v_last = flat.take(left.take(_last(first, len(left))) + 1).astype(np.float64)
        offset = row * span - base
        run_lo, run_hi = offset + np.fmin(v_first, v_last), offset + np.fmax(v_first, v_last)
        order_lo, order_hi = np.argsort(run_lo, kind="stable"), np.argsort(run_hi, kind="stable")
        return cls(c, sigma, gate, run_lo.take(order_lo), np.r_[0, np.cumsum(order_lo)], run_hi.take(order_hi),
                   np.r_[0, np.cumsum(order_hi)], run_falling, left, first, base, span)

    @cached_property
    def _line(self) -> tuple[np.ndarray, np.ndarray]:
        """Every run's samples on one line, for `find` (a grid only counted never builds it): their
        flat grid indices (a run's intervals' left samples, then its last right one: a turning sample
        in both its runs) and their keys, ascending."""
        first, last = self.first, _last(self.first, len(self.left))
        samples = np.insert(self.left, last + 1, self.left.take(last) + 1)
        v = self.c.ravel().take(samples).astype(np.float64)
        length = last - first + 2
        oriented = np.repeat(np.where(self.falling, self.base + self.span, -self.base), length)
        oriented += np.where(np.repeat(self.falling, length), -v, v)
        keys = np.repeat(np.arange(len(first)) * self.span, length)
        keys += oriented
        return samples, keys

    def _counts(self, c: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # c beyond the grid's range is held by none of its intervals: kept at the row's ends on the line,
        # not in a neighbouring row's stretch of it
        q = np.clip(c.astype(np.float64), self.base, self.base + self.span)
        q += rows.astype(np.float64) * self.span - self.base
        n_lo, n_hi = _at_most(self.lo, q), _at_most(self.hi, q)
        return n_lo - n_hi, n_lo, n_hi

    def count(self, c: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """How many intervals of row `rows` (N,) hold each coordinate `c` (N,) (min ≤ c < max)."""
        count, _, _ = self._counts(c, rows)
        return count

    def find(self, c: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, ...]:
        """For coordinates `c` (N,) on rows `rows` (N,): how many intervals hold each; the flat
        index (in (Hg, Wg − 1)) of the one holding it when that is unique (else -1); the match's
        sub-pixel grid x; the interval's step (projector px per px) and the noise interpolated at
        the match (with `sigma`)."""
        count, n_lo, n_hi = self._counts(c, rows)
        if not self.lo.size:
            nan = np.full(c.shape, np.nan)
            return count, np.full(c.shape, -1), nan, nan, nan
        # the runs holding c are those starting at or below it less those ending at or below it: where
        # that is one run, its number is the sum of the first set's numbers less the second's
        held = count == 1
        r = self.lo_sums.take(n_lo)
        r -= self.hi_sums.take(n_hi)
        r[~held] = 0
        del n_lo, n_hi
        down = self.falling.take(r)
        c64 = c.astype(np.float64)
        qk = np.where(down, self.base + self.span - c64, c64 - self.base)
        del c64
        qk += r * self.span
        # on a falling run the interval [b, a) holds c when its left sample's key is below c's: < is ≤ c's bits − 1
        samples, keys = self._line
        i = np.searchsorted(keys.view(np.int64), qk.view(np.int64) - down, side="right")
        i -= 1
        np.clip(i, 0, len(samples) - 2, out=i)
        p = samples.take(i)
        del qk, i, down
        flat = self.c.ravel()
        a, b = flat.take(p), flat[1:].take(p)
        with np.errstate(divide="ignore", invalid="ignore"):  # where no run holds c, p is any sample
            u = (c - a) / (b - a)
            x = (p - rows * self.c.shape[1]) + u
            s = np.full(c.shape, np.nan, np.float32)
            if self.sigma is not None:
                sigma = self.sigma.ravel()
                s = (1 - u) * sigma.take(p) + u * sigma[1:].take(p)
        return count, np.where(held, p - rows, -1), x, b - a, s


@dataclass(frozen=True, eq=False)
class _Search:
    """Each left pixel's search of the right camera's rectified rows (N,): whether its rows lie in
    the right grid (`inside`), no interval of one of them holds its coordinate (`none`), exactly one
    of each does and its own row holds it once (`unique`), and both intervals pass the gradient gate
    (`steep`); the match's grid position (`x`, `y`, px), the right coordinate's change per px there
    (`step`, absolute) and its noise (`sigma`, projector px), and the slope dx/dy of the line along
    which the right grid reads the coordinate there (`slope`: the matches' x on the two rows
    around it, subtracted). Only these outlive the search: its rows and per-row results are freed
    before the triangulation."""

    inside: np.ndarray
    none: np.ndarray
    unique: np.ndarray
    steep: np.ndarray
    x: np.ndarray
    y: np.ndarray
    step: np.ndarray
    sigma: np.ndarray
    slope: np.ndarray

    @classmethod
    def of(cls, rect: Rectification, left: CameraPhase, right: CameraPhase, o: str, c: np.ndarray,
           yl: np.ndarray) -> _Search:
        """The search for left coordinates `c` (N,) of orientation `o` at rectified rows `yl` (N,)."""
        z_gate = normal_isf(GRADIENT_FALSE_ACCEPT / 2)
        grid_r = rect.right
        gy = yl - grid_r.y0
        j = np.floor(gy)
        t = (gy - j).astype(np.float32)
        inside = (j >= 0) & (j + 1 < grid_r.shape[0])
        j = np.clip(j, 0, grid_r.shape[0] - 2).astype(np.intp)
        # the left's own (nearest) row must hold the coordinate once: twice means a second surface on the
        # same epipolar plane, which the right may see in this pixel's place (occlusion)
        jl = np.clip(np.rint(yl - rect.left.y0), 0, rect.left.shape[0] - 1)
        # numpy's sorts and searches release the GIL: the right rows are built while the left ones count
        with ThreadPoolExecutor(3, thread_name_prefix="binocular match") as pool:
            building = pool.submit(lambda: _Runs.of(grid_r.resample(right.coordinate[o]),
                                                    grid_r.resample(right.sigma[o]), z_gate))
            left_rows = _Runs.of(rect.left.resample(left.coordinate[o]))  # counted only: no gate, no noise
            left_count = pool.submit(left_rows.count, c, jl)
            right_rows = building.result()
            rows_found = [pool.submit(right_rows.find, c, rows) for rows in (j, j + 1)]
            (n0, k0, x0, step0, s0), (n1, k1, x1, step1, s1) = (f.result() for f in rows_found)
            once = left_count.result() <= 1
        unique = inside & (n0 == 1) & (n1 == 1) & (k0 >= 0) & (k1 >= 0) & once
        gate = right_rows.gate
        assert gate is not None
        steep = unique & gate.take(np.maximum(k0, 0)) & gate.take(np.maximum(k1, 0))
        s = 1 - t
        return cls(inside, inside & ((n0 == 0) | (n1 == 0)), unique, steep,
                   s * x0 + t * x1,  # on the rectified row through the left pixel
                   gy, np.abs(s * step0 + t * step1), s * s0 + t * s1, (x1 - x0).astype(np.float32))


_REASONS = ("outside_right_view", "no_match", "not_unique", "low_gradient", "behind", "inconsistent")


def choose_orientation(rect: Rectification, left: CameraPhase) -> str:
    """The orientation whose left coordinate changes fastest along rectified rows (median
    |dc/dx_r| over valid pixels): the one that locates a match along the epipolar line; a
    decode of one orientation has nothing to choose."""
    if len(left.coordinate) == 1:
        return next(iter(left.coordinate))
    best, best_g = None, -1.0
    xy = rect.left_xy
    for o, c in left.coordinate.items():
        dc = np.diff(c, axis=1)
        dx = np.diff(xy[0], axis=1)
        g = np.abs(dc / dx)
        g = g[np.isfinite(g)]
        med = float(np.median(g)) if g.size else 0.0
        if med > best_g:
            best, best_g = o, med
    assert best is not None
    return best


def _check_shapes(rect: Rectification, left: CameraPhase, right: CameraPhase) -> None:
    if left.coordinate.keys() != right.coordinate.keys():
        raise DecodeError(f"the cameras decoded different fringe orientations: {sorted(left.coordinate)} and "
                          f"{sorted(right.coordinate)}")
    for name, cam, lens in zip(rect.model.names, (left, right), (rect.model.left, rect.model.right)):
        got = next(iter(cam.coordinate.values())).shape
        if got != (lens.height, lens.width):
            raise DecodeError(f"camera '{name}' maps are {got[1]} x {got[0]} px, its calibration {lens.width} x "
                              f"{lens.height} px")


def match(rect: Rectification, left: CameraPhase, right: CameraPhase, orientation: str | None = None
          ) -> BinocularResult:
    """Match every left pixel to the right camera along its epipolar line and triangulate
    (see the module docstring)."""
    _check_shapes(rect, left, right)
    o = orientation or choose_orientation(rect, left)
    grid_r = rect.right
    shape = left.coordinate[o].shape
    pix = np.flatnonzero(np.isfinite(left.coordinate[o]))
    c = left.coordinate[o].ravel().take(pix)
    xl = rect.left_xy[0].ravel().take(pix)
    found = _Search.of(rect, left, right, o, c, rect.left_xy[1].ravel().take(pix))
    inside, none, unique, steep, xg = found.inside, found.none, found.unique, found.steep, found.x
    yg = found.y.astype(np.float32)
    d = xl - (xg + grid_r.x0)
    Z = -rect.f * rect.tx_mm / np.where(d != 0, d, np.nan)
    ahead = steep & (Z > 0)

    # the match's noise: both cameras' coordinate noise over the right coordinate's change per px
    s_r, slope = found.sigma, found.slope
    s_l = left.sigma[o].ravel()
    sigma_d = np.sqrt(s_l.take(pix).astype(np.float64) ** 2 + s_r.astype(np.float64) ** 2) / found.step
    sigma_Z = Z ** 2 / (rect.f * abs(rect.tx_mm)) * sigma_d
    del found, xl, d, sigma_d  # not needed past here: freed before the consistency check, the peak of memory

    # each left pixel's first reason for no point as the number of stages it passed (each stage's pixels
    # are among the previous one's): 0 outside the right view, 1 no match, 2 not unique, 3 low gradient,
    # 4 behind, 5 inconsistent, 6 consistent
    stage = inside.view(np.uint8) + (inside & ~none) + unique + steep + ahead
    passed = np.bincount(stage, minlength=6)
    checks: dict[str, float] = {"pixels_with_coordinate": float(pix.size)} | {
        name: float(passed[k]) for k, name in enumerate(_REASONS[:5])}
    w = rect.left_w.ravel().take(pix)
    others = [p for p in left.coordinate if p != o]
    if others:
        consistent, figures = _second_orientation(rect, left, right, p=others[0], pix=pix, xg=xg, yg=yg, ahead=ahead)
    else:
        at = np.flatnonzero(ahead)  # taken by index, not by the mask, for each array
        px = pix.take(at)
        X = rect.model.left.ray_grid.reshape(-1, 3).take(px, axis=0).astype(np.float64)
        X *= (Z.take(at) / w.take(at))[:, None]  # the points on their rays (mm), in place: one (N, 3) array
        c_at = c.take(at).astype(np.float64)
        sigma_at = np.hypot(s_l.take(px), s_r.take(at)).astype(np.float64)
        del at, px  # freed before the consistency check, the peak of memory
        consistent = ahead.copy()
        consistent[ahead], figures = projector_consistency(X, c_at, sigma_at)
        del X, c_at, sigma_at
    checks |= figures
    keep = consistent & np.isfinite(sigma_Z)
    checks["points"] = float(keep.sum())

    n = shape[0] * shape[1]
    z_left, sig, iso = np.full(n, np.nan, np.float32), np.full(n, np.nan, np.float32), np.full(n, np.nan, np.float32)
    kept = np.flatnonzero(keep)
    at, w_kept = pix.take(kept), w.take(kept)
    z_left[at] = Z.take(kept) / w_kept
    sig[at] = sigma_Z.take(kept) / w_kept
    iso[at] = slope.take(kept)
    reason = np.full(n, len(_REASONS) + 1, np.uint8)  # pixels without a coordinate: no reason
    reason[pix] = stage + consistent
    masks = {name: (reason == k).reshape(shape) for k, name in enumerate(_REASONS)}
    cloud = cloud_from_depth(z_left.reshape(shape), *rect.left_ray_planes, to_texture8(left.texture, left.bit_depth))
    return BinocularResult(cloud, sig.reshape(shape), rect.model, o, iso.reshape(shape), masks, checks)


def calibration_jacobian(model: StereoModel, points: np.ndarray, iso_slope: np.ndarray) -> np.ndarray:
    """∂X/∂θ (N, 3, 24) of left-camera points X (N, 3, mm) matched by `match` with the iso-line
    slopes `iso_slope` (N,) (`BinocularResult.iso_slope`), over the parameters θ of
    `model.covariance` (module docstring, 5.): −A⁻¹B, A = ∂(π_l, n·π_r)/∂X, B = ∂(π_l, n·π_r)/∂θ,
    n ⊥ the tangent (s, 1) of the iso-line carried from the rectified frame into the right
    camera's pixels (through R_rightᵀ and ∂π_r/∂X_r; the tangent's scale does not matter)."""
    X = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 1, 3)
    n = len(X)
    if n == 0:
        return np.zeros((0, 3, N_PARAMETERS))
    L, Rc, T = model.left, model.right, model.right_from_left
    _, R2, _, _ = _rectifying(model)
    _, Jl = cv2.projectPoints(X, np.zeros(3), np.zeros(3), L.K, L.dist)
    _, Jr = cv2.projectPoints(X, cv2.Rodrigues(T[:3, :3])[0].ravel(), T[:3, 3], Rc.K, Rc.dist)
    Jl, Jr = Jl.reshape(n, 2, -1), Jr.reshape(n, 2, -1)  # columns: rvec, tvec, fx, fy, cx, cy, k1, k2, p1, p2, k3
    s = np.asarray(iso_slope, dtype=np.float64).ravel()
    tangent = np.einsum("nij,nj->ni", Jr[:, :, 3:6], np.column_stack([s, np.ones(n), np.zeros(n)]) @ R2)
    normal = np.column_stack([tangent[:, 1], -tangent[:, 0]])
    A = np.concatenate([Jl[:, :, 3:6], np.einsum("ni,nij->nj", normal, Jr[:, :, 3:6])[:, None, :] @ T[:3, :3]], axis=1)
    k = len(INTRINSIC_NAMES)
    B = np.zeros((n, 3, N_PARAMETERS))
    B[:, :2, :k] = Jl[:, :, 6:15]
    B[:, 2, k:2 * k] = np.einsum("ni,nij->nj", normal, Jr[:, :, 6:15])
    B[:, 2, 2 * k:] = np.einsum("ni,nij->nj", normal, Jr[:, :, 0:6])
    return -np.linalg.solve(A, B)


PROJECTOR_FIT_SAMPLES = 50_000  # points the projector model is fitted on (17 parameters): every k-th point


def projector_consistency(X: np.ndarray, c: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
    """Which points X (N, 3) agree with the projector coordinate c (N,) they were matched on,
    the projector's geometry estimated from the points themselves (no calibration): a 1-D
    projective camera c = a·X̃ / b·X̃ (direct linear fit), then a cubic in (that coordinate,
    y/z) absorbing the projector's lens distortion (fitted twice, without the points beyond
    5 robust sigmas), both on every k-th point (PROJECTOR_FIT_SAMPLES). A point is kept when
    its residual over sqrt(σ_l² + σ_r²) (the two cameras' coordinate noise) is within z robust
    sigmas, z for CHECK_FALSE_REFUSE two-sided. This is what removes, with one fringe
    orientation, the left points the right camera cannot see that matched another surface on
    the same epipolar plane (their residuals are pixels)."""
    n = len(X)
    if n < 50:
        return np.ones(n, bool), {"projector_fit_points": float(n)}
    fit = slice(None, None, max(n // PROJECTOR_FIT_SAMPLES, 1))
    m, scale = X[fit].mean(axis=0), float(X[fit].std()) or 1.0
    cm, cs = float(c[fit].mean()), float(c[fit].std()) or 1.0

    def homogeneous(P: np.ndarray) -> np.ndarray:
        return np.column_stack([(P - m) / scale, np.ones(len(P))])

    H = homogeneous(X[fit])
    cn = (c[fit] - cm) / cs
    A = np.column_stack([H, -cn[:, None] * H])
    p = np.linalg.eigh(A.T @ A)[1][:, 0]

    def features(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Hp = homogeneous(P)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (Hp @ p[:4]) / (Hp @ p[4:])
            y = P[:, 1] / P[:, 2]
        return u, np.column_stack([np.ones(len(P)), u, y, u * u, u * y, y * y, u ** 3, u * u * y, u * y * y, y ** 3])

    u, F = features(X[fit])
    r = (cn - u) * cs
    w = 1.0 / sigma[fit]
    use = np.isfinite(r) & np.isfinite(F).all(axis=1) & np.isfinite(w)
    for _ in range(2):
        Fw = F[use] * w[use, None]
        coef = np.linalg.solve(Fw.T @ Fw, Fw.T @ (r[use] * w[use]))
        res = (r - F @ coef) * w
        spread = 1.4826 * float(np.median(np.abs(res[use])))
        use &= np.abs(res) <= 5 * spread
    # every point's residual, the features evaluated without forming them (Horner in u)
    a = p[:3] / scale
    b = p[4:7] / scale
    with np.errstate(divide="ignore", invalid="ignore"):
        u_all = (X @ a + (p[3] - m @ a)) / (X @ b + (p[7] - m @ b))
        y = X[:, 1] / X[:, 2]
    k = coef
    poly = k[0] + u_all * (k[1] + u_all * (k[3] + u_all * k[6])) + y * (k[2] + u_all * (k[4] + u_all * k[7])
                                                                      + y * (k[5] + u_all * k[8] + y * k[9]))
    res_all = (c - cm) - cs * u_all - poly
    keep = np.abs(res_all / sigma) <= normal_isf(CHECK_FALSE_REFUSE / 2) * spread
    return keep, {"projector_fit_sigma": spread, "projector_fit_refused": float((~keep).sum())}


def _second_orientation(rect: Rectification, left: CameraPhase, right: CameraPhase, *, p: str, pix: np.ndarray,
                        xg: np.ndarray, yg: np.ndarray, ahead: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
    """Which matches the other orientation confirms (both cameras read the same coordinate
    within z·σ, z for CHECK_FALSE_REFUSE two-sided), and the epipolar offsets it measures (px)."""
    grid = rect.right
    cr = grid.resample(right.coordinate[p])
    c_right = bilinear(cr, xg, yg)
    s2 = left.sigma[p].ravel()[pix] ** 2 + bilinear(grid.resample(right.sigma[p]), xg, yg) ** 2
    g_y = bilinear(np.gradient(cr, axis=0), xg, yg)  # the coordinate's change across rectified rows
    s2 += (np.nan_to_num(g_y) * np.float32(rect.model.epipolar_sigma_px)) ** 2
    r = left.coordinate[p].ravel()[pix] - c_right
    judged = ahead & np.isfinite(r)
    consistent = judged & (np.abs(r) <= np.float32(normal_isf(CHECK_FALSE_REFUSE / 2)) * np.sqrt(s2))
    offset = (r / g_y)[judged & (np.abs(g_y) > 0)].astype(np.float64)
    return consistent, {"second_orientation_refused": float((judged & ~consistent).sum()),
                        "second_orientation_missing": float((ahead & ~judged).sum()),
                        "epipolar_offset_median_px": float(np.median(offset)) if offset.size else float("nan"),
                        "epipolar_offset_rms_px": float(np.sqrt(np.mean(offset ** 2))) if offset.size else float("nan")}


@dataclass(eq=False)
class BinocularReconstructor:
    """Binocular reconstruction for one stereo model; the rectification is computed once."""

    model: StereoModel

    @cached_property
    def rectification(self) -> Rectification:
        return Rectification.of(self.model)

    def reconstruct(self, left: DecodeResult, right: DecodeResult, orientation: str | None = None) -> BinocularResult:
        """The binocular cloud of two cameras' decodes of one scan."""
        return match(self.rectification, CameraPhase.of(left), CameraPhase.of(right), orientation)


RECONSTRUCTORS_KEPT = 2  # stereo models whose rectification a process keeps (~130 MB each at 2 x 1.3 MP)


def reconstructor_for(model: StereoModel) -> BinocularReconstructor:
    """The reconstructor of `model`, kept (by the model's content) for the last RECONSTRUCTORS_KEPT
    models: a process scanning again with one rig rectifies it once (~1 s at 2 x 1.3 MP), not per scan."""
    return _kept(_ByContent(json.dumps(model.to_dict(), sort_keys=True), model))


@dataclass(frozen=True)
class _ByContent:
    """A stereo model compared and hashed by its content (`StereoModel` compares by identity)."""

    key: str
    model: StereoModel = field(compare=False, hash=False)


@lru_cache(maxsize=RECONSTRUCTORS_KEPT)
def _kept(model: _ByContent) -> BinocularReconstructor:
    return BinocularReconstructor(model.model)
