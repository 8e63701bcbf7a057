"""The simulator's board pose planner for two cameras (sim/stereo_bench.py) against an independent
check: the printed sheet's outline (the pattern's outer squares and the white border around them,
from the board file) projected with cv2.projectPoints through the rig file's true lenses and poses
must lie inside both camera images and inside the projector's (which lights it). The seeds are
drawn fresh and printed."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.board import Board
from scanner.config import CONFIG_DIR
from scanner.geometry import Pinhole
from scanner.rig import RigConfig
from sim.calibration_bench import Target
from sim.stereo_bench import BINOCULAR, plan_stereo_poses

BOARD = Board.load(CONFIG_DIR / "boards" / "sim_chess_9x7.toml")


def _sheet(board: Board, per_edge: int = 400) -> np.ndarray:
    """(4 * per_edge, 3) points along the edges of the printed sheet (board frame, mm): the
    pattern's outline widened by the board's white margin."""
    x0, y0, x1, y1 = board.pattern_extent_mm
    m = board.margin_mm
    xs, ys = np.linspace(x0 - m, x1 + m, per_edge), np.linspace(y0 - m, y1 + m, per_edge)
    edges = [np.c_[xs, np.full(per_edge, y0 - m)], np.c_[xs, np.full(per_edge, y1 + m)],
             np.c_[np.full(per_edge, x0 - m), ys], np.c_[np.full(per_edge, x1 + m), ys]]
    return np.c_[np.concatenate(edges), np.zeros(4 * per_edge)]


def _outside_px(device: Pinhole, device_from_board: np.ndarray, points: np.ndarray) -> float:
    """How far (px) the farthest of `points` lies outside the device's image, whose edges are
    half a pixel beyond the outer pixel centres (0 when all are inside)."""
    R, t = device_from_board[:3, :3], device_from_board[:3, 3]
    assert ((points @ R.T + t)[:, 2] > 0).all()
    uv = cv2.projectPoints(points, cv2.Rodrigues(R)[0], t, device.K, device.dist)[0].reshape(-1, 2)
    w, h = device.size
    return float(max(0.0, -0.5 - uv.min(), (uv - [w - 0.5, h - 0.5]).max()))


def test_stereo_poses_show_both_cameras_the_whole_sheet_lit() -> None:
    """The full-size binocular rig, 12 poses (the calibration's default): each sheet inside both
    camera images and the projector's, through the rig's true stereo geometry."""
    config = RigConfig.load(BINOCULAR)
    truth = config.stereo_model(nominal=True)
    rig = config.nominal_model()
    target = Target(np.ones((4, 4), np.float32), BOARD.size_mm, BOARD.image_origin_mm, BOARD.object_points())
    sheet = _sheet(BOARD)
    seeds = [int(s) for s in np.random.SeedSequence().generate_state(3) % 2 ** 31]
    print(f"seeds {seeds}")
    for seed in seeds:
        poses = plan_stereo_poses(config, target, 12, seed)
        assert len(poses) == 12
        for k, P in enumerate(poses):
            out = [_outside_px(truth.left, P, sheet), _outside_px(truth.right, truth.right_from_left @ P, sheet),
                   _outside_px(rig.projector, rig.proj_from_cam @ P, sheet)]
            assert out == [0.0, 0.0, 0.0], (seed, k, out)
