"""Two cameras calibrated together from board poses both see: each camera's intrinsics from its
own views (Zhang, `calibration.intrinsics`), their relative pose from the per-view board poses,
then one joint least-squares refinement of both cameras' intrinsics, the relative pose and every
board pose (`calibration.stereo.joint_refine`, the second camera in the projector's place: the
same problem as OpenCV's `stereoCalibrate` without fixed intrinsics), whose covariance gives the
uncertainty of every parameter.

The epipolar error is what binocular matching relies on: for every board corner both cameras
found, the two detections rectified with the solved model must lie on one row; its RMS (px, in
the rectified frame of focal f) is the calibration's `epipolar_sigma_px`, which the second
orientation's check allows for (scanner/binocular.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from calibration.errors import NotEnoughData
from calibration.intrinsics import DeviceCalibration, ViewPoints, calibrate_device, outlier_views
from calibration.stereo import RIG_PARAMETERS, StereoCalibration, initial_extrinsics, joint_refine
from scanner.binocular import Rectification, StereoModel


@dataclass(frozen=True, eq=False)
class StereoCameraCalibration:
    """Two cameras' joint calibration. `left`, `right`: each camera on its own views (the
    start); `joint`: the refinement (its `camera` is the left, its `projector` the right, its
    `proj_from_cam` our `right_from_left`); `views`: indices of the board poses both saw;
    `epipolar_px`: per common corner, the rectified row difference (px)."""

    names: tuple[str, str]
    left: DeviceCalibration
    right: DeviceCalibration
    joint: StereoCalibration
    views: list[int]
    epipolar_px: np.ndarray

    def outliers(self, factor: float) -> list[int]:
        """Board poses (indices into the capture) whose joint RMS in either camera exceeds
        `factor` times the median pose's (`calibration.intrinsics.outlier_views`), worst first."""
        worst = np.maximum(self.joint.per_view_rms_px("camera"), self.joint.per_view_rms_px("projector"))
        return [self.views[i] for i in outlier_views(worst, factor)]

    @property
    def epipolar_rms_px(self) -> float:
        return float(np.sqrt(np.mean(self.epipolar_px ** 2))) if self.epipolar_px.size else float("nan")

    @property
    def model(self) -> StereoModel:
        j = self.joint
        return StereoModel(j.camera, j.projector, j.proj_from_cam, self.names, self.epipolar_rms_px)

    def parameter_names(self) -> list[str]:
        """The covariance's rows: the left's then the right's intrinsics (px, distortion
        unitless), then right_from_left as a Rodrigues vector (rad) and a translation (mm)."""
        a, b = self.names
        return [n.replace("camera.", f"{a}.").replace("projector.", f"{b}.") for n in RIG_PARAMETERS]

    def report(self) -> dict[str, Any]:
        """The figures of the solve, for the calibration file and people (px, mm, degrees)."""
        j = self.joint
        a, b = self.names
        std = {k.replace("camera.", f"{a}.").replace("projector.", f"{b}."): v for k, v in j.std.items()}
        per_view = np.maximum(j.per_view_rms_px("camera"), j.per_view_rms_px("projector"))
        rms_px = {a: j.camera_rms_px, b: j.projector_rms_px, "stereo": j.rms_px, f"{a}_alone": self.left.rms_px,
                  f"{b}_alone": self.right.rms_px}
        return {"views": self.views, "per_view_rms_px": dict(zip(self.views, per_view.tolist())), "rms_px": rms_px,
                "epipolar_rms_px": self.epipolar_rms_px,
                "epipolar_max_px": float(np.abs(self.epipolar_px).max()) if self.epipolar_px.size else None,
                "baseline_mm": float(np.linalg.norm(j.proj_from_cam[:3, 3])), "std": std,
                "covariance": {"parameters": self.parameter_names(), "matrix": j.covariance.tolist()}}


def common_corners(a: ViewPoints, b: ViewPoints) -> tuple[np.ndarray, np.ndarray]:
    """The pixels (N, 2) each view has of the board points both found (same board coordinates)."""
    keys_a = {tuple(p): i for i, p in enumerate(np.round(a.object_points, 6))}
    pairs = [(keys_a[tuple(p)], j) for j, p in enumerate(np.round(b.object_points, 6)) if tuple(p) in keys_a]
    if not pairs:
        return np.empty((0, 2)), np.empty((0, 2))
    ia, ib = np.array(pairs).T
    return a.image_points[ia], b.image_points[ib]


def epipolar_errors(model: StereoModel, pairs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The rectified row difference (px) of each pair of pixels (left, right) seeing one point."""
    rect = Rectification.of(model)
    P = np.array([[rect.f, 0.0, 0.0], [0.0, rect.f, 0.0], [0.0, 0.0, 1.0]])
    out = []
    for pl, pr in pairs:
        if not len(pl):
            continue
        yl = cv2.undistortPoints(pl.reshape(-1, 1, 2), model.left.K, model.left.dist, R=rect.R_left, P=P)
        yr = cv2.undistortPoints(pr.reshape(-1, 1, 2), model.right.K, model.right.dist, R=rect.R_right, P=P)
        out.append(yl.reshape(-1, 2)[:, 1] - yr.reshape(-1, 2)[:, 1])
    return np.concatenate(out) if out else np.empty(0)


def calibrate_stereo_cameras(views: list[tuple[ViewPoints | None, ViewPoints | None]], sizes: tuple[tuple[int, int],
                             tuple[int, int]], names: tuple[str, str] = ("left", "right"), fix_k3: bool = False,
                             min_views: int = 4) -> StereoCameraCalibration:
    """Solve both cameras (module docstring) from per-pose detections (None: the board not found
    by that camera in that pose); `sizes` the cameras' (width, height)."""
    own = []
    for k, (name, size) in enumerate(zip(names, sizes)):
        mine = [v[k] for v in views if v[k] is not None]
        if len(mine) < min_views:
            raise NotEnoughData(f"camera '{name}' found the board in {len(mine)} pose(s); at least {min_views} needed")
        own.append(calibrate_device(name, mine, size, fix_k3))  # type: ignore[arg-type]
    both = [i for i, (a, b) in enumerate(views) if a is not None and b is not None]
    if len(both) < min_views:
        raise NotEnoughData(f"both cameras found the board in {len(both)} pose(s); at least {min_views} needed")
    index = [{i: n for n, i in enumerate(j for j, v in enumerate(views) if v[k] is not None)} for k in range(2)]
    left_poses = own[0].poses[[index[0][i] for i in both]]
    right_poses = own[1].poses[[index[1][i] for i in both]]
    right_from_left = initial_extrinsics(left_poses, right_poses)
    left_views = [views[i][0] for i in both]
    right_views = [views[i][1] for i in both]
    joint = joint_refine(left_views, right_views, own[0].pinhole, own[1].pinhole,  # type: ignore[arg-type]
                         right_from_left, left_poses, fix_k3=fix_k3)
    model = StereoModel(joint.camera, joint.projector, joint.proj_from_cam, names)
    pairs = [common_corners(a, b) for a, b in zip(left_views, right_views)]  # type: ignore[arg-type]
    errors = epipolar_errors(model, pairs)
    return StereoCameraCalibration(names, own[0], own[1], joint, both, errors)
