"""The simulator's truth for rigs with several cameras: which of one camera's points another
camera sees, and fresh random scenes to judge binocular reconstruction on."""

from __future__ import annotations

import numpy as np

from scanner.geometry import pose_from_dict
from sim.evaluate import Truth, smooth_region
from sim.render import GroundTruth
from sim.scene import Scene, SceneObject


def seen_by(first: GroundTruth, other: GroundTruth, tolerance_mm: float = 0.5) -> np.ndarray:
    """Pixels (H, W) of camera `first` whose true point camera `other` sees too: its own first
    hit along its ray to the point is that point (within `tolerance_mm`), on a smooth lit part
    of its image (`smooth_region`, away from its depth edges)."""
    P = first.points.reshape(-1, 3)
    T = np.linalg.inv(other.model.world_from_cam) @ first.model.world_from_cam
    X = P @ T[:3, :3].T + T[:3, 3]
    ok = np.isfinite(X[:, 2]) & (X[:, 2] > 0)
    uv = np.zeros((len(P), 2))
    uv[ok] = other.model.camera.project(X[ok])
    u = np.rint(uv).astype(int)
    h, w = other.depth.shape
    ok &= (u[:, 0] >= 0) & (u[:, 1] >= 0) & (u[:, 0] < w) & (u[:, 1] < h)
    smooth = smooth_region(Truth.of(other))
    seen = np.zeros(len(P), bool)
    seen[ok] = (np.abs(other.depth[u[ok, 1], u[ok, 0]] - X[ok, 2]) < tolerance_mm) & smooth[u[ok, 1], u[ok, 0]]
    return seen.reshape(first.depth.shape)


def random_scene(rng: np.random.Generator, working_distance_mm: float = 400.0) -> Scene:
    """A reference plane (tilted up to ~14 degrees, 30-70 mm behind the working distance), a
    sphere and a box at random places and sizes in front of it, matte albedos 0.4-0.9: a fresh
    case each draw."""
    wd = working_distance_mm

    def pose(rotation: np.ndarray, translation: list[float]) -> np.ndarray:
        return pose_from_dict({"rotation_rad": [float(v) for v in rotation], "translation_mm": translation})

    plane = SceneObject("reference_plane", "plane", pose(np.r_[rng.uniform(-0.25, 0.25, 2), 0.0],
                                                          [0.0, 0.0, wd + float(rng.uniform(30, 70))]),
                        float(rng.uniform(0.5, 0.9)), size_mm=(1000.0, 1000.0))
    sphere = SceneObject("sphere", "sphere", pose(np.zeros(3), [float(rng.uniform(-25, 25)),
                                                                float(rng.uniform(-20, 20)),
                                                                wd + float(rng.uniform(-20, 10))]),
                         float(rng.uniform(0.4, 0.9)), radius_mm=float(rng.uniform(12, 25)))
    box = SceneObject("box", "box", pose(rng.uniform(-0.6, 0.6, 3), [float(rng.uniform(-40, 40)),
                                                                    float(rng.uniform(-30, 30)),
                                                                    wd + float(rng.uniform(0, 25))]),
                      float(rng.uniform(0.4, 0.9)), size_mm=tuple(float(v) for v in rng.uniform(15, 35, 3)))
    return Scene((sphere, box), reference_plane=plane, name="random")
