"""Solving the rig from the correspondences of all views: camera, projector, stereo, joint
refinement; outlier views; quality limits; leave-one-pose-out stability.

Order: the camera's intrinsics from its corners, the projector's from its corners (each
view's board pose is solved by both); the projector's pose relative to the camera from
the per-view pose pairs; then one joint refinement of everything (`stereo.joint_refine`). Views
whose joint reprojection error stands out are reported, and dropped when asked; a solved
rig whose error exceeds the limits is refused (`check_limits`) naming the worst views.

The joint refinement keeps the camera's intrinsics only where it determines them: when its
one-sigma uncertainty on the camera's fx, fy, cx or cy exceeds `max_joint_camera_std` of the
focal length, the camera's values come from the projector's corners as much as from its
own, and the projector's corners are derived data (decoded through the camera's image,
with the projector's lens model) whose systematic errors would move them — by 1.8 % of the
principal point on a real five-pose capture whose camera-only calibration agreed with the
published one to 0.2 %. The camera then keeps the intrinsics of its own views, fixed, and
the refinement solves the projector, the extrinsics and the board poses (the sequential
calibration of Moreno & Taubin, and OpenCV's `stereoCalibrate` default). `CameraChoice`
records which was used and why.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from calibration.errors import CalibrationRejected, NotEnoughData
from calibration.intrinsics import DeviceCalibration, ViewPoints, calibrate_device, outlier_views
from calibration.stereo import CornerLinks, StereoCalibration, covariance, initial_extrinsics, joint_refine
from calibration.views import Correspondence


@dataclass(frozen=True)
class CalibrationSettings:
    """How to solve and when to refuse (pixels, mm).

    `min_views`: fewer usable views is an error (10-15 recommended); `fix_k3`: keep the
    sixth-order radial term at 0 (narrow lenses rarely determine it); `outlier_factor`: a
    view is an outlier when its RMS exceeds this many times the median view's;
    `drop_outliers`: solve again without them; `max_*_rms_px`, `max_validation_mm`: limits
    above which the calibration is not saved; `max_joint_camera_std`: the joint refinement's
    one-sigma on the camera's fx, fy, cx, cy (fraction of the focal length) above which the
    camera keeps its own views' intrinsics (see the module docstring)."""

    min_views: int = 4
    fix_k3: bool = False
    outlier_factor: float = 3.0
    drop_outliers: bool = False
    max_camera_rms_px: float = 0.5
    max_projector_rms_px: float = 1.0
    max_validation_mm: float = 0.1
    max_joint_camera_std: float = 0.001

    def __post_init__(self) -> None:
        if self.min_views < 3:
            raise ValueError("min_views must be >= 3 (three views of a plane determine a camera)")
        if not (self.outlier_factor > 1 and self.max_camera_rms_px > 0 and self.max_projector_rms_px > 0
                and self.max_validation_mm > 0 and self.max_joint_camera_std > 0):
            raise ValueError(f"implausible calibration settings: {self}")


@dataclass(frozen=True)
class CameraChoice:
    """Where the saved camera intrinsics come from: 'joint refinement' or
    'camera views' (the camera's own calibration, fixed in the refinement), and why.
    `joint` holds the joint refinement's fx, fy, cx, cy (px) and `joint_std` their one-sigma,
    `limit_px` the largest one-sigma accepted (max_joint_camera_std x focal length)."""

    source: str
    reason: str
    joint: dict[str, float]
    joint_std: dict[str, float]
    limit_px: float


_PINHOLE_NAMES = ("fx", "fy", "cx", "cy")


def choose_camera(camera: DeviceCalibration, joint: StereoCalibration, max_std: float) -> CameraChoice:
    """Keep the joint refinement's camera intrinsics when it determines them to `max_std` of
    the focal length (see the module docstring)."""
    K = joint.camera.K
    values = dict(zip(_PINHOLE_NAMES, (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))))
    std = {n: joint.std[f"camera.{n}"] for n in _PINHOLE_NAMES}
    limit = max_std * float(np.sqrt(K[0, 0] * K[1, 1]))
    loose = [n for n in _PINHOLE_NAMES if std[n] > limit]
    own = camera.pinhole.K
    shift = ", ".join(f"{n} {values[n] - v:+.2f}" for n, v in zip(_PINHOLE_NAMES, (own[0, 0], own[1, 1], own[0, 2],
                                                                                  own[1, 2])))
    if not loose:
        return CameraChoice("joint refinement", f"it determines fx, fy, cx, cy to {max(std.values()):.3f} px (limit "
                                                f"{limit:.3f} px); it moved them by {shift} px from the camera's own "
                                                f"calibration", values, std, limit)
    worst = max(loose, key=lambda n: std[n])
    return CameraChoice("camera views", f"the joint refinement determines the camera's {', '.join(loose)} only to "
                                        f"±{std[worst]:.2f} px ({worst}), above the limit {limit:.2f} px "
                                        f"({max_std:.2%} of the focal length); it would have moved them by {shift} "
                                        f"px, following the projector's corners: the camera keeps its own views' "
                                        f"intrinsics", values, std, limit)


@dataclass(frozen=True, eq=False)
class Solution:
    """A solved rig. `names` are the views used, in order; `dropped` the views left out
    (name -> reason); `camera`/`projector` the separate calibrations that started the
    joint refinement `stereo`; `camera_choice` where `stereo`'s camera intrinsics come from;
    `outlier_corners` the corners that fail the outlier test, per view: board point id ->
    its statistic (`outlier_points`)."""

    names: list[str]
    correspondences: list[Correspondence]
    camera: DeviceCalibration
    projector: DeviceCalibration
    stereo: StereoCalibration
    camera_choice: CameraChoice
    dropped: dict[str, str] = field(default_factory=dict)
    outlier_corners: dict[str, dict[int, float]] = field(default_factory=dict)

    def outliers(self, device: str, factor: float) -> list[int]:
        """Indices (into `names`) of views whose joint RMS for `device` stands out, worst first."""
        return outlier_views(self.stereo.per_view_rms_px(device), factor)

    def worst_views(self, n: int = 3) -> list[int]:
        """The views with the largest joint error, both devices together, worst first."""
        e = [np.sqrt((np.sum(c ** 2) + np.sum(p ** 2)) / max(len(c) + len(p), 1))
             for c, p in zip(self.stereo.camera_residuals, self.stereo.projector_residuals)]
        return [int(i) for i in np.argsort(e)[::-1][:n]]


def solve(views: list[Correspondence], camera_size: tuple[int, int], projector_size: tuple[int, int],
          settings: CalibrationSettings = CalibrationSettings()) -> Solution:
    """The rig from the views' correspondences (see the module docstring)."""
    solution = _solve_once(views, camera_size, projector_size, settings, {})
    if not settings.drop_outliers:
        return solution
    bad = sorted({*solution.outliers("camera", settings.outlier_factor),
                  *solution.outliers("projector", settings.outlier_factor)})
    if not bad:
        return solution
    dropped = {solution.names[i]: (f"outlier: camera {solution.stereo.per_view_rms_px('camera')[i]:.3f} px, projector "
                                   f"{solution.stereo.per_view_rms_px('projector')[i]:.3f} px RMS") for i in bad}
    kept = [c for i, c in enumerate(solution.correspondences) if i not in bad]
    return _solve_once(kept, camera_size, projector_size, settings, dropped)


def _solve_once(views: list[Correspondence], camera_size: tuple[int, int], projector_size: tuple[int, int],
                settings: CalibrationSettings, dropped: dict[str, str]) -> Solution:
    """Solve; corners whose points fail the outlier test (`outlier_points`) are named in
    the solution, not left out: on the real procam capture leaving them out (5-7 corners
    of the poses seen through a glass pane's edge) made the left-out poses' corner
    distances worse (0.15 -> 0.50 mm RMS on one), the poses' errors being fields over the
    board rather than single corners."""
    if len(views) < settings.min_views:
        raise NotEnoughData(f"{len(views)} usable board pose(s), at least {settings.min_views} are needed "
                            f"(10-15 recommended): capture more poses, tilted different ways")
    camera, projector, stereo, choice = _refine(views, camera_size, projector_size, settings)
    flagged = {c.name: {_board_id(c, i): t for i, t in sorted(b.items())}
               for c, b in zip(views, outlier_points(views, stereo)) if b}
    return Solution([c.name for c in views], list(views), camera, projector, stereo, choice, dict(dropped), flagged)


OUTLIER_ALPHA = 1e-4  # the chance that a point following the noise model fails the outlier test
OUTLIER_GATE = -2.0 * float(np.log(OUTLIER_ALPHA))  # the chi-square (2 dof) point it is exceeded with that chance


def outlier_points(views: list[Correspondence], stereo: StereoCalibration) -> list[dict[int, float]]:
    """Per view, the camera corners (index into its camera points -> statistic) whose camera
    or projector point fails the outlier test: its standardised residuals' sum of squares
    under the noise model (`StereoCalibration.camera_tests`, chi-square with 2 degrees of
    freedom) above OUTLIER_GATE. A good point fails with probability OUTLIER_ALPHA (0.15
    good corners of a 12-view calibration of 63-corner boards, on average); a corner the
    detector or the decoding got wrong by several sigma fails."""
    out = []
    for c, cam_t, proj_t in zip(views, stereo.camera_tests, stereo.projector_tests):
        bad = {int(i): float(cam_t[i]) for i in np.flatnonzero(cam_t > OUTLIER_GATE)}
        on_camera = _projector_to_camera(c)
        for k in np.flatnonzero(proj_t > OUTLIER_GATE):
            i = int(on_camera[k])
            bad[i] = max(bad.get(i, 0.0), float(proj_t[k]))
        out.append(bad)
    return out


def _projector_to_camera(c: Correspondence) -> np.ndarray:
    """Index into the camera points of each projector point's corner."""
    if c.projector_corners is not None:
        return np.flatnonzero(c.projector_corners.found)
    same = np.all(np.isclose(c.projector.object_points[:, None, :], c.camera.object_points[None, :, :]), axis=2)
    return np.argmax(same, axis=1)


def _board_id(c: Correspondence, index: int) -> int:
    """The board point id of camera point `index` of a view."""
    return int(c.detection.ids[index]) if c.detection is not None else int(index)


def _refine(views: list[Correspondence], camera_size: tuple[int, int], projector_size: tuple[int, int],
            settings: CalibrationSettings) -> tuple[DeviceCalibration, DeviceCalibration, StereoCalibration,
                                                    CameraChoice]:
    """Each device from its own views, then the joint refinement (module docstring)."""
    camera = calibrate_device("camera", [c.camera for c in views], camera_size, settings.fix_k3)
    projector = calibrate_device("projector", [c.projector for c in views], projector_size, settings.fix_k3)
    start = initial_extrinsics(camera.poses, projector.poses)
    cams, projs = [c.camera for c in views], [c.projector for c in views]
    links = corner_links(views)
    stereo = joint_refine(cams, projs, camera.pinhole, projector.pinhole, start, camera.poses, fix_k3=settings.fix_k3,
                          links=links)
    choice = choose_camera(camera, stereo, settings.max_joint_camera_std)
    if choice.source != "joint refinement":
        fixed = joint_refine(cams, projs, camera.pinhole, projector.pinhole, start, camera.poses,
                             fix_k3=settings.fix_k3, fix_camera=True,
                             camera_covariance=own_covariance(camera, cams, settings.fix_k3), links=links)
        stereo = replace(fixed, std=fixed.std | {f"camera.{n}": v for n, v in camera.std.items()})
    return camera, projector, stereo, choice


def corner_links(views: list[Correspondence]) -> list[CornerLinks] | None:
    """How each view's projector points were measured from its camera corners (None when
    the views do not say, e.g. correspondences made elsewhere: errors then independent)."""
    if any(c.projector_corners is None for c in views):
        return None
    out = []
    for c in views:
        found = c.projector_corners.found
        out.append(CornerLinks(np.flatnonzero(found), c.projector_corners.jacobian[found]))
    return out


def own_covariance(device: DeviceCalibration, views: list[ViewPoints], fix_k3: bool) -> np.ndarray:
    """The covariance (9, 9) of a device's intrinsics and distortion (INTRINSIC_NAMES) from
    its own views, correlations included (OpenCV reports one-sigmas only), the board poses
    marginalised out: (JᵀJ)⁻¹ scaled by the residuals' variance."""
    n_views = len(views)
    rows = 2 * sum(len(v) for v in views)
    J = np.zeros((rows, 9 + 6 * n_views))
    row = 0
    for k, (v, T) in enumerate(zip(views, device.poses)):
        rvec = cv2.Rodrigues(T[:3, :3])[0]
        _, jac = cv2.projectPoints(v.object_points.astype(np.float64), rvec, T[:3, 3], device.pinhole.K,
                                   device.pinhole.dist)
        J[row:row + 2 * len(v), :9] = jac[:, 6:15]
        J[row:row + 2 * len(v), 9 + 6 * k:15 + 6 * k] = jac[:, :6]
        row += 2 * len(v)
    free = np.ones(J.shape[1], dtype=bool)
    if fix_k3:
        free[8] = False
    res = np.concatenate(device.residuals).ravel()
    cov = np.zeros((J.shape[1],) * 2)
    cov[np.ix_(free, free)] = covariance(J[:, free], float(res @ res) / max(rows - int(free.sum()), 1))
    return cov[:9, :9]


def without_view(solution: Solution, index: int, settings: CalibrationSettings) -> StereoCalibration:
    """The rig solved again from scratch without view `index` (for leave-one-out). Not
    warm-started from the full solution: the joint cost has long, nearly flat valleys
    (focal length against distortion and pose), where a warm start stops where it began
    and would report no change at all."""
    views = solution.correspondences[:index] + solution.correspondences[index + 1:]
    if len(views) < settings.min_views:
        raise NotEnoughData(f"leaving a view out leaves {len(views)}, below min_views = {settings.min_views}")
    size = (solution.stereo.camera.size, solution.stereo.projector.size)
    return _solve_once(views, *size, replace(settings, drop_outliers=False), {}).stereo


def check_limits(solution: Solution, settings: CalibrationSettings) -> None:
    """CalibrationRejected when a reprojection error exceeds its limit, naming the views
    to blame (worst first) and what to do."""
    s = solution.stereo
    for device, value, limit in (("camera", s.camera_rms_px, settings.max_camera_rms_px),
                                 ("projector", s.projector_rms_px, settings.max_projector_rms_px)):
        if value > limit:
            per_view = s.per_view_rms_px(device)
            blame = [int(i) for i in np.argsort(per_view)[::-1][:3]]
            worst = ", ".join(f"{solution.names[i]} ({per_view[i]:.3f} px)" for i in blame)
            raise CalibrationRejected(
                f"{device} reprojection error {value:.3f} px RMS exceeds the limit {limit:.3f} px; worst views: "
                f"{worst}. Re-take or drop those poses (--drop-outliers drops views that stand out), check the "
                f"board description and focus, or raise the limit if this rig cannot do better", blame)


@dataclass(frozen=True)
class Stability:
    """Spread of the solution when each view is left out in turn: per quantity, the
    full-set value and the min/max/std over the leave-one-out solutions."""

    values: dict[str, float]
    spread: dict[str, tuple[float, float, float]]  # name -> (min, max, std)
    n_solutions: int

    def lines(self) -> list[str]:
        out = []
        for name, full in self.values.items():
            lo, hi, sd = self.spread[name]
            out.append(f"{name:<28} {full:12.4f}   leave-one-out {lo:12.4f} .. {hi:12.4f}  (std {sd:.4f})")
        return out


def summary_values(s: StereoCalibration) -> dict[str, float]:
    """The quantities whose stability is reported (px, mm, degrees)."""
    Kc, Kp, T = s.camera.K, s.projector.K, s.cam_from_proj
    R = s.proj_from_cam[:3, :3]
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    return {"camera.fx": Kc[0, 0], "camera.fy": Kc[1, 1], "camera.cx": Kc[0, 2], "camera.cy": Kc[1, 2],
            "projector.fx": Kp[0, 0], "projector.fy": Kp[1, 1], "projector.cx": Kp[0, 2], "projector.cy": Kp[1, 2],
            "baseline_mm": float(np.linalg.norm(T[:3, 3])), "rotation_deg": angle,
            "stereo_rms_px": s.rms_px}


def leave_one_out(solution: Solution, settings: CalibrationSettings) -> Stability:
    """Solve again without each view in turn (needs min_views + 1 views)."""
    runs = [summary_values(without_view(solution, i, settings)) for i in range(len(solution.names))]
    full = {k: float(v) for k, v in summary_values(solution.stereo).items()}
    spread = {k: (float(min(r[k] for r in runs)), float(max(r[k] for r in runs)), float(np.std([r[k] for r in runs])))
              for k in full}
    return Stability(full, spread, len(runs))
