"""Simulated parts for inspection: a CAD tessellation placed in front of the rig as one
scene object per CAD face (so the ground truth's object id names the face), lying on a
table, optionally with known form defects imposed analytically.

Defects move a face's vertices along the face's outward normal by a known height field
d (mm, positive = excess material):

    PlaneBow    d = h (1 - r^2/rho^2), r the in-plane distance from a centre on the plane
    Lobing      d = a cos(k (theta - phase)), theta the angle about a cylinder's axis
    Taper       d = s (p - o).axis: the radius grows by s mm per mm along the axis
    Roughness   d = sum of plane waves of random direction and phase, wavelengths in a
                band, RMS height `sq_mm` over the plane (a Gaussian-like random field)

A plane with a bow or roughness is first refined (red-green midpoint refinement, so the
mesh stays watertight within the face) until no edge is longer than the defect's
`max_edge_mm`, so the mesh follows d to far below a micrometre. Every geometry array is
in mm; poses map the part frame to the camera frame (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scanner.native_threads import native_threads
from sim.scene import FIRST_OBJECT_ID, Scene, SceneObject

TABLE_SIZE_MM = (1000.0, 1000.0)


def _frame(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing `normal` to a right-handed frame."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


@dataclass(frozen=True)
class PlaneBow:
    """A dome (h > 0) or dish (h < 0) on plane face `face`: d = h (1 - r^2/rho^2)."""

    face: int
    centre_mm: tuple[float, float, float]
    normal: tuple[float, float, float]
    height_mm: float
    radius_mm: float
    max_edge_mm: float = 1.0

    def height(self, p: np.ndarray) -> np.ndarray:
        n = np.asarray(self.normal, float)
        d = p - np.asarray(self.centre_mm, float)
        r2 = np.einsum("ij,ij->i", d, d) - (d @ n) ** 2
        return self.height_mm * (1.0 - r2 / self.radius_mm ** 2)

    def direction(self, p: np.ndarray) -> np.ndarray:
        return np.broadcast_to(np.asarray(self.normal, float), p.shape)


@dataclass(frozen=True)
class _AxisDefect:
    face: int
    origin_mm: tuple[float, float, float]
    axis: tuple[float, float, float]
    sense: int  # +1: the material's outward normal points away from the axis (a boss), -1 (a bore)

    def direction(self, p: np.ndarray) -> np.ndarray:
        a = np.asarray(self.axis, float)
        d = p - np.asarray(self.origin_mm, float)
        radial = d - np.outer(d @ a, a)
        return self.sense * radial / np.linalg.norm(radial, axis=1, keepdims=True)


@dataclass(frozen=True)
class Lobing(_AxisDefect):
    """k lobes of amplitude a on cylinder face `face`: d = a cos(k (theta - phase)), theta
    measured about `axis` from `x_ref`."""

    lobes: int = 3
    amplitude_mm: float = 0.0
    phase_rad: float = 0.0
    x_ref: tuple[float, float, float] = (1.0, 0.0, 0.0)
    max_edge_mm: float | None = None

    def height(self, p: np.ndarray) -> np.ndarray:
        a = np.asarray(self.axis, float)
        x = np.asarray(self.x_ref, float)
        y = np.cross(a, x)
        d = p - np.asarray(self.origin_mm, float)
        theta = np.arctan2(d @ y, d @ x)
        return self.amplitude_mm * np.cos(self.lobes * (theta - self.phase_rad))


@dataclass(frozen=True)
class Taper(_AxisDefect):
    """The radius of cylinder face `face` grows by `per_mm` mm per mm along `axis` from
    `origin_mm` (d = 0 there)."""

    per_mm: float = 0.0
    max_edge_mm: float | None = None

    def height(self, p: np.ndarray) -> np.ndarray:
        return self.per_mm * ((p - np.asarray(self.origin_mm, float)) @ np.asarray(self.axis, float))


@dataclass(frozen=True)
class Roughness:
    """A random areal texture on plane face `face`: `waves` plane waves with wavelengths
    uniform in `wavelengths_mm`, random directions and phases, equal amplitudes, RMS
    height `sq_mm` (the ensemble value; `height` gives the realised field)."""

    face: int
    origin_mm: tuple[float, float, float]
    normal: tuple[float, float, float]
    sq_mm: float
    wavelengths_mm: tuple[float, float] = (1.5, 3.0)
    waves: int = 96
    seed: int = 0
    max_edge_mm: float = 0.06
    _k: np.ndarray = field(init=False, repr=False, compare=False)
    _phase: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        lam = rng.uniform(*self.wavelengths_mm, self.waves)
        ang = rng.uniform(0.0, np.pi, self.waves)
        k = 2 * np.pi / lam
        object.__setattr__(self, "_k", np.stack([k * np.cos(ang), k * np.sin(ang)], axis=1))
        object.__setattr__(self, "_phase", rng.uniform(0.0, 2 * np.pi, self.waves))

    def height(self, p: np.ndarray) -> np.ndarray:
        u, v = _frame(np.asarray(self.normal, float))
        d = p - np.asarray(self.origin_mm, float)
        xy = np.stack([d @ u, d @ v], axis=1)
        amp = self.sq_mm * np.sqrt(2.0 / self.waves)
        return amp * np.cos(xy @ self._k.T + self._phase).sum(axis=1)

    def direction(self, p: np.ndarray) -> np.ndarray:
        return np.broadcast_to(np.asarray(self.normal, float), p.shape)


Defect = PlaneBow | Lobing | Taper | Roughness


def refine(vertices: np.ndarray, triangles: np.ndarray, max_edge_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Red-green midpoint refinement of a planar mesh until no edge is longer than
    `max_edge_mm`: every long edge is split at its midpoint, shared by both its triangles,
    so the refined mesh has no cracks; orientation is kept."""
    v = np.asarray(vertices, float)
    t = np.asarray(triangles, np.int64)
    while True:
        e = np.stack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]], axis=1)  # (T, 3, 2): edge k opposite vertex k+2
        key = np.sort(e.reshape(-1, 2), axis=1)
        # pair (i, j), i <= j < n, as one int64 i n + j: a 1-D unique in the same order as
        # the row-wise one (which sorts a structured view, several times slower)
        n = len(v)
        code, inv = np.unique(key[:, 0] * n + key[:, 1], return_inverse=True)
        uniq = np.stack([code // n, code % n], axis=1)
        inv = inv.reshape(-1, 3)
        long = np.linalg.norm(v[uniq[:, 0]] - v[uniq[:, 1]], axis=1) > max_edge_mm
        if not long.any():
            return v, t.astype(np.int32)
        mid_index = np.full(len(uniq), -1, np.int64)
        mid_index[long] = len(v) + np.arange(long.sum())
        v = np.concatenate([v, 0.5 * (v[uniq[long, 0]] + v[uniq[long, 1]])])
        split = long[inv]  # (T, 3)
        m = split.sum(axis=1)
        # roll each triangle so its split pattern is canonical: one split -> edge 0; two -> edge 2 unsplit
        roll = np.zeros(len(t), np.int64)
        roll[m == 1] = np.argmax(split[m == 1], axis=1)
        roll[m == 2] = (np.argmin(split[m == 2], axis=1) + 1) % 3
        idx = (np.arange(3)[None, :] + roll[:, None]) % 3
        tv = np.take_along_axis(t, idx, axis=1)
        mid = np.take_along_axis(mid_index[inv], idx, axis=1)
        a, b, c = tv[:, 0], tv[:, 1], tv[:, 2]
        m0, m1, m2 = mid[:, 0], mid[:, 1], mid[:, 2]
        out = [tv[m == 0]]
        s = m == 1
        out += [np.stack([a[s], m0[s], c[s]], 1), np.stack([m0[s], b[s], c[s]], 1)]
        s = m == 2
        out += [np.stack([m0[s], b[s], m1[s]], 1), np.stack([a[s], m0[s], m1[s]], 1), np.stack([a[s], m1[s], c[s]], 1)]
        s = m == 3
        out += [np.stack([a[s], m0[s], m2[s]], 1), np.stack([m0[s], b[s], m1[s]], 1),
                np.stack([m2[s], m1[s], c[s]], 1), np.stack([m0[s], m1[s], m2[s]], 1)]
        t = np.concatenate(out)


def deform(vertices: np.ndarray, triangles: np.ndarray, face: np.ndarray,
           defects: list[Defect]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, triangles, face) of a per-face tessellation (vertices not shared between
    faces, e.g. `inspection.cad.Tessellation`) with `defects` imposed: faces with a
    planar defect are refined first, then every vertex of a face moves by the sum of its
    defects' heights along their directions. BLAS runs on one thread inside, as for
    `sim.render.compute_ground_truth` (the heights are thin products over every vertex)."""
    verts, tris, labels = [], [], []
    offset = 0
    with native_threads(1):
        for f in np.unique(face):
            fv, ft = _face_mesh(vertices, triangles, face, int(f))
            mine = [d for d in defects if d.face == f]
            edges = [d.max_edge_mm for d in mine if d.max_edge_mm is not None]
            if edges:
                fv, ft = refine(fv, ft, min(edges))
            moved = fv.copy()
            for d in mine:
                moved += d.height(fv)[:, None] * d.direction(fv)
            verts.append(moved)
            tris.append(ft + offset)
            labels.append(np.full(len(ft), f, np.int32))
            offset += len(fv)
    return np.concatenate(verts), np.concatenate(tris).astype(np.int32), np.concatenate(labels)


def _face_mesh(vertices: np.ndarray, triangles: np.ndarray, face: np.ndarray, f: int) -> tuple[np.ndarray, np.ndarray]:
    tri = triangles[face == f]
    used, inverse = np.unique(tri, return_inverse=True)
    return vertices[used], inverse.reshape(-1, 3).astype(np.int64)


def lying_pose(vertices: np.ndarray, turn_rad: float = 0.0, distance_mm: float = 400.0,
               tilt_rad: tuple[float, float] = (0.0, 0.0),
               up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Part -> camera pose of a part whose CAD `up` direction faces the camera, turned by
    `turn_rad` about the camera axis and tilted by `tilt_rad` (about the camera's x and y
    axes), its bounding box centred on the camera axis at `distance_mm`."""
    from scipy.spatial.transform import Rotation

    to_z, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [up])  # CAD up -> +z
    R = (Rotation.from_euler("xy", tilt_rad) * Rotation.from_euler("z", turn_rad)
         * Rotation.from_euler("x", np.pi) * to_z).as_matrix()
    w = vertices @ R.T
    pose = np.eye(4)
    pose[:3, :3] = R
    pose[:3, 3] = np.array([0.0, 0.0, distance_mm]) - (w.min(axis=0) + w.max(axis=0)) / 2
    return pose


def part_scene(vertices: np.ndarray, triangles: np.ndarray, face: np.ndarray, pose: np.ndarray,
               *, up: tuple[float, float, float] = (0.0, 0.0, 1.0), albedo: float = 0.7, table: bool = True,
               name: str = "part") -> tuple[Scene, np.ndarray]:
    """(scene, face_of_id): one mesh object per face, placed by `pose` (part -> camera),
    lying on a table: the plane through the part's lowest point along its CAD `up`
    direction, perpendicular to it. `face_of_id[object id]` is the CAD face index an
    object id shows, -1 for the background and the table."""
    faces = np.unique(face)
    objects = []
    for f in faces:
        fv, ft = _face_mesh(vertices, triangles, face, int(f))
        objects.append(SceneObject(name=f"{name}_face{int(f)}", kind="mesh", pose=pose, albedo=albedo,
                                   vertices=fv, triangles=ft.astype(np.int32), body=name))
    plane = None
    if table:
        n = np.asarray(up, float) / np.linalg.norm(up)
        low = vertices[np.argmin(vertices @ n)]
        u, v = _frame(n)
        T = np.eye(4)
        T[:3, :3] = np.stack([u, v, n], axis=1)  # the table's z = 0 is the plane, in part coordinates
        T[:3, 3] = low
        plane = SceneObject(name="table", kind="plane", pose=pose @ T, albedo=0.8, size_mm=TABLE_SIZE_MM)
    face_of_id = np.full(FIRST_OBJECT_ID + len(faces), -1, np.int64)
    face_of_id[FIRST_OBJECT_ID:] = faces
    return Scene(objects=tuple(objects), reference_plane=plane, name=name), face_of_id
