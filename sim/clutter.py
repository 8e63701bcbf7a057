"""Cluttered labelled clouds with ground truth, for region growing (paper 002).

`clutter_cloud` builds a room corner (floor, wall), boxes (resting on the floor, against
the wall, touching each other), pipes of several diameters (lying, standing, resting on a
box) and a dome, casts rays from five scanner positions around it (so density varies with
range and view, and contacts and undersides are occluded as in real scans), adds
per-surface roughness along the normal, and labels every point with its surface (each box
face, each pipe's mantle and caps are separate surfaces). Surfaces smaller than the level of detail (area < π r²) are
unlabelled (-1), like the paper's ground truth ignoring small features.

Units: mm, rad.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim.bins import rotation_about


@dataclass(frozen=True, eq=False)
class ClutterCloud:
    """An unordered cloud (N, 3) mm with ground-truth surface labels (N,) (-1: none),
    the surface names (index = label) and the radius of interest it was made for."""

    points: np.ndarray
    labels: np.ndarray
    surfaces: tuple[str, ...]
    radius_mm: float
    roughness_mm: dict[str, float] = field(default_factory=dict)


@dataclass
class _Builder:
    """Triangles with a surface label each, and each surface's roughness."""

    vertices: list[np.ndarray] = field(default_factory=list)
    triangles: list[np.ndarray] = field(default_factory=list)
    labels: list[np.ndarray] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    rough: list[float] = field(default_factory=list)
    count: int = 0

    def surface(self, name: str, roughness: float) -> int:
        self.names.append(name)
        self.rough.append(roughness)
        return len(self.names) - 1

    def add(self, v: np.ndarray, t: np.ndarray, label: int) -> None:
        self.vertices.append(v)
        self.triangles.append(t + self.count)
        self.labels.append(np.full(len(t), label))
        self.count += len(v)

    def quad(self, corners: np.ndarray, label: int) -> None:
        self.add(corners, np.array([[0, 1, 2], [0, 2, 3]]), label)

    def box(self, name: str, size: np.ndarray, pose: np.ndarray, roughness: float) -> None:
        h = np.asarray(size, float) / 2
        for axis in range(3):
            for sign in (-1, 1):
                u, w = [(axis + 1) % 3, (axis + 2) % 3]
                c = np.zeros((4, 3))
                c[:, axis] = sign * h[axis]
                c[:, u] = np.array([-1, 1, 1, -1]) * h[u]
                c[:, w] = np.array([-1, -1, 1, 1]) * h[w]
                face = "xyz"[axis] + ("-" if sign < 0 else "+")
                self.quad(c @ pose[:3, :3].T + pose[:3, 3], self.surface(f"{name}/{face}", roughness))

    def cylinder(self, name: str, radius: float, length: float, pose: np.ndarray, roughness: float,
                 segments: int = 256) -> None:
        a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
        ring = np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)
        bottom = np.c_[ring, np.full(segments, -length / 2)]
        top = np.c_[ring, np.full(segments, length / 2)]
        i = np.arange(segments)
        j = (i + 1) % segments
        mantle = np.concatenate([np.stack([i, j, j + segments], 1), np.stack([i, j + segments, i + segments], 1)])
        world = lambda p: p @ pose[:3, :3].T + pose[:3, 3]  # noqa: E731
        self.add(world(np.concatenate([bottom, top])), mantle, self.surface(f"{name}/mantle", roughness))
        for cap, z in (("cap-", -length / 2), ("cap+", length / 2)):
            fan = np.c_[np.zeros((1, 2)), [[z]]]
            verts = np.concatenate([fan, np.c_[ring, np.full(segments, z)]])
            self.add(world(verts), np.stack([np.zeros(segments, int), i + 1, j + 1], 1),
                     self.surface(f"{name}/{cap}", roughness))

    def dome(self, name: str, radius: float, centre: np.ndarray, roughness: float, n: int = 64) -> None:
        """The upper half of a sphere (a UV mesh)."""
        th = np.linspace(0, np.pi / 2, n // 2 + 1)
        ph = np.linspace(0, 2 * np.pi, n, endpoint=False)
        T, Ph = np.meshgrid(th, ph, indexing="ij")
        v = np.stack([np.sin(T) * np.cos(Ph), np.sin(T) * np.sin(Ph), np.cos(T)], -1).reshape(-1, 3) * radius + centre
        rows, cols = len(th), len(ph)
        r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols), indexing="ij")
        a = r * cols + c
        b = r * cols + (c + 1) % cols
        t = np.concatenate([np.stack([a, b + cols, b], -1).reshape(-1, 3),
                            np.stack([a, a + cols, b + cols], -1).reshape(-1, 3)])
        self.add(v, t, self.surface(name, roughness))


def _pose(yaw: float = 0.0, tilt_axis: str | None = None,
          position: tuple[float, float, float] = (0, 0, 0)) -> np.ndarray:
    T = np.eye(4)
    R = rotation_about(np.array([0.0, 0.0, 1.0]), yaw)
    if tilt_axis == "x":   # a cylinder's axis (its z) laid along the yawed x
        R = R @ rotation_about(np.array([0.0, 1.0, 0.0]), np.pi / 2)
    T[:3, :3] = R
    T[:3, 3] = position
    return T


def clutter_cloud(seed: int = 0, spacing_mm: float = 1.0, radius_mm: float | None = 12.0) -> ClutterCloud:
    """A cluttered room corner scanned from five positions (see the module docstring);
    `spacing_mm` sets the nearest scanner's point spacing (the others are coarser);
    `radius_mm` the radius of interest (None: `slscan segment`'s default for the cloud,
    `inspection.regions.region_growing.default_radius`)."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    b = _Builder()
    rough = lambda: float(rng.choice([0.05, 0.1, 0.2, 0.4]))  # noqa: E731
    b.quad(np.array([[-350, -250, 0], [350, -250, 0], [350, 250, 0], [-350, 250, 0]], float),
           b.surface("floor", rough()))
    b.quad(np.array([[-350, 250, 0], [350, 250, 0], [350, 250, 300], [-350, 250, 300]], float),
           b.surface("wall", rough()))
    jitter = lambda s: rng.uniform(-s, s)  # noqa: E731
    # a layout with clearance between objects (no interpenetration), jittered within it:
    # a box against the wall with a box on top, two boxes touching side by side (different
    # heights), pipes lying on the floor, one standing, a dome
    x0 = -180 + jitter(10)
    b.box("box0", np.array([160, 90, 120]), _pose(0, None, (x0, 250 - 45, 60)), rough())
    b.box("box3", np.array([70, 60, 40]), _pose(jitter(0.5), None, (x0 + jitter(20), 205 + jitter(5), 140)), rough())
    yaw = jitter(0.3)
    b.box("box1", np.array([100, 100, 70]), _pose(yaw, None, (80, -60, 35)), rough())
    # box2 touches box1's x+ face with one vertical edge, turned 0.35 rad from it (touching
    # faces of two aligned boxes would be one plane: one surface, not two)
    turn = 0.35
    offset = np.array([50 + 40 * np.cos(turn) + 50 * np.sin(turn), -25.0])   # the edge at y = 8 on the face
    beside = np.array([80.0, -60.0]) + rotation_about(np.array([0, 0, 1.0]), yaw)[:2, :2] @ offset
    b.box("box2", np.array([80, 100, 110]), _pose(yaw + turn, None, (beside[0], beside[1], 55)), rough())
    for k, (r_pipe, x, y, along_y, length) in enumerate(((8.0, -300, -130, True, 180), (15.0, -240, -130, True, 180),
                                                         (25.0, 170, 110, False, 220), (40.0, -80, 70, False, 200))):
        b.cylinder(f"pipe{k}", r_pipe, length, _pose(np.pi / 2 * along_y + jitter(0.1), "x", (x, y, r_pipe)), rough())
    b.cylinder("pipe_standing", 20.0, 180, _pose(0, None, (280 + jitter(10), -150 + jitter(10), 90)), rough())
    b.dome("dome", 45.0, np.array([-250 + jitter(5), 20 + jitter(5), 0.0]), rough())

    V = np.concatenate(b.vertices)
    T = np.concatenate(b.triangles)
    tri_label = np.concatenate(b.labels)
    scene = o3d.t.geometry.RaycastingScene()
    cpu = o3d.core.Device("CPU:0")
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32), o3d.core.float32, cpu),
                        o3d.core.Tensor(T.astype(np.uint32), o3d.core.uint32, cpu))
    points, labels = [], []
    target = np.array([0.0, 0.0, 60.0])
    for pos, step in (((-500, -700, 650), 1.0), ((550, -650, 700), 1.4), ((0, -900, 900), 1.8),
                      ((-650, 100, 750), 2.2), ((700, 150, 800), 2.0)):
        origin = np.asarray(pos, float) + rng.uniform(-30, 30, 3)
        dist = float(np.linalg.norm(target - origin))
        dirs = _view_rays(origin, target, 1.25 * 450 / dist, step * spacing_mm / dist)
        rays = np.c_[np.tile(origin, (len(dirs), 1)), dirs].astype(np.float32)
        ans = scene.cast_rays(o3d.core.Tensor(rays, o3d.core.float32, cpu))
        t = ans["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t)
        prim = ans["primitive_ids"].numpy()[hit].astype(np.int64)
        nrm = ans["primitive_normals"].numpy()[hit].astype(np.float64)
        p = origin + dirs[hit] * t[hit, None]
        lab = tri_label[prim]
        sigma = np.asarray(b.rough)[lab]
        p += nrm * (sigma * rng.standard_normal(len(p)))[:, None]
        points.append(p)
        labels.append(lab)
    P = np.concatenate(points)
    lab = np.concatenate(labels).astype(np.int32)
    if radius_mm is None:
        from inspection.regions.region_growing import default_radius

        radius_mm = default_radius(P)
    lab = _drop_small(P, lab, radius_mm)
    return ClutterCloud(P, lab, tuple(b.names), radius_mm, dict(zip(b.names, b.rough)))


def _view_rays(origin: np.ndarray, target: np.ndarray, half_angle: float, step: float) -> np.ndarray:
    """Unit ray directions on a square angular grid of `step` rad around the view axis."""
    axis = (target - origin) / np.linalg.norm(target - origin)
    u = np.cross(axis, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    a = np.arange(-half_angle, half_angle, step)
    A, B = np.meshgrid(a, a)
    d = axis + np.tan(A.ravel())[:, None] * u + np.tan(B.ravel())[:, None] * v
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _drop_small(points: np.ndarray, labels: np.ndarray, radius_mm: float) -> np.ndarray:
    """Unlabel surfaces whose sampled area (occupied voxels of 0.1 r) is below π r²."""
    voxel = 0.1 * radius_mm
    key = np.floor(points / voxel).astype(np.int64)
    cells = np.unique(np.c_[labels, key], axis=0)
    area = np.bincount(cells[:, 0], minlength=labels.max() + 1) * voxel * voxel
    small = area < np.pi * radius_mm ** 2
    return np.where(small[labels], -1, labels).astype(np.int32)
