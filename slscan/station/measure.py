"""The measuring step: a typed seam between the station and whatever measures a scan, and
the measurements a station config can name (`MEASUREMENTS`).

A `Measurement` takes the sessions of one part (one per view, each complete and
processed: `outputs/cloud.ply` in mm, camera frame) and the part program, and returns one
`MeasuredValue` per characteristic. It does not judge: the station compares values with
the program's tolerances (`Characteristic.conforms`), so a verdict never depends on who
measured. A characteristic that cannot be measured on a scan gets no value and a reason;
a part whose scan cannot be registered to the CAD model gets a failed `MeasurementResult`.
Neither is ever a number.

- `inspection` (`InspectionMeasurement`): per view, the session's cloud registered to the
  CAD model, segmented by face and evaluated by the `inspection` package; its report is
  the per-face table, `{"faces": [{"label": "#12", "type": ..., "points": n, <value
  columns>}, ...], "fitness": f, "rmse_mm": r}` with the value columns of `REPORT_COLUMNS`.
- `simulator-truth` (`SimulatorTruth`): the simulated part's imposed defects
  (`sim_part.json`, written into each session by the simulated bench) reported as if
  measured. It measures nothing: it exercises a station's loop, storage, views and verdict
  logic without the cost of inspection (tests, demonstrations).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Protocol, Sequence

import numpy as np

from scanner.errors import ConfigError
from scanner.session import Session, write_json

if TYPE_CHECKING:
    from inspection.cad import CadModel
from slscan.station.program import Characteristic, PartProgram

REPORT_FILE = "inspection.json"  # written into the session's outputs/ by the adapter

# (kind, method) -> the report's per-face column that gives the value, in mm. The profile
# value is the report's zone width 2 max|d| of the signed deviations of the form surface
# (noise filtered out like the form figures; the raw points' extremes carry 4-5 sigma of noise).
REPORT_COLUMNS: dict[tuple[str, str | None], str] = {
    ("flatness", "minimum_zone"): "flatness_mz_mm",
    ("flatness", "least_squares"): "flatness_ls_mm",
    ("cylindricity", "minimum_zone"): "cylindricity_mz_mm",
    ("cylindricity", "least_squares"): "cylindricity_ls_mm",
    ("sq", None): "sq_mm",
    ("profile", None): "profile_mm",
}


@dataclass(frozen=True)
class MeasuredValue:
    """One characteristic on one part: `value_mm` None when it could not be measured
    (`note` says why); `points` the scan points the value rests on; `view` the session
    index it came from."""

    characteristic: str
    value_mm: float | None
    points: int = 0
    view: int = 0
    note: str = ""


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


class Measurement(Protocol):
    """The seam: anything that measures a part's scans for a part program."""

    name: str

    def unavailable(self) -> str | None:
        """None when it can measure; otherwise why not (shown to the operator)."""
        ...

    def measure(self, sessions: Sequence[Session], program: PartProgram) -> MeasurementResult:
        """Measure every characteristic of `program` on one part's processed sessions."""
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
        # (CAD path, unit, view) -> the last part's registration: the next part in the same fixture starts
        # from it (inspection.registration.warm_start; checked, with the global search as fallback)
        self._priors: dict[tuple[Path, str, int], Any] = {}

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
        from inspection.inspect_scan import inspect
        from inspection.measured_cloud import load_session

        model = self._model(program)
        tables: list[dict[str, dict[str, Any]]] = []
        details: dict[str, Any] = {}
        paths: list[Path] = []
        for k, session in enumerate(sessions):
            prior_key = (program.cad_path, program.mesh_unit, k)
            try:
                report = inspect(load_session(session.root), model, prior=self._priors.get(prior_key))
            except InspectionError as exc:
                return MeasurementResult(False, message=f"session {session.root}: {exc}", details=details)
            self._priors[prior_key] = report.registration
            data = report.as_dict() if hasattr(report, "as_dict") else dict(report)
            path = session.outputs / REPORT_FILE
            write_json(path, data)
            paths.append(path)
            details[f"view{k}"] = {key: data[key] for key in ("fitness", "rmse_mm") if key in data}
            tables.append({str(row["label"]): row for row in data["faces"]})
        values = tuple(_pick(c, tables) for c in program.characteristics)
        return MeasurementResult(True, values, details=details, report_paths=tuple(paths))


def _pick(c: Characteristic, tables: Sequence[Mapping[str, Mapping[str, Any]]]) -> MeasuredValue:
    """A characteristic's value from the view whose report has the most points on its face."""
    rows = [(k, t[c.face]) for k, t in enumerate(tables) if c.face in t and int(t[c.face].get("points", 0)) > 0]
    if not rows:
        return MeasuredValue(c.name, None, note=f"face {c.face} not seen in any view")
    k, row = max(rows, key=lambda kr: int(kr[1]["points"]))
    column = REPORT_COLUMNS[(c.kind, c.method)]
    value = row.get(column)
    limit = row.get(column.removesuffix("_mm") + "_limit_mm")
    if value is None and limit is not None:  # below its detection limit: at most the limit (inspection.uncertainty)
        return MeasuredValue(c.name, float(limit), int(row["points"]), k,
                             note=f"below the detection limit {float(limit) * 1e3:.1f} um")
    if value is None or not np.isfinite(float(value)):
        reason = row.get("note") or row.get("status") or f"no {column} in the report"
        return MeasuredValue(c.name, None, int(row["points"]), k, note=f"face {c.face}: {reason}")
    return MeasuredValue(c.name, float(value), int(row["points"]), k)


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


# the measurements a station config or `--measurement` can name
MEASUREMENTS: dict[str, type[InspectionMeasurement] | type[SimulatorTruth]] = {
    "inspection": InspectionMeasurement, "simulator-truth": SimulatorTruth}
DEFAULT_MEASUREMENT = "inspection"


def load_measurement(name: str, where: object = "--measurement") -> Measurement:
    """The measurement called `name` (one of `MEASUREMENTS`)."""
    if name not in MEASUREMENTS:
        raise ConfigError(where, "measurement", f"unknown measurement '{name}'; known: {sorted(MEASUREMENTS)}")
    return MEASUREMENTS[name]()
