"""Intrinsics and distortion of one device (the camera, or the projector as an inverse
camera) from views of a planar board, with per-view errors and outlier views.

Zhang's method as OpenCV implements it (`calibrateCameraExtended`): the 5-coefficient
Brown-Conrady model (k1, k2, p1, p2, k3), pixel coordinates with centres at integers.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.errors import NotEnoughData
from scanner.geometry import Pinhole

MIN_VIEWS = 3  # Zhang's method needs three views of a plane for five intrinsics
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass(frozen=True, eq=False)
class ViewPoints:
    """The correspondences of one view: board points (N, 3) mm and their pixels (N, 2)."""

    object_points: np.ndarray
    image_points: np.ndarray

    def __len__(self) -> int:
        return len(self.object_points)


@dataclass(frozen=True, eq=False)
class DeviceCalibration:
    """One device's calibration from board views.

    `poses` (V, 4, 4): board -> device per view; `residuals`: (N_v, 2) observed − projected
    pixels per view; `std`: one-sigma uncertainty of each intrinsic (INTRINSIC_NAMES)."""

    name: str
    pinhole: Pinhole
    rms_px: float
    per_view_rms_px: np.ndarray
    poses: np.ndarray
    residuals: list[np.ndarray]
    std: dict[str, float]

    def summary(self) -> str:
        K = self.pinhole.K
        return (f"{self.name}: fx {K[0, 0]:.2f} ± {self.std['fx']:.2f}, fy {K[1, 1]:.2f} ± {self.std['fy']:.2f}, "
                f"cx {K[0, 2]:.2f} ± {self.std['cx']:.2f}, cy {K[1, 2]:.2f} ± {self.std['cy']:.2f} px; "
                f"RMS {self.rms_px:.3f} px over {len(self.residuals)} views")


def pose_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))[0]
    T[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return T


def reprojection_residuals(pinhole: Pinhole, views: list[ViewPoints], poses: np.ndarray) -> list[np.ndarray]:
    """Observed − projected pixels (N_v, 2) per view, board poses (V, 4, 4) board -> device."""
    out = []
    for v, T in zip(views, poses):
        X = v.object_points @ T[:3, :3].T + T[:3, 3]
        out.append(v.image_points - pinhole.project(X))
    return out


def rms(residuals: list[np.ndarray] | np.ndarray) -> float:
    """RMS length of 2D residual vectors."""
    r = np.concatenate(residuals) if isinstance(residuals, list) else residuals
    return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))) if len(r) else float("nan")


def calibrate_device(name: str, views: list[ViewPoints], size: tuple[int, int],
                     fix_k3: bool = False) -> DeviceCalibration:
    """Intrinsics, distortion and board poses of a device of `size` = (width, height) px."""
    if len(views) < MIN_VIEWS:
        raise NotEnoughData(f"{name}: {len(views)} usable view(s); at least {MIN_VIEWS} are needed (10-15 recommended)")
    n_points = sum(len(v) for v in views)
    if n_points < 4 * len(views) or min(len(v) for v in views) < 4:
        raise NotEnoughData(f"{name}: a view has fewer than 4 points; a pose cannot be solved from it")
    obj = [v.object_points.astype(np.float32) for v in views]
    img = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in views]
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    found = cv2.calibrateCameraExtended(  # type: ignore[call-overload]  # stubs refuse None: OpenCV estimates K, dist
        obj, img, size, None, None, flags=flags, criteria=_CRITERIA)
    _, K, dist, rvecs, tvecs, std_in, _, _ = found
    pinhole = Pinhole(size[0], size[1], K, dist.ravel()[:5])
    poses = np.stack([pose_matrix(r, t) for r, t in zip(rvecs, tvecs)])
    residuals = reprojection_residuals(pinhole, views, poses)
    std = dict(zip(INTRINSIC_NAMES, (float(s) for s in np.asarray(std_in).ravel()[:9])))
    return DeviceCalibration(name, pinhole, rms(residuals), np.array([rms(r) for r in residuals]), poses, residuals,
                             std)


def outlier_views(per_view_rms_px: np.ndarray, factor: float = 3.0, floor_px: float = 0.05) -> list[int]:
    """Views whose RMS error stands out: above `factor` times the median per-view RMS (and
    above `floor_px`, so that uniformly excellent views are never flagged), worst first."""
    e = np.asarray(per_view_rms_px, dtype=np.float64)
    limit = max(factor * float(np.median(e)), floor_px)
    bad = np.flatnonzero(e > limit)
    return [int(i) for i in bad[np.argsort(-e[bad])]]
