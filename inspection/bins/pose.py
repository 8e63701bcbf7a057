"""Poses of thin flat parts lying in a bin (paper 001, sections 3-4), one per instance: the
part's model (`part_model`) fitted to the instance in its plane (`instance_plane`).

Per instance (`estimate_pose`), for each side up (both flipped hypotheses: the mirror
outline in the same place is the other side): coarse poses by SAC-IA (FPFH, triplets, the
Huber score of Eq. 22: `registration.sac_ia.coarse_feature_poses`; a search per side, as local
descriptors hardly tell an outline from its mirror image) or by NDT (Eq. 23-26, Newton
steps from 12 yaws about the instance's plane); the best one also turned end for end and
flipped over about either in-plane axis (the confusions of a nearly symmetric view); each
refined by point-to-plane ICP with normal-angle rejection (Eq. 27-29,
`registration.icp`) and judged by the outline fit: fitness of the extruded instance cloud,
plus the fraction of its true outline points on the part's outline, minus the fraction of
the posed face that would lie where the scene shows a lower surface (2 at best); the best
one refined on the full instance. A pose is reported only when it explains the instance
(its points on the posed face, its outline on the part's outline, no face over a lower
surface, planarity, size) and no distinct pose (or the other side) is judged within
`ambiguity_margin` of it: otherwise the instance is reported as failed, with the reason.
A covered part's fragment may be (nearly) symmetric about a line in its plane, and then
explained as well by the part turned over: from `mirror_occlusion` up the best pose is
also flipped about lines through the fragment (those rivals judged too), and above
`max_pose_occlusion` no pose is reported (the search cannot be trusted to find the rival).

Work saved: the side whose silhouette handedness
(Hu's seventh moment, its sign flips in a mirror image) matches the instance's is searched
first, and the other side's search is skipped when the first explains a mostly visible
instance within the margin of the best score (its mirror image is still tried by the
flips); the hypotheses of one side are judged in one batched query; SAC-IA attempts
(it is randomised) keep the poses judged before, so a rival once found stays one, and an
ambiguity no better pose could settle (a rival within the margin of the best possible
score) ends the estimation at once.

The occlusion estimate is the fraction of the posed visible face that falls where the
scene shows a higher surface (unobserved cells — shadows, outside the view — excluded).

Poses are part -> camera (4x4, mm). Units: mm, rad.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import TypedDict, Unpack

import numpy as np

from inspection.bins.instance_plane import InstancePatch, SceneContext, instance_patch, onto_plane
from inspection.bins.instances import Instance
from inspection.bins.part_model import SideModel, ThinPartModel
from inspection.bins.pose_settings import DEFAULT_POSE_SETTINGS, PoseError, PoseSettings
from inspection.downsample import downsample
from inspection.registration import RegistrationSettings, fitness, icp, pose_difference, transform_points
from inspection.registration.hypotheses import with_flips
from inspection.registration.ndt import ndt_grid, ndt_refine
from inspection.registration.rigid import distinct_poses
from inspection.registration.sac_ia import coarse_feature_poses


@dataclass(frozen=True, eq=False)
class PartPose:
    """The pose of one instance, or why there is none. `pose` part -> camera (4x4, mm),
    `side` "front" or "back" (the face toward the camera), `fitness`: fraction of the
    instance's points on the posed face, `rmse_mm` their RMS distance to it, `occlusion`:
    fraction of the posed visible face covered by something higher, `side_margin`:
    outline-fit score of the chosen side minus the other's; `time_s` (wall) and `cpu_s`
    (process CPU) of the estimation."""

    instance_id: int
    ok: bool
    reason: str
    method: str
    points: int
    pose: np.ndarray | None = None
    side: str | None = None
    fitness: float = 0.0
    rmse_mm: float = float("nan")
    occlusion: float = float("nan")
    side_margin: float = float("nan")
    time_s: float = 0.0
    cpu_s: float = 0.0
    label: str | None = None
    edge_fit: float = float("nan")

    def posed(self) -> tuple[np.ndarray, str]:
        """(`pose`, `side`) of an instance posed (`ok`); PoseError for one without a pose."""
        if self.pose is None or self.side is None:
            raise PoseError(f"instance {self.instance_id} has no pose: {self.reason}")
        return self.pose, self.side


class _Figures(TypedDict, total=False):
    """What a failed PartPose reports of its best pose (PartPose's fields of those names)."""

    fitness: float
    rmse_mm: float
    occlusion: float
    side_margin: float
    edge_fit: float


# (why the instance fails, the figures of its best pose, whether another attempt may succeed)
_Failure = tuple[str, _Figures, bool]


def estimate_pose(instance: Instance, model: ThinPartModel, context: SceneContext | None = None,
                  settings: PoseSettings = DEFAULT_POSE_SETTINGS) -> PartPose:
    """The pose of `model` explaining `instance` (camera frame), or a failed PartPose
    saying why (see the module docstring)."""
    t0, c0 = time.perf_counter(), time.process_time()
    method = f"{settings.method}+icp"
    pts = np.asarray(instance.points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]

    def failed(reason: str, **kw: Unpack[_Figures]) -> PartPose:
        return PartPose(instance.id, False, reason, method, len(pts), time_s=time.perf_counter() - t0,
                        cpu_s=time.process_time() - c0, label=instance.label, **kw)

    if len(pts) < settings.min_points:
        return failed(f"only {len(pts)} points (needs {settings.min_points})")
    flat, raw, sigma, inside = onto_plane(pts, settings.max_plane_rms_mm)
    if sigma > settings.max_plane_rms_mm or inside < settings.min_plane_fraction:
        return failed(f"not one flat part: {inside:.0%} of the points lie within {settings.max_plane_rms_mm:g} mm of "
                      f"their plane (needs {settings.min_plane_fraction:.0%}), robust RMS {sigma:.3g} mm")
    try:
        patch = instance_patch(flat, context, model.thickness_mm, settings)
    except PoseError as exc:
        return failed(str(exc))
    area = len(pts) * patch.spacing ** 2
    if patch.extent_mm > 1.2 * model.length_mm or area > 1.3 * model.area_mm2:
        return failed(f"larger than one part: {patch.extent_mm:.1f} mm across, ~{area:.0f} mm² "
                      f"(the part: {model.length_mm:.1f} mm, {model.area_mm2:.0f} mm²); merged instances?")
    rng = np.random.default_rng(settings.seed)
    outcome: _Failure = ("", {}, True)
    judged: list[tuple[float, str, np.ndarray]] = []   # every attempt's judged poses: a rival found once stays one
    for _ in range(settings.attempts if settings.method == "sacia" else 1):   # SAC-IA is randomised: retry
        result = _fit(flat, raw, patch, model=model, settings=settings, rng=rng, judged=judged)
        if isinstance(result, PartPose):
            return replace(result, instance_id=instance.id, points=len(pts), time_s=time.perf_counter() - t0,
                           cpu_s=time.process_time() - c0, label=instance.label)
        outcome = result
        if not outcome[2]:   # no attempt can settle it
            break
    return failed(outcome[0], **outcome[1])


def _fit(pts: np.ndarray, raw: np.ndarray, patch: InstancePatch, *, model: ThinPartModel, settings: PoseSettings,
         rng: np.random.Generator, judged: list[tuple[float, str, np.ndarray]]) -> PartPose | _Failure:
    """One coarse + fine fit of the instance's points on its plane `pts` (`raw`: as
    measured, row for row), adding its judged poses to those of earlier attempts
    (`judged`, extended in place: a later attempt that misses a rival must not report the
    pose it rivals): the PartPose (id, points, time filled by the caller), or (why it
    fails, the figures of the best pose, whether another attempt may succeed)."""
    face = downsample(pts, settings.voxel_mm, "density_centre").points   # paper 001 Eq. 9-16
    src = np.concatenate([face, patch.wall_pts])
    src_n = np.concatenate([np.tile(patch.n, (len(face), 1)), patch.wall_nrm])
    keep = rng.choice(len(src), size=min(600, len(src)), replace=False)
    sp, sn = src[keep], src_n[keep]
    searched = len(judged)
    # each side's own coarse search (mirror images look alike to local descriptors), the
    # side the silhouette's handedness suggests first; the other side's search is skipped
    # when the first explains a mostly visible instance (occlusion below `visible_occlusion`)
    # within the ambiguity margin of the highest possible score (2): the flips of its
    # best pose below still put the other side's mirror image beside it, and a view that
    # both sides explain is symmetric about one of its axes, which is what they test.
    # Heavily occluded views get both searches (the flips alone miss some of their rivals).
    # For the same reason a side's further coarse poses are not refined once its first one
    # explains such an instance
    def explained() -> bool:
        if len(judged) == searched:
            return False
        score, best_side, T = max(judged[searched:], key=lambda j: j[0])
        return (score > 2.0 - settings.ambiguity_margin
                and _occlusion(patch, model.sides[best_side], T) < settings.visible_occlusion)

    first = "front" if np.sign(patch.skew) == np.sign(model.sides["front"].skew) else "back"
    for side in (first, "back" if first == "front" else "front"):
        if explained():
            break
        sm = model.sides[side]
        if settings.method == "sacia":
            rs = RegistrationSettings(descriptors=("fpfh",), coarse="sac-ia", spheres=(100,),
                                      hypotheses=settings.hypotheses, verify=settings.verify, seed=settings.seed,
                                      prescored=settings.prescored)
            coarse = coarse_feature_poses(src, src_n, sm.target, rs, rng, workers=1)
        else:
            coarse = _ndt_poses(src, patch, model, sm, settings.verify)
        judged += _judge(patch, sm, sp, sn, coarse[:1], settings)
        if not explained():
            judged += _judge(patch, sm, sp, sn, coarse[1:], settings)
    if len(judged) == searched:
        return f"{settings.method}: no coarse pose (no consistent correspondences)", {}, True
    best = max(judged[searched:], key=lambda j: j[0])
    judged.sort(key=lambda j: -j[0])
    ambiguous = _ambiguity(judged, patch, settings)
    if ambiguous is not None and not ambiguous[2]:   # no further pose can settle it
        return ambiguous
    # this attempt's best pose turned end for end, and flipped over about either in-plane
    # axis (the other side up): what a nearly symmetric view of the strip is confused
    # with; if one of those turns out best, its own turns too (the coarse search may have
    # missed both a pose and its mirror image)
    for _ in range(2):
        _, side0, T0 = best
        other = "back" if side0 == "front" else "front"
        turned = with_flips([T0], pts)[1:]   # about the normal first
        new = (_judge(patch, model.sides[side0], sp, sn, turned[:1], settings)
               + _judge(patch, model.sides[other], sp, sn, turned[1:], settings))
        judged += new
        best = max([best] + new, key=lambda j: j[0])
        if best[2] is T0:
            break
    # a covered part shows a fragment, and a fragment symmetric about some line in its
    # plane is explained as well by the part flipped over about that line (the other side
    # up): the best pose flipped about lines through the fragment's centroid every
    # `mirror_step_deg` (its symmetry axes pass through it), so that such a rival is judged
    _, side0, T0 = best
    if _occlusion(patch, model.sides[side0], T0) >= settings.mirror_occlusion:
        other = "back" if side0 == "front" else "front"
        judged += _judge(patch, model.sides[other], sp, sn, mirror_flips(T0, pts, patch, settings.mirror_step_deg),
                         settings, keep=3)
    judged.sort(key=lambda j: -j[0])
    ambiguous = _ambiguity(judged, patch, settings)
    if ambiguous is not None:
        return ambiguous
    _, side, T = judged[0]
    margin = _side_margin(judged)
    sm = model.sides[side]
    v = settings.voxel_mm
    fine = downsample(pts, 2.0 * patch.spacing, "density_centre").points
    fine = fine[rng.choice(len(fine), size=min(600, len(fine)), replace=False)]
    walls = patch.wall_pts[: len(patch.wall_pts) // settings.wall_levels]
    fp = np.concatenate([fine, walls])
    fn = np.concatenate([np.tile(patch.n, (len(fine), 1)), patch.wall_nrm[: len(walls)]])
    T = icp(fp, fn, sm.target.dense, T=T, max_dist=2.0 * v, min_dist=2.0 * patch.spacing,
            max_normal_deg=settings.max_normal_deg, iterations=15)
    pose = np.linalg.inv(T)
    pick = rng.choice(len(pts), size=min(2000, len(pts)), replace=False)
    q = transform_points(T, pts[pick])
    near, j = sm.face.tree.query(q)
    dist = np.einsum("ij,ij->i", transform_points(T, raw[pick]) - sm.face.points[j], sm.face.normals[j])
    inl = (near < settings.inlier_mm) & (np.abs(dist) < settings.inlier_mm)
    fit = float(inl.mean())
    rmse = float(np.sqrt(np.mean(dist[inl] ** 2))) if inl.any() else float("nan")
    edge = _edge_fit(patch, sm, T, settings.inlier_mm)
    spill = _spill(patch, sm, T)
    occl = _occlusion(patch, sm, T)
    kw: _Figures = {"fitness": fit, "rmse_mm": rmse, "occlusion": occl, "side_margin": margin, "edge_fit": edge}
    if fit < settings.min_fitness:
        return (f"the best pose ({side} up) puts only {fit:.0%} of the points on the part's face within "
                f"{settings.inlier_mm:g} mm (needs {settings.min_fitness:.0%}): not this part, or a wrongly "
                f"segmented instance", kw, True)
    if edge < settings.min_edge_fit:
        return (f"the best pose ({side} up) puts only {edge:.0%} of the instance's outline points within "
                f"{settings.inlier_mm:g} mm of the part's outline (needs {settings.min_edge_fit:.0%})", kw, True)
    if spill > settings.max_spill:
        return (f"the best pose ({side} up) puts {spill:.0%} of the part's face where a lower surface is seen "
                f"(limit {settings.max_spill:.0%}): no pose explains the instance's outline", kw, True)
    if occl > settings.max_pose_occlusion:
        return (f"the best pose ({side} up) leaves {occl:.0%} of the part covered (limit "
                f"{settings.max_pose_occlusion:.0%}): too little of it shows to rule out the part turned over",
                kw, False)
    return PartPose(0, True, "", f"{settings.method}+icp", 0, pose, side, fit, rmse, occl, margin, edge_fit=edge)


def _ambiguity(judged: list[tuple[float, str, np.ndarray]], patch: InstancePatch,
               settings: PoseSettings) -> _Failure | None:
    """(why the instance is ambiguous, the side margin, whether another attempt may settle
    it) when a pose distinct from the best (or the other side) is judged within the
    ambiguity margin of it (`judged` sorted best first), else None. A rival within the
    margin of the highest possible score (2: every point on the face, every outline point
    on the outline, no spill) stays a rival whatever better pose is found later, so more
    poses or attempts cannot settle it."""
    score, side, T = judged[0]
    for rival_score, rival_side, R in judged[1:]:
        if rival_score <= score - settings.ambiguity_margin:
            return None
        angle, shift = pose_difference(T, R, patch.c)
        if rival_side != side or angle > 2.0 or shift > 0.5:
            return (f"ambiguous: another pose ({rival_side} up, {angle:.0f} deg / {shift:.1f} mm away) explains the "
                    f"instance as well ({rival_score:.2f} vs {score:.2f}); too little of its outline is visible",
                    {"side_margin": _side_margin(judged)}, rival_score <= 2.0 - settings.ambiguity_margin)
    return None


def mirror_flips(T: np.ndarray, pts: np.ndarray, patch: InstancePatch, step_deg: float) -> list[np.ndarray]:
    """Pose `T` (scan -> part) after a half turn of the scan about lines in the instance's
    plane through the centroid of its points `pts`, one every `step_deg` over 180 deg."""
    c = pts.mean(axis=0)
    out = []
    for a in np.radians(np.arange(0.0, 180.0, step_deg)):
        axis = np.cos(a) * patch.e1 + np.sin(a) * patch.e2
        F = np.eye(4)
        F[:3, :3] = 2.0 * np.outer(axis, axis) - np.eye(3)   # rotation by pi about the axis
        F[:3, 3] = c - F[:3, :3] @ c
        out.append(T @ F)
    return out


def _side_margin(judged: list[tuple[float, str, np.ndarray]]) -> float:
    """Score of the best pose (`judged` sorted best first) minus the best of the other side's."""
    others = [j[0] for j in judged if j[1] != judged[0][1]]
    return judged[0][0] - max(others) if others else float("inf")


def _judge(patch: InstancePatch, sm: SideModel, sp: np.ndarray, sn: np.ndarray, poses: list[np.ndarray],
           settings: PoseSettings, *, keep: int | None = None) -> list[tuple[float, str, np.ndarray]]:
    """(outline-fit score, side, pose) of each pose (scan -> part) refined by point-to-plane
    ICP with normal-angle rejection on the instance's extruded cloud `sp`/`sn` (coarse to
    fine: `PoseSettings.judge_icp_stride`, `judge_icp_iterations`): fitness
    (within 1.5 voxels, one batched query) plus the fraction of the true outline on the
    part's outline, minus the fraction of the face over a lower surface. With `keep`,
    only the `keep` poses of best fitness as given (within ICP's first reach, 6 voxels)
    are refined and judged. KD-tree queries here and in the coarse search are
    single-threaded: the clouds are small, and starting threads costs more than it saves
    on a busy machine."""
    if not poses:
        return []
    v = settings.voxel_mm
    if keep is not None and len(poses) > keep:
        first = fitness(sp, sn, sm.target.coarse, T=np.array(poses), inlier_mm=6.0 * v,
                        max_normal_deg=settings.max_normal_deg, workers=1)
        poses = [poses[i] for i in np.argsort(-first)[:keep]]
    # coarse to fine: the threshold shrinking from 6 voxels on every k-th point, then the
    # last iterations on all of them at the final threshold (the best pose is refined
    # again on the dense instance: these poses are only judged)
    k, (first_its, last_its) = settings.judge_icp_stride, settings.judge_icp_iterations
    deg, tgt = settings.max_normal_deg, sm.target.coarse
    near = [icp(sp[::k], sn[::k], tgt, T=T, max_dist=6.0 * v, min_dist=0.5 * v, max_normal_deg=deg,
                iterations=first_its) for T in poses]
    posed = [icp(sp, sn, tgt, T=T, max_dist=0.5 * v, min_dist=0.5 * v, max_normal_deg=deg, iterations=last_its)
             for T in near]
    fit = fitness(sp, sn, sm.target.coarse, T=np.array(posed), inlier_mm=1.5 * v,
                  max_normal_deg=settings.max_normal_deg,
                  workers=1)
    return [(float(f) + _edge_fit(patch, sm, T, 2 * settings.inlier_mm) - _spill(patch, sm, T), sm.side, T)
            for f, T in zip(fit, posed)]


def _edge_fit(patch: InstancePatch, sm: SideModel, T: np.ndarray, tol_mm: float) -> float:
    """Fraction of the instance's true outline points within `tol_mm` of the side's outline
    (1 when the instance shows no true outline edge)."""
    if not len(patch.edge_pts):
        return 1.0
    d, _ = sm.outline_tree.query(transform_points(T, patch.edge_pts), distance_upper_bound=tol_mm)
    return float(np.isfinite(d).mean())


def _face_cells(patch: InstancePatch, sm: SideModel, T: np.ndarray, n: int = 1500) -> tuple[np.ndarray, ...]:
    """Grid cells (row, col, inside) of up to n of the side's face samples posed in the camera frame."""
    face = sm.face.points[:: max(1, len(sm.face.points) // n)]
    return patch.cells(transform_points(np.linalg.inv(T), face))


def face_evidence(patch: InstancePatch, sm: SideModel, T: np.ndarray) -> tuple[float, float]:
    """(covered, contradicted): the fractions of the posed face (its interior samples,
    scan -> part pose `T`) that the scan shows covered by a surface in front of it, and
    beyond it (a lower surface seen where the face would hide it), among its samples
    with a measurement. With the organised scan in the patch's context every sample is
    checked at its own pixel, however far from the instance; without it, on the
    instance's grid (samples off the grid, or unobserved, left out)."""
    context = patch.context
    if context is not None and context.image is not None:
        d = context.beyond(transform_points(np.linalg.inv(T), sm.interior))
        known = np.isfinite(d)
        n = max(int(known.sum()), 1)
        return float(np.sum(d[known] < -patch.step) / n), float(np.sum(d[known] > patch.step) / n)
    r, c, inside = _face_cells(patch, sm, T)
    covered = inside & patch.higher[r, c] & ~patch.observed[r, c]
    known = inside & (patch.observed[r, c] | patch.higher[r, c] | patch.lower[r, c])
    return float(covered.sum() / max(known.sum(), 1)), float(np.mean(inside & patch.lower[r, c]))


def _evidence(patch: InstancePatch, sm: SideModel, T: np.ndarray) -> tuple[float, float]:
    """`face_evidence`, kept on the patch per side and pose (asked again for the best poses)."""
    key = (id(sm), T.tobytes())
    if key not in patch.evidence:
        patch.evidence[key] = face_evidence(patch, sm, T)
    return patch.evidence[key]


def _spill(patch: InstancePatch, sm: SideModel, T: np.ndarray) -> float:
    """Fraction of the posed face where a lower surface is seen (it would hide it)."""
    return _evidence(patch, sm, T)[1]


def _occlusion(patch: InstancePatch, sm: SideModel, T: np.ndarray) -> float:
    """Fraction of the posed face covered by a surface in front of it."""
    return _evidence(patch, sm, T)[0]


def _ndt_poses(src: np.ndarray, patch: InstancePatch, model: ThinPartModel, sm: SideModel,
               n_best: int) -> list[np.ndarray]:
    """Paper 001 NDT (Eq. 23-26, `registration`'s Newton steps) from 12 yaws about the
    instance's plane, the side's face laid on it and the centroids matched, on cells of
    2 mm with every other point (300 at most); the 2 n_best best distinct ones (10 deg /
    1 mm apart: many yaws end in the same place) refined on cells of 1 mm. The n_best by
    score (scan -> model transforms)."""
    cells = (2.0, 1.0)
    for cell in cells:
        if cell not in sm.ndt:
            sm.ndt[cell] = ndt_grid(sm.target.dense.points, cell)
    sign = 1.0 if sm.side == "front" else -1.0
    a = sign * model.axis
    u0 = model.u0
    M = np.stack([u0, np.cross(a, u0), a], axis=1)   # part basis, third axis toward the camera
    mc = sm.face.points.mean(axis=0)
    sub = src[:: max(1, len(src) // 600)]
    poses, scores = [], []
    for yaw in np.radians(np.arange(0.0, 360.0, 30.0)):
        s1 = np.cos(yaw) * patch.e1 + np.sin(yaw) * patch.e2
        S = np.stack([s1, np.cross(patch.n, s1), patch.n], axis=1)
        P = np.eye(4)   # model -> scan
        P[:3, :3] = S @ M.T
        P[:3, 3] = patch.c - P[:3, :3] @ mc
        T, score = ndt_refine(sub[::2], np.linalg.inv(P), sm.ndt[cells[0]], cells[0], 10)
        poses.append(T)
        scores.append(score)
    fine = [ndt_refine(sub, T, sm.ndt[cells[1]], cells[1], 10)
            for T in distinct_poses(np.array(poses), np.argsort(-np.array(scores)), 2 * n_best, 10.0, 1.0)]
    fine.sort(key=lambda f: -f[1])
    return [T for T, _ in fine[:n_best]]


def estimate_poses(instances: list[Instance], model: ThinPartModel, context: SceneContext | None = None,
                   settings: PoseSettings = DEFAULT_POSE_SETTINGS) -> list[PartPose]:
    """`estimate_pose` for every instance, with the scene as context (None: every
    instance edge is taken as a true outline edge)."""
    return [estimate_pose(i, model, context, settings) for i in instances]
