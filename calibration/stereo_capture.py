"""Board poses seen by every camera of a rig with several: the board placed (by a person, or the
simulator's bench), lit by the projector's full white, one frame grabbed from each camera in
software-triggered lock-step, the board found in each (`calibration.detect`). The frames are kept
under `out/pose_NNN/<camera>.png`, with `out/stereo_capture.json` naming the board, the cameras in
order (the first is the rig's frame) and their sizes, so the solve can be repeated from disk
(`open_stereo_capture`, `read_board_views`: `slscan calibrate --from DIR`). A folder written before
the file existed reads with the board and the cameras' order given."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from calibration.board import Board
from calibration.capture import WHITE
from calibration.detect import detect
from calibration.errors import CalibrationError
from calibration.intrinsics import ViewPoints
from calibration.store import CAPTURE_FILE, read_manifest
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


STEREO_CAPTURE_FILE = "stereo_capture.json"
STEREO_CAPTURE_FORMAT = "slscan-stereo-calibration-capture"
STEREO_CAPTURE_VERSION = 1


@dataclass(frozen=True, eq=False)
class StereoCapture:
    """A folder of board poses seen by several cameras: `names` in order (the first is the rig's
    frame), `sizes` each camera's (width, height) px, `poses` the pose folders in order."""

    root: Path
    board: Board
    names: tuple[str, ...]
    sizes: tuple[tuple[int, int], ...]
    poses: tuple[Path, ...]


def is_stereo_capture(root: Path) -> bool:
    """Whether `root` holds board poses of several cameras (its manifest, or pose folders with a
    frame per camera and no single-camera capture's manifest)."""
    if (root / STEREO_CAPTURE_FILE).is_file():
        return True
    first = sorted(root.glob("pose_*"))
    return not (root / CAPTURE_FILE).exists() and bool(first) and len(list(first[0].glob("*.png"))) >= 2


def open_stereo_capture(root: Path, *, board: Board | None = None, names: tuple[str, ...] | None = None
                        ) -> StereoCapture:
    """The capture in `root`: its manifest, or (a folder without one) `board` and the cameras'
    `names` in order given, which the frames cannot tell. CalibrationError naming what is missing."""
    poses = tuple(sorted(p for p in root.glob("pose_*") if p.is_dir()))
    if not poses:
        raise CalibrationError(f"{root}: no pose_NNN folders; not a capture of board poses")
    path = root / STEREO_CAPTURE_FILE
    manifest: dict[str, Any] = {}
    if path.is_file():
        manifest = read_manifest(path, STEREO_CAPTURE_FORMAT, STEREO_CAPTURE_VERSION)
    found = sorted(p.stem for p in poses[0].glob("*.png"))
    order = tuple(manifest.get("cameras", ())) or names
    if not order or not set(order) <= set(found):
        raise CalibrationError(f"{root}: {'no ' + STEREO_CAPTURE_FILE + ' and ' if not manifest else ''}the cameras' "
                               f"order is not known (frames of {', '.join(found)} in {poses[0].name}); give --rig with "
                               f"these cameras as [[cameras]], the first the rig's frame")
    if manifest:
        board = Board.from_dict(manifest["board"], path)
    if board is None:
        raise CalibrationError(f"{root}: no {STEREO_CAPTURE_FILE}, so the board is not known; give --board BOARD.toml")
    sizes = []
    for name in order:
        image = cv2.imread(str(poses[0] / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise CalibrationError(f"{poses[0] / (name + '.png')}: unreadable image")
        sizes.append((int(image.shape[1]), int(image.shape[0])))
    if manifest and [tuple(s) for s in manifest.get("sizes", sizes)] != sizes:
        raise CalibrationError(f"{path}: says the cameras are {manifest['sizes']} px, the frames are {sizes} px")
    return StereoCapture(root, board, tuple(order), tuple(sizes), poses)


def _write_manifest(out: Path, rig: Rig, board: Board) -> None:
    out.mkdir(parents=True, exist_ok=True)
    cameras = list(rig.cameras.values())
    (out / STEREO_CAPTURE_FILE).write_text(json.dumps(
        {"format": STEREO_CAPTURE_FORMAT, "version": STEREO_CAPTURE_VERSION, "rig": rig.config.name,
         "cameras": list(rig.cameras), "sizes": [[c.width, c.height] for c in cameras], "board": board.to_dict()},
        indent=1))


def _found(board: Board, image: np.ndarray) -> ViewPoints | None:
    d = detect(board, image)
    return None if d is None else ViewPoints(board.object_points()[d.ids], d.image_points)


def _said(k: int, names: list[str], found: list[ViewPoints | None]) -> str:
    return f"pose {k}: " + ", ".join(f"{n} {'no board' if v is None else f'{len(v)} points'}"
                                     for n, v in zip(names, found))


def capture_board_views(rig: Rig, bench: BoardBench, board: Board, poses: int, out: Path,
                        say: Callable[[str], None]) -> list[tuple[ViewPoints | None, ...]]:
    """For each pose the bench places, every camera's board points (None where a camera does
    not find the board); the frames are written under `out` with its manifest."""
    _write_manifest(out, rig, board)
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
            found.append(_found(board, image))
        say(_said(k, list(frames), found))
        views.append(tuple(found))
    return views


def read_board_views(capture: StereoCapture, say: Callable[[str], None]) -> list[tuple[ViewPoints | None, ...]]:
    """Every pose's board points per camera (in `capture.names`' order) found in its frames on
    disk, as `capture_board_views` found them when capturing."""
    views: list[tuple[ViewPoints | None, ...]] = []
    for k, folder in enumerate(capture.poses):
        found = []
        for name in capture.names:
            image = cv2.imread(str(folder / f"{name}.png"), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise CalibrationError(f"{folder / (name + '.png')}: missing or unreadable; every pose needs a frame "
                                       f"from every camera")
            found.append(_found(board=capture.board, image=image))
        say(_said(k, list(capture.names), found))
        views.append(tuple(found))
    return views
