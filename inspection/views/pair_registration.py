"""Registering one view of a part to another view of it, with no pose known: what
`slscan register SCAN CLOUD` does when the target is a cloud.

Two views of one part overlap only in part: the source is not a subset of the target, so
judging a pose by the share of the whole source lying on the target (as against a CAD
model) refuses right poses. Here:

1. the search is the CAD registration's (`inspection.registration.register`: RSCS
   spheres, FPFH and SHOT descriptors, SAC-IA, hypotheses refined by ICP and verified, the
   target being the other view), with its fitness gates opened;
2. the pose is refined on the overlap (`pairwise.refine_pair`: point-to-plane ICP, partners
   near the noise only, against the target at full density);
3. the overlap is estimated: `overlap` is the share of the source within `region` (two
   voxels) of the target, i.e. where the target has surface at all; the fit is judged on it
   alone: `fitness` is the share of those points within `inlier_mm` of the target (half a
   voxel) with normals agreeing. A wrong pose that lays the views across each other puts
   many points near the target but few on it; a right one puts its overlap on it.
   `overlap` given (`--overlap 0.4`) replaces the estimate: fitness = inliers / (given
   overlap x points), for views whose overlap is known;
4. free space: laying one big face of a view onto another's fits an overlap well at a
   wrong pose, but then parts of the source lie in front of surfaces the target's sensor
   saw through that space, or parts of the target in front of what the source's sensor saw
   (`free_space_violations`, both ways, for views that know their viewpoint). Judged on the
   target's own pixels (a session's cloud), the true poses of the 1280 x 1024 turntable
   views 45-135 deg apart show at most 0.013 % (limit 0.1 %), wrong ones 0.2-8 %; judged in
   ray bins (a cloud file) true poses showed up to 0.23 % there (limit 0.2 %);
5. ambiguity: a pose that a symmetric part's other views explain as well shows no free-space
   violation (a turn of 180 deg on 135-deg views of the demo part: 0 %, fitness 0.878
   where the true pose would score 0.862), and the search then never proposed the true one
   but ranked distinct poses within its ambiguity margin: such a pair is refused. Of the 24
   pairs 45-135 deg apart of a 1280 x 1024 turntable scan, the search flagged that 135-deg
   pair (as on an older scan), one wrong 90-deg pose (refused anyway) and one right 90-deg
   pose (0.22 deg off: the price); no 45-deg pair;
6. a pose the overlap barely fixes: two views 90 deg apart may share little more than the
   boss (a cylinder) and the top faces (planes across its axis), which leave the turn about
   the boss's axis to the few points on the edges. ICP, its partner distance shrinking to
   the noise, drops those points as outliers once they lie a little off, and stalls: pair
   0 -> 2 of the 8-view 1280 x 1024 turntable scan settled 1.18 deg / 0.51 mm off, at
   fitness 0.887 with 0.02 % in front, where the truth refines to 0.901 and 0 %. The
   overlap's information on the pose (`constraint.overlap_constraint`, eigenvalues of the
   scaled 6x6 point-to-plane information per partner) names the weak motions, but its
   smallest-to-largest ratio does not tell a stalled pose from a right one (the 24 pairs
   45-135 deg apart: right poses 0.0026-0.071, the stalled one 0.0035). So the kept pose is
   probed: started `PROBE_MM` either way along each of its `PROBED` weakest motions and
   refined again; a start that settles elsewhere (beyond `SAME_DEG` / `SAME_MM`) and fits
   better (fitness less violations) shows ICP stalled on a motion the overlap barely
   fixes, and the pair is refused, naming that motion. On those 24 pairs the probes of the
   wrong poses (0 -> 2 at 90 deg; 2 -> 5 at 135 deg, refused by free space anyway)
   settled 0.8-1.2 deg away and fitted 0.008-0.014 better; those of right poses settled
   at the same pose (within 0.11 deg), or elsewhere (0.5-1.2 deg) fitting 0.0016-0.012
   worse; one right pose 0.67 deg off (135 deg) had a probe settle 0.03 deg
   from the truth fitting 0.005 better, and is refused.

The search's best pose and its near-equal alternatives are each refined (point-to-plane ICP,
partners no nearer than the target's sample spacing) and judged; the one with the best
fitness less violations is kept, and refused (RegistrationFailed, with the figures) when
fitness < `min_fitness`, the overlap < `min_overlap`, more than `max_violations` of the
source lies in front of the target's surface, the search was ambiguous or (those passed) a
probe along a weak motion fits better. Transforms map SOURCE
points onto the TARGET's frame; mm.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from inspection.errors import RegistrationFailed
from inspection.measured_cloud import ScanCloud, fit_plane, part_mask
from inspection.registration import ModelTarget, RegistrationSettings, register, transform_points
from inspection.views.align import pose_error
from inspection.views.constraint import Constraint, along, overlap_constraint
from inspection.views.pairwise import PairSettings, PairView, paired, refine_pair, thin
from scanner.geometry import Pinhole

MIN_FITNESS = 0.8
MIN_OVERLAP = 0.1
MAX_VIOLATIONS = 0.002  # in front of the target's surface, judged in ray bins (a cloud file target)
MAX_VIOLATIONS_ON_PIXELS = 0.001  # ... judged on the target's own pixels (a session target)
PROBED, PROBE_MM = 2, 1.0  # the weakest motions probed, how far (mm at the overlap's RMS radius)
SAME_DEG, SAME_MM = 0.2, 0.2  # a probe settling nearer is the same pose
OPEN_GATE = 1e-9  # the CAD search's min_fitness when a view is the target (settings refuse 0)


@dataclass(frozen=True, eq=False)
class ViewPair:
    """`transform` source -> target; `overlap` estimated (or given: `overlap_given`);
    `fitness` on the overlap; `rmse_mm` of the inliers; `inlier_mm`, `region_mm` used."""

    transform: np.ndarray
    overlap: float
    overlap_given: bool
    fitness: float
    rmse_mm: float
    inlier_mm: float
    region_mm: float
    violations: float
    method: str
    ambiguous: bool
    timings_s: dict[str, float]


def without_support(scan: ScanCloud, seed: int = 0) -> ScanCloud:
    """The view without the table or platter the part stands on: its dominant plane, when
    that plane spreads wider than 1.3 times the rest (`measured_cloud.part_mask`, with the
    rest's extent for the model's); the view as it is otherwise. A square platter turning
    with the part would otherwise register four ways."""
    _, plane = fit_plane(scan.points, 0.01 * float(np.linalg.norm(np.ptp(scan.points, axis=0))), seed)
    rest = ~plane
    if rest.sum() < 500:
        return scan
    diagonal = float(np.linalg.norm(np.ptp(scan.points[rest], axis=0)))
    if np.linalg.norm(np.ptp(scan.points[~rest], axis=0)) <= 1.3 * diagonal:
        return scan
    return scan.subset(part_mask(scan, diagonal, seed))


def free_space_violations(points: np.ndarray, target: ScanCloud, tolerance_mm: float,
                          camera: Pinhole | None = None, cell: float = 4e-4) -> float:
    """The share of `points` (target frame) that lie in front of the target's surface as its
    sensor saw it: on a ray from the target's viewpoint, nearer than the surface it hit by
    more than `tolerance_mm`. Such a point would have hidden that surface from the target's
    sensor, so the pose that put it there is wrong. A point on a ray the target saw no
    surface on counts as no violation. 0 without a viewpoint.

    With the target's `camera` (a session cloud: camera frame, every point on its pixel) the
    points are projected into the target's own image: a point is in front where the target
    measured that pixel and its 3 x 3 neighbourhood and the point is nearer than every one of
    those nine surfaces (the edge of what the target measured is no evidence: at the true
    poses of 1280 x 1024 views every such point lay on the target's last measured pixel
    beside a silhouette, 4-28 mm in front of the far side). Without one, rays are binned by
    direction (x/z, y/z from the viewpoint, bins of `cell`, about a camera pixel at 2500 px
    focal length): a bin mixes a silhouette's near and far surfaces and true poses of
    1280 x 1024 views show up to 0.23 % there."""
    if target.viewpoint is None or len(points) == 0:
        return 0.0
    if camera is not None and target.pixels is not None:
        return _in_front_on_pixels(points, target, tolerance_mm, camera)

    def rays(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v = p - target.viewpoint
        ok = v[:, 2] > 1e-6
        key = np.floor(v[:, :2] / np.maximum(v[:, 2:3], 1e-6) / cell).astype(np.int64)
        return key[:, 0] * 1_000_003 + key[:, 1], np.linalg.norm(v, axis=1), ok

    tkey, trange, tok = rays(target.points)
    order = np.argsort(tkey[tok])
    keys, first = np.unique(tkey[tok][order], return_index=True)
    nearest = np.minimum.reduceat(trange[tok][order], first)
    qkey, qrange, qok = rays(points)
    at = np.clip(np.searchsorted(keys, qkey), 0, len(keys) - 1)
    seen = qok & (keys[at] == qkey)
    return float((seen & (qrange < nearest[at] - tolerance_mm)).mean())


def _in_front_on_pixels(points: np.ndarray, target: ScanCloud, tolerance_mm: float, camera: Pinhole) -> float:
    """`free_space_violations` on the target's pixel grid (points in its camera frame, mm)."""
    assert target.pixels is not None
    h, w = camera.height, camera.width
    distance = np.full((h, w), np.inf)
    distance[target.pixels[:, 1], target.pixels[:, 0]] = np.linalg.norm(target.points, axis=1)
    nearest = ndimage.minimum_filter(distance, size=3, mode="constant", cval=np.inf)
    inner = ndimage.binary_erosion(np.isfinite(distance), np.ones((3, 3), bool))
    ahead = points[:, 2] > 1e-6
    px = np.full((len(points), 2), -1, dtype=np.int64)
    px[ahead] = np.rint(camera.project(points[ahead])).astype(np.int64)
    inside = ahead & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    u, v = np.where(inside, px[:, 0], 0), np.where(inside, px[:, 1], 0)
    seen = inside & inner[v, u]
    return float((seen & (np.linalg.norm(points, axis=1) < nearest[v, u] - tolerance_mm)).mean())


def session_camera(scan: ScanCloud) -> Pinhole | None:
    """The camera of the session a cloud was loaded from (`load_session`: camera frame, every
    point on its pixel), None for a cloud file."""
    from scanner.session import Session

    if scan.pixels is None or not Path(scan.source).is_dir():
        return None
    return Session.open(scan.source).rig_model().camera


def register_view_pair(scan: ScanCloud, target: ScanCloud, overlap: float | None = None,
                       settings: RegistrationSettings = RegistrationSettings(), min_fitness: float = MIN_FITNESS,
                       min_overlap: float = MIN_OVERLAP, max_violations: float | None = None,
                       refuse_ambiguous: bool = True) -> ViewPair:
    """The pose of view `scan` in view `target` (see the module docstring); `max_violations`
    None: the limit for how free space is judged there."""
    if overlap is not None and not 0 < overlap <= 1:
        raise ValueError(f"overlap must be a share in (0, 1], got {overlap}")
    model = ModelTarget.from_cloud(target)
    # its fitness gate assumes a subset (opened to the smallest it takes): the pose is judged below
    coarse = register(scan, model, replace(settings, min_fitness=OPEN_GATE))
    voxel = model.voxel_mm
    keep = thin(scan.points, 0.5 * voxel)
    source = paired(scan.points, scan.normals, keep)
    dense = paired(target.points, target.normals, np.arange(len(target.points)))
    tree = cKDTree(target.points)
    cameras = session_camera(target), session_camera(scan)
    if max_violations is None:
        max_violations = MAX_VIOLATIONS_ON_PIXELS if None not in cameras else MAX_VIOLATIONS

    def judge(T: np.ndarray) -> _Judged:
        return _judge(source, dense, tree, T, (target, scan), cameras, voxel, overlap, settings)

    best = max((judge(T) for T in (coarse.transform, *coarse.alternatives)), key=_score)
    result = ViewPair(best.transform, best.overlap, overlap is not None, min(best.fitness, 1.0), best.rmse_mm,
                      0.5 * voxel, 2.0 * voxel, best.violations, coarse.method + "+overlap-icp", coarse.ambiguous,
                      coarse.timings_s)
    failed = [text for bad, text in (
        (best.fitness < min_fitness, f"only {best.fitness:.0%} of the overlap lies within {0.5 * voxel:.3g} mm of "
                                     f"{target.source} (needs {min_fitness:.0%})"),
        (best.overlap < min_overlap, f"the overlap is {best.overlap:.0%} of the scan "
                                     f"({'given' if overlap is not None else 'estimated'}; needs {min_overlap:.0%})"),
        (best.violations > max_violations, f"{best.violations:.1%} of the scan would lie in front of what the "
                                           f"target's sensor saw (at most {max_violations:.1%}): a wrong pose"),
        (refuse_ambiguous and coarse.ambiguous, "the search found other poses that explain it about as well "
                                                "(a symmetric part?): ambiguous")) if bad]
    loose = None if failed else _loose(best, judge, scan.points.mean(axis=0))
    if loose is not None:
        failed.append(loose)
    if failed:
        raise RegistrationFailed(f"{scan.source}: {'; '.join(failed)}; not the same part, too little in common, or "
                                 f"give the overlap with --overlap", best.fitness, best.rmse_mm)
    return result


def _score(j: _Judged) -> float:
    return j.fitness - j.violations


def _loose(best: _Judged, judge: Callable[[np.ndarray], _Judged], centre: np.ndarray) -> str | None:
    """Why the overlap does not fix `best` (None when it does): a start `PROBE_MM` either way
    along one of its `PROBED` weakest motions settles elsewhere (more than `SAME_DEG` or
    `SAME_MM` at the source's `centre`, source frame) and fits better (fitness less violations)."""
    for k in range(PROBED):
        for shift in (-PROBE_MM, PROBE_MM):
            probe = judge(along(best.constraint, k, shift) @ best.transform)
            deg, mm = pose_error(best.transform, probe.transform, centre)
            if (deg > SAME_DEG or mm > SAME_MM) and _score(probe) > _score(best):
                return (f"the overlap barely fixes the {best.constraint.describe(k)}: a start {shift:+g} mm along it "
                        f"settles {deg:.2f} deg / {mm:.2f} mm away and fits better ({probe.fitness:.3f} against "
                        f"{best.fitness:.3f}), so ICP stalled short of the best pose")
    return None


@dataclass(frozen=True, eq=False)
class _Judged:
    transform: np.ndarray
    overlap: float
    fitness: float
    rmse_mm: float
    violations: float
    constraint: Constraint


def _judge(source: PairView, target: PairView, tree: cKDTree, T: np.ndarray, clouds: tuple[ScanCloud, ScanCloud],
           cameras: tuple[Pinhole | None, Pinhole | None], voxel: float, overlap: float | None,
           settings: RegistrationSettings) -> _Judged:
    """A pose refined on the overlap and judged there (see the module docstring)."""
    T = refine_pair(source, target, T, PairSettings(voxel_mm=voxel, max_distance_mm=2.0 * voxel,
                                                    min_distance_mm=0.02)).transform
    q = transform_points(T, source.points)
    n = source.normals @ T[:3, :3].T
    d, j = tree.query(q, distance_upper_bound=2.0 * voxel, workers=-1)
    near = np.isfinite(d)
    j = np.where(near, j, 0)
    agree = np.einsum("ij,ij->i", n, target.normals[j]) > np.cos(np.radians(settings.max_normal_deg))
    on = near & agree & (d <= 0.5 * voxel)
    share = overlap if overlap is not None else float(near.mean())
    fitness = float(on.sum() / max(share * len(q), 1.0))
    rmse = float(np.sqrt(np.mean(d[on] ** 2))) if on.any() else float("inf")
    back = np.linalg.inv(T)  # and the other way round: the target in the source's view
    seen_back = transform_points(back, target.points[thin(target.points, 0.5 * voxel)])
    violations = max(free_space_violations(q, clouds[0], 2.0 * voxel, cameras[0]),
                     free_space_violations(seen_back, clouds[1], 2.0 * voxel, cameras[1]))
    return _Judged(T, share, fitness, rmse, violations, overlap_constraint(q[on], target.normals[j[on]]))
