"""Rerun recording of a scan session: one `.rrd` file per session, beside the raw data.

A `SessionRecording` wraps one explicit `rerun.RecordingStream` (never the global one, so
several sessions can be recorded in one process) that streams into `<path>.part` and is
renamed to `<path>` when it is closed, footer written: a `.rrd` that exists is complete.

Entity paths are module constants and stay stable, because users build viewer layouts on
them. Units are millimetres and radians; the 3D space `world` is the rig's world frame in
the OpenCV convention (x right, y down, z forward).

=========================================  ==========================================  ===============
entity path                                content                                      timelines
=========================================  ==========================================  ===============
``world``                                  ViewCoordinates RDF                          static
``world/camera``                           Transform3D world_from_cam + Pinhole         static
``world/camera/image``                     raw frames, EncodedImage: lossless PNG at    pattern, scan
                                           their bit depth
``world/projector``                        Transform3D world_from_cam·cam_from_proj     static
                                           + Pinhole
``world/scan/cloud``                       Points3D in the world frame, grey colours    scan
                                           (every `step`-th pixel's at level display)
``world/scan/normals``                     Arrows3D, a subsample of the normals (opt.)  scan
``frames/spec``                            TextLog: the pattern each frame shows        pattern, scan
``rig``                                    TextDocument: the rig model as JSON          static
``maps``                                   AnnotationContext naming the mask classes    static
``maps/<orientation>/coordinate``          DepthImage: projector px, 0 where invalid    scan
``maps/<orientation>/phase``               DepthImage: absolute phase, 0 where invalid  scan
``maps/<orientation>/wrapped/<i>``         DepthImage: wrapped phase [0, 2π) of         scan
                                           frequency i (index into PatternSet.fringes)
``maps/<orientation>/modulation/<i>``      DepthImage: modulation B (DN) of frequency i scan
``maps/<orientation>/background``          Image: background A (DN)                     scan
``maps/<orientation>/masks``               SegmentationImage: rejection reason per px   scan
``maps/texture``                           Image: mean intensity (DN)                   scan
``maps/masks``                             SegmentationImage: reason over all           scan
                                           orientations; class 0 == DecodeResult.valid
``metrics/<name>``                         Scalars (timings in s, fractions, errors)    scan
``events``                                 TextLog: session events and errors           as logged
=========================================  ==========================================  ===============

Levels (`level=`, a rig's ``[recording] level``): ``"full"`` logs every map pixel and every
point; ``"display"`` the same entities with the maps and the organised cloud taken every
`display_step(H, W)`-th row and column (the longest side at most DISPLAY_MAX_SIDE_PX; the maps'
images are smaller than the camera's then), so a station can keep a recording per part; the
frames are the record and stay lossless at every level. ``"none"`` (a rig's option) writes no
recording: `pipeline.scan` then makes no `SessionRecording` at all.

Timelines: ``pattern`` is the frame's index in its pattern sequence (`PatternSet.frames()`),
``scan`` the scan's index in the session; Rerun adds ``log_time`` (wall clock) by itself.

Mask classes (``maps/masks``, ``maps/<orientation>/masks``): 0 valid (transparent),
1 saturated, 2 shadow, 3 low_modulation, 4 order_error, 5 discontinuity, 6 interreflection
(a second light path: interreflection or a specular glint's spill), then any other
reason `decode` reports (in name order), and 255 "rejected" for a pixel invalid without a
named reason. A pixel rejected for several reasons shows the one with the lowest id.

Rerun images cannot carry NaN sensibly (the viewer's colour range skips NaN, but the GPU's
colour of a NaN texel is undefined), so NaN map pixels are written as 0 with the colour
range set from the valid pixels; the mask overlay in the blueprint marks them.

Rerun places the centre of pixel (0, 0) at (0.5, 0.5) while OpenCV puts it at (0, 0): the
logged pinholes have the principal point shifted by +0.5 px so 3D points land on the right
pixel of the logged images.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, get_args

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from scanner.decode import DecodeResult, OrientationMaps
from scanner.devices import Frame
from scanner.errors import ScannerError
from scanner.geometry import Pinhole, RigModel
from scanner.pattern_families import FrameKind
from scanner.patterns import FrameSpec, PatternSet
from scanner.pointcloud import OrganisedCloud
from scanner.rig_schema import RecordingLevel

APPLICATION_ID = "slscan"
RECORDING_NAME = "recording.rrd"  # file name inside a session folder
FLUSH_SLICE_S = 2.0  # a writer that writes nothing for this long while data waits, with little space left, has stopped
LOW_SPACE_BYTES = 64 * 1024 ** 2  # "little space": below what one flush of a scan's recording can need
CLOSE_TIMEOUT_S = 30.0  # longest wait for the writer to flush (twice this for the whole close)
LEVELS: tuple[str, ...] = get_args(RecordingLevel)  # "full", "display", "none"
DISPLAY_MAX_SIDE_PX = 800  # level "display": maps and cloud decimated until their longest side is at most this
PNG_FAST = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
# frames encoded here (not read from disk): lossless; Huffman coding only: the 18 frames of a 1.3 MP
# import 8.0 MB in 432 ms CPU, where deflate level 1 took 518 ms for 10.3 MB

TIMELINE_PATTERN = "pattern"
TIMELINE_SCAN = "scan"

WORLD = "world"
CAMERA = "world/camera"
CAMERA_IMAGE = "world/camera/image"
PROJECTOR = "world/projector"
CLOUD = "world/scan/cloud"
NORMALS = "world/scan/normals"
FRAME_SPEC = "frames/spec"
RIG_INFO = "rig"
MAPS = "maps"
MAP_TEXTURE = "maps/texture"
MAP_MASKS = "maps/masks"
METRICS = "metrics"
EVENTS = "events"

MAP_KINDS = ("coordinate", "phase", "wrapped", "modulation", "background", "masks")

VALID_CLASS = 0
REJECTED_CLASS = 255
REASONS = ("saturated", "shadow", "low_modulation", "order_error", "discontinuity",
           "interreflection")  # class ids 1, 2, ...
_REASON_COLORS = {"saturated": (230, 40, 40, 255), "shadow": (70, 90, 200, 255),
                  "low_modulation": (240, 160, 30, 255), "order_error": (220, 40, 220, 255),
                  "discontinuity": (40, 200, 200, 255), "interreflection": (250, 110, 90, 255)}
_OTHER_REASON_COLOR = (120, 120, 120, 255)



class RecordingError(ScannerError):
    """A recording cannot be written, or a `.rrd` file cannot be read back."""


# ---------------------------------------------------------------- entity path helpers


def map_path(kind: str, orientation: str | None = None, level: int | None = None) -> str:
    """Entity path of a decoded map: `maps/<orientation>/<kind>[/<level>]`."""
    if kind not in MAP_KINDS and kind != "texture":
        raise ValueError(f"unknown map kind '{kind}'; known: {MAP_KINDS + ('texture',)}")
    parts = [MAPS] + ([orientation] if orientation else []) + [kind] + ([str(level)] if level is not None else [])
    return "/".join(parts)


def metric_path(name: str) -> str:
    """Entity path of a metric: `metrics/<name>` (`name` may contain '/' to group)."""
    name = name.strip("/")
    if not name:
        raise ValueError("metric name is empty")
    return f"{METRICS}/{name}"


def display_step(height: int, width: int) -> int:
    """Row and column step of level "display": the smallest that brings the longest side
    of an (height, width) image to at most DISPLAY_MAX_SIDE_PX."""
    return max(1, math.ceil(max(height, width) / DISPLAY_MAX_SIDE_PX))


def png_bytes(image: np.ndarray) -> bytes:
    """`image` (H, W) uint8/uint16 as a lossless PNG at its bit depth."""
    ok, buf = cv2.imencode(".png", image, PNG_FAST)
    if not ok:
        raise RecordingError(f"could not encode a {image.dtype} {image.shape} frame as PNG")
    return buf.tobytes()


def spec_name(spec: FrameSpec) -> str:
    """Short human-readable name of a frame's pattern, e.g. 'vertical phase f0 s2'."""
    if spec.kind is FrameKind.PHASE:
        return f"{spec.orientation} phase f{spec.level} s{spec.step}"
    return f"{spec.orientation} {spec.kind} b{spec.level}"


def _rerun_pinhole(p: Pinhole, image_plane_mm: float | None) -> rr.Pinhole:
    K = p.K.copy()
    K[0, 2] += 0.5  # OpenCV pixel centres at integers, Rerun's at +0.5
    K[1, 2] += 0.5
    return rr.Pinhole(image_from_camera=K, resolution=[p.width, p.height], camera_xyz=rr.ViewCoordinates.RDF,
                      image_plane_distance=image_plane_mm)


def _transform(T: np.ndarray) -> rr.Transform3D:
    T = np.asarray(T, dtype=np.float64)
    return rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


def _grey_rgba(grey: np.ndarray) -> np.ndarray:
    """uint8 grey levels as packed 0xRRGGBBAA colours."""
    c = grey.astype(np.uint32)
    c *= np.uint32(0x01010100)
    c |= np.uint32(0xFF)
    return c


def _finite_range(a: np.ndarray, valid: np.ndarray | None = None) -> tuple[float, float] | None:
    vals = a[valid] if valid is not None else a[np.isfinite(a)]
    if vals.size == 0:
        return None
    lo, hi = float(vals.min()), float(vals.max())
    return (lo, hi) if hi > lo else (lo - 1.0, hi + 1.0)


def _reason_ids(names: Sequence[str]) -> dict[str, int]:
    """Class id per rejection reason: the known reasons first, others after them."""
    ordered = [r for r in REASONS if r in names] + sorted(n for n in names if n not in REASONS)
    ids = {r: i + 1 for i, r in enumerate(REASONS)}
    for n in ordered:
        if n not in ids:
            ids[n] = len(ids) + 1
    if len(ids) >= REJECTED_CLASS:
        raise RecordingError(f"too many rejection reasons to label ({len(ids)})")
    return ids


def _reason_image(masks: Mapping[str, np.ndarray], valid: np.ndarray, ids: Mapping[str, int]) -> np.ndarray:
    """uint8 class image: 0 valid, else the first reason (in class id order) that applies."""
    cls = np.zeros(valid.shape, dtype=np.uint8)
    cls[~valid] = REJECTED_CLASS
    for name in sorted(masks, key=lambda n: ids[n], reverse=True):  # lowest id written last, so it wins
        cls[masks[name] & ~valid] = ids[name]
    return cls


def _every(masks: Mapping[str, np.ndarray], step: int) -> dict[str, np.ndarray]:
    """Each mask's every `step`-th row and column."""
    return {name: mask[::step, ::step] for name, mask in masks.items()}


def _annotation_context(ids: Mapping[str, int]) -> rr.AnnotationContext:
    infos = [rr.AnnotationInfo(id=VALID_CLASS, label="valid", color=(0, 0, 0, 0)),
             rr.AnnotationInfo(id=REJECTED_CLASS, label="rejected", color=_OTHER_REASON_COLOR)]
    infos += [rr.AnnotationInfo(id=i, label=n, color=_REASON_COLORS.get(n, _OTHER_REASON_COLOR))
              for n, i in ids.items()]
    return rr.AnnotationContext(infos)


# ---------------------------------------------------------------- blueprint


def blueprint(orientations: Sequence[str] = ("vertical",), n_freq: int = 3) -> rrb.Blueprint:
    """The default viewer layout: the 3D world and the metrics on the left; the camera image
    and one tab of decoded maps per orientation (plus one for the combined maps) on the right."""

    def overlay(origin: str, masks: str, name: str) -> rrb.Spatial2DView:
        return rrb.Spatial2DView(origin=origin, contents=["$origin/**", masks], name=name)

    tabs = []
    for o in orientations:
        masks = map_path("masks", o)
        views = [overlay(map_path("coordinate", o), masks, f"{o} coordinate (px)"),
                 overlay(map_path("phase", o), masks, f"{o} phase (rad)"),
                 rrb.Spatial2DView(origin=masks, name=f"{o} rejected"),
                 rrb.Spatial2DView(origin=map_path("background", o), name=f"{o} background")]
        for i in range(n_freq):
            views.append(rrb.Spatial2DView(origin=map_path("wrapped", o, i), name=f"{o} wrapped f{i}"))
        for i in range(n_freq):
            views.append(rrb.Spatial2DView(origin=map_path("modulation", o, i), name=f"{o} modulation f{i}"))
        tabs.append(rrb.Grid(*views, name=o))
    tabs.append(rrb.Grid(rrb.Spatial2DView(origin=MAP_TEXTURE, name="texture"),
                         rrb.Spatial2DView(origin=MAP_MASKS, name="rejected (all)"), name="combined"))
    left = rrb.Vertical(
        rrb.Spatial3DView(origin=WORLD, name="3D"),
        rrb.Tabs(rrb.TimeSeriesView(origin=METRICS, name="metrics"),
                 rrb.TextLogView(origin="/", contents=[f"{FRAME_SPEC}/**", f"{EVENTS}/**"], name="log")),
        row_shares=[3, 1])
    right = rrb.Vertical(rrb.Spatial2DView(origin=CAMERA, name="camera"), rrb.Tabs(*tabs, name="maps"),
                         row_shares=[1, 1])
    return rrb.Blueprint(rrb.Horizontal(left, right, column_shares=[1, 1]),
                         rrb.TimePanel(timeline=TIMELINE_SCAN), collapse_panels=False)


# ---------------------------------------------------------------- the recording


ABANDONED: list[Any] = []
"""Recording streams whose writer stopped (a full disk): never destroyed, since destroying
one waits for its writer; a process holding any must end with `os._exit`."""


def _free_bytes(path: Path) -> int:
    """Bytes free for a writer on the file system holding `path` (a large number when unknown)."""
    try:
        st = os.statvfs(path.parent)
    except OSError:
        return 1 << 62
    return st.f_bavail * st.f_frsize


def _disk_full(path: Path) -> bool:
    """Whether the file system holding `path` has no block left for a writer."""
    return _free_bytes(path) == 0


class SessionRecording:
    """One session's Rerun recording, written to `path` (a `.rrd` file).

    Use it as a context manager, or call `close()`: the file only gets its footer (and its
    final name; until then it is `<path>.part`) when the recording is closed, which
    happens even when the `with` block raises. Pass `patterns` to lay the maps out in the
    default blueprint from the start; otherwise the layout follows the first decode logged.
    `level` "display" decimates the maps and the cloud (module docstring).
    """

    def __init__(self, path: str | Path, session_id: str, *, patterns: PatternSet | None = None,
                 send_blueprint: bool = True, application_id: str = APPLICATION_ID, level: str = "full") -> None:
        if level not in LEVELS or level == "none":
            raise RecordingError(f"recording level '{level}': a recording is 'full' or 'display' ('none' makes "
                                 f"no recording)")
        self.level = level
        self.path = Path(path)
        if not self.path.parent.is_dir():
            raise RecordingError(f"{self.path}: folder does not exist; create the session folder first")
        self.partial_path = self.path.with_name(self.path.name + ".part")
        if self.partial_path.is_symlink() or self.partial_path.exists():  # a dead writer's: never written through
            self.partial_path.unlink()
        self.session_id = str(session_id)
        self._world_from_cam = np.eye(4)
        self._reason_ids: dict[str, int] = _reason_ids(REASONS)
        self._blueprint_pending = send_blueprint
        self._closed = False
        self._scan = 0  # the last scan index logged, for events
        self.stream = rr.RecordingStream(application_id, recording_id=self.session_id)
        try:
            self.stream.save(self.partial_path)
            self.stream.send_recording_name(f"{application_id} {self.session_id}")
            self.stream.log(MAPS, _annotation_context(self._reason_ids), static=True, strict=True)
            if patterns is not None:
                self._send_blueprint(patterns.orientations, len(patterns.fringes))
        except Exception as exc:
            self.stream.disconnect()
            raise RecordingError(f"{self.partial_path}: cannot start the recording: {exc}") from exc

    @classmethod
    def for_session(cls, folder: str | Path, session_id: str, **kw: Any) -> SessionRecording:
        """The recording of the session in `folder`, at `folder/recording.rrd`."""
        return cls(Path(folder) / RECORDING_NAME, session_id, **kw)

    # -- lifecycle

    def __enter__(self) -> SessionRecording:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc is None:
            self.close()
            return
        try:  # never mask the original exception
            if not self._closed:
                self.log_event(f"session aborted: {exc_type.__name__ if exc_type else 'error'}: {exc}", level="ERROR")
            self.close()
        except Exception:
            pass

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Flush, write the footer, and give the file its final name. Idempotent. Waits at
        most CLOSE_TIMEOUT_S: a writer that died (a full disk) or stalls raises
        RecordingError and leaves `<path>.part`; nothing else of the session is touched."""
        if self._closed:
            return
        self._closed = True
        errors: list[BaseException] = []
        if _disk_full(self.partial_path):  # the writer cannot finish: do not wait for it, nor let exit wait
            self._abandon()
            raise RecordingError(f"{self.partial_path}: the disk is full, the recording cannot be finished; the "
                                 f"session's other files are kept (free space, then `slscan decode` records it again)")

        def finish() -> None:
            try:
                if self._blueprint_pending:
                    self._send_blueprint((), 0)
                self._flush()
            except Exception as exc:  # a writer that cannot flush cannot disconnect either
                errors.append(exc)
                return
            try:
                self.stream.disconnect()  # closes the file sink: footer written
            except Exception as exc:
                errors.append(exc)

        worker = threading.Thread(target=finish, name=f"close {self.path.name}", daemon=True)
        worker.start()
        worker.join(2 * CLOSE_TIMEOUT_S)
        if worker.is_alive() or errors:
            self._abandon()
        if worker.is_alive():
            raise RecordingError(f"{self.partial_path}: the recording writer did not finish within "
                                 f"{2 * CLOSE_TIMEOUT_S:g} s (a full disk or a stalled file system?); the recording "
                                 f"is incomplete, the session's other files are kept")
        if errors:
            raise RecordingError(f"{self.partial_path}: the recording could not be finished ({errors[0]}); the "
                                 f"disk may be full; the session's other files are kept")
        if self.partial_path.exists():
            self.partial_path.replace(self.path)

    def _flush(self) -> None:
        """Wait until the writer has written everything logged, up to CLOSE_TIMEOUT_S; a
        writer that wrote nothing for FLUSH_SLICE_S while data waits, on a file system with
        less than LOW_SPACE_BYTES free, has stopped (Rerun's writer ends at its first failed
        write, which on a healthy file system only running out of space causes), and
        RecordingError says so at once instead of after the whole timeout. A busy machine
        that merely delays the writer keeps its recording (space is left)."""
        deadline = time.monotonic() + CLOSE_TIMEOUT_S
        size = -1
        while True:
            try:
                self.stream.flush(timeout_sec=FLUSH_SLICE_S)
                return
            except RuntimeError as exc:
                if "timed out" not in str(exc).lower():
                    raise  # the writer failed (its own message)
                now = self.partial_path.stat().st_size if self.partial_path.exists() else 0
                if (now == size and _free_bytes(self.partial_path) < LOW_SPACE_BYTES) or time.monotonic() > deadline:
                    raise RecordingError(f"{self.partial_path}: the recording writer stopped writing (a full disk or "
                                         f"a failed file system?)") from None
                size = now

    def _abandon(self) -> None:
        """A recording whose writer is stuck: Rerun's exit handler, and the stream's own
        destructor, would flush it forever (the process would never end). The handler is
        unregistered (every other recording is closed explicitly before exit anyway) and the
        stream kept (`ABANDONED`), so `slscan.cli` ends the process without tearing it down."""
        rr.unregister_shutdown()
        ABANDONED.append(self.stream)

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"{self.path}: recording is closed")

    def _send_blueprint(self, orientations: Sequence[str], n_freq: int) -> None:
        # default only, not active: a layout the user made for this application stays in use
        self.stream.send_blueprint(blueprint(orientations, n_freq), make_active=False, make_default=True)
        self._blueprint_pending = False

    @property
    def world_from_cam(self) -> np.ndarray:
        """The rig's world frame as logged with `log_rig` (identity before): the 4x4 (mm)
        that content logged under `world` by other modules maps camera-frame geometry by."""
        return self._world_from_cam.copy()

    def at_scan(self, scan: int) -> None:
        """Set this thread's time to scan `scan` on the scan timeline alone, for content
        other modules log through `stream`."""
        self._check_open()
        self._at(scan)

    def _at(self, scan: int | None = None, pattern: int | None = None) -> None:
        """Set this thread's time context to exactly the given timelines."""
        self.stream.reset_time()
        if scan is not None:
            self._scan = int(scan)
            self.stream.set_time(TIMELINE_SCAN, sequence=int(scan))
        if pattern is not None:
            self.stream.set_time(TIMELINE_PATTERN, sequence=int(pattern))

    # -- content

    def log_rig(self, model: RigModel, *, image_plane_mm: float | None = 100.0) -> None:
        """The camera and the projector as posed pinholes under `world` (static)."""
        self._check_open()
        s = self.stream
        self._world_from_cam = np.asarray(model.world_from_cam, dtype=np.float64)
        s.log(WORLD, rr.ViewCoordinates.RDF, static=True, strict=True)
        s.log(CAMERA, _transform(self._world_from_cam), _rerun_pinhole(model.camera, image_plane_mm),
              static=True, strict=True)
        s.log(PROJECTOR, _transform(self._world_from_cam @ model.cam_from_proj),
              _rerun_pinhole(model.projector, image_plane_mm), static=True, strict=True)
        text = "```json\n" + json.dumps(model.to_dict(), indent=1) + "\n```"
        s.log(RIG_INFO, rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True, strict=True)

    def log_frame(self, index: int, frame: np.ndarray | Frame, spec: FrameSpec | None = None, *,
                  scan: int = 0, png: bytes | None = None) -> None:
        """One raw frame (an image, or a device `Frame`) as it arrives, as a lossless PNG:
        `png` is the frame's file as written to the session (else it is encoded here);
        `index` is its place in the pattern sequence, `spec` the pattern it shows."""
        self._check_open()
        image = np.asarray(frame.image if isinstance(frame, Frame) else frame)
        if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
            raise RecordingError(f"frame {index}: expected an (H, W) uint8 or uint16 image, "
                                 f"got {image.dtype} {image.shape}")
        self.log_png_frame(index, png if png is not None else png_bytes(image), spec, scan=scan)

    def log_png_frame(self, index: int, png: bytes, spec: FrameSpec | None = None, *, scan: int = 0) -> None:
        """One raw frame given as its PNG file's bytes (a session's own frame, as stored)."""
        self._check_open()
        self._at(scan, index)
        self.stream.log(CAMERA_IMAGE, rr.EncodedImage(contents=png, media_type=rr.MediaType.PNG), strict=True)
        if spec is not None:
            self.stream.log(FRAME_SPEC, rr.TextLog(f"{index}: {spec_name(spec)}", level="INFO"), strict=True)

    def log_frames(self, stack: np.ndarray, specs: Sequence[FrameSpec] | None = None, *, scan: int = 0,
               first_index: int = 0) -> None:
        """A whole (N, H, W) stack at once (e.g. re-logged from a session folder), columnar,
        each frame a lossless PNG."""
        self._check_open()
        stack = np.asarray(stack)
        if stack.ndim != 3 or stack.dtype not in (np.uint8, np.uint16):
            raise RecordingError(f"expected an (N, H, W) uint8 or uint16 stack, got {stack.dtype} {stack.shape}")
        n = len(stack)
        if specs is not None and len(specs) != n:
            raise RecordingError(f"{n} frames but {len(specs)} pattern specs")
        idx = np.arange(first_index, first_index + n)
        times = [rr.TimeColumn(TIMELINE_PATTERN, sequence=idx), rr.TimeColumn(TIMELINE_SCAN, sequence=np.full(n, scan))]
        self.stream.send_columns(CAMERA_IMAGE, times, rr.EncodedImage.columns(
            blob=[png_bytes(f) for f in stack], media_type=[rr.MediaType.PNG] * n), strict=True)
        if specs is not None:
            self.stream.send_columns(FRAME_SPEC, times, rr.TextLog.columns(
                text=[f"{i}: {spec_name(s)}" for i, s in zip(idx, specs)], level=["INFO"] * n), strict=True)

    def _step(self, height: int, width: int) -> int:
        """Row and column step of the maps and the cloud at this recording's level."""
        return display_step(height, width) if self.level == "display" else 1

    def log_decode(self, result: DecodeResult, *, scan: int = 0, detail: bool = True) -> None:
        """The decoded maps as 2D images under `maps/` (decimated at level "display").
        `detail=False` logs only the coordinates, masks and texture (the per-frequency maps
        are the bulk of the data)."""
        self._check_open()
        if self._blueprint_pending:
            self._send_blueprint(tuple(result.maps), len(result.patterns.fringes))
        names = sorted({n for m in result.maps.values() for n in m.masks})
        ids = _reason_ids(names)
        if ids != self._reason_ids:
            self._reason_ids = ids
            self.stream.log(MAPS, _annotation_context(ids), static=True, strict=True)
        self._at(scan)
        log = self.stream.log
        step = self._step(*result.valid.shape)
        valid = result.valid[::step, ::step]
        for o, m in result.maps.items():
            self._orientation_maps(o, m, ids, detail, step)
        log(MAP_TEXTURE, rr.Image(np.asarray(result.texture[::step, ::step], dtype=np.float32)), strict=True)
        combined = np.zeros(valid.shape, dtype=np.uint8)
        for m in result.maps.values():  # the first orientation that rejects a pixel names the reason
            cls = _reason_image(_every(m.masks, step), m.valid[::step, ::step], ids)
            np.copyto(combined, cls, where=(combined == VALID_CLASS))
        combined[~valid & (combined == VALID_CLASS)] = REJECTED_CLASS
        log(MAP_MASKS, rr.SegmentationImage(combined), strict=True)

    def _orientation_maps(self, o: str, m: OrientationMaps, ids: Mapping[str, int], detail: bool,
                          step: int) -> None:
        log = self.stream.log
        valid = m.valid[::step, ::step]
        for kind, data in (("coordinate", m.coordinate[::step, ::step]), ("phase", m.phase[::step, ::step])):
            rng = _finite_range(data, valid)
            img = np.where(valid, data, np.float32(0)).astype(np.float32, copy=False)
            log(map_path(kind, o), rr.DepthImage(img, colormap="turbo", depth_range=rng), strict=True)
        log(map_path("masks", o), rr.SegmentationImage(_reason_image(_every(m.masks, step), valid, ids)), strict=True)
        if not detail:
            return
        for i, (phi, b) in enumerate(zip(m.wrapped, m.modulation)):
            log(map_path("wrapped", o, i), rr.DepthImage(np.asarray(phi[::step, ::step], dtype=np.float32),
                                                         colormap="twilight", depth_range=(0.0, 2.0 * np.pi)),
                strict=True)
            b = np.asarray(b[::step, ::step], dtype=np.float32)
            log(map_path("modulation", o, i), rr.DepthImage(b, colormap="viridis",
                                                            depth_range=(0.0, max(float(b.max()), 1.0))), strict=True)
        log(map_path("background", o), rr.Image(np.asarray(m.background[::step, ::step], dtype=np.float32)),
            strict=True)

    def log_cloud(self, cloud: OrganisedCloud, model: RigModel | None = None, *, scan: int = 0,
                  normals_step: int = 0, normal_length_mm: float = 2.0) -> int:
        """The valid points (camera frame in `cloud`) moved into the world frame with
        `model.world_from_cam` (default: the rig logged with `log_rig`), with their grey
        colours; at level "display" those of every `display_step`-th row and column only.
        Returns the number of points logged. `normals_step` > 0 also logs every n-th
        normal as an arrow of `normal_length_mm`."""
        self._check_open()
        step = self._step(*cloud.valid.shape)
        if step > 1:
            cloud = OrganisedCloud(cloud.points[::step, ::step], cloud.colors[::step, ::step],
                                   cloud.normals[::step, ::step])
        pts, grey, nrm = cloud.flat()
        T = self._world_from_cam if model is None else np.asarray(model.world_from_cam, dtype=np.float64)
        if not np.array_equal(T, np.eye(4)):
            pts = pts @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)
            nrm = nrm @ T[:3, :3].T.astype(np.float32)
        self._at(scan)
        self.stream.log(CLOUD, rr.Points3D(np.ascontiguousarray(pts, dtype=np.float32), colors=_grey_rgba(grey)),
                        strict=True)
        if normals_step > 0:
            sel = slice(None, None, int(normals_step))
            o, v = pts[sel], nrm[sel]
            ok = np.isfinite(v).all(axis=1)
            self.stream.log(NORMALS, rr.Arrows3D(origins=o[ok], vectors=v[ok] * np.float32(normal_length_mm)),
                            strict=True)
        return len(pts)

    def log_metrics(self, values: Mapping[str, float], *, scan: int = 0) -> None:
        """Scalars under `metrics/<name>` on the scan timeline (seconds, fractions, mm, px)."""
        self._check_open()
        self._at(scan)
        for name, value in values.items():
            self.stream.log(metric_path(name), rr.Scalars(float(value)), strict=True)

    def log_event(self, text: str, *, level: str = "INFO", scan: int | None = None) -> None:
        """A line in the session's event log (`events`), at `scan` (default: the last scan
        logged, so the line shows on the scan timeline)."""
        self._check_open()
        self._at(self._scan if scan is None else scan)
        self.stream.log(EVENTS, rr.TextLog(text, level=level), strict=True)
