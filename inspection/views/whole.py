"""The whole part from a multi-view session: align the views, fuse them, mesh the part, and
write the results into the session's outputs/ (`scanner.multiview`):

    alignment.json   each view's prior and refined pose (part_from_view), the pairs and the
                     pairs refused, timings, and the stage model the priors came from
                     (`stage_model`: its axes and `calibration`, the stage-axis file or "")
    merged.ply       the fused cloud of the part (the platter it stood on removed): x y z,
                     nx ny nz, sigma (expected noise, relative mm) and views (how many views
                     each point fuses), part frame, mm
    mesh.ply, mesh.stl   the trimmed Poisson mesh of the merged cloud (`mesh.py`)
    views.json       the figures: points, cell, timings, the mesh's state

Every file appears complete or not at all.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from inspection.measured_cloud import ScanCloud
from inspection.views.align import Alignment, AlignSettings, align_views
from inspection.views.merge import Merged, fuse, platter_plane
from inspection.views.mesh import MeshSettings, SurfaceMesh, mesh_surface, write_mesh
from inspection.views.view_clouds import ViewCloud, load_views
from scanner.multiview import MultiViewSession
from scanner.session import write_json
from scanner.stage import AxisKind
from scanner.stage_model import StageModel

Progress = Callable[[str, int, int], None]


def _quiet(stage: str, done: int, total: int) -> None:
    pass


@dataclass(frozen=True)
class ViewsSettings:
    """`cell_mm`: the fusion cell (None: the median point spacing of the views);
    `platter_mm`: points within this of the platter plane are not the part (None: keep the
    platter); the alignment's and the mesh's own settings."""

    align: AlignSettings = field(default_factory=AlignSettings)
    mesh: MeshSettings = field(default_factory=MeshSettings)
    cell_mm: float | None = None
    platter_mm: float | None = 1.0
    seed: int = 0


@dataclass(frozen=True, eq=False)
class WholePart:
    session: MultiViewSession
    views: list[ViewCloud]
    alignment: Alignment
    merged: Merged
    mesh: SurfaceMesh | None
    timings_s: dict[str, float]


def point_spacing(view: ViewCloud, sample: int = 2000, seed: int = 0) -> float:
    """Median distance from a point of `view` to its nearest neighbour (mm)."""
    from scipy.spatial import cKDTree

    idx = np.random.default_rng(seed).choice(len(view), size=min(sample, len(view)), replace=False)
    d, _ = cKDTree(view.points).query(view.points[idx], k=2, workers=-1)
    return float(np.median(d[:, 1]))


def whole_part(session: MultiViewSession, settings: ViewsSettings = ViewsSettings(), mesh: bool = True,
               progress: Progress = _quiet, stage_model: StageModel | None = None) -> WholePart:
    """Align, fuse and mesh the views of `session`; write outputs/ (see the module docstring).
    `stage_model`: the stage geometry the priors come from (a stage-axis calibration made
    after the scan, `MultiViewSession.stage_axis_file`); default the one the views were
    captured with."""
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    progress("load views", 0, len(session.views))
    views = load_views(session, stage_model)
    times["load"] = time.perf_counter() - t0
    progress("align", 0, 1)
    alignment = align_views(views, settings.align)
    times["align"] = sum(alignment.timings_s.values())
    progress("merge", 0, 1)
    t0 = time.perf_counter()
    cell = settings.cell_mm or point_spacing(views[0])
    kept = views
    if settings.platter_mm is not None:
        kept = off_platter(views, list(alignment.poses), _turning_axis(stage_model or session.stage_model),
                           settings.platter_mm, settings.seed)
    merged = fuse(kept, list(alignment.poses), cell)
    times["merge"] = time.perf_counter() - t0
    surface = None
    if mesh:
        progress("mesh", 0, 1)
        t0 = time.perf_counter()
        surface = mesh_surface(merged, settings.mesh)
        times["mesh"] = time.perf_counter() - t0
    out = session.outputs
    out.mkdir(exist_ok=True)
    write_json(out / "alignment.json", {**alignment.as_dict(),
                                        "stage_model": (stage_model or session.stage_model).to_dict()})
    write_merged(out / "merged.ply", merged)
    figures: dict[str, Any] = {"views": len(views), "points": len(merged), "cell_mm": cell,
                               "fused_points": int((merged.views > 1).sum()), "timings_s": times}
    if surface is not None:
        write_mesh(out / "mesh.ply", surface)
        write_mesh(out / "mesh.stl", surface)
        figures["mesh"] = {"triangles": len(surface.triangles), "area_mm2": surface.area_mm2,
                           "watertight": surface.watertight, "closed_watertight": surface.closed_watertight,
                           "boundary_edges": surface.boundary_edges, "removed_area_mm2": surface.removed_area_mm2,
                           "depth": surface.depth}
    write_json(out / "views.json", figures)
    progress("done", 1, 1)
    return WholePart(session, views, alignment, merged, surface, {k: round(v, 4) for k, v in times.items()})


def _turning_axis(model: StageModel) -> np.ndarray:
    rotary = [a for a in model.axes if a.kind is AxisKind.ROTARY]
    return rotary[-1].direction if rotary else model.axes[-1].direction


def off_platter(views: list[ViewCloud], poses: list[np.ndarray], axis: np.ndarray, tolerance_mm: float,
                seed: int = 0) -> list[ViewCloud]:
    """The views without their points on or under the platter, found once in all of them
    (part frame); the views as they are when there is no platter in sight."""
    rng = np.random.default_rng(seed)
    moved = [v.moved(T) for v, T in zip(views, poses)]
    sample = np.concatenate([m.points[rng.choice(len(m), size=min(len(m), 20000), replace=False)] for m in moved])
    plane = platter_plane(sample, axis, tolerance_mm, seed)
    if plane is None:
        return views
    n, d = plane
    return [v.subset(m.points @ n + d > tolerance_mm) for v, m in zip(views, moved)]


def write_merged(path: Path, merged: Merged) -> None:
    """The merged cloud as a binary PLY with per-point sigma and views; complete or absent."""
    from plyfile import PlyData, PlyElement

    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
             ("sigma", "<f4"), ("views", "u1")]
    rec = np.empty(len(merged), dtype=dtype)
    for i, k in enumerate("xyz"):
        rec[k] = merged.points[:, i]
        rec["n" + k] = merged.normals[:, i]
    rec["sigma"] = merged.sigma
    rec["views"] = np.minimum(merged.views, 255)
    tmp = path.with_name(f".{path.name}.part")
    PlyData([PlyElement.describe(rec, "vertex")], comments=["slscan merged multi-view cloud, mm, part frame"]
            ).write(str(tmp))
    tmp.replace(path)


def load_merged(session: MultiViewSession) -> ScanCloud:
    """The merged cloud of a multi-view session as a scan to inspect (outputs/merged.ply,
    made first when missing). It has no single viewpoint: normals are the fused ones."""
    from plyfile import PlyData

    from inspection.measured_cloud import make_scan

    path = session.outputs / "merged.ply"
    if not path.is_file():
        whole_part(session)
    vertex = PlyData.read(str(path))["vertex"]
    points = np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float64)
    normals = np.stack([vertex[f"n{k}"] for k in "xyz"], axis=1).astype(np.float64)
    return make_scan(points, normals, str(session.root), None)
