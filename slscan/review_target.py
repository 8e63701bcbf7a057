"""What `slscan review` opens: the Rerun recordings of anything slscan writes, found by
what the folder holds, and a blueprint that puts that kind's important views first.

    scan session        manifest.json: recording.rrd and outputs/*.rrd (inspection, poses)
    multi-view folder   multiview.json or views.json: its recording.rrd and outputs/*.rrd, else
                        each view's recording
    station part        part.json: every session of the part (view*/), as scan sessions; or
                        its multi-view session (multiview/), as a multi-view folder
    calibration folder  calibration.json, capture/ or rejected.txt: recording.rrd
    anything else       a .rrd file, or a folder with .rrd files in it (verify output, a station
                        report folder's control_charts.rrd, ...)

A folder with none of these is refused in one line; a session folder without a manifest
is reported as the incomplete session it is (`scanner.session.Session.open`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import rerun.blueprint as rrb

from scanner.session_recording import (
    CAMERA,
    EVENTS,
    FRAME_SPEC,
    METRICS,
    RECORDING_NAME,
    WORLD,
    RecordingError,
)
from slscan.station.loop import PART_RECORD

MULTIVIEW_FILES = ("multiview.json", "views.json")
CALIBRATION_MARKS = ("calibration.json", "capture", "rejected.txt")
INSPECTION_FILE = "inspection.json"


@dataclass(frozen=True)
class ReviewTarget:
    """`kind` of what was asked for, the recordings to open together, and the blueprint
    for them (None: the recordings' own)."""

    kind: str
    recordings: tuple[Path, ...]
    blueprint: rrb.Blueprint | None

    def describe(self) -> str:
        return f"{self.kind}: " + ", ".join(str(p) for p in self.recordings)


def find_target(path: str | Path) -> ReviewTarget:
    """What to open for `path` (see the module docstring); RecordingError in one line when
    slscan wrote nothing there to review."""
    path = Path(path)
    if path.is_file():
        if path.suffix != ".rrd":
            raise RecordingError(f"{path}: not a Rerun recording (.rrd); give a folder slscan wrote or a .rrd file")
        return ReviewTarget("recording", (path,), _blueprint_for_files((path,)))
    if not path.is_dir():
        raise RecordingError(f"{path}: no such file or folder")
    if any((path / f).is_file() for f in MULTIVIEW_FILES):
        own = _recordings(path) + _outputs(path)
        views = tuple(sorted(path.glob(f"view_*/{RECORDING_NAME}")))
        return _target("multi-view folder", own or views, path, None)
    if (path / PART_RECORD).is_file():
        whole = sorted(p for p in path.iterdir() if any((p / f).is_file() for f in MULTIVIEW_FILES))
        if whole:  # a part measured whole on a stage: its multi-view session
            return find_target(whole[0])
        sessions = sorted(p for p in path.iterdir() if (p / "manifest.json").is_file())  # view0, view1, ...
        files = tuple(f for s in sessions for f in _recordings(s) + _outputs(s))
        return _target("station part", files, path, _scan_blueprint(any(_inspected(s) for s in sessions)))
    if (path / "manifest.json").is_file() or (path / "frames").is_dir():
        from scanner.session import Session

        session = Session.open(path)  # an incomplete session: its own message
        files = _recordings(session.root) + _outputs(session.root)
        if not files:
            raise RecordingError(f"{path}: no recording; run `slscan decode {path}` to make one")
        blueprint = _scan_blueprint(_inspected(session.root)) or _blueprint_for_files(files)  # a bin: its poses
        return _target("scan session", files, path, blueprint)
    if any((path / m).exists() for m in CALIBRATION_MARKS):
        return _target("calibration folder", _recordings(path), path, calibration_blueprint())
    files = tuple(sorted(path.glob("*.rrd"))) or tuple(sorted(path.glob("*/*.rrd")))
    if files:
        return ReviewTarget("recordings", files, _blueprint_for_files(files))
    raise RecordingError(f"{path}: nothing slscan wrote to review here (no session manifest, part.json, "
                         f"calibration.json, views.json or .rrd recording)")


def _recordings(folder: Path) -> tuple[Path, ...]:
    return tuple(p for p in (folder / RECORDING_NAME,) if p.is_file())


def _outputs(folder: Path) -> tuple[Path, ...]:
    return tuple(sorted((folder / "outputs").glob("*.rrd")))


def _inspected(folder: Path) -> bool:
    return (folder / "outputs" / INSPECTION_FILE).is_file()


def _target(kind: str, files: tuple[Path, ...], path: Path, blueprint: rrb.Blueprint | None) -> ReviewTarget:
    if not files:
        part = next(iter(path.glob("**/*.rrd.part")), None)
        hint = f"; {part} exists but was never closed (interrupted)" if part else ""
        raise RecordingError(f"{path}: a {kind} without a recording to review{hint}")
    return ReviewTarget(kind, files, blueprint)


def _blueprint_for_files(files: tuple[Path, ...]) -> rrb.Blueprint | None:
    """A poses or control-chart recording gets its views; others keep their own."""
    names = {f.name for f in files}
    if "poses.rrd" in names:
        return poses_blueprint()
    if "control_charts.rrd" in names:
        return rrb.Blueprint(rrb.TimeSeriesView(origin="control", name="control charts"), collapse_panels=False)
    return None


def _log_views() -> tuple[rrb.TimeSeriesView, rrb.TextLogView]:
    return (rrb.TimeSeriesView(origin=METRICS, name="metrics"),
            rrb.TextLogView(origin="/", contents=[f"{FRAME_SPEC}/**", f"{EVENTS}/**"], name="log"))


def _scan_blueprint(inspected: bool) -> rrb.Blueprint | None:
    """An inspected scan: the 3D view of the CAD model and the deviations beside the
    deviation map, the inspection report across the full width below (its table is ~145
    characters wide); the time and selection panels collapsed, the list of recordings (a
    station part's views) kept. The 3D view holds only the inspection's entities: with the
    rig's frusta in it the part was a small patch in a corner, and the raw cloud and the
    face-coloured points, drawn at the same places, hid the deviation colours (all still in
    the streams); the deviations' colour legend stands beside the part. A scan alone keeps
    the recording's own blueprint."""
    if not inspected:
        return None
    from inspection.inspection_recording import CAD, DEVIATION, DEVIATION_LEGEND, DEVIATION_MAP, REPORT

    three_d = rrb.Spatial3DView(origin=WORLD, contents=[f"+ {CAD}", f"+ {DEVIATION}", f"+ {DEVIATION_LEGEND}"],
                                name="3D: CAD, deviations")
    top = rrb.Horizontal(three_d, rrb.Tabs(rrb.Spatial2DView(origin=DEVIATION_MAP, name="deviation map"),
                                           rrb.Spatial2DView(origin=CAMERA, name="camera")), column_shares=[1, 1])
    bottom = rrb.Tabs(rrb.TextDocumentView(origin=REPORT, name="inspection report"), *_log_views())
    return rrb.Blueprint(rrb.Vertical(top, bottom, row_shares=[3, 2]), rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed"))


def calibration_blueprint() -> rrb.Blueprint:
    """Coverage of the camera and projector images first, the views with their residuals,
    the board poses in 3D, the errors and the log."""
    from calibration.calibration_recording import ROOT

    coverage = rrb.Horizontal(rrb.Spatial2DView(origin=f"{ROOT}/camera/coverage", name="camera coverage"),
                              rrb.Spatial2DView(origin=f"{ROOT}/projector/coverage", name="projector coverage"))
    views = rrb.Horizontal(rrb.Spatial2DView(origin=f"{ROOT}/camera/image", name="view (corners, residuals)"),
                           rrb.Spatial3DView(origin=WORLD, name="3D: board poses, artefact"))
    charts = rrb.Tabs(rrb.TimeSeriesView(origin=f"{ROOT}/errors", name="RMS per view"),
                      rrb.TimeSeriesView(origin=f"{ROOT}/gamma", name="gamma"),
                      rrb.TimeSeriesView(origin=METRICS, name="metrics"),
                      rrb.TextLogView(origin="/", contents=[f"{EVENTS}/**"], name="log"))
    return rrb.Blueprint(rrb.Vertical(coverage, views, charts, row_shares=[2, 2, 1]), collapse_panels=False)


def poses_blueprint() -> rrb.Blueprint:
    """The parts in 3D (the instances' points, the posed models, the pick order) above the
    poses table across the full width (~110 characters a row). Not the rig's frusta nor the
    scan's cloud (still in the streams): with them the viewer framed the rig or the dark
    background plane and the pile of parts was a small patch in the middle."""
    from inspection.bins.picking import INSTANCES, MODELS, PICK_ORDER, TABLE

    three_d = rrb.Spatial3DView(origin=WORLD, contents=[f"+ {INSTANCES}", f"+ {MODELS}/**", f"+ {PICK_ORDER}"],
                                name="3D: instances, poses, pick order")
    return rrb.Blueprint(rrb.Vertical(three_d, rrb.TextDocumentView(origin=TABLE, name="poses"), row_shares=[3, 2]),
                         rrb.SelectionPanel(state="collapsed"), rrb.TimePanel(state="collapsed"))
