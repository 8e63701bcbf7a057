"""Scenes the registration tests share: a plain block's STEP file (symmetric: its half turn
fits as well) and a simulated view of a model from a random start."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from sim.parts import lying_pose
from sim.parts_demo import write_step
from tests.test_inspection_registration import virtual_view


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
    from inspection.measured_cloud import ScanCloud

    moved = ScanCloud(view.points @ G[:3, :3].T + G[:3, 3], view.normals @ G[:3, :3].T, "moved view", G[:3, 3].copy())
    return moved, np.linalg.inv(pose) @ np.linalg.inv(G)


def write_ply(scan: Any, path: Path) -> Path:
    """`scan`'s points and normals as a PLY cloud at `path`."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan.points))
    pc.normals = o3d.utility.Vector3dVector(scan.normals)
    o3d.io.write_point_cloud(str(path), pc)
    return path
