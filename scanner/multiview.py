"""Multi-view sessions: the part turned on the rig's stage, one complete session per view.

Layout of a multi-view folder (every file appears complete or not at all):
    views.json          written first: the plan (format version, multi-view id, the rig, the
                        stage model the scanner believes: nominal or calibrated axes, and each
                        view's target stage position)
    view_000/ …         one session folder per view (`scanner.session`), written as it is
                        captured; its manifest (written last) records under `stage` the
                        position the stage reported after the move and the pose
                        `world_from_stage` the stage model gives for it
    multiview.json      written last, atomically, once every view is complete: the views (folder,
                        session id, position, pose), timings; the multi-view session is complete
    error.json          instead of multiview.json when a move or a capture failed: the view
                        and stage, the error, the views kept (every earlier view is complete)
    outputs/            regenerable from the views: alignment.json (each view's pose in the part
                        frame, before and after refinement), merged.ply (the fused cloud), mesh.ply
                        and mesh.stl (see `inspection.views`)
    recording.rrd       the merged cloud, the mesh and each view's pose (Rerun)

The part frame is the stage frame: the rig's world frame with the stage at 0, so view k's
cloud X (world frame) is X_part = inv(world_from_stage(q_k)) X. A folder without
multiview.json is incomplete: `MultiViewSession.open` refuses it naming the views kept and
what stopped the run; `MultiViewSession.open(path, partial=True)` gives the complete views.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scanner import __version__
from scanner.errors import IncompleteSession, ScannerError, SessionError
from scanner.rig import Rig
from scanner.session import ERROR, MANIFEST, Session, StageRecord, ViewPlace, stop_reason, write_json
from scanner.session_lock import session_lock
from scanner.stage import AxisKind
from scanner.stage_model import StageConfig, StageModel, load_stage_model

MULTIVIEW_VERSION = 1
PLAN = "views.json"
MULTIVIEW = "multiview.json"
OUTPUTS_DIR = "outputs"
MOVE_MARGIN_S = 5.0  # a move's wait outlasts its own deadline by this (the status fails itself first)

ViewProgress = Callable[[int, int, str], None]  # (view, views, what is happening)


def _quiet(view: int, views: int, what: str) -> None:
    pass


def view_name(k: int) -> str:
    return f"view_{k:03d}"


def is_multiview(path: str | Path) -> bool:
    """Whether `path` is a multi-view folder (complete or not)."""
    return (Path(path) / PLAN).is_file()


def plan_views(stage: StageConfig, views: int | None = None, angles_deg: Sequence[float] | None = None,
               axis: str | None = None) -> list[dict[str, float]]:
    """Target stage positions, one per view: `views` equal steps over a turn, or the
    `angles_deg` given, of the rotary axis `axis` (default: the stage's first rotary one)."""
    if (views is None) == (angles_deg is None):
        raise ScannerError("give either a number of views or a list of angles, one of them")
    rotary = [a for a in stage.axes if a.kind is AxisKind.ROTARY]
    if axis is None:
        if not rotary:
            raise ScannerError(f"{stage.path}: the stage has no rotary axis to turn the part between views")
        turn = rotary[0]
    else:
        matches = [a for a in rotary if a.name == axis]
        if not matches:
            raise ScannerError(f"{stage.path}: no rotary stage axis named {axis!r}; rotary axes: "
                               f"{[a.name for a in rotary]}")
        turn = matches[0]
    if views is not None:
        if not 1 <= views <= 360:
            raise ScannerError(f"--views must be 1..360, got {views}")
        angles = [360.0 * k / views for k in range(views)]
    else:
        angles = [float(a) for a in angles_deg or []]
        if not angles or not all(math.isfinite(a) for a in angles):
            raise ScannerError(f"angles must be finite numbers in degrees, got {angles_deg}")
    lo, hi = turn.limits
    outside = [a for a in angles if not lo <= math.radians(a) <= hi]
    if outside:
        raise ScannerError(f"{stage.path}: view angles {outside} deg lie outside {turn.name}'s travel "
                           f"{math.degrees(lo):.6g} .. {math.degrees(hi):.6g} deg")
    return [{turn.name: math.radians(a)} for a in angles]


@dataclass(frozen=True, eq=False)
class View:
    """One complete view: its session, the stage position reported after the move (rad,
    mm) and the pose of the stage frame in the world the stage model gives for it."""

    index: int
    session: Session
    position: dict[str, float]
    world_from_stage: np.ndarray

    @property
    def name(self) -> str:
        return view_name(self.index)


@dataclass(frozen=True, eq=False)
class MultiViewSession:
    """A multi-view folder read back (see the module docstring). `complete` is False only
    for a folder opened with `partial=True` that has no multiview.json."""

    root: Path
    plan: dict[str, Any]
    views: tuple[View, ...]
    complete: bool

    @property
    def id(self) -> str:
        return self.plan["multiview_id"]

    @property
    def stage_model(self) -> StageModel:
        return StageModel.from_dict(self.plan["stage_model"], self.root / PLAN)

    def stage_axis_file(self, file: str | Path, key: str = "--stage-axis") -> StageModel:
        """The stage model of a stage-axis calibration file (`slscan calibrate --stage-axis`),
        checked against the axes these views were captured with; errors name `key`."""
        return load_stage_model(Path(file), self.stage_model, self.root / PLAN, key)

    @property
    def outputs(self) -> Path:
        return self.root / OUTPUTS_DIR

    @property
    def recording_path(self) -> Path:
        return self.root / "recording.rrd"

    @classmethod
    def open(cls, path: str | Path, partial: bool = False) -> MultiViewSession:
        """A multi-view folder; an incomplete one raises IncompleteSession (saying which
        views were kept and why the run stopped) unless `partial`, which gives its
        complete views."""
        root = Path(path)
        plan = _read_json(root / PLAN, "multi-view plan")
        if plan.get("slscan_multiview") != MULTIVIEW_VERSION:
            raise SessionError(f"{root / PLAN}: multi-view version {plan.get('slscan_multiview')!r}, this slscan "
                               f"reads {MULTIVIEW_VERSION}")
        done = (root / MULTIVIEW).is_file()
        if not done and not partial:
            raise IncompleteSession(describe_incomplete(root))
        views = []
        for k in range(len(plan["views"])):
            folder = root / view_name(k)
            if not (folder / MANIFEST).is_file():
                if done:
                    raise SessionError(f"{folder}: view {k} of a complete multi-view session has no {MANIFEST}")
                break  # views are captured in order: the first incomplete one ends the run
            session = Session.open(folder)
            stage = session.manifest.stage  # validated with the manifest (`StageRecord`)
            if stage is None:
                raise SessionError(f"{folder / MANIFEST}: no stage pose recorded: not a view of a multi-view session")
            views.append(View(k, session, dict(stage.position), np.array(stage.world_from_stage)))
        return cls(root, plan, tuple(views), done)


def describe_incomplete(root: Path) -> str:
    """Why a multi-view folder is incomplete, for people: the views kept and the error."""
    plan = _read_json(root / PLAN, "multi-view plan")
    n = len(plan.get("views", []))
    kept = [view_name(k) for k in range(n) if (root / view_name(k) / MANIFEST).is_file()]
    msg = f"{root}: incomplete multi-view session (no {MULTIVIEW}); {len(kept)} of {n} views complete"
    msg += f" ({', '.join(kept)})" if kept else ""
    return (msg + stop_reason(root, "run", at_view=True)
            + ". The complete views are kept: `slscan inspect`/`slscan register` can use them (--partial).")


def _read_json(path: Path, what: str) -> dict[str, Any]:
    if not path.is_file():
        raise SessionError(f"{path.parent}: not a multi-view session folder (no {path.name})")
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SessionError(f"{path}: unreadable {what}: {exc}") from None
    if not isinstance(d, dict):
        raise SessionError(f"{path}: unreadable {what}: not a JSON object")
    return d


class MultiViewWriter:
    """Writes one multi-view capture: the plan first, then view folders, then multiview.json."""

    def __init__(self, root: Path, rig: Rig, plan: Sequence[Mapping[str, float]],
                 model: StageModel | None = None) -> None:
        stage = rig.config.stage
        if stage is None or rig.stage is None:
            raise ScannerError(f"{rig.config.path}: the rig has no [stage]: multi-view scanning needs one to turn "
                               f"the part")
        self.root = root
        self.id = f"{dt.datetime.now().strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:6]}"
        self.model = model or stage.model
        self.started = dt.datetime.now(dt.UTC)
        self.views: list[dict[str, Any]] = []
        write_json(root / PLAN, {
            "slscan_multiview": MULTIVIEW_VERSION, "multiview_id": self.id, "software_version": __version__,
            "created": self.started.isoformat(), "rig_config_path": str(rig.config.path.resolve()),
            "rig_config": rig.config.raw,
            "stage_model": self.model.to_dict(), "views": [{"target": dict(q)} for q in plan]})

    @classmethod
    def create(cls, out_dir: str | Path, rig: Rig, plan: Sequence[Mapping[str, float]],
               model: StageModel | None = None) -> MultiViewWriter:
        root = Path(out_dir)
        if root.exists() and any(root.iterdir()):
            raise SessionError(f"{root}: output folder exists and is not empty; choose a new --out folder so no "
                               f"earlier session is overwritten")
        root.mkdir(parents=True, exist_ok=True)
        return cls(root, rig, plan, model)

    def stage_record(self, position: Mapping[str, float]) -> StageRecord:
        """What a view's manifest records of the stage: position and the model's pose."""
        return StageRecord(position=dict(position), world_from_stage=self.model.world_from_stage(position).tolist(),
                           stage_model=self.model.to_dict())

    def view_done(self, k: int, session: Session, position: Mapping[str, float], timings: dict[str, float]) -> None:
        self.views.append({"view": k, "folder": view_name(k), "session_id": session.id, "position": dict(position),
                           "world_from_stage": self.model.world_from_stage(position), "timings_s": timings})

    def finish(self) -> Path:
        write_json(self.root / MULTIVIEW, {
            "slscan_multiview": MULTIVIEW_VERSION, "multiview_id": self.id, "created": self.started.isoformat(),
            "completed": dt.datetime.now(dt.UTC).isoformat(), "views": self.views})
        return self.root / MULTIVIEW

    def fail(self, error: BaseException, view: int, stage: str) -> None:
        write_json(self.root / ERROR, {
            "multiview_id": self.id, "view": view, "stage": stage, "error": type(error).__name__,
            "message": str(error), "views_kept": [v["folder"] for v in self.views],
            "time": dt.datetime.now(dt.UTC).isoformat()})


def capture_views(rig: Rig, plan: Sequence[Mapping[str, float]], out_dir: str | Path,
                  scan_view: Callable[[Path, ViewPlace], Session],
                  progress: ViewProgress = _quiet, model: StageModel | None = None) -> MultiViewSession:
    """Move the stage to each planned position and scan a view there; return the complete
    multi-view session. `scan_view(folder, place)` captures (and processes) one view into
    the new session folder `folder`, its `ViewPlace` in its manifest (`scanner.pipeline.scan`).
    `model`: the stage geometry the views' poses are recorded with (default the rig's:
    its [stage] calibration file's, else the nominal axes).

    On any failure (a move, a capture, Ctrl-C) every earlier view stays complete on disk,
    error.json names the view and the error, and the error is raised again."""
    writer = MultiViewWriter.create(out_dir, rig, plan, model)
    with session_lock(writer.root, command="slscan scan --views"):
        return _capture_views(writer, rig, plan, scan_view, progress)


def _capture_views(writer: MultiViewWriter, rig: Rig, plan: Sequence[Mapping[str, float]],
                   scan_view: Callable[[Path, ViewPlace], Session], progress: ViewProgress) -> MultiViewSession:
    stage = rig.stage
    assert stage is not None
    n = len(plan)
    for k, target in enumerate(plan):
        what = "move"
        try:
            progress(k, n, "move")
            t0 = time.perf_counter()
            status = stage.move_to(target)
            status.wait(stage.action_deadline_s + MOVE_MARGIN_S)
            position = stage.position()
            moved = time.perf_counter() - t0
            what = "capture"
            progress(k, n, "capture")
            t0 = time.perf_counter()
            session = scan_view(writer.root / view_name(k), ViewPlace(k, writer.id, writer.stage_record(position)))
            writer.view_done(k, session, position,
                             {"move": round(moved, 4), "scan": round(time.perf_counter() - t0, 4)})
        except BaseException as exc:
            writer.fail(exc, k, what)
            raise
    writer.finish()
    return MultiViewSession.open(writer.root)
