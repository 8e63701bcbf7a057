"""Session folders: one per scan, written as the data arrives.

Layout (all files appear complete or not at all):
    frames/frame_000.png …   raw camera frames, lossless, at their bit depth (8- or 16-bit PNG)
    frames.jsonl             one line per frame as it arrives: index, pattern, timestamp, exposure
    phase_to_height.npz      the phase-to-height maps of the rig model (reference phase, per-pixel
                             l and K), when its calibration has them (a hard link to the
                             calibration's where possible): the session decodes alone
    manifest.json            written last, atomically, once the capture is complete: rig config
                             snapshot, rig model (with the calibration file it came from), pattern
                             set, device settings, software version, timings, frame list
    error.json               written instead of the manifest when a capture fails
    outputs/                 regenerable from the raw frames: cloud.ply, maps.npz, result.json
    recording.rrd            the session's Rerun recording
A folder without a manifest is an incomplete session and is refused for decoding.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import uuid
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from scanner import __version__
from scanner.devices import Frame
from scanner.errors import IncompleteSession, SessionError
from scanner.geometry import PhaseToHeight, RigModel
from scanner.patterns import PatternSet

MANIFEST_VERSION = 1
MANIFEST = "manifest.json"
ERROR = "error.json"
FRAME_LOG = "frames.jsonl"
FRAMES_DIR = "frames"
OUTPUTS_DIR = "outputs"
RECORDING = "recording.rrd"
PHASE_TO_HEIGHT_MAPS = "phase_to_height.npz"


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` so that `path` either holds all of it or does not exist."""
    tmp = path.with_name(f".{path.name}.part")
    with tmp.open("wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(path)


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """A compressed .npz of `arrays` (read by np.load) that appears complete or not at all;
    deflate at level 1: float maps hardly compress further, and level 6 took 4x longer."""
    tmp = path.with_name(f".{path.name}.part.npz")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for name, a in arrays.items():
            with z.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)
    tmp.replace(path)


def keep_maps(model: PhaseToHeight, path: Path) -> None:
    """The model's maps at `path`: a hard link to the file it was loaded from when the file
    system allows (a calibration's maps are ~12 MB at 1280 x 1024, as much as a scan's raw
    frames; files are only ever replaced, never rewritten in place, so the link keeps the
    content it was made with), else a copy written from memory."""
    if model.maps_file:
        try:
            os.link(model.maps_file, path)
            return
        except OSError:
            pass
    write_npz(path, model.maps())


def write_json(path: Path, obj: Any) -> None:
    write_atomic(path, (json.dumps(obj, indent=2, default=_json_default) + "\n").encode())


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def frame_name(k: int) -> str:
    return f"frame_{k:03d}.png"


class SessionWriter:
    """Writes one capture into a new session folder."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.id = f"{dt.datetime.now().strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:6]}"
        self.frames: list[dict[str, Any]] = []
        self.started = dt.datetime.now(dt.timezone.utc)
        (root / FRAMES_DIR).mkdir(parents=True, exist_ok=False)

    @classmethod
    def create(cls, out_dir: str | Path) -> SessionWriter:
        """A new session folder; `out_dir` must not exist or be empty."""
        root = Path(out_dir)
        if root.exists() and any(root.iterdir()):
            raise SessionError(f"{root}: output folder exists and is not empty; choose a new --out folder "
                               f"so no earlier session is overwritten")
        root.mkdir(parents=True, exist_ok=True)
        return cls(root)

    def add_frame(self, k: int, frame: Frame) -> None:
        """Store frame k losslessly, then log it; both are complete before they are visible."""
        img = frame.image
        ok, png = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise SessionError(f"{self.root}: could not encode frame {k} ({img.dtype} {img.shape})")
        write_atomic(self.root / FRAMES_DIR / frame_name(k), png.tobytes())
        entry = {"k": k, "file": f"{FRAMES_DIR}/{frame_name(k)}", "index": frame.index,
                 "pattern_index": frame.pattern_index, "timestamp_s": frame.timestamp_s,
                 "exposure_s": frame.exposure_s, "bit_depth": frame.bit_depth,
                 "shape": list(img.shape), "dtype": str(img.dtype)}
        self.frames.append(entry)
        with (self.root / FRAME_LOG).open("a") as f:
            f.write(json.dumps(entry) + "\n")

    def finish(self, rig_config: dict[str, Any], model: RigModel, patterns: PatternSet,
               devices: dict[str, Any], timings: dict[str, float], extra: dict[str, Any] | None = None) -> Path:
        """Write the manifest: from now on the session is complete. The phase-to-height
        maps of `model`, if any, are put in the session first (`keep_maps`)."""
        if model.phase_to_height is not None:
            keep_maps(model.phase_to_height, self.root / PHASE_TO_HEIGHT_MAPS)
            model = replace(model, phase_to_height=replace(model.phase_to_height, maps_file=PHASE_TO_HEIGHT_MAPS))
        manifest = {
            "slscan_manifest": MANIFEST_VERSION, "session_id": self.id, "software_version": __version__,
            "python": platform.python_version(), "created": self.started.isoformat(),
            "completed": dt.datetime.now(dt.timezone.utc).isoformat(),
            "rig_config": rig_config, "rig_model": model.to_dict(), "patterns": patterns.to_dict(),
            "devices": devices, "timings_s": timings, "frames": self.frames, **(extra or {}),
        }
        write_json(self.root / MANIFEST, manifest)
        return self.root / MANIFEST

    def fail(self, error: BaseException, stage: str) -> None:
        """Record why the capture stopped; the frames already stored stay."""
        write_json(self.root / ERROR, {
            "session_id": self.id, "stage": stage, "error": type(error).__name__, "message": str(error),
            "frames_stored": len(self.frames), "time": dt.datetime.now(dt.timezone.utc).isoformat()})


@dataclass(frozen=True, eq=False)
class Session:
    """A complete session read back from disk."""

    root: Path
    manifest: dict[str, Any]

    @classmethod
    def open(cls, path: str | Path) -> Session:
        root = Path(path)
        if not root.is_dir():
            raise SessionError(f"{root}: no such session folder")
        mpath = root / MANIFEST
        if not mpath.exists():
            raise IncompleteSession(describe_incomplete(root))
        try:
            manifest = json.loads(mpath.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise SessionError(f"{mpath}: unreadable manifest: {exc}") from None
        version = manifest.get("slscan_manifest")
        if version != MANIFEST_VERSION:
            raise SessionError(f"{mpath}: manifest version {version!r}, this slscan reads {MANIFEST_VERSION}")
        return cls(root, manifest)

    @property
    def id(self) -> str:
        return self.manifest["session_id"]

    @property
    def patterns(self) -> PatternSet:
        return PatternSet.from_dict(self.manifest["patterns"], self.root / MANIFEST)

    def rig_model(self) -> RigModel:
        """The geometry the session was captured with, its phase-to-height model (and maps) included."""
        return RigModel.from_dict(self.manifest["rig_model"], f"{self.root / MANIFEST}: rig_model", self.root)

    @property
    def bit_depth(self) -> int:
        return int(self.manifest["frames"][0]["bit_depth"])

    def load_stack(self) -> np.ndarray:
        """The raw frames as (N, H, W), checked against the manifest (count, size, type)."""
        entries = self.manifest["frames"]
        n_expected = self.patterns.n_frames
        if len(entries) != n_expected:
            raise SessionError(f"{self.root / MANIFEST}: lists {len(entries)} frames, pattern set needs {n_expected}")
        cam = self.manifest["rig_model"]["camera"]
        shape = (cam["height"], cam["width"])
        stack = None
        for k, e in enumerate(entries):
            path = self.root / e["file"]
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise SessionError(f"{path}: frame {k} missing or unreadable")
            if img.shape != shape or str(img.dtype) != e["dtype"]:
                raise SessionError(f"{path}: frame {k} is {img.dtype} {img.shape[1]}x{img.shape[0]}, expected "
                                   f"{e['dtype']} {shape[1]}x{shape[0]}")
            if stack is None:
                stack = np.empty((len(entries), *shape), dtype=img.dtype)
            stack[k] = img
        assert stack is not None
        return stack

    @property
    def outputs(self) -> Path:
        return self.root / OUTPUTS_DIR

    @property
    def recording_path(self) -> Path:
        return self.root / RECORDING


def describe_incomplete(root: Path) -> str:
    """Why a session folder cannot be used, for the user."""
    frames = sorted((root / FRAMES_DIR).glob("frame_*.png")) if (root / FRAMES_DIR).is_dir() else []
    msg = f"{root}: incomplete session (no {MANIFEST}); {len(frames)} raw frame(s) on disk"
    err = root / ERROR
    if err.exists():
        try:
            e = json.loads(err.read_text())
            msg += f"; capture stopped during {e.get('stage')}: {e.get('error')}: {e.get('message')}"
        except (OSError, json.JSONDecodeError):
            msg += f"; {ERROR} unreadable"
    else:
        msg += "; no error recorded (the scan was interrupted)"
    return msg + ". Re-scan the part; the frames are kept for inspection."
