"""Board poses seen by every camera of a rig with several: the board placed (by a person, or the
simulator's bench), lit by the projector's full white, one frame grabbed from each camera in
software-triggered lock-step, the board found in each (`calibration.detect`). The frames are kept
under `out/pose_NNN/<camera>.png` so the solve can be repeated from disk."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Protocol

import cv2
import numpy as np

from calibration.board import Board
from calibration.capture import WHITE
from calibration.detect import detect
from calibration.intrinsics import ViewPoints
from scanner.acquisition import AcquisitionSettings, acquire_images_from
from scanner.devices import TriggerMode, TriggerType
from scanner.rig import Rig


class BoardBench(Protocol):
    def place_board(self, index: int, needed: list[str]) -> bool: ...


def white_frames(rig: Rig) -> dict[str, np.ndarray]:
    """One frame per camera under the projector's full white (software-triggered in lock-step,
    each camera's trigger setting restored afterwards)."""
    p = rig.projector
    cameras = list(rig.cameras.values())
    saved = [(c.trigger_type, c.trigger_mode) for c in cameras]
    for c in cameras:
        c.set_trigger(TriggerType.SOFTWARE, TriggerMode.ONCE)
    try:
        white = np.full((1, p.height, p.width), WHITE, np.uint8)
        stacks = acquire_images_from(rig, cameras, white, AcquisitionSettings.for_rig(rig), wiring="software")
    finally:
        for c, s in zip(cameras, saved):
            c.set_trigger(*s)
    return {name: stack[0] for name, stack in zip(rig.cameras, stacks)}


def capture_board_views(rig: Rig, bench: BoardBench, board: Board, poses: int, out: Path,
                        say: Callable[[str], None]) -> list[tuple[ViewPoints | None, ...]]:
    """For each pose the bench places, every camera's board points (None where a camera does
    not find the board); the frames are written under `out`."""
    points = board.object_points()
    views: list[tuple[ViewPoints | None, ...]] = []
    for k in range(poses):
        if not bench.place_board(k, []):
            break
        frames = white_frames(rig)
        folder = out / f"pose_{k:03d}"
        folder.mkdir(parents=True, exist_ok=True)
        found = []
        for name, image in frames.items():
            cv2.imwrite(str(folder / f"{name}.png"), image)
            d = detect(board, image)
            found.append(None if d is None else ViewPoints(points[d.ids], d.image_points))
        say(f"pose {k}: " + ", ".join(f"{n} {'no board' if v is None else f'{len(v)} points'}"
                                      for n, v in zip(frames, found)))
        views.append(tuple(found))
    return views
