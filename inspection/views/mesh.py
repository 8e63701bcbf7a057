"""A triangle mesh of the merged cloud: screened Poisson reconstruction (Open3D), trimmed
to what the views saw.

Poisson fits one closed (watertight) surface to the oriented points (their normals face the
sensors that saw them, i.e. out of the part), closing every region no view saw by a smooth
guess (the base standing on the platter, a deep bore). The guess is not measured, so
triangles farther than `max_gap_mm` from every merged point are removed: the mesh stays
closed where the views close around the part and is open where they do not. `SurfaceMesh`
says both (`closed_watertight`: the untrimmed surface; `watertight`, `boundary_edges`: the
trimmed one; watertight meaning every edge shared by exactly two triangles, edge-manifold)
and how much area was removed. The octree depth follows the merged cloud's
cell (a leaf about a cell wide, at most depth 10).

Files: `write_mesh` writes PLY or STL by the suffix, each complete or not at all.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from inspection.errors import CloudError
from inspection.views.merge import Merged

MAX_DEPTH = 9  # a 512-cell octree: 0.2 mm leaves on a 100 mm part, about the view's point spacing


@dataclass(frozen=True)
class MeshSettings:
    """`max_gap_mm`: triangles with a vertex farther than this from the merged points are
    removed (None: 4 cells); `max_points`: the merged cloud is thinned to at most this many
    points for the solve; `depth`: Poisson octree depth (None: from the cell)."""

    max_gap_mm: float | None = None
    max_points: int = 400_000
    depth: int | None = None
    seed: int = 0


@dataclass(frozen=True, eq=False)
class SurfaceMesh:
    """`vertices` (V, 3) mm part frame, `triangles` (T, 3); see the module docstring."""

    vertices: np.ndarray
    triangles: np.ndarray
    watertight: bool
    closed_watertight: bool
    boundary_edges: int
    area_mm2: float
    removed_area_mm2: float
    depth: int
    timings_s: dict[str, float]

    def summary(self) -> str:
        state = "watertight" if self.watertight else f"open along {self.boundary_edges} boundary edges"
        return (f"{len(self.triangles)} triangles, {self.area_mm2:.0f} mm^2, {state} (Poisson depth {self.depth}; "
                f"{self.removed_area_mm2:.0f} mm^2 no view saw removed; before that "
                f"{'watertight' if self.closed_watertight else 'not watertight'})")


def mesh_surface(merged: Merged, settings: MeshSettings = MeshSettings()) -> SurfaceMesh:
    """The trimmed Poisson mesh of `merged` (see the module docstring)."""
    import open3d as o3d

    if len(merged) < 1000:
        raise CloudError("merged cloud", f"only {len(merged)} points: too few to mesh")
    t0 = time.perf_counter()
    keep = np.arange(len(merged))
    if len(keep) > settings.max_points:
        keep = np.sort(np.random.default_rng(settings.seed).choice(len(keep), settings.max_points, replace=False))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(merged.points[keep]))
    pc.normals = o3d.utility.Vector3dVector(merged.normals[keep])
    extent = float(np.max(np.ptp(merged.points, axis=0)))
    depth = settings.depth or int(np.clip(math.ceil(math.log2(1.1 * extent / merged.cell_mm)), 6, MAX_DEPTH))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=depth, scale=1.1)
    solved = time.perf_counter() - t0
    t0 = time.perf_counter()
    closed = boundary_edges(np.asarray(mesh.triangles)) == 0 and mesh.is_edge_manifold()
    area_before = float(mesh.get_surface_area())
    gap = settings.max_gap_mm if settings.max_gap_mm is not None else 4.0 * merged.cell_mm
    vertices = np.asarray(mesh.vertices)
    far, _ = cKDTree(merged.points).query(vertices, distance_upper_bound=gap, workers=-1)
    mesh.remove_vertices_by_mask(~np.isfinite(far))
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    mesh.compute_triangle_normals()
    triangles = np.asarray(mesh.triangles)
    boundary = boundary_edges(triangles)
    area = float(mesh.get_surface_area())
    return SurfaceMesh(np.asarray(mesh.vertices).copy(), triangles.copy(), boundary == 0 and mesh.is_edge_manifold(),
                       closed, boundary, area, area_before - area, depth,
                       {"poisson": round(solved, 4), "trim": round(time.perf_counter() - t0, 4)})


def boundary_edges(triangles: np.ndarray) -> int:
    """Edges used by one triangle only: 0 for a closed (watertight) surface."""
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    return int((uses == 1).sum())


def write_mesh(path: str | Path, surface: SurfaceMesh) -> Path:
    """Write `surface` as PLY or STL (binary, by `path`'s suffix); complete or not at all."""
    import open3d as o3d

    path = Path(path)
    if path.suffix.lower() not in (".ply", ".stl"):
        raise CloudError(path, "a mesh is written as .ply or .stl")
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(surface.vertices),
                                     o3d.utility.Vector3iVector(surface.triangles))
    mesh.compute_triangle_normals()
    mesh.compute_vertex_normals()
    tmp = path.with_name(f".{path.stem}.part{path.suffix}")
    if not o3d.io.write_triangle_mesh(tmp, mesh, write_ascii=False):
        raise CloudError(path, "Open3D could not write the mesh")
    tmp.replace(path)
    return path
