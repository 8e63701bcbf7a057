"""Stage-axis calibration: where a turntable's axis lies, from a board it turns.

The board is fixed on the platter and the stage turns it to several angles q_k; at each the
camera (calibrated) sees it under full white and the board's pose cam_from_board_k follows
from its detected corners (OpenCV's solvePnP, iterative). A board point X is then at
M(q_k) B X in the world, M(q) the rotation by q about the axis (direction d, through p) and
B the board's pose at q = 0. The axis is solved in two steps:

1. closed form: each relative rotation R_k R_0^T turns about d by q_k - q_0 (d: the
   least-squares mean of their rotation axes, signed by the commanded turns); p from the
   translations, (I - R) p = t for every relative pose, in the least-squares sense, its
   component along d set to that of the board's centre (any point of the line does);
2. least squares (scipy) over d, p and B on the 3D positions of every detected corner,
   sum |M(q_k) B X - cam_from_board_k X|^2 (mm): the axis that explains all views at once.

`StageAxisSolution` gives the axis, the RMS of those residuals (`residual_mm`), and how far
each view's fitted turn is from the commanded one (`angle_residuals_deg`: a slipping board
or a stage that lost steps shows there). `write_stage_axis` writes the calibration file the
rig's `[stage] calibration` names (format: `scanner.stage_model`). Units mm, rad (degrees
in reports).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.board import Board
from calibration.detect import detect
from scanner import __version__
from scanner.errors import ScannerError
from scanner.geometry import Pinhole
from scanner.session import write_json
from scanner.stage import AxisKind
from scanner.stage_model import STAGE_AXIS_VERSION, AxisGeometry, StageModel, rotation_about

MIN_VIEWS = 3
MIN_SPAN_DEG = 20.0


class StageAxisError(ScannerError):
    """The stage axis cannot be solved from these views (too few, too little turn)."""


@dataclass(frozen=True, eq=False)
class StageAxisSolution:
    """The axis in the rig's world frame: unit `direction` (turns right-handed about it by
    the stage's positive positions) through `point_mm`; `residual_mm` the RMS 3D residual of
    the board's corners; `angle_residuals_deg` per view; `views` used."""

    direction: np.ndarray
    point_mm: np.ndarray
    residual_mm: float
    angle_residuals_deg: tuple[float, ...]
    views: int

    def axis(self, name: str) -> AxisGeometry:
        return AxisGeometry(name, AxisKind.ROTARY, self.direction, self.point_mm)


def board_pose(board: Board, image: np.ndarray, camera: Pinhole) -> tuple[np.ndarray, np.ndarray] | None:
    """(cam_from_board 4x4, ids of the detected corners) of the board in `image`, or None
    when it is not found (or too little of it for a pose)."""
    found = detect(board, image)
    if found is None or len(found) < 6:
        return None
    obj = board.object_points()[found.ids]
    ok, rvec, tvec = cv2.solvePnP(obj, found.image_points, camera.K, camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T, found.ids


def solve_stage_axis(poses: Sequence[np.ndarray], angles_rad: Sequence[float], points: Sequence[np.ndarray],
                     world_from_cam: np.ndarray | None = None) -> StageAxisSolution:
    """The axis from board poses `poses` (cam_from_board) at stage angles `angles_rad`,
    `points[k]` the board points (N_k, 3) seen in view k (see the module docstring)."""
    n = len(poses)
    if n < MIN_VIEWS or len(angles_rad) != n or len(points) != n:
        raise StageAxisError(f"the stage axis needs at least {MIN_VIEWS} views of the board, got {n}")
    q = np.asarray(angles_rad, float)
    if math.degrees(q.max() - q.min()) < MIN_SPAN_DEG:
        raise StageAxisError(f"the views span {math.degrees(q.max() - q.min()):.1f} deg; turn the board through at "
                             f"least {MIN_SPAN_DEG:.0f} deg so the axis is defined")
    W = np.eye(4) if world_from_cam is None else np.asarray(world_from_cam, float)
    world = [W @ T for T in poses]  # world_from_board per view
    d, p = _closed_form(world, q)
    B0 = np.linalg.inv(_motion(d, p, q[0])) @ world[0]
    x0 = np.concatenate([_direction_angles(d), p, Rotation.from_matrix(B0[:3, :3]).as_rotvec(), B0[:3, 3]])
    targets = [T[:3, :3] @ X.T + T[:3, 3:4] for T, X in zip(world, points)]

    def residuals(x: np.ndarray) -> np.ndarray:
        dd, pp, B = _unpack(x)
        out = []
        for qk, X, Y in zip(q, points, targets):
            M = _motion(dd, pp, qk) @ B
            out.append((M[:3, :3] @ X.T + M[:3, 3:4] - Y).ravel())
        return np.concatenate(out)

    fit = least_squares(residuals, x0, method="lm")
    d, p, _ = _unpack(fit.x)
    p = p + d * (d @ (world[0][:3, 3] - p))  # the point of the line level with the board (the fit leaves it free)
    r = fit.fun.reshape(-1)
    rms = float(np.sqrt(np.mean(r ** 2) * 3))
    turns = [_turn_about(d, world[k] @ np.linalg.inv(world[0])) for k in range(n)]
    angle_res = tuple(float(math.degrees(t - (qk - q[0]))) for t, qk in zip(turns, q))
    return StageAxisSolution(d, p, rms, angle_res, n)


def _closed_form(world: list[np.ndarray], q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    axes = []
    A, b = [], []
    for k in range(1, len(world)):
        rel = world[k] @ np.linalg.inv(world[0])
        rv = Rotation.from_matrix(rel[:3, :3]).as_rotvec()
        if np.linalg.norm(rv) > 1e-6:
            axes.append(rv * np.sign(q[k] - q[0]))
        A.append(np.eye(3) - rel[:3, :3])
        b.append(rel[:3, 3])
    d = np.sum(axes, axis=0)
    d /= np.linalg.norm(d)
    p, *_ = np.linalg.lstsq(np.vstack(A), np.concatenate(b), rcond=None)
    centre = world[0][:3, 3]
    p = p + d * (d @ (centre - p))  # the point of the line level with the board
    return d, p


def _direction_angles(d: np.ndarray) -> np.ndarray:
    return np.array([math.acos(np.clip(d[2], -1, 1)), math.atan2(d[1], d[0])])


def _unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    theta, phi = x[0], x[1]
    d = np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)])
    B = np.eye(4)
    B[:3, :3] = Rotation.from_rotvec(x[5:8]).as_matrix()
    B[:3, 3] = x[8:11]
    return d, x[2:5], B


def _motion(d: np.ndarray, p: np.ndarray, q: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation_about(d, q)
    T[:3, 3] = p - T[:3, :3] @ p
    return T


def _turn_about(d: np.ndarray, rel: np.ndarray) -> float:
    """The signed angle (rad) of a relative pose's rotation about d."""
    rv = Rotation.from_matrix(rel[:3, :3]).as_rotvec()
    return float(rv @ d)


def calibrate_stage_axis(images: Callable[[float], np.ndarray], angles_rad: Sequence[float], board: Board,
                         camera: Pinhole, world_from_cam: np.ndarray | None = None,
                         say: Callable[[str], None] = lambda text: None) -> StageAxisSolution:
    """Turn the stage to each angle, take the image `images(angle)` (the board under full
    white, the stage settled there), find the board's pose, and solve the axis. Views
    without the board are left out (said); fewer than MIN_VIEWS left is an error."""
    poses, used, points = [], [], []
    for q in angles_rad:
        found = board_pose(board, images(q), camera)
        if found is None:
            say(f"stage at {math.degrees(q):.1f} deg: board not found; view left out")
            continue
        T, ids = found
        say(f"stage at {math.degrees(q):.1f} deg: {len(ids)} board points")
        poses.append(T)
        used.append(q)
        points.append(board.object_points()[ids])
    return solve_stage_axis(poses, used, points, world_from_cam)


def write_stage_axis(path: str | Path, solution: StageAxisSolution, nominal: StageModel, axis_name: str) -> Path:
    """The stage-axis calibration file (`scanner.stage_model` reads it): the rig's axes with
    `axis_name` replaced by the solved one."""
    axes = tuple(solution.axis(axis_name) if a.name == axis_name else a for a in nominal.axes)
    if all(a.name != axis_name for a in nominal.axes):
        raise StageAxisError(f"the rig's stage has no axis named {axis_name!r}")
    path = Path(path)
    write_json(path, {"slscan_stage_axis": STAGE_AXIS_VERSION, "software_version": __version__,
                      "created": dt.datetime.now(dt.UTC).isoformat(),
                      **StageModel(axes).to_dict(), "residual_mm": solution.residual_mm,
                      "angle_residuals_deg": list(solution.angle_residuals_deg), "views": solution.views})
    return path
