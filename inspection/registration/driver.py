"""The registration's stages strung together (`register`) and its result (`Registration`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from inspection.errors import RegistrationFailed
from inspection.measured_cloud import ScanCloud
from inspection.registration.alternatives import surviving, unrejected
from inspection.registration.clouds import voxel_grid
from inspection.registration.evidence import (
    Comparison,
    FreeMotion,
    PoseCovariance,
    covers,
    disagreement,
    free_motions,
    within,
)
from inspection.registration.fine import fine_pose, fit_covariance
from inspection.registration.hypotheses import plane_poses, with_flips
from inspection.registration.ndt import coarse_ndt_poses
from inspection.registration.point_to_plane import icp
from inspection.registration.sac_ia import coarse_feature_poses
from inspection.registration.settings import DEFAULT_REGISTRATION_SETTINGS, RegistrationSettings
from inspection.registration.target import ModelTarget
from inspection.registration.verification import evaluate_pose, explore, fitness

PROVEN = "ok"
AMBIGUOUS = "ambiguous"
FREE = "free"


@dataclass(frozen=True)
class Registration:
    """`transform` (4x4) takes scan points onto the model; `fitness`: fraction of scan
    points within `inlier_mm` of the model (normals agreeing); `rmse_mm` their RMS
    distance; `coarse` the pose before the fine step; `timings_s` per stage.

    What the evidence proves (`evidence`): `status` "ok" when the pose is proven (every
    other pose the search found rejected, every motion fixed or a symmetry of the part),
    "ambiguous" when another pose explains the scan as well, "free" when the view leaves a
    motion free that is not a symmetry of the part (the pose is known up to it: the faces
    it does not move can still be measured); `reason` why in a sentence; `ambiguous` the
    first as a flag;
    `alternatives` the poses the test could not reject (4x4 each), `comparisons` every
    comparison made; `covariance` the pose's (None: not computed); `free` the motions the
    fit leaves free (a symmetry of the part, or what the view does not fix)."""

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
    status: str = PROVEN
    reason: str = ""
    comparisons: tuple[Comparison, ...] = ()
    covariance: PoseCovariance | None = None
    free: tuple[FreeMotion, ...] = ()

    @property
    def proven(self) -> bool:
        return self.status == PROVEN

    @property
    def unbounded(self) -> tuple[FreeMotion, ...]:
        """The free motions the view does not fix at all and that are no symmetry of the
        part: the pose's covariance says nothing along them."""
        return tuple(m for m in self.free if not m.symmetry and not np.isfinite(m.u))

    def as_dict(self) -> dict[str, object]:
        return {"transform": self.transform.tolist(), "fitness": self.fitness, "rmse_mm": self.rmse_mm,
                "inlier_mm": self.inlier_mm, "method": self.method, "status": self.status, "reason": self.reason,
                "ambiguous": self.ambiguous, "alternatives": [c.as_dict() for c in self.comparisons
                                                              if any(c.transform is a for a in self.alternatives)],
                "rejected_alternatives": [c.as_dict() for c in self.comparisons
                                          if not any(c.transform is a for a in self.alternatives)],
                "free_motions": [m.as_dict() for m in self.free],
                **({} if self.covariance is None else self.covariance.as_dict()),
                "hidden_fraction": self.hidden_fraction, "timings_s": self.timings_s}


def register(scan: ScanCloud, target: ModelTarget,
             settings: RegistrationSettings = DEFAULT_REGISTRATION_SETTINGS) -> Registration:
    """The pose taking `scan` onto `target` (the stages: `inspection.registration`), with
    what its evidence proves (`Registration.status`). Raises RegistrationFailed when no
    pose explains the scan."""
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
    before = [coarse_icp(sp, sn, target, T, settings) for T in poses]
    refined = list(before)
    fits = fitness(sp, sn, target.coarse, T=np.array(refined), inlier_mm=inlier, max_normal_deg=settings.max_normal_deg)
    order = np.argsort(-fits)
    for k in order[:settings.explored]:  # the most promising few: explored further
        refined[k] = explore(sp, sn, target.coarse, T=refined[k], inlier_mm=inlier, degrees=settings.coarse_turns_deg,
                             icp_mm=4.0 * v, settings=settings)
    judged = []
    for k, T in enumerate(refined):  # a handful of distinct hypotheses
        fit, rmse = evaluate_pose(sp, sn, target.dense, T, inlier, settings.max_normal_deg)
        hidden = target.hidden_fraction(T, sp, scan.viewpoint, 2.0 * v) if scan.viewpoint is not None else 0.0
        judged.append((fit - hidden, fit, rmse, hidden, T, before[k]))
    judged.sort(key=lambda j: -j[0])
    best = judged[0]
    times["verify"] = time.perf_counter() - t0
    if best[1] < settings.min_fitness - 0.1:  # the coarse fit counts at a looser distance
        raise RegistrationFailed(f"{scan.source}: the best pose fits only {best[1]:.0%} of the scan within "
                                 f"{inlier:.3g} mm of {target.name} (needs {settings.min_fitness - 0.1:.0%}); "
                                 f"wrong part, too little of it in view, or other units", best[1], best[2])
    method = f"rscs+{'+'.join(settings.descriptors)}+{settings.coarse}+icp" if settings.coarse != "ndt" else "ndt+icp"
    reg = refine(scan, target, best[4], settings=settings, rng=rng, times=times, method=method)
    t0 = time.perf_counter()
    comparisons = surviving(scan, target, (best[5], best[4]), final=reg.transform,
                            candidates=[j[5] for j in judged[1:]], coarse_points=(sp, sn),
                            free=list(reg.free), cov=reg.covariance, settings=settings, rng=rng)
    times["alternatives"] = time.perf_counter() - t0
    times["total"] = sum(x for k, x in times.items() if k != "total")
    return judge(reg, comparisons, settings, {k: round(x, 4) for k, x in times.items()})


def judge(reg: Registration, comparisons: tuple[Comparison, ...], settings: RegistrationSettings,
          timings: dict[str, float] | None = None) -> Registration:
    """`reg` with its status (`Registration`): ambiguous when an alternative is not rejected
    that lies outside the region the pose's own U covers, free when a motion is free that is
    not a symmetry of the part. An unrejected alternative inside that region (`covers`) is
    no other pose but the pose's own uncertainty showing: it is kept as one more free motion,
    the move to it (its U that move's size), so the pose is not proven, and the figures that
    do not depend on the motion are measured (a climb along a loose motion ending 0.02 deg /
    0.10 mm away, p 0.89 in the fit's covariance, had refused every figure of a scan)."""
    from dataclasses import replace

    standing = unrejected(comparisons, settings)
    cov = reg.covariance
    inside = [c for c in standing if cov is not None and covers(reg.transform, c.transform, cov)]
    standing = tuple(c for c in standing if not any(c is d for d in inside))
    if cov is not None:
        reg = replace(reg, free=reg.free + tuple(
            disagreement(reg.transform, c.transform, cov.centre, cov.radius_mm,
                         "a pose the scan explains as well lies this far off, inside this pose's U") for c in inside))
    loose = [m for m in reg.free if not m.symmetry]
    reasons = []
    if standing:
        reasons.append(f"ambiguous between the best pose and {len(standing)} other pose(s) that explain the scan "
                       "as well (" + "; ".join(
            f"{c.angle_deg:.1f} deg / {c.shift_mm:.2f} mm away, p = {c.p_value:.2g}" for c in standing) + ")")
    if loose:
        reasons.append("the view does not fix the " + "; ".join(m.describe() for m in loose))
    status = AMBIGUOUS if standing else FREE if loose else PROVEN
    return replace(reg, status=status, ambiguous=bool(standing), reason="; ".join(reasons),
                   alternatives=tuple(c.transform for c in standing), comparisons=comparisons,
                   timings_s=timings if timings is not None else reg.timings_s)


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
    near = icp(sp[::3], sn[::3], target.coarse, T=T, max_dist=8.0 * v, min_dist=0.5 * v, max_normal_deg=deg,
               iterations=20, tangential=tw)
    return icp(sp, sn, target.coarse, T=near, max_dist=8.0 * v, min_dist=0.5 * v, max_normal_deg=deg, iterations=10,
               tangential=tw)


def refine(scan: ScanCloud, target: ModelTarget, coarse: np.ndarray, *, settings: RegistrationSettings,
           rng: np.random.Generator, times: dict[str, float], method: str, local_search: bool = True) -> Registration:
    """The fine step from a verified coarse pose (local search and ICP on the dense scan,
    then the exact faces), the final judgement on `settings.max_points` scan points
    (RegistrationFailed when too little of the scan lies near the model), and the pose's
    covariance and free motions (`evidence`). `local_search` False leaves out the search
    about `coarse` (a warm start's: its prior is a pose the search has already settled).
    `times` gains "fine", "evaluate" and "total" (s)."""
    v = target.voxel_mm
    t0 = time.perf_counter()
    T = coarse
    if local_search:
        dense = rng.choice(len(scan), size=min(3000, len(scan)), replace=False)
        T = explore(scan.points[dense], scan.normals[dense], target.dense, T=T, inlier_mm=0.3 * v,
                    degrees=settings.fine_turns_deg,
                    icp_mm=1.0 * v, settings=settings)
    T, fit_points = fine_pose(scan, target, T, settings, rng)
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
    cov = (fit_covariance(scan, target, T, fit_points, max_incidence_deg=settings.max_incidence_deg)
           if len(fit_points.index) >= 6 else None)
    model = target.dense if target.model is not None else None
    free = () if cov is None else tuple(free_motions(cov, settings.pose_tolerance_deg, settings.pose_tolerance_mm,
                                                     None if model is None else model.points,
                                                     None if model is None else model.normals))
    claimed = fit_points.claimed
    if cov is not None and claimed is not None and not within(T, claimed, cov.centre, settings.pose_tolerance_deg,
                                                               settings.pose_tolerance_mm, list(free)):
        free += (disagreement(T, claimed, cov.centre, cov.radius_mm, "the faces the pose rests on and the other "
                              "faces it claims place the part this far apart"),)
    times["evaluate"] = time.perf_counter() - t0
    times["total"] = sum(x for k, x in times.items() if k != "total")
    return Registration(T, fit, rmse, fine_inlier, coarse, method, hidden_fraction=hidden,
                        timings_s={k: round(x, 4) for k, x in times.items()}, covariance=cov, free=free)
