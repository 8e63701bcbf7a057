"""Alignment of the views of a multi-view session in the part frame.

1. Prior: each view's stage pose (`ViewCloud.prior`, from the stage model: the calibrated
   axis when the rig has one).
2. Pairs: every two views the prior turns at most `max_pair_deg` apart are registered from
   the prior's relative pose (`pairwise.refine_pair`, partial overlap). A pair is refused
   when too little of it overlaps, or when the refinement moved it further from the prior
   than a stage can be off (`max_correction_*`): a slid pose, not a correction. Views are
   ordered by their turn about the stage's axis; a pair of views further apart than
   neighbours must also agree with the chain of neighbouring pairs between them within
   `max_inconsistency_*`: two views a quarter turn apart on a turntable may share only the
   platter, top faces and a boss, which leave the pose free to turn about the boss, and
   such a pair slides where its neighbours' chain holds.
3. Global: Open3D's pose-graph optimisation (Levenberg-Marquardt) over all views, the pairs
   as edges weighted by their point-to-plane information; the view at stage position 0
   (or the nearest) is held, so the part frame stays the stage frame. Steps 2-3 run
   `rounds` times, each from the poses of the one before.

Poses are 4x4 `part_from_view` (view points, world frame, into the part frame); mm, degrees
in reports, translations at the part (the centre of the views' points).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any

import numpy as np

from inspection.errors import InspectionError
from inspection.views.pairwise import PairFit, PairSettings, pair_view, refine_pair
from inspection.views.view_clouds import ViewCloud


class AlignmentFailed(InspectionError):
    """The views cannot be tied together (a view overlaps none of the others)."""


@dataclass(frozen=True)
class AlignSettings:
    """See the module docstring; angles in degrees, lengths in mm."""

    pair: PairSettings = field(default_factory=lambda: PairSettings(voxel_mm=1.0))
    max_pair_deg: float = 100.0
    min_overlap: float = 0.1
    max_correction_deg: float = 5.0
    max_correction_mm: float = 10.0
    max_inconsistency_deg: float = 0.1
    max_inconsistency_mm: float = 0.1
    rounds: int = 1

    def __post_init__(self) -> None:
        if not (0 < self.max_pair_deg <= 180 and 0 <= self.min_overlap < 1 and self.max_correction_deg > 0
                and self.max_correction_mm > 0 and self.rounds >= 1):
            raise ValueError(f"alignment settings out of range: {self}")


@dataclass(frozen=True, eq=False)
class Alignment:
    """`poses[k]`: view k's refined part_from_view; `priors[k]` the stage's; `edges` the
    pairs of the last round; `refused` (source, target, why) the pairs left out."""

    names: tuple[str, ...]
    centre: np.ndarray
    poses: tuple[np.ndarray, ...]
    priors: tuple[np.ndarray, ...]
    edges: tuple[PairFit, ...]
    refused: tuple[tuple[int, int, str], ...]
    timings_s: dict[str, float]

    def corrections(self) -> list[tuple[float, float]]:
        """(rotation deg, translation mm) from each view's prior to its refined pose."""
        return [pose_error(p, q, self.centre) for p, q in zip(self.priors, self.poses)]

    def edge_residuals(self) -> list[tuple[float, float]]:
        """(deg, mm) between each edge's own pose and the one the final poses imply."""
        return [pose_error(e.transform, np.linalg.inv(self.poses[e.target]) @ self.poses[e.source],
                           self._in_view(e.source)) for e in self.edges]

    def _in_view(self, k: int) -> np.ndarray:
        """The part's centre in view k's frame."""
        T = np.linalg.inv(self.poses[k])
        return T[:3, :3] @ self.centre + T[:3, 3]

    def as_dict(self) -> dict[str, Any]:
        return {"views": [{"name": n, "prior": p.tolist(), "pose": q.tolist(),
                           "correction_deg": c[0], "correction_mm": c[1]}
                          for n, p, q, c in zip(self.names, self.priors, self.poses, self.corrections())],
                "edges": [{"source": e.source, "target": e.target, "overlap": e.overlap, "rmse_mm": e.rmse_mm,
                           "correspondences": e.correspondences, "residual_deg": r[0], "residual_mm": r[1]}
                          for e, r in zip(self.edges, self.edge_residuals())],
                "refused": [{"source": s, "target": t, "why": w} for s, t, w in self.refused],
                "timings_s": self.timings_s}


def rotation_deg(R: np.ndarray) -> float:
    """The angle of a rotation matrix, degrees."""
    return math.degrees(math.acos(float(np.clip((np.trace(R[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))


def pose_error(a: np.ndarray, b: np.ndarray, at: np.ndarray | None = None) -> tuple[float, float]:
    """(rotation deg, translation mm) of a^-1 b; the translation is that of the point `at`
    (default the origin) moved by a^-1 b."""
    d = np.linalg.inv(a) @ b
    p = np.zeros(3) if at is None else np.asarray(at, float)
    return rotation_deg(d), float(np.linalg.norm(d[:3, :3] @ p + d[:3, 3] - p))


def align_views(views: list[ViewCloud], settings: AlignSettings = AlignSettings()) -> Alignment:
    """Align `views` (see the module docstring); AlignmentFailed when a view is tied to no
    other."""
    t0 = time.perf_counter()
    clouds = [pair_view(v, settings.pair.voxel_mm) for v in views]
    priors = [v.prior for v in views]
    order = turn_order(priors)
    within = {(i, j) for i in range(len(views)) for j in range(i + 1, len(views))
              if rotation_deg(np.linalg.inv(priors[j]) @ priors[i]) <= settings.max_pair_deg}
    ring = {tuple(sorted(p)) for p in pairwise(order)}
    ring |= {tuple(sorted((order[-1], order[0])))} & within  # closing the turn, if its ends are near
    pairs = sorted(ring | within)
    ref = _reference(views)
    centre = views[ref].moved(priors[ref]).points.mean(axis=0)
    times = {"thin": time.perf_counter() - t0, "pairs": 0.0, "graph": 0.0}
    poses = list(priors)
    edges: list[PairFit] = []
    refused: list[tuple[int, int, str]] = []
    for _ in range(settings.rounds):
        t0 = time.perf_counter()
        fits: dict[tuple[int, int], PairFit] = {}
        refused = []
        for i, j in pairs:
            fit = refine_pair(clouds[i], clouds[j], np.linalg.inv(poses[j]) @ poses[i], settings.pair, (i, j))
            at = np.linalg.inv(priors[i])[:3, :3] @ centre + np.linalg.inv(priors[i])[:3, 3]
            deg, mm = pose_error(np.linalg.inv(priors[j]) @ priors[i], fit.transform, at)
            if fit.overlap < settings.min_overlap:
                refused.append((i, j, f"overlap {fit.overlap:.0%} < {settings.min_overlap:.0%}"))
            elif deg > settings.max_correction_deg or mm > settings.max_correction_mm:
                refused.append((i, j, f"moved {deg:.2f} deg / {mm:.2f} mm from the stage prior"))
            else:
                fits[(i, j)] = fit
        edges = [fits[p] for p in pairs if p in ring and p in fits]
        for p in pairs:
            if p in fits and p not in ring:
                why = _inconsistency(fits[p], fits, order, priors, centre, settings)
                if why:
                    refused.append((*p, why))
                else:
                    edges.append(fits[p])
        times["pairs"] += time.perf_counter() - t0
        _check_connected(views, edges, refused)
        t0 = time.perf_counter()
        poses = optimise(poses, edges, settings.pair.voxel_mm, ref, centre)
        times["graph"] += time.perf_counter() - t0
    return Alignment(tuple(v.name for v in views), centre, tuple(poses), tuple(priors), tuple(edges),
                     tuple(refused), {k: round(v, 4) for k, v in times.items()})


def turn_order(priors: list[np.ndarray]) -> list[int]:
    """The views ordered by their turn about the stage's axis (the axis of the largest turn
    among the priors; for a stage that only turns, every prior turns about it)."""
    from scipy.spatial.transform import Rotation

    rotvecs = Rotation.from_matrix(np.stack([p[:3, :3] for p in priors])).as_rotvec()
    biggest = rotvecs[np.argmax(np.linalg.norm(rotvecs, axis=1))]
    if np.linalg.norm(biggest) < 1e-9:
        return list(range(len(priors)))
    return [int(k) for k in np.argsort(rotvecs @ (biggest / np.linalg.norm(biggest)), kind="stable")]


def _inconsistency(fit: PairFit, fits: dict[tuple[int, int], PairFit], order: list[int], priors: list[np.ndarray],
                   centre: np.ndarray, settings: AlignSettings) -> str:
    """Why `fit` disagrees with the chain of neighbouring pairs between its views ("" if it
    agrees, or if no complete chain of accepted neighbours joins them)."""
    position = {k: n for n, k in enumerate(order)}
    a, b = position[fit.source], position[fit.target]
    n = len(order)
    forward = [order[(a + s) % n] for s in range((b - a) % n + 1)]
    backward = [order[(a - s) % n] for s in range((a - b) % n + 1)]
    for path in (forward, backward):
        chain = np.eye(4)
        for u, v in pairwise(path):
            step = fits.get((u, v)) or fits.get((v, u))
            if step is None:
                break
            chain = (step.transform if step.source == u else np.linalg.inv(step.transform)) @ chain
        else:
            at = np.linalg.inv(priors[fit.source])[:3, :3] @ centre + np.linalg.inv(priors[fit.source])[:3, 3]
            deg, mm = pose_error(chain, fit.transform, at)
            if deg > settings.max_inconsistency_deg or mm > settings.max_inconsistency_mm:
                return f"{deg:.3f} deg / {mm:.3f} mm off the chain of neighbouring views (a sliding pair)"
            return ""
    return ""


def optimise(poses: list[np.ndarray], edges: list[PairFit], distance_mm: float, reference: int,
             centre: np.ndarray) -> list[np.ndarray]:
    """Open3D's global pose-graph optimisation from `poses`; edges between neighbouring
    views (consecutive indices, or first and last) are trusted, the others may be pruned.

    The graph is solved in a frame at the part's `centre` (mm, the poses' frame): Open3D
    stops when a step is below 1e-6 of the norm of all the poses' parameters, and in the
    rig's world frame (the part some 400 mm from its origin) that let corrections of a few
    thousandths of a degree stop it before its first step (eight views with exact stage
    priors and neighbouring pairs 0.001-0.013 deg off came back unchanged). Its relative
    step and residual limits are set to 1e-12, so it runs until the poses settle."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    at = np.eye(4)
    at[:3, 3] = centre
    into, back = np.linalg.inv(at), at
    graph = reg.PoseGraph()
    for T in poses:
        graph.nodes.append(reg.PoseGraphNode(into @ np.asarray(T, float) @ back))
    n = len(poses)
    for e in edges:
        neighbours = abs(e.source - e.target) in (1, n - 1)
        graph.edges.append(reg.PoseGraphEdge(e.source, e.target, into @ e.transform @ back,
                                             moved_information(e.information, centre), uncertain=not neighbours))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=distance_mm, edge_prune_threshold=0.25,
                                          preference_loop_closure=1.0, reference_node=reference)
    criteria = reg.GlobalOptimizationConvergenceCriteria()
    criteria.min_relative_increment = criteria.min_relative_residual_increment = 1e-12
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(), criteria, option)
    return [back @ np.asarray(node.pose) @ into for node in graph.nodes]


def moved_information(information: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """A pose's 6x6 information (rotation, then translation) about the frame origin,
    expressed about `origin` (mm) instead: a small motion (w, v) about `origin` is
    (w, v + origin x w) about the frame origin."""
    o = np.asarray(origin, float)
    M = np.eye(6)
    M[3:, :3] = np.array([[0.0, -o[2], o[1]], [o[2], 0.0, -o[0]], [-o[1], o[0], 0.0]])
    return M.T @ information @ M


def _reference(views: list[ViewCloud]) -> int:
    """The view whose prior is closest to the identity (the stage at 0): held fixed."""
    return int(np.argmin([rotation_deg(v.prior) + np.linalg.norm(v.prior[:3, 3]) for v in views]))


def _check_connected(views: list[ViewCloud], edges: list[PairFit], refused: list[tuple[int, int, str]]) -> None:
    linked = {0}
    changed = True
    while changed:
        changed = False
        for e in edges:
            if (e.source in linked) != (e.target in linked):
                linked |= {e.source, e.target}
                changed = True
    alone = [views[k].name for k in range(len(views)) if k not in linked]
    if alone:
        why = "; ".join(f"{views[s].name}-{views[t].name}: {w}" for s, t, w in refused) or "no pair within reach"
        raise AlignmentFailed(f"{', '.join(alone)} cannot be tied to the other views ({why}); turn the part by "
                              f"smaller steps so that neighbouring views overlap")
