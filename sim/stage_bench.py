"""The simulator's stage-axis bench: a calibration board lying on the turntable, which the
simulated stage turns with everything else in the scene (`sim.virtual_stage`).

`board_on_stage(target, stage)` is the scene: the board flat on the platter, printed side
up (toward the camera side of the axis), its centre `offset_mm` from the axis, at the
height of the axis point, with the stage at 0. `slscan calibrate --stage-axis` opens the
simulated rig on it and turns it. `part_on_stage` stands a CAD part on the platter (the
NIST parts of `slscan bench views --part`).
"""

from __future__ import annotations

import numpy as np

from scanner.stage import AxisKind
from scanner.stage_model import StageModel
from sim.calibration_bench import Target
from sim.scene import Scene, SceneObject


def board_on_stage(target: Target, stage: StageModel, offset_mm: float = 10.0) -> Scene:
    """The board on the platter of `stage`'s (first rotary) axis, as the scene at stage 0."""
    axis = next(a for a in stage.axes if a.kind is AxisKind.ROTARY)
    up = axis.direction
    x = np.cross(up, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
    y = np.cross(-up, x)  # board frame: x along its columns, y down its rows, z into it (-up)
    R = np.stack([x, y, -up], axis=1)
    centre = axis.point_mm + offset_mm * x + 0.05 * up
    pose = np.eye(4)
    pose[:3, :3] = R
    pose[:3, 3] = centre - R @ target.centre
    return Scene(objects=(target.scene_object(pose, "board"),), name="stage-axis bench")


def part_on_stage(vertices: np.ndarray, triangles: np.ndarray, face: np.ndarray, up: tuple[float, float, float],
                  stage: StageModel, *, platter_mm: float = 160.0, placement: np.ndarray | None = None) -> Scene:
    """A part (a tessellated CAD model, one mesh object per face) standing on the platter of
    `stage`'s first rotary axis: its CAD `up` along the axis, its bounding box centred on the
    axis, its lowest point on the platter (a square plane of `platter_mm`, through the axis
    point), as the scene at stage 0. `placement` (4x4, part frame, mm): how the part stands
    off that, a turn about `up` and a shift across it (as an operator places it)."""
    from scipy.spatial.transform import Rotation

    from sim.parts import part_scene

    axis = next(a for a in stage.axes if a.kind is AxisKind.ROTARY)
    a = axis.direction
    R = Rotation.align_vectors([a], [np.asarray(up, float)])[0].as_matrix()
    w = vertices @ R.T
    centre = (w.min(axis=0) + w.max(axis=0)) / 2
    centre -= a * (a @ centre)
    pose = np.eye(4)
    pose[:3, :3] = R
    pose[:3, 3] = axis.point_mm - centre - a * (w @ a).min()
    if placement is not None:
        pose = pose @ placement
    scene, _ = part_scene(vertices, triangles, face, pose, up=(float(up[0]), float(up[1]), float(up[2])), table=False)
    x = np.cross(a, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    plate = np.eye(4)
    plate[:3, :3] = np.stack([x, np.cross(a, x), a], axis=1)
    plate[:3, 3] = axis.point_mm - 0.01 * a
    platter = SceneObject(name="platter", kind="plane", pose=plate, albedo=0.5, size_mm=(platter_mm, platter_mm))
    return Scene(objects=(*scene.objects, platter), name="part on the turntable")
