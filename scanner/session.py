"""Session folders: one per scan, written as the data arrives.

Layout (all files appear complete or not at all):
    frames/frame_000.png …   raw camera frames, lossless, at their bit depth (8- or 16-bit PNG)
    frames.jsonl             one line per frame as it arrives: index, pattern, timestamp, exposure,
                             the SHA-256 of the frame's file
    phase_to_height.npz      the phase-to-height maps of the rig model (reference phase, per-pixel
                             l and K), when its calibration has them (a hard link to the
                             calibration's where possible): the session decodes alone
    manifest.json            written last, atomically, once the capture is complete: rig config
                             snapshot, rig model (with the calibration file it came from), the
                             SHA-256 of its canonical JSON (`rig_model_sha256`) and of that file
                             (`calibration_sha256`), pattern set (and its `patterns_sha256`),
                             device settings, software version, timings, frame list, and
                             (`exposure`) the exposures chosen and why: a multi-exposure (HDR)
                             session holds the whole pattern set once per exposure, frames
                             i·N .. i·N + N − 1 at exposures_s[i] (ascending), every one kept;
                             a view of a multi-view session adds `stage`, `view` and
                             `multiview_id` (`ViewPlace`), an imported session `import`
                             (`ImportRecord`)
    capture.json             written before the first frame: the manifest-to-be (rig, patterns, devices,
                             provenance), so `slscan decode --recover` can rebuild a manifest a kill prevented
    error.json               written instead of the manifest when a capture fails
    outputs/                 regenerable from the raw frames: cloud.ply, maps.npz, result.json
    recording.rrd            the session's Rerun recording
A folder without a manifest is an incomplete session and is refused for decoding.

Reading a session back trusts nothing: the manifest is validated (`Manifest`: keys, types,
ranges, the rig model's geometry), frame paths must stay inside the session folder (no
absolute paths, no `..`, no symlinks out), each frame's bytes must match the SHA-256 the
manifest holds for it, and its pixels must fit its bit depth. Sessions written before
frames carried checksums are read with `Session.integrity` saying they could not be
checked. (That the frames fit the patterns is checked by the pipeline before decoding.)
"""

from __future__ import annotations

import datetime as dt
import errno
import hashlib
import json
import math
import os
import platform
import uuid
import zipfile
from contextlib import suppress
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any, BinaryIO, Literal

import cv2
import numpy as np
from pydantic import (
    ConfigDict,
    Field,
    ModelWrapValidatorHandler,
    PrivateAttr,
    ValidationInfo,
    field_validator,
    model_validator,
)

from scanner import __version__, schema
from scanner.devices import Frame
from scanner.errors import ConfigError, IncompleteSession, SessionError
from scanner.file_checks import FileRefused, decode_image, read_regular
from scanner.geometry import PhaseToHeight, RigModel
from scanner.patterns import PatternFile, PatternSet
from scanner.rig_schema import RecordedRig, RigModelSchema, check_geometry
from scanner.stage_model import StageModel

ManifestVersion = Literal[1]  # the manifest format this slscan writes and reads
MANIFEST_VERSION: ManifestVersion = 1
MANIFEST = "manifest.json"
CAPTURE = "capture.json"
ERROR = "error.json"
FRAME_LOG = "frames.jsonl"
FRAMES_DIR = "frames"
OUTPUTS_DIR = "outputs"
RECORDING = "recording.rrd"
PHASE_TO_HEIGHT_MAPS = "phase_to_height.npz"
MAX_MANIFEST_BYTES = 64 * 1024 ** 2  # a manifest lists frames and settings: a few hundred kB at most


def temp_path(path: Path, suffix: str = "") -> Path:
    """A temporary name beside `path`, unique to this writer (PID and a random part), that
    `scanner.session_lock.leftovers` recognises should the writer be killed."""
    return path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.part{suffix}")


def open_new(path: Path) -> BinaryIO:
    """`path` opened for writing only if it does not exist yet, and not through a symbolic
    link (a link planted at a temporary name cannot redirect the write)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    return os.fdopen(fd, "wb")


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` so that `path` either holds all of it or does not exist (a failed write,
    e.g. on a full disk, leaves no partial file behind and raises the OSError)."""
    tmp = temp_path(path)
    try:
        with open_new(tmp) as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_npz(path: Path, arrays: dict[str, np.ndarray], deflate_floats: bool = True) -> None:
    """An .npz of `arrays` (read by np.load) that appears complete or not at all. Masks and
    other integer arrays are deflated (level 1: long runs, ~100x smaller for next to no
    CPU); float arrays too unless `deflate_floats` is False: decoded maps hardly compress
    (coordinate and phase to ~82 %) and deflating a 1.3 MP scan's maps took ~0.65 s CPU of
    its write stage (level 6: 4x more), so a scan's outputs store them as they are (26 MB
    instead of 18 MB there). np.load reads either member kind, so older files still load."""
    tmp = temp_path(path, ".npz")
    try:
        with open_new(tmp) as file, zipfile.ZipFile(file, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
            for name, a in arrays.items():
                a = np.asanyarray(a)
                member: str | zipfile.ZipInfo = f"{name}.npy"  # deflated, at the file's level
                if not deflate_floats and a.dtype.kind in "fc":
                    member = zipfile.ZipInfo(f"{name}.npy")  # stored; dated 1980 as ZipFile dates a named member,
                    # so the same maps give the same file (a session re-decodes bit-identically)
                with z.open(member, "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, a, allow_pickle=False)
        tmp.replace(path)
    except BaseException:  # e.g. a full disk: no partial file left behind
        tmp.unlink(missing_ok=True)
        raise


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
    """Atomic, indented JSON. JSON has no NaN or infinity: a non-finite number is written as
    null (a writer whose figures can be undefined says why beside them)."""
    write_atomic(path, (json.dumps(json_ready(obj), indent=2, allow_nan=False) + "\n").encode())


def json_ready(o: Any) -> Any:
    """`o` with numpy arrays and scalars as lists and numbers, paths as strings, records
    (`schema.Schema`) as the objects their files hold and every non-finite float as None."""
    if isinstance(o, schema.Schema):  # a record as its writer built it: the keys it was given, in declared order
        return json_ready(o.model_dump(by_alias=True, exclude_unset=True))
    if isinstance(o, dict):
        return {str(k): json_ready(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_ready(v) for v in o]
    if isinstance(o, np.ndarray):
        return json_ready(o.tolist())
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return json_ready(o.item())
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, Path):
        return str(o)
    if o is None or isinstance(o, (str, int, bool)):
        return o
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def disk_problem(exc: OSError) -> str:
    """A file-system error for people: the path, and what to do about a full disk or a
    read-only folder."""
    what = exc.strerror or str(exc)
    hint = {errno.ENOSPC: "free space on the disk or choose another folder",
            errno.EDQUOT: "free space on the disk or choose another folder",
            errno.EROFS: "the file system is read-only: choose another folder",
            errno.EACCES: "no permission to write there: choose another folder",
            errno.EPERM: "no permission to write there: choose another folder"}.get(exc.errno or 0)
    return f"{exc.filename + ': ' if exc.filename else ''}{what}" + (f" ({hint})" if hint else "")


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def calibration_sha256(path: str) -> dict[str, str]:
    """{"calibration_sha256": the SHA-256 of the calibration file a rig model names} when it
    names a readable one, else {}: what the session's model came from, by content."""
    try:
        return {"calibration_sha256": sha256(Path(path).read_bytes())} if path else {}
    except OSError:
        return {}


def rig_model_sha256(model_dict: dict[str, Any]) -> str:
    """The SHA-256 of a description (a rig model's `RigModel.to_dict`, a pattern set's
    `PatternSet.to_dict`; JSON-ready) in canonical JSON: what a manifest records at capture,
    to know later whether it was edited."""
    return sha256(json.dumps(model_dict, sort_keys=True, separators=(",", ":"), allow_nan=False).encode())


def frame_name(k: int) -> str:
    return f"frame_{k:03d}.png"


def manifest_record(root: Path, session_id: str, started: dt.datetime, *, rig_config: dict[str, Any], model: RigModel,
                    patterns: PatternSet, devices: dict[str, Any], extra: dict[str, Any] | None) -> dict[str, Any]:
    """A session's manifest without its frames and timings. The phase-to-height maps of
    `model`, if any, are put in the session folder `root` (`keep_maps`) once."""
    if model.phase_to_height is not None:
        if not (root / PHASE_TO_HEIGHT_MAPS).exists():
            keep_maps(model.phase_to_height, root / PHASE_TO_HEIGHT_MAPS)
        model = replace(model, phase_to_height=replace(model.phase_to_height, maps_file=PHASE_TO_HEIGHT_MAPS))
    rig_model = json_ready(model.to_dict())
    return {"slscan_manifest": MANIFEST_VERSION, "session_id": session_id, "software_version": __version__,
            "python": platform.python_version(), "created": started.isoformat(),
            "rig_config": rig_config, "rig_model": rig_model, "rig_model_sha256": rig_model_sha256(rig_model),
            **calibration_sha256(model.calibration), "patterns": patterns.to_dict(),
            "patterns_sha256": rig_model_sha256(json_ready(patterns.to_dict())), "devices": devices, **(extra or {})}


def refuse_used_folder(root: Path) -> None:
    """SessionError unless `root` (a new session's folder) is new or empty: no earlier session
    is overwritten. Commands check it before their slow start (the demo's CAD and libraries)."""
    try:
        used = root.exists() and any(root.iterdir())
    except OSError as exc:
        raise SessionError(f"cannot use the session folder {root}: {disk_problem(exc)}") from None
    if used:
        raise SessionError(f"{root}: output folder exists and is not empty; choose a new --out folder so no "
                           f"earlier session is overwritten")


class SessionWriter:
    """Writes one capture into a new session folder."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.id = f"{dt.datetime.now().strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:6]}"
        self.frames: list[dict[str, Any]] = []
        self.camera_frames: dict[str, list[dict[str, Any]]] = {}  # a rig with several cameras: each one's frames
        self.started = dt.datetime.now(dt.UTC)
        (root / FRAMES_DIR).mkdir(parents=True, exist_ok=False)

    @classmethod
    def create(cls, out_dir: str | Path) -> SessionWriter:
        """A new session folder; `out_dir` must not exist or be empty, and must be writable."""
        root = Path(out_dir)
        try:
            refuse_used_folder(root)
            root.mkdir(parents=True, exist_ok=True)
            return cls(root)
        except OSError as exc:
            raise SessionError(f"cannot create the session folder {root}: {disk_problem(exc)}") from None

    def add_frame(self, k: int, frame: Frame, camera: str | None = None) -> None:
        """Store frame k losslessly, then log it with its SHA-256; both are complete before
        they are visible. A write that fails (full disk, read-only folder) raises
        SessionError; the frames stored before it stay. `camera`: the frame of that camera of a
        rig with several, stored under frames/<camera>/ and listed in `camera_frames`."""
        img = frame.image
        ok, png = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise SessionError(f"{self.root}: could not encode frame {k} ({img.dtype} {img.shape})")
        data = png.tobytes()
        folder = FRAMES_DIR if camera is None else f"{FRAMES_DIR}/{camera}"
        (self.root / folder).mkdir(exist_ok=True)
        entry = {"k": k, "file": f"{folder}/{frame_name(k)}", "index": frame.index,
                 "pattern_index": frame.pattern_index, "timestamp_s": frame.timestamp_s,
                 "exposure_s": frame.exposure_s, "bit_depth": frame.bit_depth,
                 "shape": list(img.shape), "dtype": str(img.dtype), "sha256": sha256(data)}
        try:
            write_atomic(self.root / folder / frame_name(k), data)
            with (self.root / FRAME_LOG).open("a") as f:
                f.write(json.dumps(entry) + "\n")
        except OSError as exc:
            raise SessionError(f"cannot store frame {k}: {disk_problem(exc)}; the {len(self.frames)} frame(s) "
                               f"stored before it are kept in {self.root / FRAMES_DIR}") from None
        (self.frames if camera is None else self.camera_frames.setdefault(camera, [])).append(entry)

    def _record(self, rig_config: dict[str, Any], model: RigModel, patterns: PatternSet,
                devices: dict[str, Any], extra: dict[str, Any] | None) -> dict[str, Any]:
        return manifest_record(self.root, self.id, self.started, rig_config=rig_config, model=model, patterns=patterns,
                               devices=devices, extra=extra)

    def begin(self, rig_config: dict[str, Any], model: RigModel, patterns: PatternSet,
              devices: dict[str, Any], extra: dict[str, Any] | None = None) -> None:
        """Write capture.json before the first frame: what the manifest will say but its
        frames, so a capture killed after its last frame can still be completed
        (`scanner.session_recovery`)."""
        try:
            write_json(self.root / CAPTURE, self._record(rig_config, model, patterns, devices, extra))
        except OSError as exc:
            raise SessionError(f"cannot write {CAPTURE}: {disk_problem(exc)}") from None

    def finish(self, rig_config: dict[str, Any], model: RigModel, patterns: PatternSet,
               devices: dict[str, Any], timings: dict[str, float], extra: dict[str, Any] | None = None) -> Path:
        """Write the manifest: from now on the session is complete."""
        manifest = {**self._record(rig_config, model, patterns, devices, extra),
                    "completed": dt.datetime.now(dt.UTC).isoformat(), "timings_s": timings,
                    "frames": self.frames}
        try:
            write_json(self.root / MANIFEST, manifest)
        except OSError as exc:
            raise SessionError(f"cannot write the manifest: {disk_problem(exc)}; the {len(self.frames)} frames "
                               f"are kept in {self.root / FRAMES_DIR}") from None
        return self.root / MANIFEST

    def fail(self, error: BaseException, stage: str) -> None:
        """Record why the capture stopped; the frames already stored stay. When even that
        cannot be written (the disk is full), the error itself is what the user sees."""
        with suppress(OSError):
            write_json(self.root / ERROR, {
                "session_id": self.id, "stage": stage, "error": type(error).__name__, "message": str(error),
                "frames_stored": len(self.frames), "time": dt.datetime.now(dt.UTC).isoformat()})


BitDepth = Annotated[int, Field(strict=True, ge=1, le=16)]
Count = Annotated[int, Field(strict=True, ge=0)]
Share = Annotated[float, Field(strict=True, ge=0, le=1)]  # of a whole
ExposureMode = Literal["given", "auto", "hdr"]  # exposures as listed, one chosen, several chosen (HDR)


class FrameEntry(schema.Schema):
    """One frame as `SessionWriter.add_frame` records it (frames.jsonl, the manifest)."""

    k: Annotated[int, Field(strict=True, ge=0)]
    file: Annotated[str, Field(strict=True, min_length=1)]
    index: schema.Int
    pattern_index: schema.Int | None = None
    timestamp_s: schema.Float
    exposure_s: schema.Float | None = None
    bit_depth: BitDepth
    shape: Annotated[list[schema.PositiveInt], Field(min_length=2, max_length=3)]
    dtype: Literal["uint8", "uint16"]
    sha256: Annotated[str, Field(strict=True, pattern="^[0-9a-f]{64}$")] | None = None

    @model_validator(mode="after")
    def _depth(self) -> FrameEntry:
        if (self.bit_depth <= 8) != (self.dtype == "uint8"):
            raise ValueError(f"a {self.bit_depth}-bit frame is not stored as {self.dtype}")
        return self


class ExposureRecord(schema.Schema):
    """manifest.json `exposure` (`scanner.exposure.plan_exposures` builds it): the exposures
    captured (s, ascending: frames i·N .. i·N + N − 1 at exposures_s[i]), how they were chosen
    (`mode`) and why; an auto or HDR plan adds the pre-capture's figures (a given plan has
    none): the probe's exposure (s), the lit ROI pixels and the rectangle asked for (x, y,
    width, height px; None: every lit pixel), the share of the ROI the plan is predicted to
    cover, the best single exposure (s) and its share, the fringes' contrast (0..1) and the
    probes taken (3 frames each)."""

    exposures_s: Annotated[list[schema.PositiveFloat], Field(min_length=1)]
    mode: ExposureMode
    reason: str
    probe_exposure_s: schema.PositiveFloat | None = None
    roi_pixels: schema.PositiveInt | None = None
    roi_box: Annotated[list[Count], Field(min_length=4, max_length=4)] | None = None
    predicted_coverage: Share | None = None
    best_single_exposure_s: schema.PositiveFloat | None = None
    best_single_coverage: Share | None = None
    fringe_contrast: Share | None = None
    probe_captures: Count = 0

    @model_validator(mode="after")
    def _ascending(self) -> ExposureRecord:
        if any(b <= a for a, b in zip(self.exposures_s, self.exposures_s[1:])):
            raise ValueError(f"exposures_s must ascend without repeats, got {self.exposures_s}")
        return self


class FileRecord(schema.Schema):
    """A file the session depends on, recorded so that a session moved, or opened from
    another folder, still finds it or knows it changed: its absolute path, its path
    relative to the session folder, and its SHA-256."""

    path: Annotated[str, Field(strict=True, min_length=1)]
    relative: Annotated[str, Field(strict=True, min_length=1)]
    sha256: Annotated[str, Field(strict=True, pattern="^[0-9a-f]{64}$")]


class Provenance(schema.Schema):
    """manifest.json `provenance` (`scanner.pipeline.provenance` builds it): the rig TOML and
    the calibration file (None: the rig names none) the session was captured with, by path
    and content (`FileRecord`)."""

    rig: FileRecord
    calibration: FileRecord | None = None


def file_record(path: Path, session_root: Path) -> FileRecord:
    """`FileRecord` of `path` as seen from the session folder `session_root`."""
    real = Path(path).resolve()
    return FileRecord(path=str(real), relative=os.path.relpath(real, Path(session_root).resolve()),
                      sha256=sha256(read_regular(real)))


def find_recorded(record: FileRecord, session_root: Path) -> tuple[Path | None, str]:
    """The file a `FileRecord` names, looked for at its absolute path and then relative to
    the session folder, accepted only with the recorded SHA-256: (path or None, what was
    found, for people)."""
    seen = []
    for candidate in (Path(record.path), Path(session_root) / record.relative):
        try:
            data = read_regular(candidate)
        except FileRefused:
            continue
        if sha256(data) == record.sha256:
            return candidate, "found"
        seen.append(str(candidate))
    if seen:
        return None, f"{seen[0]} has changed since the capture (its SHA-256 differs)"
    return None, f"{record.path} is gone (not found there or at {record.relative} from the session)"


class StageRecord(schema.Schema):
    """manifest.json `stage`, in a view of a multi-view session (`scanner.multiview`): the
    position the stage reported after the move (axis name -> rad or mm), the pose of the
    stage frame in the world the stage model gives for it (4x4, mm) and that model
    (`StageModel.to_dict`)."""

    position: dict[str, schema.Float]
    world_from_stage: schema.Matrix4
    stage_model: dict[str, Any]

    @field_validator("world_from_stage")
    @classmethod
    def _rigid(cls, T: list[list[float]]) -> list[list[float]]:
        a = np.array(T)
        R = a[:3, :3]
        if not (a[3].tolist() == [0.0, 0.0, 0.0, 1.0] and np.allclose(R.T @ R, np.eye(3), atol=1e-6)
                and np.linalg.det(R) > 0):
            raise ValueError("not a rigid motion (a rotation, a translation and the last row 0 0 0 1)")
        return T

    @field_validator("stage_model")
    @classmethod
    def _model(cls, d: dict[str, Any]) -> dict[str, Any]:
        try:
            StageModel.from_dict(d, "stage_model")
        except ConfigError as exc:
            raise ValueError(exc.problem) from None
        return d


@dataclass(frozen=True)
class ViewPlace:
    """Where a session lies in a multi-view session: its view (0-based), the multi-view id
    and the stage's record; its manifest holds them as `stage`, `view` and `multiview_id`."""

    view: int
    multiview_id: str
    stage: StageRecord

    def manifest_keys(self) -> dict[str, Any]:
        return {"stage": self.stage, "view": self.view, "multiview_id": self.multiview_id}


class ImportedCalibration(schema.Schema):
    """manifest.json `import.calibration`: the other tool's calibration the rig model was
    read from (`file`; a binocular capture's stereo calibration: `files`), its format and,
    for one camera, the projector scale applied to it."""

    file: str | None = None
    files: Annotated[list[str], Field(min_length=1)] | None = None
    format: str
    projector_scale: schema.PositiveFloat | None = None

    @model_validator(mode="after")
    def _one(self) -> ImportedCalibration:
        if (self.file is None) == (self.files is None):
            raise ValueError("names its calibration by 'file' (one camera) or 'files' (two), one of them")
        return self


class ConventionFinding(schema.Schema):
    """How `slscan import` settled one convention key (`scanner.convention_detection.Finding`):
    its value, the source (given, detected or assumed) and the evidence, for people."""

    value: Any
    source: str
    evidence: str


class ImportRecord(schema.Schema):
    """manifest.json `import` (`slscan import`): where the frames came from (one folder and
    its files in order, or a binocular capture's two folders), how they were chosen and
    stored (hard-linked or copied), the pattern file and projector size given, the frames'
    bit depth (a binocular capture's: one per camera), the calibration read and the
    conventions settled (a binocular capture's: per camera)."""

    source_folder: str | None = None
    source_folders: Annotated[list[str], Field(min_length=2, max_length=2)] | None = None
    sources: list[str] | None = None  # one folder's files; sessions before it have only source_folder
    frames_glob: str | None
    patterns_file: str
    projector_size: Annotated[list[schema.PositiveInt], Field(min_length=2, max_length=2)]
    bit_depth: BitDepth | list[BitDepth]
    hard_linked: Count
    copied: Count
    calibration: ImportedCalibration | None
    conventions: dict[str, ConventionFinding] | dict[str, dict[str, ConventionFinding]]

    @model_validator(mode="after")
    def _one(self) -> ImportRecord:
        if (self.source_folder is None) == (self.source_folders is None):
            raise ValueError("names where the frames came from by 'source_folder' (one camera) or 'source_folders' "
                             "(two), one of them")
        return self


class Manifest(schema.Schema):
    """manifest.json: what decoding reads is typed and checked; the other keys (devices,
    timings, versions, ...) are a record for people and kept as written. The object the file
    held is kept too (`recorded`): the descriptions checksummed at capture are compared as
    written, and the records other modules validate (the binocular keys) are read from it."""

    model_config = ConfigDict(extra="allow")

    slscan_manifest: ManifestVersion
    session_id: Annotated[str, Field(strict=True, min_length=1)]
    rig_config: dict[str, Any] = Field(default_factory=dict)
    rig_model: RigModelSchema
    patterns: PatternFile
    frames: Annotated[list[FrameEntry], Field(min_length=1)]
    exposure: ExposureRecord | None = None
    rig_model_sha256: Annotated[str, Field(strict=True, pattern="^[0-9a-f]{64}$")] | None = None  # of rig_model
    calibration_sha256: Annotated[str, Field(strict=True, pattern="^[0-9a-f]{64}$")] | None = None  # its file's
    patterns_sha256: Annotated[str, Field(strict=True, pattern="^[0-9a-f]{64}$")] | None = None  # of patterns
    provenance: Provenance | None = None  # sessions before it had only rig_config_path
    rig_config_path: str | None = None  # sessions before `provenance`: the rig TOML they were captured with
    calibrated: schema.Bool = True  # False: imported without a calibration (decoded maps, no cloud)
    imported: ImportRecord | None = Field(default=None, alias="import")  # `slscan import`: where from, how
    stage: StageRecord | None = None  # a view of a multi-view session (`ViewPlace`): the stage's position and pose
    view: Count | None = None  # its view
    multiview_id: Annotated[str, Field(strict=True, min_length=1)] | None = None  # its multi-view session
    timings_s: dict[str, Any] = Field(default_factory=dict)  # seconds per stage of the capture
    _recorded: dict[str, Any] = PrivateAttr(default_factory=dict)
    _path: str | Path = PrivateAttr(default=MANIFEST)  # the file read (`schema.parse`): its session's

    @model_validator(mode="wrap")  # before `_frames`, which reads `recorded_rig`: it needs `_path`
    @classmethod
    def _keep(cls, data: Any, handler: ModelWrapValidatorHandler[Manifest], info: ValidationInfo) -> Manifest:
        manifest = handler(data)
        manifest._recorded = data
        if isinstance(info.context, schema.Source):
            manifest._path = info.context.path
        return manifest

    @cached_property
    def recorded_rig(self) -> RecordedRig:
        """`rig_config` read through typed tables (`scanner.rig_schema.RecordedRig`), each
        validated when first read, errors naming the session's manifest: an imported
        session's stand-in reads as empty tables."""
        return RecordedRig(self.rig_config, self._path)

    def recorded(self, key: str) -> Any:
        """The value of `key` exactly as the file holds it (None when absent); not to be changed."""
        return self._recorded.get(key)

    def as_recorded(self) -> dict[str, Any]:
        """The object the file held (a shallow copy)."""
        return dict(self._recorded)

    @model_validator(mode="after")
    def _frames(self) -> Manifest:
        depths = {f.bit_depth for f in self.frames}
        if len(depths) > 1:
            raise ValueError(f"frames of different bit depths {sorted(depths)} in one stack")
        for k, f in enumerate(self.frames):
            if f.k != k:
                raise ValueError(f"frames[{k}] is numbered k = {f.k}")
            if tuple(f.shape[:2]) != (self.rig_model.camera.height, self.rig_model.camera.width):
                raise ValueError(f"frames[{k}] is {f.shape[1]} x {f.shape[0]} px, the camera "
                                 f"{self.rig_model.camera.width} x {self.rig_model.camera.height} px")
        if len({f.sha256 is None for f in self.frames}) > 1:
            raise ValueError("some frames have a sha256 and others not: the frame list was edited")
        configured = self.recorded_rig.camera.bit_depth
        if configured is not None and configured not in depths:
            raise ValueError(f"frames are {depths.pop()}-bit, the rig_config's camera.bit_depth is {configured!r}")
        return self


@dataclass(frozen=True, eq=False)
class Session:
    """A complete session read back from disk, its manifest validated (`Manifest`) once: what
    the layers above read is the typed record."""

    root: Path
    manifest: Manifest

    @classmethod
    def open(cls, path: str | Path) -> Session:
        root = Path(path)
        if not root.is_dir():
            raise SessionError(f"{root}: no such session folder")
        mpath = root / MANIFEST
        if not mpath.exists():
            raise IncompleteSession(describe_incomplete(root))
        try:
            manifest = json.loads(read_regular(mpath, limit=MAX_MANIFEST_BYTES))
        except FileRefused as exc:
            raise SessionError(str(exc)) from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            raise SessionError(f"{mpath}: unreadable manifest: {exc}") from None
        if not isinstance(manifest, dict):
            raise SessionError(f"{mpath}: not a session manifest (a JSON {type(manifest).__name__}, not an object)")
        version = manifest.get("slscan_manifest")
        if version != MANIFEST_VERSION:
            raise SessionError(f"{mpath}: manifest version {version!r}, this slscan reads {MANIFEST_VERSION}")
        return cls.checked(root, manifest)

    @classmethod
    def checked(cls, root: Path, manifest: dict[str, Any]) -> Session:
        """The session in `root` with the manifest `manifest` (a JSON object), validated as a
        file's would be: keys and types, the pattern set's rules, the rig model's geometry."""
        mpath = root / MANIFEST
        try:
            m = schema.parse(Manifest, manifest, mpath)
            session = cls(root, m)
            session.pattern_set  # noqa: B018  # the family's rules, checked once here
            try:
                distance = m.recorded_rig.rig.working_distance_mm
            except ConfigError:  # a malformed [rig] states no distance: judged at any, as before the typed read
                distance = None
            check_geometry(RigModel.from_dict(m.recorded("rig_model"), f"{mpath}: rig_model"),
                           distance if distance is not None and distance > 0 else None, mpath, "rig_model")
        except ConfigError as exc:
            raise SessionError(str(exc)) from None
        return session

    def replaced(self, **keys: Any) -> Session:
        """The session as it would be with these manifest keys (JSON-ready values) instead of
        its own, in memory only, validated as `checked` does (SessionError otherwise)."""
        return Session.checked(self.root, {**self.manifest.as_recorded(), **keys})

    @property
    def id(self) -> str:
        return self.manifest.session_id

    @cached_property
    def pattern_set(self) -> PatternSet:
        """The manifest's pattern set as recorded, parsed once (`checked` parses it first)."""
        return PatternSet.from_dict(self.manifest.recorded("patterns"), self.root / MANIFEST, "patterns")

    @cached_property
    def patterns(self) -> PatternSet:
        """The pattern set on the session's projector (its Gray code's bits and whole-pixel
        periods follow the projector's size, as the frames were rendered)."""
        projector = self.manifest.rig_model.projector
        return self.pattern_set.for_projector((projector.width, projector.height))

    def rig_model(self) -> RigModel:
        """The geometry the session was captured with, its phase-to-height model (and maps) included."""
        return self._rig_model

    @cached_property
    def _rig_model(self) -> RigModel:  # read once: the maps are ~12 MB at 1280 x 1024
        return RigModel.from_dict(self.manifest.recorded("rig_model"), f"{self.root / MANIFEST}: rig_model", self.root)

    @property
    def bit_depth(self) -> int:
        return self.manifest.frames[0].bit_depth

    @property
    def exposures_s(self) -> tuple[float, ...]:
        """The exposures the pattern set was captured at, ascending (one for a plain session:
        its frames' recorded exposure, or 0 when not recorded)."""
        if self.manifest.exposure is not None:
            return tuple(self.manifest.exposure.exposures_s)
        return (self.manifest.frames[0].exposure_s or 0.0,)

    @property
    def integrity(self) -> str:
        """What `load_stack` can vouch for: "sha256" when every frame carries its checksum,
        else a sentence saying the frames cannot be checked (sessions written before
        checksums were recorded)."""
        if all(e.sha256 for e in self.manifest.frames):
            return "sha256"
        return ("not checked: this session was written before slscan recorded frame checksums, so altered or "
                "replaced frames cannot be detected")

    def frame_path(self, k: int) -> Path:
        """Frame k's file (`confined_frame_path`)."""
        return confined_frame_path(self.root, self.manifest.frames[k].file, k,
                                   f"{self.root / MANIFEST}, key 'frames[{k}].file'")

    def load_stack(self) -> np.ndarray:
        """The raw frames as (N, H, W), each checked: inside the session folder, its SHA-256
        as recorded (when the session has checksums), its size, type and bit depth."""
        entries = self.manifest.frames
        n_exposures = len(self.exposures_s)
        n_expected = self.patterns.n_frames * n_exposures
        if len(entries) != n_expected:
            times = f" x {n_exposures} exposures" if n_exposures > 1 else ""
            raise SessionError(f"{self.root / MANIFEST}: lists {len(entries)} frames, pattern set needs "
                               f"{self.patterns.n_frames}{times}")
        cam = self.manifest.rig_model.camera
        shape = (cam.height, cam.width)
        stack = None
        for k, e in enumerate(entries):
            path = self.frame_path(k)
            try:
                data = read_regular(path, limit=frame_bytes_limit(shape, e.dtype))
            except FileRefused as exc:
                raise SessionError(f"{path}: frame {k} missing or unreadable ({exc.problem})") from None
            if e.sha256 and sha256(data) != e.sha256:
                raise SessionError(f"{path}: frame {k} has been altered or replaced since it was captured (its "
                                   f"SHA-256 is not the one in the manifest); re-scan, or restore the original file")
            declared = png_size(data)
            if declared is not None and declared != (shape[1], shape[0]):
                raise SessionError(f"{path}: frame {k} is a {declared[0]} x {declared[1]} PNG, expected "
                                   f"{shape[1]} x {shape[0]}")
            img, said = decode_image(data)
            if img is None:
                raise SessionError(f"{path}: frame {k} missing or unreadable "
                                   f"(not an image{': ' + said if said else ''})")
            if img.shape != shape or str(img.dtype) != e.dtype:
                raise SessionError(f"{path}: frame {k} is {_describe(img)}, expected {e.dtype} "
                                   f"{shape[1]}x{shape[0]} single-channel")
            if int(img.max()) >= 2 ** e.bit_depth:
                raise SessionError(f"{path}: frame {k} holds values up to {int(img.max())}, beyond its "
                                   f"{e.bit_depth}-bit depth in the manifest")
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


def confined_frame_path(root: Path, name: str, k: int, where: str) -> Path:
    """Frame k's file `name`, which must lie inside the session folder `root` (no control
    character, no absolute path, no '..', no symbolic link leading out); `where` names the
    record it came from."""
    rel = Path(name)
    if any(ord(c) < 32 for c in name):
        raise SessionError(f"{where}: frame path {name!r} holds a control character; frames are named "
                           f"frames/{frame_name(k)}")
    if rel.is_absolute() or ".." in rel.parts or "\\" in name:
        raise SessionError(f"{where}: frame path {name!r} leaves the session folder; frames must be "
                           f"inside it (e.g. frames/{frame_name(k)})")
    path = root / rel
    if not path.resolve().is_relative_to(root.resolve()):
        raise SessionError(f"{where}: {name!r} is a link to {path.resolve()}, outside the session folder")
    return path


def frame_bytes_limit(shape: tuple[int, int], dtype: str) -> int:
    """The most bytes a lossless file of one (H, W) frame can need, with up to 4 channels (so
    a colour file is refused by what it is, not its size): every row stored uncompressed
    with its filter byte, 1 % of block overhead, 64 kB of chunks beside."""
    return int(shape[0] * (4 * shape[1] * np.dtype(dtype).itemsize + 1) * 1.01) + 65536


def png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) a PNG's header declares, read before decoding (a header that lies
    about its size would otherwise size the decoder's buffer); None for another format."""
    if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR" or len(data) < 24:
        return None
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def _describe(img: np.ndarray) -> str:
    channels = f", {img.shape[2]} channels" if img.ndim == 3 else " single-channel"
    return f"{img.dtype} {img.shape[1]}x{img.shape[0]}{channels}"


def describe_incomplete(root: Path) -> str:
    """Why a session folder cannot be used, for the user."""
    frames = sorted((root / FRAMES_DIR).glob("frame_*.png")) if (root / FRAMES_DIR).is_dir() else []
    finish = (f"If the capture finished (every frame logged), `slscan decode --recover {root}` completes it; "
              f"else re-scan the part" if frames else "Re-scan the part")
    return (f"{root}: incomplete session (no {MANIFEST}); {len(frames)} raw frame(s) on disk"
            f"{stop_reason(root, 'scan')}. {finish}; the frames are kept for inspection.")


def stop_reason(root: Path, run: str, at_view: bool = False) -> str:
    """What the folder's error.json says stopped the capture (`at_view`: a multi-view run,
    naming the view), as "; ..." to append to a message; `run` names what was interrupted
    when nothing was recorded."""
    err = root / ERROR
    if not err.exists():
        return f"; no error recorded (the {run} was interrupted)"
    try:
        e = json.loads(err.read_text())
    except (OSError, json.JSONDecodeError):
        return f"; {ERROR} unreadable"
    where = f"stopped at view {e.get('view')}" if at_view else "capture stopped"
    return f"; {where} during {e.get('stage')}: {e.get('error')}: {e.get('message')}"
