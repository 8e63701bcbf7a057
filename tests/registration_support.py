"""Scenes the registration tests share: the demo part's STEP file, a plain block's (symmetric:
its half turn fits as well), and simulated views of a model, placed or from a random start;
and one registration shared by the inspections of one cloud."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from inspection import inspect_scan
from inspection.measured_cloud import ScanCloud, make_scan
from inspection.sampling import sample_model
from scanner.config import CONFIG_DIR
from sim.parts import lying_pose
from sim.parts_demo import write_step

STEP = CONFIG_DIR / "parts" / "demo_part.step"  # the demo part's model


def virtual_view(model, pose: np.ndarray, noise_mm: float = 0.014, spacing_mm: float = 0.25, seed: int = 0,
                 offsets: dict[str, float] | None = None) -> ScanCloud:
    """The model's surface seen from a camera at the origin (model placed by `pose`, part ->
    camera): visible samples, with noise along the viewing rays; normals estimated.
    `offsets`: faces (by label) moved as a whole along their outward normal (mm)."""
    import open3d as o3d

    s = sample_model(model, spacing_mm, seed=seed)
    points = s.points.copy()
    for label, mm in (offsets or {}).items():
        sel = s.face == model.by_label(label).index
        points[sel] += mm * s.normals[sel]
    p = points @ pose[:3, :3].T + pose[:3, 3]
    n = s.normals @ pose[:3, :3].T
    tess = model.tessellation
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((tess.vertices @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)),
                        o3d.core.Tensor(tess.triangles.astype(np.uint32)))
    dist = np.linalg.norm(p, axis=1)
    ray = p / dist[:, None]
    hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([np.zeros_like(p), ray], 1).astype(np.float32)))
    seen = (hit["t_hit"].numpy() > dist - 0.01) & (np.einsum("ij,ij->i", n, ray) < -0.1)
    rng = np.random.default_rng(seed)
    q = p[seen] + ray[seen] * rng.normal(0, noise_mm, seen.sum())[:, None]
    return make_scan(q, None, "virtual view", np.zeros(3))


def box_step(path: Path) -> Path:
    """A 60 x 40 x 15 mm block written as STEP to `path`."""
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox
    from OCP.gp import gp_Pnt

    write_step(BRepPrimAPI_MakeBox(gp_Pnt(-30, -20, 0), gp_Pnt(30, 20, 15)).Shape(), path)
    return path


def moved_view(model: Any, tilt: tuple[float, float], seed: int) -> tuple[Any, np.ndarray]:
    """A view of `model` from a random start: (scan, the true moved-scan -> model pose)."""
    pose = lying_pose(model.tessellation.vertices, 0.4, 400.0, tilt)
    view = virtual_view(model, pose, seed=seed)
    G = np.eye(4)
    G[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    G[:3, 3] = [80.0, -120.0, 60.0]
    moved = ScanCloud(view.points @ G[:3, :3].T + G[:3, 3], view.normals @ G[:3, :3].T, "moved view", G[:3, 3].copy())
    return moved, np.linalg.inv(pose) @ np.linalg.inv(G)


def write_ply(scan: Any, path: Path) -> Path:
    """`scan`'s points and normals as a PLY cloud at `path`."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan.points))
    pc.normals = o3d.utility.Vector3dVector(scan.normals)
    o3d.io.write_point_cloud(str(path), pc)
    return path


@contextmanager
def shared_registrations() -> Iterator[None]:
    """Inside, `inspection.inspect_scan.inspect` registers a part cloud once: its global
    registration (no prior) is kept by its inputs (the part's points and normals, the
    target's samples, the settings) and given again to an inspection of the same inputs,
    e.g. `slscan inspect` of one session with other tolerances. The registration is
    repeatable bit for bit (test_inspection_sim.py's four of one session: the same
    transform, fitness, covariance and free motions; 5 s each)."""
    register = inspect_scan.register_with_prior
    done: dict[tuple[str, str], Any] = {}

    def once(scan: ScanCloud, target: Any, prior: Any, settings: Any) -> Any:
        if prior is not None:
            return register(scan, target, prior, settings)
        digest = hashlib.sha256()
        for a in (scan.points, scan.normals, target.dense.points, target.dense.normals):
            digest.update(np.ascontiguousarray(a).tobytes())
        key = (digest.hexdigest(), repr(settings))
        if key not in done:
            done[key] = register(scan, target, prior, settings)
        return done[key]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(inspect_scan, "register_with_prior", once)
        yield
