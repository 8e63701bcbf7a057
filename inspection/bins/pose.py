"""Poses of thin flat parts lying in a bin (paper 001, sections 3-4), one per instance.

A thin sheet-metal part (paper 001's nickel tab; `sim.bins.TabPart`) seen from above is a
flat patch: its 0.25 mm walls are below the scanner's resolution, so local 3D descriptors
see a plane and nothing else, and its two faces are indistinguishable by depth. What
carries the pose in the plane, and the side, is the outline. So both the model and each
instance are turned into "extruded" clouds — the visible face plus walls dropped from its
outline, away from the camera, `PoseSettings.extrude_mm` deep — on which FPFH, NDT and
point-to-plane ICP see the outline as 3D shape:

- model (`ThinPartModel`, from a triangle mesh): the part's thin axis (area-weighted
  normal covariance), its two large faces (front: normal along the axis, back: against
  it), dense face samples, the boundary edges of each face (exact, from the mesh) sampled
  with outward normals, and one extruded cloud per side (`SideModel`);
- instance: its plane (SVD; normal toward the camera) and an occupancy grid in that
  plane, with the scene's points brought onto it along the camera rays (so what the
  camera sees beside an edge lands beside it); a boundary point is on a "true" outline
  edge unless the first surface seen beyond it (past a shadow, up to `SHADOW_MM`) is
  higher — a part lying across it. Only true edges get walls, placed on the outermost
  points and moved out by half a point spacing (the mean inset of pixel samples behind
  an edge).

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
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from inspection.bins.instances import Instance
from inspection.downsample import downsample
from inspection.errors import CadError, InspectionError
from inspection.registration import (
    ModelTarget,
    RegistrationSettings,
    Samples,
    fitness,
    icp,
    pose_difference,
    transform_points,
)
from inspection.registration.hypotheses import with_flips
from inspection.registration.ndt import ndt_grid, ndt_refine
from inspection.registration.rigid import distinct_poses
from inspection.registration.sac_ia import coarse_feature_poses

METHODS = ("sacia", "ndt")
MAX_OFF_PLANE_MM = 1.0  # instance points farther from its plane are not on the part
SHADOW_MM = 2.5  # beyond an edge, look this far for the first surface seen (past shadows)
SIDES = ("front", "back")


class PoseError(InspectionError):
    """A part model or pose-estimation input is unusable (not a thin flat part, bad settings)."""


@dataclass(frozen=True)
class PoseSettings:
    """`method`: coarse step, "sacia" or "ndt"; `extrude_mm` / `wall_levels`: depth and
    levels of the walls dropped from outlines; `voxel_mm`: the coarse clouds' voxel;
    `max_normal_deg`: ICP's normal-angle rejection; `min_fitness`: fraction of the
    instance's points on the posed face (within `inlier_mm`) below which the pose fails;
    `min_edge_fit`: the same for the instance's true outline points on the part's outline;
    `ambiguity_margin`: a distinct pose (or the other side) judged within it of the best
    makes the instance ambiguous (failed); `max_spill`: fraction of the posed face allowed where a lower surface is seen;
    `max_plane_rms_mm`, `min_plane_fraction`: an instance with a larger robust RMS
    distance to its plane, or a smaller fraction of its points within that distance, is
    not one flat part;
    `max_occlusion`: above it a part is not offered for picking; `min_points`: smaller
    instances are not posed; `hypotheses`: SAC-IA triplets scored; `verify`: its distinct
    coarse poses refined per side; `attempts`: SAC-IA runs (fresh samples) before an
    instance is reported as failed."""

    method: str = "sacia"
    extrude_mm: float = 1.5
    wall_levels: int = 3
    voxel_mm: float = 0.3
    max_normal_deg: float = 30.0
    min_fitness: float = 0.9
    min_edge_fit: float = 0.8
    inlier_mm: float = 0.15
    max_spill: float = 0.05
    ambiguity_margin: float = 0.1
    max_plane_rms_mm: float = 0.1
    min_plane_fraction: float = 0.8
    max_occlusion: float = 0.3
    min_points: int = 200
    hypotheses: int = 100
    verify: int = 2
    attempts: int = 3
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise PoseError(f"unknown pose method {self.method!r}; use one of {METHODS}")
        if not (self.extrude_mm > 0 and self.wall_levels >= 1 and self.voxel_mm > 0 and 0 < self.min_fitness <= 1):
            raise PoseError(f"inconsistent pose settings: {self}")


# ------------------------------------------------------------------------------- model


@dataclass(eq=False)
class SideModel:
    """One side of the part facing the camera (part frame): `face` samples of the visible
    face with its outward normal, `outline` samples of its boundary with outward in-plane
    normals, `target`: face plus walls dropped `extrude_mm` away from the camera, and
    `skew`: Hu's seventh moment of the face's silhouette as the camera sees it (its sign
    tells the side of a chiral outline; `_skew_moment`)."""

    side: str
    face: Samples
    outline: np.ndarray
    outline_normals: np.ndarray
    target: ModelTarget
    skew: float
    ndt: dict[float, tuple] = field(default_factory=dict)
    outline_tree: cKDTree = field(init=False)

    def __post_init__(self) -> None:
        self.outline_tree = cKDTree(self.outline)


@dataclass(eq=False)
class ThinPartModel:
    """A thin flat part from its mesh (part frame, mm): `axis` the unit normal of the front
    face, `thickness_mm`, face `area_mm2`, in-plane `length_mm` (largest extent) and the
    two `sides`; `u0` the face's principal in-plane direction (for NDT starts)."""

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    axis: np.ndarray
    u0: np.ndarray
    thickness_mm: float
    area_mm2: float
    length_mm: float
    sides: dict[str, SideModel]

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, triangles: np.ndarray, name: str,
                  settings: PoseSettings = PoseSettings(), spacing_mm: float = 0.1) -> ThinPartModel:
        """The model of a closed thin plate given as a triangle mesh (mm). The front face is
        the large face whose normal has a positive part-frame z (or x, y if z is in-plane)."""
        v = np.asarray(vertices, dtype=np.float64)
        t = np.asarray(triangles, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3 or not len(t):
            raise CadError(name, f"not a triangle mesh: vertices {v.shape}, triangles {t.shape}")
        if t.min() < 0 or t.max() >= len(v) or not np.isfinite(v).all():
            raise CadError(name, "triangle indices out of range or non-finite vertices")
        cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        area = 0.5 * np.linalg.norm(cross, axis=1)
        ok = area > 1e-12
        normal = np.zeros_like(cross)
        normal[ok] = cross[ok] / (2 * area[ok, None])
        w, vec = np.linalg.eigh(np.einsum("n,ni,nj->ij", area, normal, normal))
        axis = vec[:, 2]
        k = 2 if abs(axis[2]) >= 0.3 else int(np.argmax(np.abs(axis)))
        axis = axis * np.sign(axis[k])
        cos = normal @ axis
        front, back = ok & (cos > np.cos(np.radians(3))), ok & (cos < -np.cos(np.radians(3)))
        if not front.any() or not back.any():
            raise CadError(name, "no pair of opposite large flat faces: not a thin flat part")
        levels = v @ axis
        thickness = float(levels[t[front]].mean() - levels[t[back]].mean())
        extent = np.ptp(v - np.outer(levels, axis), axis=0)
        length = float(np.linalg.norm(extent))
        face_area = float(area[front].sum())
        if not (thickness > 0 and thickness < 0.2 * np.sqrt(face_area)) or w[2] < 0.6 * w.sum():
            raise CadError(name, f"not a thin flat part: thickness {thickness:.3g} mm for a face of "
                                 f"{face_area:.3g} mm²; pose estimation here handles flat sheet parts only")
        rng = np.random.default_rng(0)
        sides = {}
        u0 = None
        for side, sel, sign in (("front", front, 1.0), ("back", back, -1.0)):
            tri = t[sel]
            pts = _sample_triangles(v, tri, area[sel], spacing_mm, rng)
            if u0 is None:
                c = pts - pts.mean(axis=0)
                u0 = np.linalg.eigh(c.T @ c)[1][:, 2]
            edges, outward = _boundary_edges(v, tri, sign * axis)
            b_pts, b_nrm = _sample_edges(v, edges, outward, spacing_mm / 2)
            face_n = np.tile(sign * axis, (len(pts), 1))
            depth = settings.extrude_mm * np.arange(1, settings.wall_levels + 1) / settings.wall_levels
            walls = (b_pts[None] - sign * depth[:, None, None] * axis).reshape(-1, 3)
            wall_n = np.tile(b_nrm, (len(depth), 1))
            rim_n = np.tile(sign * axis, (len(b_pts), 1))
            target = ModelTarget(np.concatenate([pts, b_pts, walls]), np.concatenate([face_n, rim_n, wall_n]),
                                 f"{name} ({side} up)", settings.voxel_mm)
            up = sign * axis   # toward the camera; (u0, up x u0, up) right-handed like an instance's grid
            uv = np.stack([pts @ u0, pts @ np.cross(up, u0)], axis=1)
            ij = np.floor((uv - uv.min(axis=0)) / (2.0 * spacing_mm)).astype(np.int64)
            mask = np.zeros(ij.max(axis=0)[::-1] + 1, np.uint8)
            mask[ij[:, 1], ij[:, 0]] = 1
            skew = _skew_moment(cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)))
            sides[side] = SideModel(side, Samples(pts, face_n), b_pts, b_nrm, target, skew)
        return cls(name, v, t, axis, u0, thickness, face_area, length, sides)


def _skew_moment(mask: np.ndarray) -> float:
    """Hu's seventh moment invariant of a silhouette (2D boolean grid, first in-plane axis
    along the columns): unchanged by turns and shifts in the plane, its sign flips in a
    mirror image, i.e. when a flat chiral part shows its other face."""
    return float(cv2.HuMoments(cv2.moments(mask.astype(np.uint8), binaryImage=True))[6, 0])


def _sample_triangles(v: np.ndarray, tri: np.ndarray, area: np.ndarray, spacing: float,
                      rng: np.random.Generator) -> np.ndarray:
    """Points uniformly on the triangles, about one per `spacing`² of area."""
    n = max(int(area.sum() / spacing ** 2), 100)
    which = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    a, b, c = (v[tri[which, k]] for k in range(3))
    return (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c


def _boundary_edges(v: np.ndarray, tri: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges (E, 2) used by one triangle only of a face, and their outward in-plane unit
    directions (E, 3) (away from the triangle's third vertex)."""
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    third = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]])
    key = np.sort(e, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inv.ravel()] == 1
    e, third = e[once], third[once]
    d = v[e[:, 1]] - v[e[:, 0]]
    out = np.cross(d, normal)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out[np.einsum("ij,ij->i", out, v[third] - v[e[:, 0]]) > 0] *= -1.0
    return e, out


def _sample_edges(v: np.ndarray, edges: np.ndarray, outward: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step` along the edges, with their edge's outward direction."""
    a, b = v[edges[:, 0]], v[edges[:, 1]]
    n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / step).astype(np.int64), 1)
    which = np.repeat(np.arange(len(edges)), n)
    frac = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / n[which]
    return a[which] + frac[:, None] * (b - a)[which], outward[which]


# ---------------------------------------------------------------------------- instance


@dataclass(eq=False)
class SceneContext:
    """All scan points of the scene (camera frame, mm) and their KD-tree: what lies around
    an instance tells its true outline edges from the edges where a part covers it."""

    points: np.ndarray
    tree: cKDTree = field(init=False)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64)
        self.tree = cKDTree(self.points)


@dataclass(eq=False)
class _Patch:
    """An instance in its own plane: centroid `c`, basis `e1`, `e2`, normal `n` (toward the
    camera), point `spacing`; grid (origin `lo`, cell `g`) labels: `observed` (the
    instance), `higher` (a surface above its plane seen there), `lower` (below it,
    outside the instance); `edge_pts` its true outline points (camera frame) and the
    walls dropped from them (`wall_pts`, outward `wall_nrm`); RMS distance of its points
    to the plane and its extent in the plane (mm)."""

    c: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    n: np.ndarray
    spacing: float
    lo: np.ndarray
    g: float
    observed: np.ndarray
    higher: np.ndarray
    lower: np.ndarray
    edge_pts: np.ndarray
    wall_pts: np.ndarray
    wall_nrm: np.ndarray
    plane_rms: float
    extent_mm: float
    skew: float

    def cells(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) grid cells of camera-frame points (via their plane coordinates)."""
        d = p - self.c
        ij = np.floor((np.stack([d @ self.e2, d @ self.e1], axis=1) - self.lo[::-1]) / self.g).astype(np.int64)
        h, w = self.observed.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < h) & (ij[:, 1] >= 0) & (ij[:, 1] < w)
        return np.clip(ij[:, 0], 0, h - 1), np.clip(ij[:, 1], 0, w - 1), inside


def _patch(points: np.ndarray, context: SceneContext | None, thickness: float, settings: PoseSettings) -> _Patch:
    """The instance's plane, grid labels, true outline points and walls (see the module
    docstring); scene points more than half the part's `thickness` (or 4 plane RMS) above
    the plane, toward the camera, count as higher, the others as lower."""
    c = points.mean(axis=0)
    d = points - c
    _, s, vt = np.linalg.svd(d[:: max(1, len(d) // 5000)], full_matrices=False)
    n = vt[2] * (-1.0 if vt[2] @ c > 0 else 1.0)   # toward the camera at the origin
    e1 = vt[0] - (vt[0] @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    uv = np.stack([d @ e1, d @ e2], axis=1)
    height = d @ n
    plane_rms = float(np.sqrt(np.mean(height ** 2)))
    tree = cKDTree(uv)
    spacing = max(float(np.median(tree.query(uv[:: max(1, len(uv) // 2000)], k=2)[0][:, 1])), 1e-3)
    g = 1.5 * spacing
    margin = SHADOW_MM + 2 * g
    lo = uv.min(axis=0) - margin
    shape = (int(np.ceil((uv[:, 1].max() + margin - lo[1]) / g)), int(np.ceil((uv[:, 0].max() + margin - lo[0]) / g)))
    if shape[0] * shape[1] > 4e6:
        raise PoseError(f"an instance spans {np.ptp(uv, axis=0).round(1).tolist()} mm at a point spacing of "
                        f"{spacing:.3g} mm: too large for one part")
    ij = np.floor((uv[:, ::-1] - lo[::-1]) / g).astype(np.int64)
    observed = np.zeros(shape, np.uint8)
    observed[ij[:, 0], ij[:, 1]] = 1
    observed = cv2.morphologyEx(observed, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)
    higher = np.zeros(shape, bool)
    lower = np.zeros(shape, bool)
    if context is not None:
        radius = float(np.hypot(*(np.array(shape) * g))) / 2
        centre = c + (lo + np.array(shape[::-1]) * g / 2) @ np.stack([e1, e2])
        near = context.points[context.tree.query_ball_point(centre, radius + 1.0, workers=1)]
        hn = (near - c) @ n
        # onto the plane along the camera rays (the camera at the origin): what the camera
        # sees beside the instance's edge lands beside it, however far below or above
        ray = near @ n
        dn = near * ((c @ n) / np.where(np.abs(ray) > 1e-9, ray, 1e-9))[:, None] - c
        cij = np.floor((np.stack([dn @ e2, dn @ e1], axis=1) - lo[::-1]) / g).astype(np.int64)
        ok = (cij[:, 0] >= 0) & (cij[:, 0] < shape[0]) & (cij[:, 1] >= 0) & (cij[:, 1] < shape[1]) & (np.abs(hn) < 20.0)
        step = max(0.5 * thickness, 4 * plane_rms, 0.05)
        higher[cij[ok & (hn > step), 0], cij[ok & (hn > step), 1]] = True
        lower[cij[ok & (hn <= step), 0], cij[ok & (hn <= step), 1]] = True
        lower &= ~observed & ~higher
    # boundary: observed cells next to unobserved ones, each point with its outward
    # direction; an edge is a true outline edge unless the first surface seen beyond it
    # (within SHADOW_MM: a shadow may lie between) is higher — a part lying across it
    edge = observed & ~cv2.erode(observed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    blur = cv2.GaussianBlur(observed.astype(np.float32), (0, 0), 1.5)
    gy, gx = np.gradient(blur)
    on = edge[ij[:, 0], ij[:, 1]]
    out2 = -np.stack([gx[ij[on, 0], ij[on, 1]], gy[ij[on, 0], ij[on, 1]]], axis=1)
    norm = np.linalg.norm(out2, axis=1)
    good = norm > 1e-6
    out2 = out2[good] / norm[good, None]
    idx = np.flatnonzero(on)[good]
    steps = g * np.arange(1, int(np.ceil(SHADOW_MM / g)) + 1)
    probe = np.floor((uv[idx, None, ::-1] + steps[None, :, None] * out2[:, None, ::-1] - lo[::-1]) / g).astype(np.int64)
    r, cc = np.clip(probe[..., 0], 0, shape[0] - 1), np.clip(probe[..., 1], 0, shape[1] - 1)
    seen = np.where(higher[r, cc], 1, np.where(lower[r, cc], 2, 0))
    first = seen[np.arange(len(idx)), np.argmax(seen > 0, axis=1)]
    idx, out2 = idx[first != 1], out2[first != 1]
    # keep the outermost points of the band (no neighbour farther out along the outward direction)
    dist, nb = tree.query(uv[idx], k=9)
    along = np.einsum("knj,kj->kn", uv[np.minimum(nb, len(uv) - 1)] - uv[idx, None], out2)
    outer = ~np.any(np.isfinite(dist) & (dist < 2.0 * spacing) & (along > 0.5 * spacing), axis=1)
    idx, out2 = idx[outer], out2[outer]
    out3 = out2[:, :1] * e1 + out2[:, 1:] * e2
    edge_pts = c + (uv[idx] + 0.5 * spacing * out2) @ np.stack([e1, e2]) + np.outer(height[idx], n)
    depth = settings.extrude_mm * np.arange(1, settings.wall_levels + 1) / settings.wall_levels
    walls = (edge_pts[None] - depth[:, None, None] * n).reshape(-1, 3)
    return _Patch(c, e1, e2, n, spacing, lo, g, observed, higher, lower, edge_pts,
                  walls, np.tile(out3, (len(depth), 1)), plane_rms, float(np.linalg.norm(np.ptp(uv, axis=0))),
                  _skew_moment(observed))


# -------------------------------------------------------------------------------- pose


@dataclass(frozen=True, eq=False)
class PartPose:
    """The pose of one instance, or why there is none. `pose` part -> camera (4x4, mm),
    `side` "front" or "back" (the face toward the camera), `fitness`: fraction of the
    instance's points on the posed face, `rmse_mm` their RMS distance to it, `occlusion`:
    fraction of the posed visible face covered by something higher, `side_margin`:
    outline-fit score of the chosen side minus the other's; `time_s` of the estimation."""

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
    label: str | None = None
    edge_fit: float = float("nan")


def estimate_pose(instance: Instance, model: ThinPartModel, context: SceneContext | None = None,
                  settings: PoseSettings = PoseSettings()) -> PartPose:
    """The pose of `model` explaining `instance` (camera frame), or a failed PartPose
    saying why (see the module docstring)."""
    t0 = time.perf_counter()
    method = f"{settings.method}+icp"
    pts = np.asarray(instance.points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]

    def failed(reason: str, **kw: float) -> PartPose:
        return PartPose(instance.id, False, reason, method, len(pts), time_s=time.perf_counter() - t0,
                        label=instance.label, **kw)

    if len(pts) < settings.min_points:
        return failed(f"only {len(pts)} points (needs {settings.min_points})")
    flat, raw, sigma, inside = _onto_plane(pts, settings.max_plane_rms_mm)
    if sigma > settings.max_plane_rms_mm or inside < settings.min_plane_fraction:
        return failed(f"not one flat part: {inside:.0%} of the points lie within {settings.max_plane_rms_mm:g} mm of "
                      f"their plane (needs {settings.min_plane_fraction:.0%}), robust RMS {sigma:.3g} mm")
    try:
        patch = _patch(flat, context, model.thickness_mm, settings)
    except PoseError as exc:
        return failed(str(exc))
    area = len(pts) * patch.spacing ** 2
    if patch.extent_mm > 1.2 * model.length_mm or area > 1.3 * model.area_mm2:
        return failed(f"larger than one part: {patch.extent_mm:.1f} mm across, ~{area:.0f} mm² "
                      f"(the part: {model.length_mm:.1f} mm, {model.area_mm2:.0f} mm²); merged instances?")
    rng = np.random.default_rng(settings.seed)
    outcome: tuple[str, dict, bool] = ("", {}, True)
    judged: list[tuple[float, str, np.ndarray]] = []   # every attempt's judged poses: a rival found once stays one
    for _ in range(settings.attempts if settings.method == "sacia" else 1):   # SAC-IA is randomised: retry
        outcome = _fit(flat, raw, patch, model, settings, rng, judged)
        if isinstance(outcome, PartPose):
            return replace(outcome, instance_id=instance.id, points=len(pts), time_s=time.perf_counter() - t0,
                           label=instance.label)
        if not outcome[2]:   # no attempt can settle it
            break
    return failed(outcome[0], **outcome[1])


def _fit(pts: np.ndarray, raw: np.ndarray, patch: _Patch, model: ThinPartModel, settings: PoseSettings,
         rng: np.random.Generator, judged: list[tuple[float, str, np.ndarray]]) -> PartPose | tuple[str, dict, bool]:
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
    # when the first explains a mostly visible instance (occlusion below `max_occlusion`)
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
                and _occlusion(patch, model.sides[best_side], T) < settings.max_occlusion)

    first = "front" if np.sign(patch.skew) == np.sign(model.sides["front"].skew) else "back"
    for side in (first, "back" if first == "front" else "front"):
        if explained():
            break
        sm = model.sides[side]
        if settings.method == "sacia":
            rs = RegistrationSettings(descriptors=("fpfh",), coarse="sac-ia", spheres=(100,),
                                      hypotheses=settings.hypotheses, verify=settings.verify, seed=settings.seed)
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
    judged.sort(key=lambda j: -j[0])
    ambiguous = _ambiguity(judged, patch, settings)
    if ambiguous is not None:
        return ambiguous
    score, side, T = judged[0]
    margin = _side_margin(judged)
    sm = model.sides[side]
    v = settings.voxel_mm
    fine = downsample(pts, 2.0 * patch.spacing, "density_centre").points
    fine = fine[rng.choice(len(fine), size=min(600, len(fine)), replace=False)]
    walls = patch.wall_pts[: len(patch.wall_pts) // settings.wall_levels]
    fp = np.concatenate([fine, walls])
    fn = np.concatenate([np.tile(patch.n, (len(fine), 1)), patch.wall_nrm[: len(walls)]])
    T = icp(fp, fn, sm.target.dense, T, 2.0 * v, 2.0 * patch.spacing, settings.max_normal_deg, 15)
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
    kw = dict(fitness=fit, rmse_mm=rmse, occlusion=occl, side_margin=margin, edge_fit=edge)
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
    return PartPose(0, True, "", f"{settings.method}+icp", 0, pose, side, fit, rmse, occl, margin, edge_fit=edge)


def _ambiguity(judged: list[tuple[float, str, np.ndarray]], patch: _Patch,
               settings: PoseSettings) -> tuple[str, dict, bool] | None:
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


def _side_margin(judged: list[tuple[float, str, np.ndarray]]) -> float:
    """Score of the best pose (`judged` sorted best first) minus the best of the other side's."""
    others = [j[0] for j in judged if j[1] != judged[0][1]]
    return judged[0][0] - max(others) if others else float("inf")


def _judge(patch: _Patch, sm: SideModel, sp: np.ndarray, sn: np.ndarray, poses: list[np.ndarray],
           settings: PoseSettings) -> list[tuple[float, str, np.ndarray]]:
    """(outline-fit score, side, pose) of each pose (scan -> part) refined by point-to-plane
    ICP with normal-angle rejection on the instance's extruded cloud `sp`/`sn`: fitness
    (within 1.5 voxels, one batched query) plus the fraction of the true outline on the
    part's outline, minus the fraction of the face over a lower surface. KD-tree queries
    here and in the coarse search are single-threaded: the clouds are small, and starting
    threads costs more than it saves on a busy machine."""
    if not poses:
        return []
    v = settings.voxel_mm
    posed = [icp(sp, sn, sm.target.coarse, T, 6.0 * v, 0.5 * v, settings.max_normal_deg, 15) for T in poses]
    fit = fitness(sp, sn, sm.target.coarse, np.array(posed), 1.5 * v, settings.max_normal_deg, workers=1)
    return [(float(f) + _edge_fit(patch, sm, T, 2 * settings.inlier_mm) - _spill(patch, sm, T), sm.side, T)
            for f, T in zip(fit, posed)]


def _edge_fit(patch: _Patch, sm: SideModel, T: np.ndarray, tol_mm: float) -> float:
    """Fraction of the instance's true outline points within `tol_mm` of the side's outline
    (1 when the instance shows no true outline edge)."""
    if not len(patch.edge_pts):
        return 1.0
    d, _ = sm.outline_tree.query(transform_points(T, patch.edge_pts), distance_upper_bound=tol_mm)
    return float(np.isfinite(d).mean())


def _onto_plane(points: np.ndarray, tol_mm: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(points moved onto their plane along the camera rays, the points kept as measured,
    robust RMS distance to the plane mm, fraction within `tol_mm` of it). The plane is
    fitted robustly (twice, to the points within 3 robust sigma): pixels straddling an
    edge (depth mixed with what lies behind) and decoding outliers do not tilt it, and
    moved along their rays they land where the camera saw them. Points more than
    MAX_OFF_PLANE_MM off belong to something else and are dropped."""
    keep = np.ones(len(points), bool)
    for _ in range(3):
        c = points[keep].mean(axis=0)
        n = np.linalg.svd(points[keep][:: max(1, keep.sum() // 5000)] - c, full_matrices=False)[2][2]
        r = (points - c) @ n
        sigma = 1.4826 * float(np.median(np.abs(r[keep])))
        keep = np.abs(r) < max(3.0 * sigma, 0.01)
    near = np.abs(r) < MAX_OFF_PLANE_MM
    p = points[near]
    ray = p @ n
    flat = p * ((c @ n) / np.where(np.abs(ray) > 1e-9, ray, 1e-9))[:, None]
    return flat, p, sigma, float(np.mean(np.abs(r) < tol_mm))


def _face_cells(patch: _Patch, sm: SideModel, T: np.ndarray, n: int = 1500) -> tuple[np.ndarray, ...]:
    """Grid cells (row, col, inside) of up to n of the side's face samples posed in the camera frame."""
    face = sm.face.points[:: max(1, len(sm.face.points) // n)]
    return patch.cells(transform_points(np.linalg.inv(T), face))


def _spill(patch: _Patch, sm: SideModel, T: np.ndarray) -> float:
    """Fraction of the posed face where a lower surface is seen (it would hide it)."""
    r, c, inside = _face_cells(patch, sm, T)
    return float(np.mean(inside & patch.lower[r, c]))


def _occlusion(patch: _Patch, sm: SideModel, T: np.ndarray) -> float:
    """Fraction of the posed face covered by a higher surface, among its cells that are
    observed, covered or showing a lower surface (unobserved cells left out)."""
    r, c, inside = _face_cells(patch, sm, T)
    covered = inside & patch.higher[r, c] & ~patch.observed[r, c]
    known = inside & (patch.observed[r, c] | patch.higher[r, c] | patch.lower[r, c])
    return float(covered.sum() / max(known.sum(), 1))


def _ndt_poses(src: np.ndarray, patch: _Patch, model: ThinPartModel, sm: SideModel, n_best: int) -> list[np.ndarray]:
    """Paper 001 NDT (Eq. 23-26, `registration`'s Newton steps) from 12 yaws about the
    instance's plane, the side's face laid on it and the centroids matched, on cells of
    2 mm with every other point (300 at most); the 2 n_best best distinct ones (10 deg / 1 mm apart: many yaws end in the same
    place) refined on cells of 1 mm. The n_best by score (scan -> model transforms)."""
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


def estimate_poses(instances: list[Instance], model: ThinPartModel, scene_points: np.ndarray | None = None,
                   settings: PoseSettings = PoseSettings()) -> list[PartPose]:
    """`estimate_pose` for every instance, with the scene's points as context (None: every
    instance edge is taken as a true outline edge)."""
    context = SceneContext(scene_points) if scene_points is not None and len(scene_points) else None
    return [estimate_pose(i, model, context, settings) for i in instances]
