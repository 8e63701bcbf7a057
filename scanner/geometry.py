"""Pinhole device models and the rig model: the plain data that calibration produces,
the simulator takes as ground truth, and reconstruction consumes.

Units: millimetres and radians; pixel coordinates follow OpenCV (the centre of pixel (0, 0)
is at (0.0, 0.0)); frames follow the OpenCV camera convention (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from scanner.errors import ConfigError

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
RAY_GRID_STEP = 16  # px between exactly undistorted rays; a spline fills the pixels between


@dataclass(frozen=True, eq=False)
class Pinhole:
    """A camera or projector as a pinhole with Brown-Conrady distortion.

    `K` is the 3x3 intrinsic matrix in pixels; `dist` holds OpenCV's (k1, k2, p1, p2, k3).
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        d = np.zeros(5)
        given = np.asarray(self.dist, dtype=np.float64).ravel()
        d[: given.size] = given
        object.__setattr__(self, "dist", d)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (self.width, self.height)

    def perturbed(self, delta: np.ndarray) -> Pinhole:
        """This device with its calibration parameters moved by `delta` (9,): fx, fy, cx, cy (px),
        then k1, k2, p1, p2, k3 (as a calibration's covariance orders them)."""
        K = self.K.copy()
        K[0, 0] += delta[0]
        K[1, 1] += delta[1]
        K[0, 2] += delta[2]
        K[1, 2] += delta[3]
        return Pinhole(self.width, self.height, K, self.dist + delta[4:9])

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of points (N, 3) given in this device's frame (mm)."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 1, 3)
        px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)
        return px.reshape(-1, 2)

    def normalized(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (N, 2), i.e. (x/z, y/z), of pixels (N, 2)."""
        px = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if not self.dist.any():
            out = (px.reshape(-1, 2) - self.K[:2, 2]) / np.diag(self.K)[:2]
            return out
        return cv2.undistortPoints(px, self.K, self.dist, R=None, P=None, criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)

    @cached_property
    def ray_grid(self) -> np.ndarray:
        """Ray directions (H, W, 3) as (x/z, y/z, 1) for every pixel centre, float32.

        Undistorted exactly (`normalized`) on a grid every RAY_GRID_STEP pixels and spread
        to every pixel by cubic interpolation (`cubic_weights`): distortion is smooth at that
        scale, so the result matches undistorting each pixel to float32 precision (2e-8 on a
        1280 x 1024 camera with k3 = 3.1) in a tenth of the time."""
        step = RAY_GRID_STEP
        us = np.arange(-step, self.width + 3 * step, step, dtype=np.float64)
        vs = np.arange(-step, self.height + 3 * step, step, dtype=np.float64)
        u, v = np.meshgrid(us, vs)
        xy = self.normalized(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(len(vs), len(us), 2)
        wx = cubic_weights(np.arange(self.width, dtype=np.float64), us[0], step, len(us))
        wy = cubic_weights(np.arange(self.height, dtype=np.float64), vs[0], step, len(vs))
        rays = np.empty((self.height, self.width, 3), dtype=np.float32)
        rays[..., 2] = 1.0
        for k in range(2):
            rays[..., k] = wy @ xy[..., k] @ wx.T
        return rays

    def to_dict(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "K": self.K.tolist(), "dist": self.dist.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "pinhole") -> Pinhole:
        try:
            return cls(int(d["width"]), int(d["height"]), np.array(d["K"], float),
                       np.array(d.get("dist", [0] * 5), float))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(where, None, f"invalid pinhole description: {exc}") from exc

    def resampled(self, width: int, height: int) -> Pinhole:
        """The same device with its image resampled to width x height pixels (same field of
        view; pixel centres at (i + 0.5) * scale - 0.5)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return Pinhole(width, height, K, self.dist)

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, pixel_aspect: float = 1.0,
                 principal: tuple[float, float] | None = None, dist: np.ndarray | None = None) -> Pinhole:
        """A pinhole with the given horizontal field of view (degrees, human-facing) and
        pixel aspect fy/fx; the principal point defaults to the image centre."""
        fx = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        cx, cy = principal if principal is not None else ((width - 1) / 2.0, (height - 1) / 2.0)
        K = np.array([[fx, 0, cx], [0, fx * pixel_aspect, cy], [0, 0, 1.0]])
        return cls(width, height, K, np.zeros(5) if dist is None else dist)


def _cubic_taps(positions: np.ndarray, start: float, step: float, n: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """For samples taken at start + i·step, i < n: each position's sample index i (the one at
    or before it) and the cubic convolution weights (Catmull-Rom, a = −0.5, third-order
    accurate) of samples i − 1 … i + 2; each position needs one sample before it and two after."""
    t = (np.asarray(positions, np.float64) - start) / step
    i = np.floor(t).astype(np.intp)
    f = t - i
    if i.min() < 1 or i.max() > n - 3:
        raise ValueError("cubic interpolation: positions outside the sampled range")
    return i, [((-0.5 * f + 1.0) * f - 0.5) * f, (1.5 * f - 2.5) * f * f + 1.0,
               ((-1.5 * f + 2.0) * f + 0.5) * f, (0.5 * f - 0.5) * f * f]


def cubic_weights(positions: np.ndarray, start: float, step: float, n: int) -> np.ndarray:
    """(len(positions), n) matrix of the cubic convolution weights (`_cubic_taps`): for
    interpolating small sample grids by matrix products."""
    i, taps = _cubic_taps(positions, start, step, n)
    w = np.zeros((len(i), n))
    rows = np.arange(len(i))
    for k, tap in enumerate(taps):
        w[rows, i + k - 1] = tap
    return w


def cubic_interpolate(samples: np.ndarray, positions: np.ndarray, start: float, step: float, axis: int) -> np.ndarray:
    """`samples` taken at start + i·step along `axis`, interpolated at `positions` by cubic
    convolution, four taps per position (`_cubic_taps`): for many positions, where a dense
    weight matrix would be mostly zeros."""
    s = np.moveaxis(np.asarray(samples, np.float64), axis, -1)
    i, taps = _cubic_taps(positions, start, step, s.shape[-1])
    out = s[..., i - 1] * taps[0]
    for k in (1, 2, 3):
        out += s[..., i + k - 1] * taps[k]
    return np.moveaxis(out, -1, axis)


def pose_from_dict(d: dict[str, Any]) -> np.ndarray:
    """A 4x4 pose from {'rotation_rad': [rx, ry, rz] (Rodrigues), 'translation_mm': [x, y, z]}
    or {'matrix': 4x4}."""
    if "matrix" in d:
        T = np.array(d["matrix"], dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError("matrix must be 4x4")
        return T
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array(d.get("rotation_rad", [0, 0, 0]), dtype=np.float64))[0]
    T[:3, 3] = np.array(d.get("translation_mm", [0, 0, 0]), dtype=np.float64)
    return T


def perturbed_pose(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The rigid transform T (4x4) with its Rodrigues vector moved by delta[:3] (rad) and its
    translation by delta[3:6] (mm), as a calibration solves and states its extrinsic."""
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(cv2.Rodrigues(T[:3, :3])[0].ravel() + delta[:3])[0]
    out[:3, 3] = T[:3, 3] + delta[3:6]
    return out


def look_at(eye: np.ndarray, target: np.ndarray, up: npt.ArrayLike = (0.0, -1.0, 0.0)) -> np.ndarray:
    """Pose (device-to-world, 4x4) of a device at `eye` whose optical axis (+z) points at
    `target`, with image 'up' (−y) as close to `up` as possible."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


PHASE_MAP_KEYS = ("reference_phase", "l_map_mm", "k_map_rad")  # the arrays of a PhaseToHeight, as stored


@dataclass(frozen=True, eq=False)
class PhaseToHeight:
    """Reference-plane phase-to-height model of paper 000, Eq. 17:
    h = l·Δφ / (Δφ + 2π·d/λ0), with Δφ = φ_reference − φ_object (rad).

    `l_mm`: camera centre to reference plane; `d_mm`: camera-projector centre distance;
    `pitch_mm`: fringe pitch λ0 on the reference plane. `reference_phase` (H, W) is the
    unwrapped phase of the reference plane (rad, in units of the fringe of pitch λ0);
    `plane` is the reference plane (unit normal n toward the camera, offset c) with
    n·X + c = 0 in the camera frame, used to place each height along its camera ray.

    The per-pixel refinement `l_map_mm` (l, mm) and `k_map_rad` (K = 2π·d/λ0, rad), both
    (H, W) and NaN where they were not calibrated, replace the global l and K when present:
    one l, d, λ0 cannot describe a rig whose fringe pitch varies across the field, and
    outside the calibrated pixels the model gives no height rather than a wrong one.
    `maps_file` names the .npz holding the maps (PHASE_MAP_KEYS) when they are stored
    (absolute once loaded, so the description stays valid wherever it is copied).
    """

    l_mm: float
    d_mm: float
    pitch_mm: float
    reference_phase: np.ndarray
    plane: np.ndarray
    l_map_mm: np.ndarray | None = None
    k_map_rad: np.ndarray | None = None
    maps_file: str = ""

    def __post_init__(self) -> None:
        if (self.l_map_mm is None) != (self.k_map_rad is None):
            raise ValueError("phase-to-height: l_map_mm and k_map_rad come together")
        shape = self.reference_phase.shape
        for name in PHASE_MAP_KEYS[1:]:
            m = getattr(self, name)
            if m is not None and m.shape != shape:
                raise ValueError(f"phase-to-height: {name} is {m.shape}, the reference phase {shape}")

    @property
    def per_pixel(self) -> bool:
        return self.l_map_mm is not None

    def height(self, phase: np.ndarray, per_pixel: bool = True) -> np.ndarray:
        """Height above the reference plane (mm) for an unwrapped phase map (rad): with the
        per-pixel l and K when the model has them and `per_pixel`, else the global ones."""
        dphi = self.reference_phase - phase
        if per_pixel and self.per_pixel:
            return self.l_map_mm * dphi / (dphi + self.k_map_rad)
        return self.l_mm * dphi / (dphi + 2.0 * np.pi * self.d_mm / self.pitch_mm)

    def depth(self, phase: np.ndarray, rays: np.ndarray, per_pixel: bool = True) -> np.ndarray:
        """Depth z (mm) along camera rays (H, W, 3) as (x/z, y/z, 1) of the height `height`
        gives: the point at height h lies on the plane n·X + c = h."""
        n, c = self.plane[:3].astype(np.float32), np.float32(self.plane[3])
        return (self.height(phase, per_pixel) - c) / (rays @ n)

    def maps(self) -> dict[str, np.ndarray]:
        """The arrays to store (float32), by PHASE_MAP_KEYS name."""
        arrays = {"reference_phase": self.reference_phase}
        if self.l_map_mm is not None and self.k_map_rad is not None:  # per_pixel: the two come together
            arrays |= {"l_map_mm": self.l_map_mm, "k_map_rad": self.k_map_rad}
        return {k: np.asarray(v, np.float32) for k, v in arrays.items()}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready coefficients; the maps are stored in `maps_file`."""
        return {"l_mm": self.l_mm, "d_mm": self.d_mm, "pitch_mm": self.pitch_mm, "plane": self.plane.tolist(),
                "per_pixel": self.per_pixel, "maps_file": self.maps_file}

    @classmethod
    def load(cls, d: dict[str, Any], root: Path, shape: tuple[int, int], where: str) -> PhaseToHeight:
        """The model described by `d` (`to_dict`), its maps read from `d['maps_file']`
        (relative to `root`, or absolute); `shape` (H, W) is the camera's. ConfigError
        naming the file when the maps are missing, unreadable or of the wrong size."""
        from scanner.file_checks import ArraySpec, FileRefused, load_npz

        path = root / str(d["maps_file"])
        try:
            arrays = load_npz(path, {k: ArraySpec("f", 2) for k in PHASE_MAP_KEYS}, what="phase-to-height maps",
                              optional=PHASE_MAP_KEYS)
        except FileRefused as exc:
            raise ConfigError(where, "phase_to_height.maps_file", f"{path}: phase-to-height maps missing or "
                                                                  f"unreadable ({exc.problem})") from None
        wanted = PHASE_MAP_KEYS if d.get("per_pixel", False) else PHASE_MAP_KEYS[:1]
        missing = [k for k in wanted if k not in arrays]
        if missing:
            raise ConfigError(where, "phase_to_height.maps_file", f"{path}: the map(s) {missing} are missing")
        for k, a in arrays.items():
            if a.shape != tuple(shape):
                raise ConfigError(where, "phase_to_height.maps_file", f"{path}: {k} is {a.shape[1]} x {a.shape[0]} "
                                                                      f"px, the camera {shape[1]} x {shape[0]} px")
        try:
            return cls(float(d["l_mm"]), float(d["d_mm"]), float(d["pitch_mm"]), arrays["reference_phase"],
                       np.array(d["plane"], float), arrays.get("l_map_mm"), arrays.get("k_map_rad"),
                       str(path.resolve()))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(where, "phase_to_height", f"invalid phase-to-height model: {exc!r}") from None


@dataclass(frozen=True, eq=False)
class RigModel:
    """Geometry and projector response of a projector-camera rig.

    `cam_from_proj` maps projector-frame points to camera-frame points (4x4, mm).
    `world_from_cam` places the camera in the rig's world frame (identity: world = camera).
    `projector_gamma` is the projector's response exponent (displayed = command^gamma);
    patterns are pre-compensated with its inverse so the projected fringes are sinusoidal.
    `calibration` names the calibration file the geometry was loaded from ("": the
    nominal geometry of a rig TOML, or one built in memory).
    """

    camera: Pinhole
    projector: Pinhole
    cam_from_proj: np.ndarray
    world_from_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    projector_gamma: float = 1.0
    phase_to_height: PhaseToHeight | None = None
    calibration: str = ""

    @property
    def proj_from_cam(self) -> np.ndarray:
        return np.linalg.inv(self.cam_from_proj)

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.cam_from_proj[:3, 3]))

    def with_camera_size(self, width: int, height: int) -> RigModel:
        """The rig with its camera resampled to width x height at the same field of view."""
        return replace(self, camera=self.camera.resampled(width, height))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (the phase-to-height maps are stored in their own file)."""
        d: dict[str, Any] = {
            "camera": self.camera.to_dict(),
            "projector": self.projector.to_dict(),
            "cam_from_proj": self.cam_from_proj.tolist(),
            "world_from_cam": self.world_from_cam.tolist(),
            "projector_gamma": self.projector_gamma,
        }
        if self.phase_to_height is not None:
            d["phase_to_height"] = self.phase_to_height.to_dict()
        if self.calibration:
            d["calibration"] = self.calibration
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "rig model", root: Path | None = None) -> RigModel:
        """The model `to_dict` described. Its phase-to-height model, if any, is read with its
        maps from `root` (the folder of the file `d` came from); without `root`, or without a
        maps file (descriptions written before models named theirs), it is left out."""
        try:
            camera = Pinhole.from_dict(d["camera"], f"{where}: camera")
            p2h = None
            if root is not None and (d.get("phase_to_height") or {}).get("maps_file"):
                p2h = PhaseToHeight.load(d["phase_to_height"], root, (camera.height, camera.width), where)
            return cls(
                camera=camera,
                projector=Pinhole.from_dict(d["projector"], f"{where}: projector"),
                cam_from_proj=np.array(d["cam_from_proj"], float).reshape(4, 4),
                world_from_cam=np.array(d.get("world_from_cam", np.eye(4).tolist()), float).reshape(4, 4),
                projector_gamma=float(d.get("projector_gamma", 1.0)),
                phase_to_height=p2h,
                calibration=str(d.get("calibration", "")),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(where, None, f"invalid rig model: {exc!r}") from exc
