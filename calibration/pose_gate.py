"""Which board poses a calibration must not keep: each pose's residuals against the other poses'
residuals in the solve without it (leave-one-out), one test per residual group (a device's x or y
axis), at a stated chance of refusing a good calibration.

The model: a pose's residuals in group g are Gaussian with a variance of its own. A corner's error
scales inversely with the board's size in the image (on the simulated stereo bench a pose's RMS times
its corner spacing s is 104-126 px² over spacings of 12-30 px), and what is left differs from pose to
pose (tilt, blur, vignetting), so the poses' scaled log mean squares x_vg = ln(SS_vg / d_vg · s_vg²)
(SS the sum of squares, d its degrees of freedom: its rows' share of the solve's redundancy) are
taken as normal across poses, mean and spread unknown. The pose under test keeps its x_vg from the
solve that includes it; the other n poses' come from the solve without it, so an error in the pose
under test cannot raise them. A good pose's x_vg then lies above their mean by
(x_vg - mean) / (sd·√(1 + 1/n)), a Student t with n - 1 degrees of freedom (the prediction interval
of a normal sample). A pose whose t exceeds the point a good pose exceeds with probability
α / (poses x groups) fails (Bonferroni): a calibration whose poses all follow the model is refused
with probability at most α (`FALSE_REFUSAL`, 0.1 %). With few poses the t's tails are wide and only
gross failures are caught (t limit 28 sd with 5 poses, 8.6 with 9, 7.3 with 11).

Why leave the pose out: a pose the detector got wrong (a corner found pixels off, corners
mislabelled, a reflection) bends the fit towards it, which spreads its error over the other poses
and hides it: one corner 14 px off among eleven poses of 63 moved the simulated stereo bench's
principal points by 13-62 px and raised another pose's RMS fiftyfold. Its own residuals are not
predicted from the solve without it: a pose alone in a corner of the image carries the lens's
distortion there, and its prediction's error is not the detector's. Poses are tried worst first (by
the solve's scaled residuals) until one passes; a pose that fails leaves every later solve, so a
second bad pose cannot hide behind the first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.stats import t as student

from calibration.intrinsics import ViewPoints
from calibration.stereo import WEIGHT_GROUPS, StereoCalibration

FALSE_REFUSAL = 1e-3  # the chance that a calibration whose every pose follows the model is refused


@dataclass(frozen=True)
class PoseFailure:
    """One pose that fails the gate: `pose` (index into the poses tested), `group` (e.g.
    'left x'), its residuals' RMS per degree of freedom `rms_px` and the one the other poses' predict
    `expected_px` (px), `limit_px` the RMS above which it fails, and the chance `p_value` of a
    ratio this large for a good pose."""

    pose: int
    group: str
    rms_px: float
    expected_px: float
    limit_px: float
    p_value: float

    def describe(self, name: str) -> str:
        return (f"{name}: {self.group} residual RMS {self.rms_px:.3f} px where the other poses predict "
                f"{self.expected_px:.3f} px (limit {self.limit_px:.3f} px; a good pose comes this far with probability "
                f"{self.p_value:.1e})")


@dataclass(frozen=True)
class PoseGate:
    """The gate's verdict on a calibration's poses: `failures` worst first (one per failing
    pose, its worst group); `alpha` the chance of refusing a good calibration; `tests` the
    number of tests it was shared over (poses x groups)."""

    failures: tuple[PoseFailure, ...]
    alpha: float
    tests: int

    @property
    def poses(self) -> list[int]:
        return [f.pose for f in self.failures]

    def model(self) -> str:
        return (f"each pose's log mean square residual per device axis against the other poses' (Student t, "
                f"{self.tests} tests, Bonferroni): a calibration whose poses all follow the model is refused with "
                f"probability {self.alpha:g}")


def board_scale_px(view: ViewPoints) -> float:
    """The board's scale in a view: the median distance (px) from each point to its nearest."""
    p = view.image_points
    if len(p) < 2:
        return float("nan")
    d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def _log_mean_squares(residuals: list[np.ndarray], redundancy: float, scales: np.ndarray) -> np.ndarray:
    """ln(SS / d · s²) per pose of one group: d the pose's rows times the group's redundancy per
    row, s the board's scale in that pose (px; the noise taken as inversely proportional to it)."""
    rows = np.array([np.size(r) for r in residuals], dtype=np.float64)
    squares = np.array([float(np.sum(np.square(r))) for r in residuals])
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((rows > 0) & (squares > 0),
                        np.log(squares / (rows * redundancy / rows.sum()) * np.asarray(scales) ** 2), np.nan)


def _t_test(others: np.ndarray, value: float, level: float) -> tuple[float, float, float] | None:
    """(p, predicted, limit) for `value` against the normal sample `others` (module docstring),
    predicted and limit as log mean squares; None with fewer than 3 others."""
    others = others[np.isfinite(others)]
    n = len(others)
    if n < 3 or not np.isfinite(value):
        return None
    scale = float(np.std(others, ddof=1)) * float(np.sqrt(1.0 + 1.0 / n))
    mean = float(np.mean(others))
    if scale <= 0:
        return None
    return (float(student.sf((value - mean) / scale, n - 1)), mean,
            mean + float(student.isf(level, n - 1)) * scale)


def pose_gate(views: list[tuple[ViewPoints, ViewPoints]], solve: Callable[[list[int]], StereoCalibration],
              devices: tuple[str, str] = ("camera", "projector"), *, alpha: float = FALSE_REFUSAL) -> PoseGate:
    """The gate (module docstring) on `views` (per pose, the first and the second device's points);
    `solve(kept)` is the joint solve (`calibration.stereo.joint_refine`) from the poses `kept`
    (indices into `views`, ascending), its residuals in that order; `devices` name the groups."""
    names = [f"{d} {axis}" for d in devices for axis in ("x", "y")]
    tests = 2 * sum(len(a) > 0 for a, _ in views) + 2 * sum(len(b) > 0 for _, b in views)
    level = alpha / max(tests, 1)
    scales = np.array([[board_scale_px(v[k]) for v in views] for k in (0, 0, 1, 1)])  # (4, V) px
    pool = list(range(len(views)))
    current = _in_sample(solve(pool), scales[:, pool])  # (4, len(pool)): the pool's solve
    failures: list[PoseFailure] = []
    while len(pool) > 3:
        order = np.argsort(-np.nanmax(current - np.nanmedian(current, axis=1, keepdims=True), axis=0))
        candidate = pool[int(order[0])]
        kept = [i for i in pool if i != candidate]
        others = _in_sample(solve(kept), scales[:, kept])
        worst: PoseFailure | None = None
        for g in range(len(names)):
            value = float(current[g, pool.index(candidate)])
            test = _t_test(others[g], value, level)
            if test is None or test[0] >= level:
                continue
            p, mean, limit = test
            failure = PoseFailure(candidate, names[g], float(np.sqrt(np.exp(value))) / scales[g, candidate],
                                  float(np.sqrt(np.exp(mean))) / scales[g, candidate],
                                  float(np.sqrt(np.exp(limit))) / scales[g, candidate], p)
            if worst is None or failure.p_value < worst.p_value:
                worst = failure
        if worst is None:
            break
        failures.append(worst)
        pool, current = kept, others
    return PoseGate(tuple(failures), alpha, tests)


def _in_sample(joint: StereoCalibration, scales: np.ndarray) -> np.ndarray:
    """(4, V) the joint solve's log mean squares per group (WEIGHT_GROUPS) and pose, each scaled
    by its board scale `scales` (4, V) px squared."""
    per_device = (joint.camera_residuals, joint.camera_residuals, joint.projector_residuals,
                  joint.projector_residuals)
    return np.stack([_log_mean_squares([r[:, k % 2] for r in per_device[k]], joint.noise.redundancy[k], scales[k])
                     for k in range(len(WEIGHT_GROUPS))])
