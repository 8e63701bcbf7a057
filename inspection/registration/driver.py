"""The registration's stages strung together (`register`) and its result (`Registration`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from inspection.errors import RegistrationFailed
from inspection.measured_cloud import ScanCloud
from inspection.registration.clouds import voxel_grid
from inspection.registration.fine import fine_pose
from inspection.registration.hypotheses import plane_poses, with_flips
from inspection.registration.ndt import coarse_ndt_poses
from inspection.registration.point_to_plane import icp
from inspection.registration.rigid import pose_difference
from inspection.registration.sac_ia import coarse_feature_poses
from inspection.registration.settings import RegistrationSettings
from inspection.registration.target import ModelTarget
from inspection.registration.verification import evaluate_pose, explore, fitness


@dataclass(frozen=True)
class Registration:
    """`transform` (4x4) takes scan points onto the model; `fitness`: fraction of scan
    points within `inlier_mm` of the model (normals agreeing); `rmse_mm` their RMS
    distance; `coarse` the pose before the fine step; `ambiguous` when another pose
    (`alternatives`) explains the scan as well; `timings_s` per stage."""

    transform: np.ndarray
    fitness: float
    rmse_mm: float
    inlier_mm: float
    coarse: np.ndarray
    method: str
    ambiguous: bool = False
    alternatives: tuple[np.ndarray, ...] = ()
    hidden_fraction: float = 0.0
    timings_s: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        return {"transform": self.transform.tolist(), "fitness": self.fitness, "rmse_mm": self.rmse_mm,
                "inlier_mm": self.inlier_mm, "method": self.method, "ambiguous": self.ambiguous,
                "hidden_fraction": self.hidden_fraction, "timings_s": self.timings_s}


def register(scan: ScanCloud, target: ModelTarget,
             settings: RegistrationSettings = RegistrationSettings()) -> Registration:
    """The pose taking `scan` onto `target` (the stages: `inspection.registration`).
    Raises RegistrationFailed when no pose explains the scan."""
    rng = np.random.default_rng(settings.seed)
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    v = target.voxel_mm
    src_pts, src_nrm = scan_voxels(scan, target)
    times["prepare"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if settings.coarse == "ndt":
        poses = coarse_ndt_poses(src_pts, target, settings, rng)
    else:
        poses = coarse_feature_poses(src_pts, src_nrm, target, settings, rng)
    if not poses:
        raise RegistrationFailed(f"{scan.source}: no consistent correspondences between the scan and {target.name}")
    poses = with_flips(poses, src_pts) + plane_poses(src_pts, src_nrm, target)
    times["coarse"] = time.perf_counter() - t0  # the dominant-plane poses included
    t0 = time.perf_counter()
    inlier = 1.5 * v
    sub = rng.choice(len(src_pts), size=min(1500, len(src_pts)), replace=False)
    sp, sn = src_pts[sub], src_nrm[sub]
    refined = [coarse_icp(sp, sn, target, T, settings) for T in poses]
    fits = fitness(sp, sn, target.coarse, np.array(refined), inlier, settings.max_normal_deg)
    order = np.argsort(-fits)
    for k in order[:settings.explored]:  # the most promising few: explored further
        refined[k] = explore(sp, sn, target.coarse, refined[k], inlier, settings.coarse_turns_deg, 4.0 * v, settings)
    judged = []
    for T in refined:  # a handful of distinct hypotheses
        fit, rmse = evaluate_pose(sp, sn, target.dense, T, inlier, settings.max_normal_deg)
        hidden = target.hidden_fraction(T, sp, scan.viewpoint, 2.0 * v) if scan.viewpoint is not None else 0.0
        judged.append((fit - hidden, fit, rmse, hidden, T))
    judged.sort(key=lambda j: -j[0])
    best = judged[0]
    times["verify"] = time.perf_counter() - t0
    if best[1] < settings.min_fitness - 0.1:  # the coarse fit counts at a looser distance
        raise RegistrationFailed(f"{scan.source}: the best pose fits only {best[1]:.0%} of the scan within "
                                 f"{inlier:.3g} mm of {target.name} (needs {settings.min_fitness - 0.1:.0%}); wrong part, "
                                 f"too little of it in view, or other units", best[1], best[2])
    centre = src_pts.mean(axis=0)

    def apart(T: np.ndarray) -> bool:  # another pose, not the same one found twice
        angle, shift = pose_difference(T, best[4], centre)
        return angle > 10.0 or shift > 0.1 * target.diagonal_mm

    alternatives = tuple(j[4] for j in judged[1:] if j[0] >= best[0] - settings.ambiguity_margin and apart(j[4]))
    method = f"rscs+{'+'.join(settings.descriptors)}+{settings.coarse}+icp" if settings.coarse != "ndt" else "ndt+icp"
    return refine(scan, target, best[4], settings, rng, times, method, alternatives)


def scan_voxels(scan: ScanCloud, target: ModelTarget) -> tuple[np.ndarray, np.ndarray]:
    """The scan's points and normals averaged on the target's voxel grid; RegistrationFailed
    when too few voxels hold points to register."""
    v = target.voxel_mm
    src_pts, src_nrm = voxel_grid(scan.points, scan.normals, v)
    if len(src_pts) < 50:
        raise RegistrationFailed(f"{scan.source}: only {len(src_pts)} voxels of {v:.3g} mm hold scan points; "
                                 f"the scan is too small for this model")
    return src_pts, src_nrm


def coarse_icp(sp: np.ndarray, sn: np.ndarray, target: ModelTarget, T: np.ndarray,
               settings: RegistrationSettings) -> np.ndarray:
    """A coarse pose `T` refined against the model's coarse samples: ICP on every third
    point first (most of the way in), then on all of them."""
    v, deg, tw = target.voxel_mm, settings.max_normal_deg, settings.tangential_weight
    near = icp(sp[::3], sn[::3], target.coarse, T, 8.0 * v, 0.5 * v, deg, 20, tw)
    return icp(sp, sn, target.coarse, near, 8.0 * v, 0.5 * v, deg, 10, tw)


def refine(scan: ScanCloud, target: ModelTarget, coarse: np.ndarray, settings: RegistrationSettings,
           rng: np.random.Generator, times: dict[str, float], method: str,
           alternatives: tuple[np.ndarray, ...] = (), local_search: bool = True) -> Registration:
    """The fine step from a verified coarse pose (local search and ICP on the dense scan,
    then the exact faces) and the final judgement on `settings.max_points` scan points:
    RegistrationFailed when too little of the scan lies near the model. `local_search`
    False leaves out the search about `coarse` (a warm start's: its prior is a pose the
    search has already settled). `times` gains "fine", "evaluate" and "total" (s)."""
    v = target.voxel_mm
    t0 = time.perf_counter()
    T = coarse
    if local_search:
        dense = rng.choice(len(scan), size=min(3000, len(scan)), replace=False)
        T = explore(scan.points[dense], scan.normals[dense], target.dense, T, 0.3 * v, settings.fine_turns_deg,
                    1.0 * v, settings)
    T = fine_pose(scan, target, T, settings, rng)
    times["fine"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dense = rng.choice(len(scan), size=min(settings.max_points, len(scan)), replace=False)
    fine_inlier = 0.5 * v
    fit, rmse = evaluate_pose(scan.points[dense], scan.normals[dense], target.dense, T, fine_inlier,
                              settings.max_normal_deg)
    hidden = (target.hidden_fraction(T, scan.points[dense], scan.viewpoint, 2.0 * v)
              if scan.viewpoint is not None else 0.0)
    if fit < settings.min_fitness:
        raise RegistrationFailed(f"{scan.source}: after the fine step only {fit:.0%} of the scan lies within "
                                 f"{fine_inlier:.3g} mm of {target.name} (needs {settings.min_fitness:.0%}): wrong "
                                 f"part, or a part far from its model", fit, rmse)
    times["evaluate"] = time.perf_counter() - t0
    times["total"] = sum(times.values())
    return Registration(T, fit, rmse, fine_inlier, coarse, method, bool(alternatives), alternatives, hidden,
                        {k: round(x, 4) for k, x in times.items()})
