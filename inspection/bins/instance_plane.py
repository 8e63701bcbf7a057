"""An instance of a thin flat part in its own plane (paper 001, section 3): its plane (SVD;
normal toward the camera) and an occupancy grid in that plane, with the scene's points
brought onto it along the camera rays (so what the camera sees beside an edge lands beside
it); a boundary point is on a "true" outline edge unless the first surface seen beyond it
(past a shadow, up to `SHADOW_MM`) is higher — a part lying across it. Only true edges get
walls, placed on the outermost points and moved out by half a point spacing (the mean
inset of pixel samples behind an edge) plus the part's share of the next pixel out, which
a tall step leaves out of the instance (`ring_cover`). Camera frame, mm; the camera at
the origin.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from inspection.bins.part_model import skew_moment
from inspection.bins.pose_settings import PoseError, PoseSettings
from scanner.pointcloud import OrganisedCloud

MAX_OFF_PLANE_MM = 1.0  # instance points farther from its plane are not on the part
SHADOW_MM = 2.5  # beyond an edge, look this far for the first surface seen (past shadows)


@dataclass(eq=False)
class SceneContext:
    """All scan points of the scene (camera frame, mm) and their KD-tree: what lies around
    an instance tells its true outline edges from the edges where a part covers it. With
    the organised scan (`image` (H, W, 3), NaN where invalid) and its `camera` (a
    `scanner.geometry.Pinhole`), `beyond` compares any camera-frame point with what its
    pixel measured. The KD-tree is built unbalanced: median splits are 3x dearer to build
    for a scan's million points and no faster for the few ball queries made (the same
    points are found)."""

    points: np.ndarray
    image: np.ndarray | None = None
    camera: Any = None
    tree: cKDTree = field(init=False)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64)
        self.tree = cKDTree(self.points, balanced_tree=False, compact_nodes=False)

    @classmethod
    def of_cloud(cls, cloud: OrganisedCloud, camera: Any) -> SceneContext:
        return cls(cloud.points[cloud.valid], cloud.points, camera)

    def beyond(self, p: np.ndarray) -> np.ndarray:
        """Per camera-frame point (N, 3): how far (mm) beyond it, along its camera ray, the
        scan measured the surface at its pixel (negative: the scan saw something in front
        of it; NaN: its pixel has no measurement or lies outside the image)."""
        out = np.full(len(p), np.nan)
        if self.image is None:
            return out
        h, w = self.image.shape[:2]
        px = np.rint(self.camera.project(p)).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h) & (p[:, 2] > 0)
        seen = self.image[px[inside, 1], px[inside, 0]].astype(np.float64)
        out[inside] = np.linalg.norm(seen, axis=1) - np.linalg.norm(p[inside], axis=1)
        return out


@dataclass(eq=False)
class InstancePatch:
    """An instance in its own plane: centroid `c`, basis `e1`, `e2`, normal `n` (toward the
    camera), point `spacing`; grid (origin `lo`, cell `g`) labels: `observed` (the
    instance), `higher` (a surface above its plane seen there), `lower` (below it,
    outside the instance); `edge_pts` its true outline points (camera frame) and the
    walls dropped from them (`wall_pts`, outward `wall_nrm`); RMS distance of its points
    to the plane and its extent in the plane (mm); `evidence`: the face evidence of poses
    judged so far (`inspection.bins.pose`, the same pose is asked for more than once)."""

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
    step: float = 0.05
    context: SceneContext | None = None
    evidence: dict[tuple[int, bytes], tuple[float, float]] = field(default_factory=dict, repr=False)

    def cells(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) grid cells of camera-frame points (via their plane coordinates)."""
        d = p - self.c
        ij = np.floor((np.stack([d @ self.e2, d @ self.e1], axis=1) - self.lo[::-1]) / self.g).astype(np.int64)
        h, w = self.observed.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < h) & (ij[:, 1] >= 0) & (ij[:, 1] < w)
        return np.clip(ij[:, 0], 0, h - 1), np.clip(ij[:, 1], 0, w - 1), inside


def instance_patch(points: np.ndarray, context: SceneContext | None, thickness: float,
                   settings: PoseSettings) -> InstancePatch:
    """The instance's plane, grid labels, true outline points and walls (see the module
    docstring); scene points more than half the part's `thickness` (or 4 plane RMS) above
    the plane, toward the camera, count as higher, the others as lower."""
    c = points.mean(axis=0)
    d = points - c
    _, _, vt = np.linalg.svd(d[:: max(1, len(d) // 5000)], full_matrices=False)
    n = vt[2] * (-1.0 if vt[2] @ c > 0 else 1.0)   # toward the camera at the origin
    e1 = vt[0] - (vt[0] @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    uv = np.stack([d @ e1, d @ e2], axis=1)
    height = d @ n
    plane_rms = float(np.sqrt(np.mean(height ** 2)))
    tree = cKDTree(uv, balanced_tree=False, compact_nodes=False)   # built for two queries: the cheap build
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
    step = max(0.5 * thickness, 4 * plane_rms, 0.05)
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
    outer_pts = c + uv[idx] @ np.stack([e1, e2]) + np.outer(height[idx], n)
    edge_pts = outer_pts + (0.5 + ring_cover(outer_pts, out3, spacing, step, context))[:, None] * spacing * out3
    depth = settings.extrude_mm * np.arange(1, settings.wall_levels + 1) / settings.wall_levels
    walls = (edge_pts[None] - depth[:, None, None] * n).reshape(-1, 3)
    return InstancePatch(c, e1, e2, n, spacing, lo, g, observed, higher, lower, edge_pts,
                  walls, np.tile(out3, (len(depth), 1)), plane_rms, float(np.linalg.norm(np.ptp(uv, axis=0))),
                  skew_moment(observed), step, context)


def ring_cover(outer: np.ndarray, out3: np.ndarray, spacing: float, step: float,
               context: SceneContext | None) -> np.ndarray:
    """Per outermost instance point (camera frame, outward in-plane directions `out3`): how
    much (0..1) of the next pixel out the part covers, beyond the half pixel of the mean
    inset. Where the part stands above what lies beyond it, that pixel straddles the edge:
    its depth is a blend of the part's and the lower surface's, too far off the plane for
    the flat patch, so the instance lost it and the outline would sit a pixel inside. Its
    depth beyond the plane (`b1`, mm along the ray) against that of the lower surface two or
    three pixels out (`b_far`) tells the part's share, 1 - b1 / b_far; a pixel with no
    measurement between a part and a lower surface counts half covered (the share's mean).
    0 where nothing lower is seen within three pixels (a step under `step` mm: the ring is
    in the instance) or without the organised scan."""
    cover = np.zeros(len(outer))
    if context is None or context.image is None or not len(outer):
        return cover
    b1, b2, b3 = (context.beyond(outer + k * spacing * out3) for k in (1.0, 2.0, 3.0))
    with np.errstate(invalid="ignore"):
        far = np.fmax(b2, b3)
        lower = far > step
        share = np.clip(1.0 - b1 / np.where(lower, far, 1.0), 0.0, 1.0)
    cover[lower] = np.where(np.isnan(b1[lower]), 0.5, share[lower])
    return cover


def onto_plane(points: np.ndarray, tol_mm: float) -> tuple[np.ndarray, np.ndarray, float, float]:
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
