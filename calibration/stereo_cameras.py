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

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from calibration.errors import NotEnoughData
from calibration.intrinsics import DeviceCalibration, ViewPoints, calibrate_device
from calibration.pose_gate import FALSE_REFUSAL, PoseGate, pose_gate
from calibration.stereo import RIG_PARAMETERS, StereoCalibration, initial_extrinsics, joint_refine
from scanner.binocular import Rectification, StereoModel


@dataclass(frozen=True, eq=False)
class StereoCameraCalibration:
    """Two cameras' joint calibration. `left`, `right`: each camera on its own views (the
    start); `joint`: the refinement (its `camera` is the left, its `projector` the right, its
    `proj_from_cam` our `right_from_left`); `views`: indices of the board poses both saw;
    `epipolar_px`: per common corner, the rectified row difference (px); `turned`: the poses
    (indices into the capture) whose right-camera labels were turned to agree with the left's
    (a board with symmetries, `agree_labels`)."""

    names: tuple[str, str]
    left: DeviceCalibration
    right: DeviceCalibration
    joint: StereoCalibration
    views: list[int]
    epipolar_px: np.ndarray
    turned: list[int]

    @property
    def epipolar_rms_px(self) -> float:
        return float(np.sqrt(np.mean(self.epipolar_px ** 2))) if self.epipolar_px.size else float("nan")

    @property
    def model(self) -> StereoModel:
        j = self.joint
        return StereoModel(j.camera, j.projector, j.proj_from_cam, self.names, self.epipolar_rms_px,
                           covariance=j.covariance)

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
                "baseline_mm": float(np.linalg.norm(j.proj_from_cam[:3, 3])), "std": std, "turned_poses": self.turned,
                "covariance": {"parameters": self.parameter_names(), "matrix": j.covariance.tolist()}}


def _turned(view: ViewPoints, turn: np.ndarray) -> ViewPoints:
    """`view` with its board points relabelled by the board turn (4, 4)."""
    return ViewPoints(view.object_points @ turn[:3, :3].T + turn[:3, 3], view.image_points)


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


def agree_labels(left_poses: np.ndarray, right_poses: np.ndarray,
                 symmetries: Sequence[np.ndarray]) -> tuple[np.ndarray, list[int]]:
    """For a board with `symmetries` (`Board.symmetries`), the turn (index into [identity,
    *symmetries]) to apply to each pose's right-camera labels so that they agree with the
    left's, and the right's board poses relabelled (V, 4, 4).

    Every pose gives one estimate of right_from_left per labelling; with the labels agreeing
    these estimates are one rotation up to the board-pose noise (~0.01 deg here), while a wrong
    labelling is off by the turn itself (90 or 180 deg about that pose's board normal), which
    differs from pose to pose. So the labelling is the set of choices whose rotations lie
    closest together: each pose's candidate in turn is the reference, every pose takes its
    candidate nearest the reference, the smallest total angle wins. It fails only where the
    pose noise reaches ~45 deg, or every pose has one board normal (then no solve can tell)."""
    turns = [np.eye(4), *symmetries]
    inv_left = np.linalg.inv(left_poses)
    # candidate[v, t]: right_from_left from pose v with the right's labels turned by t
    poses = np.stack([right_poses @ np.linalg.inv(t) for t in turns], axis=1)
    R = (poses @ inv_left[:, None])[..., :3, :3].reshape(-1, 3, 3)
    cos = (np.einsum("aij,bij->ab", R, R) - 1) / 2
    angle = np.arccos(np.clip(cos, -1, 1)).reshape(len(R), len(left_poses), len(turns))
    choice = angle.argmin(axis=2)
    total = np.take_along_axis(angle, choice[..., None], axis=2)[..., 0].sum(axis=1)
    pick = choice[int(total.argmin())]
    return poses[np.arange(len(pick)), pick], pick.tolist()


def gated_stereo_calibration(views: list[tuple[ViewPoints | None, ViewPoints | None]],
                             sizes: tuple[tuple[int, int], tuple[int, int]], names: tuple[str, str] = ("left", "right"),
                             fix_k3: bool = False, *, symmetries: Sequence[np.ndarray] = (),
                             alpha: float = FALSE_REFUSAL) -> tuple[PoseGate, StereoCameraCalibration]:
    """`calibration.pose_gate` on the poses both cameras saw (`calibrate_stereo_cameras`' arguments),
    its failures' `pose` indices into `views`, and the calibration without the poses that fail."""
    both = [i for i, (a, b) in enumerate(views) if a is not None and b is not None]
    solved: dict[tuple[int, ...], StereoCameraCalibration] = {}

    def solve(kept: list[int]) -> StereoCalibration:
        chosen = {both[k] for k in kept}
        pick = [v if i in chosen or i not in both else (None, None) for i, v in enumerate(views)]
        cal = solved[tuple(kept)] = calibrate_stereo_cameras(pick, sizes, names, fix_k3, symmetries=symmetries)
        return cal.joint

    seen = [(a, b) for a, b in views if a is not None and b is not None]  # the poses of `both`, in order
    gate = pose_gate(seen, solve, names, alpha=alpha)
    failed = set(gate.poses)
    final = tuple(k for k in range(len(both)) if k not in failed)
    if final not in solved:
        solve(list(final))
    return replace(gate, failures=tuple(replace(f, pose=both[f.pose]) for f in gate.failures)), solved[final]


def calibrate_stereo_cameras(views: list[tuple[ViewPoints | None, ViewPoints | None]], sizes: tuple[tuple[int, int],
                             tuple[int, int]], names: tuple[str, str] = ("left", "right"), fix_k3: bool = False,
                             min_views: int = 4, *, symmetries: Sequence[np.ndarray] = ()) -> StereoCameraCalibration:
    """Solve both cameras (module docstring) from per-pose detections (None: the board not found
    by that camera in that pose); `sizes` the cameras' (width, height); `symmetries` the board's
    (`Board.symmetries`: the right camera's labels are made to agree with the left's first)."""
    own = []
    for k, (name, size) in enumerate(zip(names, sizes)):
        mine = [p for p in (v[k] for v in views) if p is not None]
        if len(mine) < min_views:
            raise NotEnoughData(f"camera '{name}' found the board in {len(mine)} pose(s); at least {min_views} needed")
        own.append(calibrate_device(name, mine, size, fix_k3))
    both = [i for i, (a, b) in enumerate(views) if a is not None and b is not None]
    if len(both) < min_views:
        raise NotEnoughData(f"both cameras found the board in {len(both)} pose(s); at least {min_views} needed")
    index = [{i: n for n, i in enumerate(j for j, v in enumerate(views) if v[k] is not None)} for k in range(2)]
    left_poses = own[0].poses[[index[0][i] for i in both]]
    right_poses, turn = agree_labels(left_poses, own[1].poses[[index[1][i] for i in both]], symmetries)
    right_from_left = initial_extrinsics(left_poses, right_poses)
    seen = [(a, b) for a, b in views if a is not None and b is not None]  # the poses of `both`, in order
    left_views = [a for a, _ in seen]
    turns = [np.eye(4), *symmetries]
    right_views = [_turned(b, turns[t]) for (_, b), t in zip(seen, turn)]
    joint = joint_refine(left_views, right_views, own[0].pinhole, own[1].pinhole,
                         right_from_left, left_poses, fix_k3=fix_k3)
    model = StereoModel(joint.camera, joint.projector, joint.proj_from_cam, names)
    pairs = [common_corners(a, b) for a, b in zip(left_views, right_views)]
    errors = epipolar_errors(model, pairs)
    return StereoCameraCalibration(names, own[0], own[1], joint, both, errors, [i for i, t in zip(both, turn) if t])
