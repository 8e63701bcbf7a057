"""Registering one view of a part to another view of it, with no pose known: what
`slscan register SCAN CLOUD` does when the target is a cloud or a session.

Two views of one part overlap only in part, so a pose is judged by what each view's sensor
could have seen of the other (`pair_evidence`): the points of each view that fall, at that
pose, on surfaces the other measured, their residuals against the noise both views show
(`sensor_view`), and the points lying in space the other sensor looked through. No pose is
returned without proof:

1. hypotheses: the CAD registration's search (`inspection.registration.register`: RSCS
   spheres, FPFH and SHOT, SAC-IA, with the other view as the model and its fitness gate
   opened, since a view is no subset of another) gives its pose and its near-equal
   alternatives, each with its half turns about the source's principal axes (what a
   prismatic or symmetric part is confused with); the views' face directions give more
   (`pose_search`: what descriptors miss when the views share mostly planes). All are
   ranked by the evidence at a voxel's tolerance on a few hundred points, the `ROUGH` best
   refined by a short ICP on the voxel grid and ranked again, and the `REFINED` best
   distinct ones go on;
2. each is refined on the overlap (`pairwise.refine_pair`: point-to-plane ICP against the
   target at full density, its nearest neighbours find the surface itself where a pixel
   would find what hides it, so it gets in from a voxel or two off), then on what the
   sensors measured (`projective`: point-to-plane on the pixels each view's points fall
   on, both ways), and judged both ways on points half a voxel apart; the best score
   (agreeing less contradicting points) among the poses the noise allows (below) leads.
   A refinement may stall on a motion the overlap barely fixes (views sharing a boss and
   planes across it leave the turn about the boss to a few edge points): the leader is
   probed, restarted `PROBE_MM` either way along its `PROBED` weakest motions
   (`constraint`) and refined again; a probe that settles elsewhere and scores better leads instead (at most
   `ROUNDS` times). Then the leader climbs along each of its six constraint motions,
   unrefined, by steps from a resolution halving down (`_climb`): a move whose residuals fit
   better leads instead. ICP's minimum is not the evidence's: along a motion few partners
   fix, their normals' errors pull it (a turntable pair of the NIST CTC-01 stopped 0.16 mm
   from the truth along a flat face, where the evidence ranked the truth 2.8 standard errors
   better, and every restart stopped there too). Last, each motion is bounded both ways
   (`_bounds`): the least step at which the evidence ranks the moved pose below the leader
   (below, by the test of the ambiguity refusal); the `spread` reaches those bounds, so it
   is the pose's uncertainty as the evidence itself states it (at 1e-3 a side), not the
   restarts' scatter, which is nil when all restarts settle in one minimum;
3. the leader is refused (`PairNotProven`, exit 1 from `register`), naming why, when
   - a view says nothing of where its sensor was (a cloud without a viewpoint): what it
     could have seen cannot be predicted;
   - the agreeing partners leave a motion free: the pose's covariance (the inverse of its
     point-to-plane information over the noise) puts a motion's standard deviation, times
     z = 3.29 (two-sided 1e-3), beyond the resolution (`resolution_deg`, `resolution_mm`:
     poses closer than that are one answer). Too small an overlap ends here, named;
   - the comparable points agree less than the noise allows: fewer than p0 = 0.9973 of
     them (K = 3 sigmas) less z = 3.09 binomial standard errors (a right pose is refused
     so with probability 1e-3 when the noise model holds);
   - the leader moved a resolution along one of its motions (the top of its ladder) is
     still allowed by the noise
     (its points agree as a right pose's would, above) and scores within z = 3.29
     standard errors of it both by its points (agreeing less contradicting) and by its
     residuals' sizes (`Evidence.sharper`; each tested at half the false-accept rate):
     the evidence does not fix that motion as well as claimed (the information's standard
     deviation assumes the residuals follow the noise; a flat score says they do not, or
     that the overlap leaves the motion to points outside it: a sphere's turns);
   - a distinct pose (beyond the resolution) that the noise allows scores within z = 3.29
     standard errors of the leader's, both ways (the score differences under
     re-measurement noise): the
     evidence does not tell them apart (a symmetric part, or views sharing only a plane and
     a cylinder), and preferring the leader would be wrong with probability above 1e-3 if
     the other were right. The alternatives are named (pose, score, how far apart).
   The leader is the best-scoring pose among those the noise allows (a half turn of a
   nearly symmetric part may agree on more points while contradicting 2 % of them: refuted
   whatever its overlap); the pose reported is the mean of it and the poses tried that the
   evidence cannot rank below it (`spread`: how far they and each motion's bounds lie from
   it).

Transforms map SOURCE points onto the TARGET's frame; mm, degrees.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.special import ndtri

from inspection.errors import CloudError, RegistrationFailed
from inspection.measured_cloud import ScanCloud, fit_plane
from inspection.registration import ModelTarget, RegistrationSettings, icp, register
from inspection.registration.clouds import voxel_grid
from inspection.registration.settings import DEFAULT_REGISTRATION_SETTINGS
from inspection.views.align import pose_error
from inspection.views.constraint import Constraint, along
from inspection.views.pair_evidence import K_SIGMA, P_AGREE, Evidence, evidence, score_only
from inspection.views.pairwise import PairSettings, paired, refine_pair, thin
from inspection.views.pose_search import face_poses
from inspection.views.projective import refine_projective
from inspection.views.quiet import stdout_to_stderr
from inspection.views.sensor_view import SensorView
from scanner.geometry import Pinhole

PROBED, PROBE_MM, ROUNDS = 2, 1.0, 2  # the weakest motions probed, how far (mm at the overlap's RMS radius), rounds
ROUGH, REFINED, ROUGH_POINTS = 24, 4, 400  # starts refined roughly, then fully; points judging them roughly
CLIMBS = 4  # moves of one step along a constraint's motion toward a better fit, per step length
MAX_HALVINGS = 12  # a ladder's steps: the resolution halved at most this often (0.5 mm -> 0.12 um)
CLIMB_HALVINGS = 4  # the climb's last step: a sixteenth of the resolution (finer offsets stay inside the spread)
SAME_START_DEG = 1.0  # starts closer than 2 of these and 2 voxels are one start
OPEN_GATE = 1e-9  # the CAD search's min_fitness when a view is the target (settings refuse 0)
SUPPORT_PLANE = 0.01  # a support plane's RANSAC band, as a share of the view's extent

Judging = tuple[np.ndarray, np.ndarray, SensorView]  # the points a view's evidence is counted on, and its sensor


@dataclass(frozen=True)
class ViewPairSettings:
    """`resolution_deg`/`resolution_mm` (at the source's centre): poses closer than both are
    one answer; `false_accept`: the chance of preferring the leader over a distinct pose
    that is right, allowed per alternative; `false_refuse`: the chance of refusing a right
    pose for its disagreeing points; `motion_risk`: two-sided, a motion's excursion beyond
    the resolution allowed with this chance."""

    resolution_deg: float = 0.3
    resolution_mm: float = 0.5
    false_accept: float = 1e-3
    false_refuse: float = 1e-3
    motion_risk: float = 1e-3

    def __post_init__(self) -> None:
        if not (self.resolution_deg > 0 and self.resolution_mm > 0
                and all(0 < p < 0.5 for p in (self.false_accept, self.false_refuse, self.motion_risk))):
            raise ValueError(f"view-pair settings out of range: {self}")


@dataclass(frozen=True, eq=False)
class Alternative:
    """A distinct pose the evidence was weighed against: `deg`/`mm` from the leader, its
    `score`, how many standard errors the leader's is above it (`z`), and whether its
    points agree as the noise allows (`consistent`; a pose they refute is no rival)."""

    transform: np.ndarray
    deg: float
    mm: float
    score: float
    z: float
    consistent: bool

    def as_dict(self) -> dict[str, Any]:
        return {"transform": self.transform.tolist(), "deg_from_best": self.deg, "mm_from_best": self.mm,
                "score": self.score, "best_above_by_se": self.z, "allowed_by_the_noise": self.consistent}


@dataclass(frozen=True, eq=False)
class ViewPair:
    """The leading pose and its evidence: `transform` source -> target; `proven` with the
    `refusals` (why not) otherwise; `overlap` the share of the source the target's sensor
    measured at that pose (`overlap_given`: the user's figure instead); `fitness` the share
    of comparable points that agree; `rmse_mm` theirs; `sigma_mm` the pair's noise;
    `spread` (deg, mm) how far the poses the evidence cannot rank below the leader lie from
    `transform` (the restarts alike, and each motion's bounds: the pose's uncertainty);
    `alternatives` every distinct pose weighed (`ambiguous`: one is not told apart);
    `weakest_motion` the least fixed motion and `weakest_sd` the largest rotation and
    translation standard deviations (deg, mm at the overlap's centre)."""

    transform: np.ndarray
    proven: bool
    refusals: tuple[str, ...]
    overlap: float
    overlap_given: bool
    fitness: float
    rmse_mm: float
    sigma_mm: float
    comparable: int
    score: float
    spread: tuple[float, float]
    alternatives: tuple[Alternative, ...]
    ambiguous: bool
    weakest_motion: str
    weakest_sd: tuple[float, float]
    method: str
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def inlier_mm(self) -> float:
        """The agreement band: K pair sigmas (mm)."""
        return K_SIGMA * self.sigma_mm

    def as_dict(self) -> dict[str, Any]:
        return {"transform": self.transform.tolist(), "proven": self.proven, "refusals": list(self.refusals),
                "fitness": self.fitness, "rmse": self.rmse_mm, "overlap": self.overlap,
                "overlap_given": self.overlap_given, "sigma_mm": self.sigma_mm, "comparable_points": self.comparable,
                "score": self.score, "spread_deg": self.spread[0], "spread_mm": self.spread[1],
                "ambiguous": self.ambiguous,
                "alternatives": [a.as_dict() for a in self.alternatives],
                "weakest_motion": {"motion": self.weakest_motion, "sd_deg": self.weakest_sd[0],
                                   "sd_mm": self.weakest_sd[1]},
                "method": self.method, "timings_s": self.timings_s}

    def text(self, source: str, target: str) -> str:
        """What `slscan register` prints for people."""
        with np.printoptions(precision=6, suppress=True, floatmode="fixed"):
            matrix = str(self.transform)
        head = (f"transform taking {source} onto {target} (mm):\n{matrix}" if self.proven else
                f"NOT MEASURED: no pose of {source} in {target} is proven ({'; '.join(self.refusals)}); the best "
                f"(not a result):\n{matrix}")
        return (f"{head}\noverlap {self.overlap:.0%} of the scan ({'given' if self.overlap_given else 'predicted'}); "
                f"{self.fitness:.2%} of the {self.comparable} points each sensor could judge agree within 3 sigma "
                f"({self.inlier_mm:.3g} mm), RMSE {self.rmse_mm:.4f} mm; poses the evidence cannot rank lie within "
                f"{self.spread[0]:.3f} deg / {self.spread[1]:.3f} mm; {len(self.alternatives)} distinct alternatives "
                f"weighed; {self.method}")


class PairNotProven(RegistrationFailed):
    """The views' evidence does not prove a pose: `pair` holds the leading pose, why it was
    refused and the alternatives."""

    def __init__(self, source: str, pair: ViewPair) -> None:
        super().__init__(f"{source}: no pose proven: {'; '.join(pair.refusals)}", pair.fitness, pair.rmse_mm)
        self.pair = pair


def support_mask(scan: ScanCloud, seed: int = 0) -> np.ndarray:
    """Which points are not the table or platter the part stands on: the dominant plane
    (RANSAC, a band of `SUPPORT_PLANE` of the view's extent) is a support when more of the
    other points lie on the sensor's side of it than behind it (a part stands on its support;
    a face of the part has the rest of the part behind it), and then it and all behind it
    go; whatever the part's size or the cloud's frame. All points stay without a viewpoint
    (which side is the sensor's is unknown) or when the plane is no support."""
    keep = np.ones(len(scan), bool)
    if scan.viewpoint is None:
        return keep
    band = SUPPORT_PLANE * float(np.linalg.norm(np.ptp(scan.points, axis=0)))
    plane, on = fit_plane(scan.points, band, seed)
    d = scan.points @ plane[:3] + plane[3]
    d *= np.sign(scan.viewpoint @ plane[:3] + plane[3]) or 1.0
    front, behind = ~on & (d > band), ~on & (d < -band)
    if front.sum() >= 500 and front.sum() > behind.sum():
        return front
    return keep


def without_support(scan: ScanCloud, seed: int = 0) -> ScanCloud:
    """The view without the table or platter the part stands on (`support_mask`)."""
    return scan.subset(support_mask(scan, seed))


def session_camera(scan: ScanCloud) -> Pinhole | None:
    """The camera of the session a cloud was loaded from (`load_session`: camera frame, every
    point on its pixel), None for a cloud file."""
    from scanner.session import Session

    if scan.pixels is None or not Path(scan.source).is_dir():
        return None
    return Session.open(scan.source).rig_model().camera


def register_view_pair(scan: ScanCloud, target: ScanCloud, overlap: float | None = None,
                       settings: RegistrationSettings = DEFAULT_REGISTRATION_SETTINGS, *, isolate: bool = False,
                       pair: ViewPairSettings = ViewPairSettings()) -> ViewPair:
    """The pose of view `scan` in view `target` (see the module docstring), or
    PairNotProven. `isolate`: the part is taken off its support in each view first (the
    whole view still says what its sensor saw); `overlap` (a share of `scan`): the user's
    figure, reported in place of the model's."""
    pose = weigh_view_pair(scan, target, overlap, settings, isolate=isolate, pair=pair)
    if not pose.proven:
        raise PairNotProven(scan.source, pose)
    return pose


def weigh_view_pair(scan: ScanCloud, target: ScanCloud, overlap: float | None = None,
                    settings: RegistrationSettings = DEFAULT_REGISTRATION_SETTINGS, *, isolate: bool = False,
                    pair: ViewPairSettings = ViewPairSettings()) -> ViewPair:
    """`register_view_pair`'s leading pose with its evidence, proven or not. Open3D's
    prints go to standard error meanwhile (stdout may be a command's JSON)."""
    if overlap is not None and not 0 < overlap <= 1:
        raise ValueError(f"overlap must be a share in (0, 1], got {overlap}")
    with stdout_to_stderr():
        return _weigh(scan, target, overlap, settings, isolate, pair)


def _weigh(scan: ScanCloud, target: ScanCloud, overlap: float | None, settings: RegistrationSettings, isolate: bool,
           pair: ViewPairSettings) -> ViewPair:
    t0 = time.perf_counter()
    views = [SensorView.build(s, session_camera(s)) for s in (scan, target)]
    missing = [s.source for s, v in zip((scan, target), views) if v is None]
    if missing:
        raise CloudError(", ".join(missing), "no viewpoint: what the other view's points should look like to this "
                                             "sensor cannot be predicted; give the session, or the cloud in its "
                                             "camera's frame (every point in front of the origin)")
    sv, tv = views
    assert sv is not None and tv is not None
    keep = [support_mask(s, settings.seed) if isolate else np.ones(len(s), bool) for s in (scan, target)]
    parts = [s.subset(k) for s, k in zip((scan, target), keep)]
    times = {"views": time.perf_counter() - t0}
    t0 = time.perf_counter()
    model = ModelTarget.from_cloud(parts[1])
    voxel = model.voxel_mm
    judged = [_judged_points(s, k, v, voxel) for s, k, v in zip((scan, target), keep, (sv, tv))]
    fine = [_judged_points(s, k, v, 0.5 * voxel) for s, k, v in zip((scan, target), keep, (sv, tv))]
    starts = _hypotheses(parts[0], model, judged, settings)
    times["search"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    centre = parts[0].points.mean(axis=0)

    source = paired(parts[0].points, parts[0].normals, thin(parts[0].points, voxel))
    dense = paired(parts[1].points, parts[1].normals, np.arange(len(parts[1])))
    icp_settings = PairSettings(voxel_mm=voxel, max_distance_mm=2.0 * voxel, min_distance_mm=0.02)

    def weigh(T: np.ndarray) -> Evidence:
        near = refine_pair(source, dense, T, icp_settings).transform
        return evidence(refine_projective(near, judged[0], judged[1], 0.5 * voxel), fine[0], fine[1])

    z_refuse = float(ndtri(1.0 - pair.false_refuse))
    tried = [weigh(T) for T in starts]
    best = max(tried, key=lambda e: _rank(e, z_refuse))
    for _ in range(ROUNDS):
        probes = [weigh(along(best.constraint, k, s) @ best.transform) for k in range(PROBED)
                  for s in (-PROBE_MM, PROBE_MM)]
        tried += probes
        better = max(probes, key=lambda e: _rank(e, z_refuse))
        if _rank(better, z_refuse) <= _rank(best, z_refuse) or \
                not _distinct(better.transform, best.transform, centre, pair):
            break
        best = better
    ladders = _ladders(best, centre, pair)
    best = _climb(best, ladders, fine, tried)
    bounds = _bounds(best, ladders, fine, pair)
    times["judge"] = time.perf_counter() - t0
    method = "rscs+" + "+".join(settings.descriptors) + f"+{settings.coarse}+face-directions+projective+sensor-evidence"
    return _verdict(best, tried, bounds, centre=centre, overlap=overlap, pair=pair, method=method,
                    times={k: round(v, 3) for k, v in times.items()})


@dataclass(frozen=True, eq=False)
class Ladder:
    """Steps along one motion of a constraint (`constraint`, eigenvector `k`), in mm at its
    RMS radius: `steps[0]` takes the pose a resolution away (`resolution_deg` or
    `resolution_mm` at the source's centre, whichever it reaches first), each next one half
    the last, down to the motion's noise floor (its standard deviation from the point-to-
    plane information, below which the evidence cannot rank two poses)."""

    constraint: Constraint
    k: int
    steps: tuple[float, ...]

    def move(self, step: float) -> np.ndarray:
        return along(self.constraint, self.k, step)


@dataclass(frozen=True, eq=False)
class Bound:
    """How far along a ladder's motion the evidence ranks poses below the leader: `steps`
    (mm at the constraint's radius, per side -/+) the least step of the ladder at which it
    does, None when not even the resolution's; `at_resolution` the poses a resolution away."""

    ladder: Ladder
    steps: tuple[float | None, float | None]
    at_resolution: tuple[Evidence, Evidence]


def _ladders(best: Evidence, centre: np.ndarray, pair: ViewPairSettings) -> list[Ladder]:
    """A Ladder per motion of the leader's constraint (module docstring, step 2). The floor
    is sigma / sqrt(partners x eigenvalue) (the constraint's eigenvalues are per partner);
    at most `MAX_HALVINGS` halvings."""
    c = best.constraint
    partners = max(int(best.forward.agree.sum()), 1)
    out = []
    for k in range(6):
        deg, mm = pose_error(np.eye(4), along(c, k, 1.0), centre)
        top = min(pair.resolution_deg / max(deg, 1e-12), pair.resolution_mm / max(mm, 1e-12))
        floor = best.forward.sigma_mm / np.sqrt(max(partners * float(c.eigenvalues[k]), 1e-300))
        halvings = int(np.clip(np.ceil(np.log2(max(top / floor, 1.0))), 0, MAX_HALVINGS))
        out.append(Ladder(c, k, tuple(top / 2.0 ** m for m in range(halvings + 1))))
    return out


def _climb(best: Evidence, ladders: list[Ladder], fine: list[Judging], tried: list[Evidence]) -> Evidence:
    """The leader moved down each ladder toward what the evidence fits best (module
    docstring, step 2): at each step, either way while the moved pose's residuals fit
    better (`Evidence.sharper`; at most `CLIMBS` moves a step), then the next, half as long,
    down to a `CLIMB_HALVINGS`-fold halving of the resolution: an offset left below that
    lies inside the bounds the spread reports (`_bounds` reach every pose the evidence does
    not rank below the leader, the better-fitting ones too), at 2 evidence evaluations a
    step. The poses left go to `tried`."""
    for ladder in ladders:
        for step in ladder.steps[:CLIMB_HALVINGS + 1]:
            for _ in range(CLIMBS):
                moved = [evidence(ladder.move(s) @ best.transform, fine[0], fine[1]) for s in (-step, step)]
                top = min(moved, key=lambda e: best.sharper(e))
                if best.sharper(top) >= 0.0:
                    break
                tried.append(best)
                best = top
    return best


def _bounds(best: Evidence, ladders: list[Ladder], fine: list[Judging], pair: ViewPairSettings) -> list[Bound]:
    """Per motion and side, the least ladder step whose pose the evidence ranks below the
    leader (refuted by its points, or `_apart` by z = 3.29 standard errors: a right pose
    that far off would rank so with probability 1e-3 / 2), found by bisection on the
    ladder (taken as monotone); None when the resolution's step is not ranked below."""
    z_accept, z_refuse = float(ndtri(1.0 - pair.false_accept / 2.0)), float(ndtri(1.0 - pair.false_refuse))

    def at(ladder: Ladder, step: float) -> Evidence:
        return evidence(ladder.move(step) @ best.transform, fine[0], fine[1])

    def below(e: Evidence) -> bool:
        return not consistent(e, z_refuse) or _apart(best, e) >= z_accept

    out = []
    for ladder in ladders:
        ends = (at(ladder, -ladder.steps[0]), at(ladder, ladder.steps[0]))
        sides: list[float | None] = []
        for sign, end in zip((-1.0, 1.0), ends):
            if not below(end):
                sides.append(None)
                continue
            ranked, unranked = 0, len(ladder.steps)  # steps[ranked] is ranked below; steps[unranked:] unknown
            while unranked - ranked > 1:
                mid = (ranked + unranked) // 2
                if below(at(ladder, sign * ladder.steps[mid])):
                    ranked = mid
                else:
                    unranked = mid
            sides.append(ladder.steps[ranked])
        out.append(Bound(ladder, (sides[0], sides[1]), ends))
    return out


def _hypotheses(scan: ScanCloud, model: ModelTarget, judged: list[Judging],
                settings: RegistrationSettings) -> list[np.ndarray]:
    """The `REFINED` most promising starting poses: the CAD search's pose and alternatives,
    each with its half turns about the source's principal axes through its centroid, and
    the poses from the views' face directions (`pose_search`); ranked by the evidence at a
    voxel's tolerance on a few hundred points, the `ROUGH` best refined by a short ICP on
    the voxel grid and ranked again at half a voxel's, each pose once."""
    try:
        found = register(scan, model, replace(settings, min_fitness=OPEN_GATE))
        searched = [found.transform, *found.alternatives]
    except RegistrationFailed:
        searched = []
    c = scan.points.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((scan.points - c).T))
    flips = [np.eye(4)]
    for a in axes.T:
        F = np.eye(4)
        F[:3, :3] = 2.0 * np.outer(a, a) - np.eye(3)  # a half turn about a
        F[:3, 3] = c - F[:3, :3] @ c
        flips.append(F)
    v = model.voxel_mm
    grid = voxel_grid(scan.points, scan.normals, v)
    starts = [T @ F for T in searched for F in flips] + list(face_poses(grid, (model.coarse.points,
                                                                             model.coarse.normals), v, settings.seed))
    rng = np.random.default_rng(settings.seed)
    few = [_few(j, rng) for j in judged]
    first = sorted(starts, key=lambda T: -_rough(T, few, v))[:ROUGH]
    pick = rng.choice(len(grid[0]), size=min(1500, len(grid[0])), replace=False)
    refined = [icp(grid[0][pick], grid[1][pick], model.coarse, T=T, max_dist=8.0 * v, min_dist=0.5 * v,
                   max_normal_deg=30.0, iterations=20) for T in first]
    kept: list[np.ndarray] = []
    for T in sorted(refined, key=lambda T: -_rough(T, few, 0.5 * v)):  # the same pose found twice counts once
        if all(max(pose_error(T, U, c)[0] / SAME_START_DEG, pose_error(T, U, c)[1] / v) > 2.0 for U in kept):
            kept.append(T)
    return kept[:REFINED]


def _few(j: Judging, rng: np.random.Generator) -> Judging:
    pick = rng.choice(len(j[0]), size=min(ROUGH_POINTS, len(j[0])), replace=False)
    return j[0][pick], j[1][pick], j[2]


def _rough(T: np.ndarray, few: list[Judging], sigma_mm: float) -> float:
    """The evidence score of pose T with a noise of `sigma_mm` (a coarse pose's error)."""
    (sp, sn, sv), (tp, tn, tv) = few
    return score_only(T, (sp, sn, replace(sv, sigma_mm=sigma_mm)), (tp, tn, replace(tv, sigma_mm=sigma_mm)))


def _judged_points(scan: ScanCloud, keep: np.ndarray, view: SensorView, spacing_mm: float) -> Judging:
    """The points of a view its evidence is counted on: the part's, measured at smooth
    pixels of the view's own sensor, one per `spacing_mm` cube (a voxel to search and
    refine, half a voxel to judge)."""
    ok = np.flatnonzero(keep & view.point_smooth)
    pick = ok[thin(scan.points[ok], spacing_mm)]
    return scan.points[pick], scan.normals[pick], view


def _distinct(a: np.ndarray, b: np.ndarray, centre: np.ndarray, pair: ViewPairSettings) -> bool:
    deg, mm = pose_error(a, b, centre)
    return deg > pair.resolution_deg or mm > pair.resolution_mm


def _verdict(best: Evidence, tried: list[Evidence], bounds: list[Bound], *, centre: np.ndarray,
             overlap: float | None, pair: ViewPairSettings, method: str, times: dict[str, float]) -> ViewPair:
    """The pose the evidence supports with every refusal it calls for (see the module
    docstring): the mean of the poses that score within z standard errors of the best (the
    evidence cannot rank them), refused when one of them lies beyond the resolution, or when
    the best moved a resolution away along a motion scores as well (`bounds`). Its spread
    reaches every such pose and each motion's bound, both ways."""
    z_accept, z_refuse = float(ndtri(1.0 - pair.false_accept / 2.0)), float(ndtri(1.0 - pair.false_refuse))
    z_motion = float(ndtri(1.0 - pair.motion_risk / 2.0))
    alike = [best] + [e for e in tried if e is not best and consistent(e, z_refuse) and _apart(best, e) < z_accept]
    pose = _mean_pose([e.transform for e in alike], centre)
    spread = [pose_error(pose, e.transform, centre) for e in alike]
    spread += [pose_error(pose, b.ladder.move(sign * step) @ best.transform, centre) for b in bounds
               for sign, step in zip((-1.0, 1.0), b.steps) if step is not None]
    alternatives: list[Alternative] = []
    for e in sorted(tried, key=lambda e: -e.score):
        if _distinct(e.transform, pose, centre, pair) and \
                all(_distinct(e.transform, a.transform, centre, pair) for a in alternatives):
            deg, mm = pose_error(pose, e.transform, centre)
            alternatives.append(Alternative(e.transform, deg, mm, e.score, _apart(best, e),
                                            consistent(e, z_refuse)))
    refusals = []
    motion, sd = _weakest(best)
    n = best.comparable
    if n == 0:
        refusals.append("at the best pose no point of either view falls where the other's sensor measured a surface: "
                        "no overlap to judge")
    elif sd[0] * z_motion > pair.resolution_deg or sd[1] * z_motion > pair.resolution_mm:
        refusals.append(f"the overlap leaves the {motion} free (standard deviation {sd[0]:.3g} deg / {sd[1]:.3g} mm "
                        f"from {best.agreeing} agreeing points; resolution {pair.resolution_deg:g} deg / "
                        f"{pair.resolution_mm:g} mm)")
    floor = _agree_floor(n, z_refuse)
    if n and best.fitness < floor:
        refusals.append(f"only {best.fitness:.2%} of the {n} points each view's sensor could judge agree with it "
                        f"within 3 sigma = {3 * best.forward.sigma_mm:.3g} mm (the noise lets at least {floor:.2%}): "
                        f"the views disagree at this pose")
    rivals = [a for a in alternatives if a.consistent and a.z < z_accept]
    loose = [(e, b.ladder) for b in bounds for e, step in zip(b.at_resolution, b.steps) if step is None]
    by_motion: dict[int, list[Evidence]] = {}  # both sides of one motion: one reason
    for e, ladder in loose:
        by_motion.setdefault(id(ladder), []).append(e)
    ladders = {id(ladder): ladder for _, ladder in loose}
    for key, moved in list(by_motion.items())[:2]:
        sides = []
        for e, way in zip(moved, ("one way", "the other way")):
            deg, mm = pose_error(best.transform, e.transform, centre)
            sides.append(f"moved {deg:.2f} deg / {mm:.2f} mm {way} along it the pose scores {e.score:.4f}, only "
                         f"{_apart(best, e):.1f} standard errors worse at most")
        refusals.append(f"the evidence does not fix the {ladders[key].constraint.describe(ladders[key].k)} to the "
                        f"resolution: {'; '.join(sides)} (against {best.score:.4f}, score and residual fit; "
                        f"needs {z_accept:.2f})")
    alternatives += [Alternative(e.transform, *pose_error(pose, e.transform, centre), e.score, _apart(best, e),
                                 consistent(e, z_refuse)) for e, _ in loose]
    if rivals:
        refusals.append("ambiguous: " + "; ".join(
            f"a pose {a.deg:.2f} deg / {a.mm:.2f} mm away scores {a.score:.4f} against {best.score:.4f} "
            f"({a.z:.1f} standard errors below, needs {z_accept:.2f})" for a in rivals[:3])
            + f" (resolution {pair.resolution_deg:g} deg / {pair.resolution_mm:g} mm)")
    return ViewPair(pose, not refusals, tuple(refusals), overlap if overlap is not None else best.overlap,
                    overlap is not None, best.fitness, best.rmse_mm, best.forward.sigma_mm, n, best.score,
                    (max(d for d, _ in spread), max(m for _, m in spread)), tuple(alternatives), bool(rivals or loose),
                    motion, sd, method, times)


def _agree_floor(comparable: int, z_refuse: float) -> float:
    """The least share of `comparable` points a right pose agrees on (at the false-refuse
    rate whose z is `z_refuse`): p0 less z binomial standard errors."""
    return P_AGREE - z_refuse * np.sqrt(P_AGREE * (1.0 - P_AGREE) / max(comparable, 1))


def consistent(e: Evidence, z_refuse: float) -> bool:
    """Whether the points each sensor can judge agree with pose `e` as the noise allows."""
    return bool(e.comparable > 0 and e.fitness >= _agree_floor(e.comparable, z_refuse))


def _rank(e: Evidence, z_refuse: float) -> tuple[bool, float]:
    """Poses the noise allows first, then by score: a pose contradicting more points than
    noise can (2 % at a symmetric part's half turn) is refuted whatever its overlap, and a
    right pose of a smaller overlap must not lose to it on agreeing points."""
    return consistent(e, z_refuse), e.score


def _apart(best: Evidence, other: Evidence) -> float:
    """How far the evidence puts `best` above `other`, in standard errors: the larger of the
    score's (points agreeing less contradicting) and the residuals' (`Evidence.sharper`)
    difference; each is tested at half the false-accept rate, so either may decide."""
    return max(best.beats(other), best.sharper(other))


def _mean_pose(poses: list[np.ndarray], centre: np.ndarray) -> np.ndarray:
    """The mean of nearby poses: their rotations' mean, and the mean place they move
    `centre` to."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_matrix(np.stack([T[:3, :3] for T in poses])).mean().as_matrix()
    moved = np.mean([T[:3, :3] @ centre + T[:3, 3] for T in poses], axis=0)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, moved - R @ centre
    return T


def _weakest(e: Evidence) -> tuple[str, tuple[float, float]]:
    """The least fixed motion (in words) and its standard deviation (deg, mm) from the
    pose's information; infinite when the partners leave it free."""
    H = e.information
    values, vectors = np.linalg.eigh(H)
    if values[-1] <= 0 or values[0] <= values[-1] * 1e-12:
        return e.constraint.describe(0), (float("inf"), float("inf"))
    cov = vectors @ np.diag(1.0 / values) @ vectors.T
    sd_deg = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1])))
    sd_mm = float(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:])[-1]))
    return e.constraint.describe(0), (sd_deg, sd_mm)
