"""The simulator's bench for rigs with two cameras: a printed board moved through poses both
cameras see whole and the projector lights (`sim.calibration_bench`'s planner, run with the second
camera in the projector's place and the first camera with the projector as a further pair); captures as
another tool makes them (its pattern rows shown as they are, its stereo file written its way); the
binocular rig file at another camera size, for quick runs."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from scanner.binocular import StereoModel
from scanner.config import CONFIG_DIR
from scanner.rig import Rig, RigConfig
from sim.calibration_bench import Target, plan_target_poses, show
from sim.scene import Scene

BINOCULAR = CONFIG_DIR / "rigs" / "sim_binocular.toml"


def plan_stereo_poses(config: RigConfig, target: Target, n: int, seed: int = 0) -> list[np.ndarray]:
    """`n` board poses (board -> first camera's frame) in which both cameras see the whole printed
    sheet (the pattern and its white border) and the projector lights all of it
    (`sim.calibration_bench.plan_target_poses` with `whole_sheet`: the board's points 3 % of each
    image inside all three; ValueError when a pose cannot be placed)."""
    models = list(config.camera_models().values())
    left, right = models[0], models[1]
    pair = replace(left, projector=right.camera, cam_from_proj=right.world_from_cam)  # second camera -> first
    return plan_target_poses(pair, target, n, config.working_distance_mm, seed, whole_sheet=True, also=(left,))


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


def binocular_rig(tmp: Path, width: int, height: int, *, projector: tuple[int, int, float] | None = None,
                  edits: dict[str, str] | None = None) -> Path:
    """config/rigs/sim_binocular.toml written to `tmp` with `width` x `height` cameras (same field of
    view); `projector` (width, height, pixel aspect) replaces the bench projector's size; `edits` are
    further text replacements."""
    text = BINOCULAR.read_text().replace("width = 1280", f"width = {width}")
    text = text.replace("height = 1024", f"height = {height}")
    text = text.replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
    text = text.replace('artefacts = "../artefacts/', f'artefacts = "{CONFIG_DIR}/artefacts/')
    if projector is not None:
        w, h, aspect = projector
        text = re.sub(r"\[projector\]\nwidth = 912\nheight = 1140\nhfov_deg = 26.0\npixel_aspect = 2.0",
                      f"[projector]\nwidth = {w}\nheight = {h}\nhfov_deg = 26.0\npixel_aspect = {aspect}", text)
    for old, new in (edits or {}).items():
        text = text.replace(old, new)
    path = tmp / "rig.toml"
    path.write_text(text)
    return path


def write_slmaster_caliinfo(path: Path, model: StereoModel, size: tuple[int, int]) -> Path:
    """`model` as SLMaster's binocular caliInfo.yml (M1/D1, S, M2/D2, R1/P1/R2/P2/Q recomputed by
    OpenCV's stereoRectify, Rlr/Tlr), the way its calibration writes it."""
    R, T = model.right_from_left[:3, :3], model.right_from_left[:3, 3].reshape(3, 1)
    L, Rc = model.left, model.right
    R1, R2, P1, P2, Q, *_ = cv2.stereoRectify(L.K, L.dist, Rc.K, Rc.dist, size, R, T, flags=0)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in (("M1", L.K), ("D1", L.dist.reshape(1, 5)), ("S", np.array([[size[0]], [size[1]]], float)),
                 ("M2", Rc.K), ("D2", Rc.dist.reshape(1, 5)), ("R1", R1), ("P1", P1), ("R2", R2), ("P2", P2),
                 ("Q", Q), ("Rlr", R), ("Tlr", T)):
        fs.write(k, np.asarray(v, np.float64))
    fs.release()
    return path
