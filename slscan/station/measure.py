"""The measuring step: a typed seam between the station and whatever measures a scan, and
the measurements a station config can name (`MEASUREMENTS`).

A `Measurement` takes the sessions of one part (one per view, each complete and
processed: `outputs/cloud.ply` in mm, camera frame; `measure`) or its multi-view session
(the views a stage turned it through, aligned and fused: `measure_whole`) and the part
program, and returns one
`MeasuredValue` per characteristic: its value with its expanded uncertainty U (k = 2), or,
for a figure too small to tell from zero, no value and its detection limit. It does not
judge the part: the station decides each value against the program's tolerance
(`Characteristic.decide`, ISO 14253-1), so a verdict never depends on who measured. A
characteristic that cannot be measured on a scan gets no value and a reason; a part whose
scan cannot be registered to the CAD model gets a failed `MeasurementResult`. Neither is
ever a number.

- `inspection` (`InspectionMeasurement`): per view, the session's cloud registered to the
  CAD model, segmented by face and evaluated by the `inspection` package with the
  program's tolerances, the session's measurement model (`slscan.measurement_model`: the
  decoder's noise and the calibration's covariance in U) and the program's decision rule;
  each characteristic's value, U and detection limit are its figure's estimate
  (`inspection.figures.asked_by`: the profile's is the zone width 2 max|d| of the form
  surface's signed deviations, the noise filtered out like the form figures'; the raw
  points' extremes carry 4-5 sigma of noise) on the report's typed face row
  (`inspection.report.FaceRow`). The report is kept (`outputs/inspection.json`: the
  per-face table `{"faces": [{"label": "#12", "type": ..., "points": n, <value columns>,
  "tolerance_<key>": t, "verdict_<figure>": v}, ...], "fitness": f, "rmse_mm": r, ...}`),
  plus `"program"`: the part program and the decision of each of its characteristics on
  this view (`view_decisions`); the inspection's recording (`outputs/inspection.rrd`: registered
  cloud, CAD, deviations, deviation map, report) unless the session's rig records nothing.
  A multi-view session's merged cloud is inspected once, its report and recording in the
  multi-view folder's outputs/. The program's `edge_margin_mm` is the form figures' edge margin.
- `simulator-truth` (`SimulatorTruth`): the simulated part's imposed defects
  (`sim_part.json`, written into each session by the simulated bench) reported as if
  measured. It measures nothing: it exercises a station's loop, storage, views and verdict
  logic without the cost of inspection (tests, demonstrations).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from inspection.figures import asked_by
from inspection.tolerances import DECISION_RULES, DECISION_STATUS
from scanner.errors import ConfigError
from scanner.session import Session, write_json
from slscan.station import MEASUREMENT_NAMES
from slscan.station.program import Characteristic, PartProgram, program_tolerances

if TYPE_CHECKING:
    from inspection.cad import CadModel
    from inspection.measured_cloud import ScanCloud
    from inspection.report import FaceRow, InspectionReport
    from inspection.uncertainty import ScanUncertainty
    from scanner.multiview import MultiViewSession

REPORT_FILE = "inspection.json"  # written into the session's outputs/ by the adapter
RECORDING_FILE = "inspection.rrd"  # the inspection's Rerun recording, beside it (`slscan review PART` shows it)


@dataclass(frozen=True)
class MeasuredValue:
    """One characteristic on one part: `value_mm` None when it could not be measured
    (`note` says why) or is below its detection limit `limit_mm`; `u_mm` the value's
    expanded uncertainty (k = 2; None: not known); `points` the scan points the value rests
    on; `view` the session index it came from."""

    characteristic: str
    value_mm: float | None
    points: int = 0
    view: int = 0
    note: str = ""
    u_mm: float | None = None
    limit_mm: float | None = None


@dataclass(frozen=True)
class MeasurementResult:
    """What measuring one part gave. `ok` False: the part could not be measured at all
    (`message` says why, `values` is empty). `details` holds figures worth keeping
    (registration fitness and RMSE per view, ...); `report_paths` the per-view reports."""

    ok: bool
    values: tuple[MeasuredValue, ...] = ()
    message: str = ""
    details: Mapping[str, Any] = field(default_factory=dict)
    report_paths: tuple[Path, ...] = ()

    def value(self, name: str) -> MeasuredValue | None:
        for v in self.values:
            if v.characteristic == name:
                return v
        return None

    def as_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "message": self.message, "details": dict(self.details),
                "values": [asdict(v) for v in self.values], "report_paths": [str(p) for p in self.report_paths]}


@dataclass(frozen=True)
class ViewReport:
    """What the station keeps of one inspection (a view's, or a multi-view session's merged
    cloud's): the registration's `fitness` and `rmse_mm`, the report's `verdict`, and the
    pose's status ("ok", "free" or "ambiguous": nothing measured) and why (`status_note`)."""

    fitness: float
    rmse_mm: float
    verdict: str
    pose_status: str = "ok"
    status_note: str = ""

    @classmethod
    def of(cls, report: InspectionReport) -> ViewReport:
        return cls(report.fitness, report.rmse_mm, report.verdict, report.status, report.status_note)

    def details(self) -> dict[str, Any]:
        """The view's entry in `MeasurementResult.details`: its figures under the keys of the
        inspection report's JSON (`status`: the verdict's, as its exit code says it)."""
        note = {"status_note": self.status_note} if self.status_note else {}
        return {"fitness": self.fitness, "rmse_mm": self.rmse_mm, "verdict": self.verdict,
                "status": DECISION_STATUS[self.verdict], **note}


FaceTable = Mapping[str, "FaceRow"]  # one inspection's face rows by label ("#657")


class Measurement(Protocol):
    """The seam: anything that measures a part's scans for a part program."""

    name: str

    def unavailable(self) -> str | None:
        """None when it can measure; otherwise why not (shown to the operator)."""
        ...

    def measure(self, sessions: Sequence[Session], program: PartProgram) -> MeasurementResult:
        """Measure every characteristic of `program` on one part's processed sessions."""
        ...

    def measure_whole(self, session: MultiViewSession, program: PartProgram) -> MeasurementResult:
        """Measure every characteristic of `program` on one part's multi-view session, its
        views aligned and fused (`inspection.views.whole.whole_part` has run)."""
        ...


def cad_faces(program: PartProgram) -> dict[str, str]:
    """The part program's CAD model's faces as label -> surface type."""
    from inspection.cad import load_cad  # inspection is imported when first used (start-up time)

    model = load_cad(program.cad_path, mesh_unit=program.mesh_unit)
    return {f.label: f.type for f in model.faces}


class InspectionMeasurement:
    """The adapter onto `inspection`: per view, the session's cloud is registered to the
    CAD model, segmented by face and evaluated (`inspection.inspect_scan.inspect`); the report is
    kept in the session's outputs; each characteristic takes its value from the view
    with the most points on its face."""

    name = "inspection"

    def __init__(self) -> None:
        self._models: dict[tuple[Path, str], CadModel] = {}  # (CAD path, unit) -> model, loaded once
        # (CAD path, unit, view; None: the merged cloud) -> the last part's registration: the next part in
        # the same fixture starts from it (inspection.registration.warm_start; checked, with the global
        # search as fallback)
        self._priors: dict[tuple[Path, str, int | None], Any] = {}

    def unavailable(self) -> str | None:
        return None

    def _model(self, program: PartProgram) -> CadModel:
        from inspection.cad import load_cad

        key = (program.cad_path, program.mesh_unit)
        if key not in self._models:
            self._models[key] = load_cad(program.cad_path, mesh_unit=program.mesh_unit)
        return self._models[key]

    def measure(self, sessions: Sequence[Session], program: PartProgram) -> MeasurementResult:
        from inspection.errors import InspectionError
        from inspection.measured_cloud import load_session
        from slscan.measurement_model import session_uncertainty

        tables: list[FaceTable] = []
        views: list[ViewReport] = []
        details: dict[str, Any] = {}
        paths: list[Path] = []
        for k, session in enumerate(sessions):
            try:
                scan = load_session(session.root)
                table, view, path = self._inspect(scan, program, session, outputs=session.outputs,
                                                  recording_id=session.id, view=k,
                                                  uncertainty=session_uncertainty(session)(scan.camera_pixels()))
            except InspectionError as exc:
                return MeasurementResult(False, message=f"session {session.root}: {exc}", details=details)
            paths.append(path)
            details[f"view{k}"] = view.details()
            tables.append(table)
            views.append(view)
        return view_values(program, tables, views, details, paths)

    def measure_whole(self, session: MultiViewSession, program: PartProgram) -> MeasurementResult:
        """The merged cloud of the views (`inspection.views.whole.load_merged`, part frame)
        inspected once: every face any view sees. Its report and recording go into the
        multi-view folder's outputs/; the noise is estimated from the data (the merged
        cloud has no one camera's pixels, as in `slscan inspect MULTIVIEW`)."""
        from inspection.errors import InspectionError
        from inspection.views.whole import load_merged

        try:
            table, whole, path = self._inspect(load_merged(session), program, session.views[0].session,
                                               outputs=session.outputs, recording_id=session.id, view=None,
                                               uncertainty=None)
        except InspectionError as exc:
            return MeasurementResult(False, message=f"multi-view session {session.root}: {exc}")
        return view_values(program, [table], [whole], {"whole": whole.details()}, [path])

    def _inspect(self, scan: ScanCloud, program: PartProgram, session: Session, *, outputs: Path, recording_id: str,
                 view: int | None, uncertainty: ScanUncertainty | None) -> tuple[FaceTable, ViewReport, Path]:
        """Inspect `scan` (one view's, or the merged cloud: `view` None) for `program`, starting
        from the registration of the last part seen the same way; write its report (and its
        recording, at the level of `session`, whose rig frames the scan) into `outputs`.
        Returns the face rows by label, what the station keeps of the report and the report's
        path. Raises InspectionError."""
        from inspection.inspect_scan import InspectionSettings, inspect
        from scanner.pipeline import recording_level
        from scanner.session_recording import SessionRecording

        prior_key = (program.cad_path, program.mesh_unit, view)
        level = recording_level(session)  # the session's own: none, display or full
        settings = InspectionSettings(form=program.form_settings())
        with (nullcontext() if level == "none" else
              SessionRecording(outputs / RECORDING_FILE, recording_id, send_blueprint=False, level=level)) as recording:
            if recording is not None:
                recording.log_rig(session.rig_model())
            report = inspect(scan, self._model(program), program_tolerances(program), settings=settings,
                             recording=recording,
                             prior=self._priors.get(prior_key), uncertainty=uncertainty)
        self._priors[prior_key] = report.registration
        table = {row.label: row for row in report.faces}
        outputs.mkdir(parents=True, exist_ok=True)
        path = outputs / REPORT_FILE
        write_json(path, {**report.as_dict(), "program": view_decisions(program, table, view)})  # the file's format
        return table, ViewReport.of(report), path


def view_decisions(program: PartProgram, table: FaceTable, view: int | None) -> dict[str, Any]:
    """The part program and the ISO 14253-1 decision of each of its characteristics on one
    view's per-face table (`view` None: a multi-view session's merged cloud's), what its
    `inspection.json` says under "program": name,
    face and its name, kind, method, tolerance, value, U, detection limit, decision, and
    the points it rests on (a face the view did not see: not measured, with the reason)."""
    rows = []
    for c in program.characteristics:
        m = _pick(c, [table])
        rows.append({"name": c.name, "face": c.face, "face_name": program.face_names.get(c.face, ""),
                     "kind": c.kind, "method": c.method, "tolerance_mm": c.tolerance_mm, "value_mm": m.value_mm,
                     "u_mm": m.u_mm, "limit_mm": m.limit_mm,
                     "decision": c.decide(m.value_mm, m.u_mm, m.limit_mm, program.decision_rule),
                     "points": m.points, "note": m.note})
    return {"name": program.name, "version": program.version, "fingerprint": program.fingerprint,
            "path": str(program.path), "view": view, "decision_rule": program.decision_rule,
            "rule": DECISION_RULES[program.decision_rule], "characteristics": rows}


def view_values(program: PartProgram, tables: Sequence[FaceTable], reports: Sequence[ViewReport],
                details: Mapping[str, Any], paths: Sequence[Path]) -> MeasurementResult:
    """The part's values from its views' face rows (`_pick`); `reports` each view's
    registration status and note. A view whose pose is not proven ("ambiguous") measured
    nothing: its faces are left out, and when no view's pose is proven the part is not
    measured at all, the message naming the ambiguity."""
    unproven = [f"view {k}: {r.status_note or r.pose_status}" for k, r in enumerate(reports)
                if r.pose_status == "ambiguous"]
    if len(unproven) == len(reports):
        return MeasurementResult(False, message="; ".join(n.replace("not measured: ", "") for n in unproven),
                                 details=details, report_paths=tuple(paths))
    proven = [t for t, r in zip(tables, reports) if r.pose_status != "ambiguous"]
    values = tuple(_pick(c, proven, unproven="; ".join(unproven)) for c in program.characteristics)
    return MeasurementResult(True, values, details=details, report_paths=tuple(paths))


def _pick(c: Characteristic, tables: Sequence[FaceTable], *, unproven: str = "") -> MeasuredValue:
    """A characteristic's value, its U and detection limit (its figure's `Estimate`) from the
    view whose report has the most points on its face; `unproven` the views left out (their
    pose not proven), named when no other view sees the face."""
    rows = [(k, t[c.face].form) for k, t in enumerate(tables) if c.face in t and int(t[c.face].form.points) > 0]
    if not rows:
        return MeasuredValue(c.name, None, note=f"face {c.face} not seen in any view"
                             + (f" with a proven pose ({unproven})" if unproven else ""))
    k, form = max(rows, key=lambda kf: int(kf[1].points))
    points = int(form.points)
    figure = asked_by(c.kind, c.method)
    e = form.figure(figure.name)
    value, limit = (None, None) if e is None else (e.value, e.limit)
    u = None if e is None or not np.isfinite(float(e.U)) else float(e.U)
    if value is None and limit is not None:  # below its detection limit (inspection.uncertainty): no value
        return MeasuredValue(c.name, None, points, k, limit_mm=float(limit),
                             note=f"below the detection limit {float(limit) * 1e3:.1f} um")
    if value is None or not np.isfinite(float(value)):
        reason = form.note or form.status or f"no {figure.value_column} in the report"
        return MeasuredValue(c.name, None, points, k, note=f"face {c.face}: {reason}")
    return MeasuredValue(c.name, float(value), points, k, u_mm=u,
                         limit_mm=None if limit is None else float(limit))


class SimulatorTruth:
    """The simulated part's imposed defects, reported as if measured (see the module
    docstring): only for sessions of a simulated bench."""

    name = "simulator-truth"

    def unavailable(self) -> str | None:
        return None

    def measure(self, sessions: Sequence[Session], program: PartProgram) -> MeasurementResult:
        from sim.station_parts import TRUTH_FILE  # the simulator is imported when used (command-line start)

        path = sessions[0].root / TRUTH_FILE
        if not path.exists():
            return MeasurementResult(False, message=f"{path}: no simulator truth (not a simulated bench's session)")
        truth = json.loads(path.read_text())["imposed_mm"]
        points = json.loads((sessions[0].outputs / "result.json").read_text())["points"]
        return MeasurementResult(True, tuple(MeasuredValue(c.name, truth[c.name], points)
                                             for c in program.characteristics))

    def measure_whole(self, session: MultiViewSession, program: PartProgram) -> MeasurementResult:
        return self.measure([v.session for v in session.views], program)


# the measurements a station config or `--measurement` can name (`MEASUREMENT_NAMES`, in this order)
MEASUREMENTS: dict[str, type[InspectionMeasurement] | type[SimulatorTruth]] = dict(zip(
    MEASUREMENT_NAMES, (InspectionMeasurement, SimulatorTruth), strict=True))
DEFAULT_MEASUREMENT = "inspection"


def load_measurement(name: str, where: object = "--measurement") -> Measurement:
    """The measurement called `name` (one of `MEASUREMENTS`)."""
    if name not in MEASUREMENTS:
        raise ConfigError(where, "measurement", f"unknown measurement '{name}'; known: {sorted(MEASUREMENTS)}")
    return MEASUREMENTS[name]()
