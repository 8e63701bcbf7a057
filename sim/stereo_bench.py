"""The simulator's bench for calibrating a rig with two cameras: a printed board moved through
poses both cameras see whole and the projector lights (`sim.calibration_bench`'s planner, run with
the second camera in the projector's place, each pose then checked against the projector too)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from scanner.rig import Rig, RigConfig
from sim.calibration_bench import Target, plan_target_poses, show, visible
from sim.scene import Scene


def plan_stereo_poses(config: RigConfig, target: Target, n: int, seed: int = 0) -> list[np.ndarray]:
    """Up to `n` board poses (board -> first camera's frame) both cameras see whole and the
    projector lights; ValueError when the planner finds none."""
    models = list(config.camera_models().values())
    left, right = models[0], models[1]
    pair = replace(left, projector=right.camera, cam_from_proj=np.linalg.inv(right.world_from_cam))
    poses = plan_target_poses(pair, target, n, config.working_distance_mm, seed)
    lit = [P for P in poses if visible(left, target, P, margin=0.0)]
    if not lit:
        raise ValueError("no planned board pose is lit by the projector")
    return lit


class StereoSimBench:
    """Places the board at each planned pose (`calibration.stereo_capture.BoardBench`)."""

    def __init__(self, rig: Rig, target: Target, poses: list[np.ndarray]) -> None:
        self.rig, self.target, self.poses = rig, target, poses

    def place_board(self, index: int, needed: list[str]) -> bool:
        if index >= len(self.poses):
            return False
        show(self.rig, Scene(objects=(self.target.scene_object(self.poses[index]),), name=f"board pose {index}"))
        return True


def render_rows(rig: Rig, rows: np.ndarray, bit_depth: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Every camera's frames (N, H, W) of projector images whose every row is `rows[k]` ((N, Wp)
    uint8, vertical fringes as another tool makes them, shown as they are: no gamma
    pre-compensation), at the camera's exposure and `bit_depth`, with fresh noise."""
    renderers = rig.extras["renderers"]
    hp = rig.projector.height
    out = {}
    for name, renderer in renderers.items():
        exposure = rig.cameras[name].exposure_s
        out[name] = np.stack([renderer.render(np.ascontiguousarray(np.broadcast_to(r, (hp, len(r)))), exposure,
                                              bit_depth, rng) for r in rows])
    return out
