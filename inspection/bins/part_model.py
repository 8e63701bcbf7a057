"""The model of a thin flat part, from its triangle mesh (paper 001, sections 3-4).

A thin sheet-metal part (paper 001's nickel tab; `inspection.bins.part_file.TabPart`) seen from above is
a flat patch: its 0.25 mm walls are below the scanner's resolution, so local 3D
descriptors see a plane and nothing else, and its two faces are indistinguishable by
depth. What carries the pose in the plane, and the side, is the outline. So the model is
turned into "extruded" clouds — the visible face plus walls dropped from its outline, away
from the camera, `PoseSettings.extrude_mm` deep — on which FPFH, NDT and point-to-plane ICP
see the outline as 3D shape: the part's thin axis (area-weighted normal covariance), its
two large faces (front: normal along the axis, back: against it), dense face samples, the
boundary edges of each face (exact, from the mesh) sampled with outward normals, and one
extruded cloud per side (`SideModel`). Part frame, mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from inspection.bins.pose_settings import DEFAULT_POSE_SETTINGS, PoseSettings
from inspection.errors import CadError
from inspection.registration import ModelTarget, Samples

INTERIOR_MM = 0.5   # face samples this far inside the outline are its interior


@dataclass(eq=False)
class SideModel:
    """One side of the part facing the camera (part frame): `face` samples of the visible
    face with its outward normal, `outline` samples of its boundary with outward in-plane
    normals, `target`: face plus walls dropped `extrude_mm` away from the camera, and
    `skew`: Hu's seventh moment of the face's silhouette as the camera sees it (its sign
    tells the side of a chiral outline; `skew_moment`)."""

    side: str
    face: Samples
    outline: np.ndarray
    outline_normals: np.ndarray
    target: ModelTarget
    skew: float
    ndt: dict[float, tuple] = field(default_factory=dict)
    outline_tree: cKDTree = field(init=False)
    interior: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.outline_tree = cKDTree(self.outline)
        # face samples away from the outline: where a scan measures the face itself, not
        # a pixel straddling its edge (depth mixed with what lies beyond)
        away = self.outline_tree.query(self.face.points)[0] > INTERIOR_MM
        self.interior = self.face.points[away][:: max(1, int(away.sum()) // 1500)]


@dataclass(eq=False)
class ThinPartModel:
    """A thin flat part from its mesh (part frame, mm): `axis` the unit normal of the front
    face, `thickness_mm`, face `area_mm2`, in-plane `length_mm` (largest extent) and the
    two `sides`; `u0` the face's principal in-plane direction (for NDT starts); where a
    robot grips it, when its part file says: `grip_point_mm` (x, y in the outline plane)
    and `approach` (unit, part frame, from the part toward the gripper, front face up)."""

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    axis: np.ndarray
    u0: np.ndarray
    thickness_mm: float
    area_mm2: float
    length_mm: float
    sides: dict[str, SideModel]
    grip_point_mm: tuple[float, float] | None = None
    approach: tuple[float, float, float] | None = None

    def up_face(self, side: str) -> tuple[np.ndarray | None, np.ndarray]:
        """(grip point on the face that is up (part frame, mm; None without a grip point),
        unit approach direction (part frame)) for `side` up: the file's approach, mirrored
        through the mid-plane when the back is up, or else the up face's outward normal."""
        sign = 1.0 if side == "front" else -1.0
        a = np.asarray(self.approach if self.approach is not None else self.axis, np.float64)
        if side == "back":
            a = a - 2.0 * (a @ self.axis) * self.axis
        grip = None
        if self.grip_point_mm is not None:
            levels = self.vertices @ self.axis
            level = levels.max() if sign > 0 else levels.min()
            g = np.r_[self.grip_point_mm, 0.0]
            grip = g + (level - g @ self.axis) * self.axis
        return grip, a / np.linalg.norm(a)

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, triangles: np.ndarray, name: str,
                  settings: PoseSettings = DEFAULT_POSE_SETTINGS, spacing_mm: float = 0.1) -> ThinPartModel:
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
                                 f"{name} ({side} up)", voxel_mm=settings.voxel_mm)
            up = sign * axis   # toward the camera; (u0, up x u0, up) right-handed like an instance's grid
            uv = np.stack([pts @ u0, pts @ np.cross(up, u0)], axis=1)
            ij = np.floor((uv - uv.min(axis=0)) / (2.0 * spacing_mm)).astype(np.int64)
            mask = np.zeros(ij.max(axis=0)[::-1] + 1, np.uint8)
            mask[ij[:, 1], ij[:, 0]] = 1
            skew = skew_moment(cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)))
            sides[side] = SideModel(side, Samples(pts, face_n), b_pts, b_nrm, target, skew)
        if u0 is None:  # the first side's samples set it
            raise CadError(name, "no in-plane direction: no face samples")
        return cls(name, v, t, axis, u0, thickness, face_area, length, sides)


def skew_moment(mask: np.ndarray) -> float:
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
