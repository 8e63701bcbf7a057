"""Calibration captures on disk, and views decoded from them.

`slscan calibrate` writes everything it captures, so a calibration can be solved again
from disk (`slscan calibrate --from DIR`):

    DIR/capture.json            written after every step, atomically: format and version,
                                board, fringe pattern set, sizes, bit depth, gamma levels,
                                poses, plate heights, artefact
    DIR/gamma/level_00.png …    flat grey levels (the projector response)
    DIR/pose_000/white.png      the board under full white …
                 black.png      … and under black
                 fringe_00.png …  the fringe sequence (both orientations)
    DIR/plate_00/fringe_00.png … the reference plate at each stage height
    DIR/artefact/fringe_00.png … the validation artefact

Images are lossless PNG at their bit depth; each file appears complete or not at all. A
writer thread encodes them while the next frames are captured (PNG encoding of a noisy
12-bit frame costs about as much as rendering it), and `capture.json` is queued behind the
frames it lists, so it never names a frame that is not on disk.

Captures made by other tools are read given a pattern description: OpenCV's Gray-code
layout (`graycode_views`) takes every sub-folder holding the layout's images, sorted by
file name, as one pose.
"""

from __future__ import annotations

import datetime as dt
import json
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np

from calibration.board import Board
from calibration.capture import PoseFrames
from calibration.errors import CalibrationError, DetectionError
from calibration.graycode import GrayCodeLayout, decode_graycode
from calibration.views import View
from scanner.decode import DecodeResult, DecodeSettings, decode
from scanner.errors import DecodeError
from scanner.patterns import PatternSet
from scanner.session import write_atomic, write_json

CAPTURE_FORMAT = "slscan-calibration-capture"
CAPTURE_VERSION = 1
CAPTURE_FILE = "capture.json"
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg")


# zlib's fastest level matching runs only (Z_RLE): a noisy frame has next to no longer
# repeats to find, a dark or clipped area is runs (a 12-bit 640 x 512 frame: 9.9 against
# 13.4 ms to encode, 3.8 against 4.2 ms to decode, 358 against 371 kB with the default
# strategy; the pixels read back the same)
PNG_OPTIONS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", image, PNG_OPTIONS)
    if not ok:
        raise CalibrationError(f"{path}: cannot encode a {image.dtype} {image.shape} image")
    write_atomic(path, data.tobytes())


def _read_image(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
    if img is None:
        raise CalibrationError(f"{path}: missing or not a readable image")
    return img


def _read_stack(folder: Path, prefix: str, n: int) -> np.ndarray:
    return np.stack([_read_image(folder / f"{prefix}_{k:02d}.png") for k in range(n)])


class CaptureWriter:
    """Writes one calibration capture into a new folder (see the module docstring). Use it
    as a context manager, or call `close()`: both wait for every queued file and raise the
    first error a write met."""

    def __init__(self, root: str | Path, board: Board, patterns: PatternSet, *, camera_size: tuple[int, int],
                 projector_size: tuple[int, int], bit_depth: int, rig_name: str) -> None:
        self.root = Path(root)
        if self.root.exists() and any(self.root.iterdir()):
            raise CalibrationError(f"{self.root}: folder exists and is not empty; choose a new --out folder so no "
                                   f"earlier capture is overwritten")
        self.root.mkdir(parents=True, exist_ok=True)
        self.manifest: dict[str, Any] = {
            "format": CAPTURE_FORMAT, "version": CAPTURE_VERSION, "rig": rig_name,
            "created": dt.datetime.now(dt.UTC).isoformat(), "board": board.to_dict(),
            "patterns": patterns.to_dict(), "camera_size": list(camera_size), "projector_size": list(projector_size),
            "bit_depth": bit_depth, "gamma_levels": None, "poses": [], "plates": [], "artefact": None}
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="capture-writer")
        self._pending: list[Future] = []
        self._save()

    def __enter__(self) -> CaptureWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Wait for every queued file; raise the first write error."""
        pending, self._pending = self._pending, []
        self._pool.shutdown(wait=True)
        for f in pending:
            f.result()

    def _save(self) -> None:
        snapshot = json.loads(json.dumps(self.manifest))  # as it is now, not when the writer gets to it
        self._pending.append(self._pool.submit(write_json, self.root / CAPTURE_FILE, snapshot))

    def _png(self, path: Path, image: np.ndarray) -> None:
        self._pending.append(self._pool.submit(_write_png, path, image))

    def _stack(self, folder: str, prefix: str, stack: np.ndarray) -> None:
        (self.root / folder).mkdir(exist_ok=True)
        for k, img in enumerate(stack):
            self._png(self.root / folder / f"{prefix}_{k:02d}.png", img)

    def add_gamma(self, levels: np.ndarray, images: np.ndarray) -> None:
        self._stack("gamma", "level", images)
        self.manifest["gamma_levels"] = [int(v) for v in levels]
        self._save()

    def add_pose(self, frames: PoseFrames, gamma: float) -> str:
        name = f"pose_{len(self.manifest['poses']):03d}"
        self._stack(name, "fringe", frames.fringes)
        self._png(self.root / name / "white.png", frames.white)
        self._png(self.root / name / "black.png", frames.black)
        self.manifest["poses"].append({"name": name, "gamma": gamma})
        self._save()
        return name

    def add_plate(self, height_mm: float, fringes: np.ndarray, gamma: float) -> None:
        name = f"plate_{len(self.manifest['plates']):02d}"
        self._stack(name, "fringe", fringes)
        self.manifest["plates"].append({"name": name, "height_mm": height_mm, "gamma": gamma})
        self._save()

    def add_artefact(self, fringes: np.ndarray, description: dict[str, Any], gamma: float) -> None:
        self._stack("artefact", "fringe", fringes)
        self.manifest["artefact"] = {"description": description, "gamma": gamma}
        self._save()


def read_manifest(path: Path, format_name: str, version: int) -> dict[str, Any]:
    """A capture's JSON manifest, checked to be `format_name` at `version` (CalibrationError
    naming the file otherwise)."""
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"{path}: unreadable: {exc}") from None
    if manifest.get("format") != format_name or manifest.get("version") != version:
        raise CalibrationError(f"{path}: format {manifest.get('format')!r} version {manifest.get('version')!r}; "
                               f"this slscan reads {format_name!r} version {version}")
    return manifest


@dataclass(frozen=True, eq=False)
class CaptureSet:
    """A capture folder written by `CaptureWriter`, read back."""

    root: Path
    manifest: dict[str, Any]

    @classmethod
    def open(cls, root: str | Path) -> CaptureSet:
        root = Path(root)
        path = root / CAPTURE_FILE
        if not path.is_file():
            raise CalibrationError(f"{root}: no {CAPTURE_FILE}; not a slscan calibration capture (for captures made "
                                   f"by other tools give --layout)")
        return cls(root, read_manifest(path, CAPTURE_FORMAT, CAPTURE_VERSION))

    @property
    def board(self) -> Board:
        return Board.from_dict(self.manifest["board"], self.root / CAPTURE_FILE)

    @property
    def patterns(self) -> PatternSet:
        return PatternSet.from_dict(self.manifest["patterns"], self.root / CAPTURE_FILE)

    @property
    def camera_size(self) -> tuple[int, int]:
        return tuple(self.manifest["camera_size"])

    @property
    def projector_size(self) -> tuple[int, int]:
        return tuple(self.manifest["projector_size"])

    @property
    def bit_depth(self) -> int:
        return int(self.manifest["bit_depth"])

    @property
    def pose_names(self) -> list[str]:
        return [p["name"] for p in self.manifest["poses"]]

    def pose(self, name: str) -> PoseFrames:
        folder = self.root / name
        return PoseFrames(_read_image(folder / "white.png"), _read_image(folder / "black.png"),
                          _read_stack(folder, "fringe", self.patterns.n_frames))

    def gamma(self) -> tuple[np.ndarray, np.ndarray] | None:
        levels = self.manifest.get("gamma_levels")
        if not levels:
            return None
        return np.array(levels, dtype=np.uint8), _read_stack(self.root / "gamma", "level", len(levels))

    def plates(self) -> list[tuple[float, float, np.ndarray]]:
        """(stage height mm, projector gamma used, fringe stack) per plate scan."""
        return [(float(p["height_mm"]), float(p["gamma"]),
                 _read_stack(self.root / p["name"], "fringe", self.patterns.n_frames)) for p in self.manifest["plates"]]

    def artefact(self) -> tuple[dict[str, Any], np.ndarray] | None:
        a = self.manifest.get("artefact")
        if not a:
            return None
        return a["description"], _read_stack(self.root / "artefact", "fringe", self.patterns.n_frames)

    def views(self) -> list[View]:
        """Every pose decoded into a view."""
        return [pose_view(n, self.pose(n), self.patterns, self.bit_depth, self.projector_size)
                for n in self.pose_names]


def decode_pose(name: str, fringes: np.ndarray, patterns: PatternSet, bit_depth: int,
                projector_size: tuple[int, int], *, judged: bool = True) -> DecodeResult:
    """The fringe stack decoded; a wrong or incomplete stack is a DetectionError naming the view.
    `judged` False: frames distorted on purpose (the plate captured without gamma compensation,
    to show what it is worth): their consistency checks are kept in the result, not enforced."""
    try:
        return decode(fringes, patterns, bit_depth, projector_size, DecodeSettings(self_check=judged))
    except DecodeError as exc:
        raise DetectionError(name, f"fringe frames cannot be decoded: {exc}") from None


def pose_view(name: str, frames: PoseFrames, patterns: PatternSet, bit_depth: int,
              projector_size: tuple[int, int]) -> View:
    """A view from one pose's frames: both fringe orientations decoded, weighted by their
    phase precision."""
    if set(patterns.orientations) != {"vertical", "horizontal"}:
        raise CalibrationError(f"pattern set {patterns.to_dict()}: projector calibration needs fringes in both "
                               f"orientations (vertical and horizontal)")
    d = decode_pose(name, frames.fringes, patterns, bit_depth, projector_size)
    mv, mh = d.maps["vertical"], d.maps["horizontal"]
    # weights: phase precision in projector pixels^-2, up to the common noise level
    wv = mv.phase_weight / np.float32(mv.period_px ** 2)
    wh = mh.phase_weight / np.float32(mh.period_px ** 2)
    return View(name, frames.white, mv.coordinate, mh.coordinate, wv, wh)


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


def graycode_views(root: str | Path, layout: GrayCodeLayout, folders: str = "*", min_contrast: float = 0.16,
                   min_bit_difference: float = 0.02) -> list[View]:
    """Views from captures in OpenCV's Gray-code layout (see `calibration.graycode`): one
    pose per sub-folder of `root` matching the glob `folders` and holding images, at least
    the layout's (taken in file-name order; extra images after them are ignored).
    Thresholds are fractions of full scale."""
    root = Path(root)
    if not root.is_dir():
        raise CalibrationError(f"{root}: no such folder")
    white = layout.white_index  # None: the layout has no white and black images
    if white is None:
        raise CalibrationError("the Gray-code layout must end with white and black images (board detection uses white)")
    views = []
    for folder in sorted(p for p in root.glob(folders) if p.is_dir()):
        files = _image_files(folder)
        if not files:
            continue
        if len(files) < layout.n_frames:
            raise DetectionError(folder.name, f"{len(files)} images in {folder}, the Gray-code layout for a "
                                              f"{layout.width} x {layout.height} projector needs {layout.n_frames}")
        stack = np.stack([_read_image(f) for f in files[:layout.n_frames]])
        full = float(np.iinfo(stack.dtype).max)
        maps = decode_graycode(stack, layout, min_contrast * full, min_bit_difference * full, folder.name)
        views.append(View(folder.name, stack[white], maps.u, maps.v, maps.weight_u, maps.weight_v))
    if not views:
        raise CalibrationError(f"{root}: no sub-folder matching '{folders}' holds images; expected one folder of "
                               f"{layout.n_frames} images per board pose")
    return views
