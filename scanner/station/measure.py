"""The measuring step: a typed seam between the station and whatever measures a scan, and
its one adapter onto the `inspection` package (issue 5).

A `Measurement` takes the sessions of one part (one per view, each complete and
processed: `outputs/cloud.ply` in mm, camera frame) and the part program, and returns one
`MeasuredValue` per characteristic. It does not judge: the station compares values with
the program's tolerances (`Characteristic.conforms`), so a verdict never depends on who
measured. A characteristic that cannot be measured on a scan gets no value and a reason;
a part whose scan cannot be registered to the CAD model gets a failed `MeasurementResult`.
Neither is ever a number.

`InspectionMeasurement` is the only code in the station that imports `inspection`. It
needs, from the inspection stage:

    inspection.cad.load_cad(path, mesh_unit) -> CadModel          (faces by label and type)
    LOAD_ENTRY(session folder) -> scan                             (the session's processed cloud)
    INSPECT_ENTRY(scan, model: CadModel) -> report                 (registered, segmented by face,
                                                                   every face evaluated)

where the report is the issue-5 per-face table, as a mapping or an object with `as_dict()`:
`{"faces": [{"label": "#12" | "F3", "type": ..., "points": n, <value columns>}, ...],
"fitness": f, "rmse_mm": r}` with the value columns of `REPORT_COLUMNS`. While an entry is
missing, `unavailable()` says which, and the station refuses to measure (it never makes
numbers up); the tests that need it are skipped with that reason.
"""

from __future__ import annotations

import importlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence

import numpy as np

from ..errors import ScannerError
from ..session import Session, write_json
from .program import Characteristic, PartProgram

CAD_ENTRY = "inspection.cad:load_cad"
LOAD_ENTRY = "inspection.scan:load_session"
INSPECT_ENTRY = "inspection.pipeline:inspect"
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


class MeasurementUnavailable(ScannerError):
    """The measuring step cannot run (its implementation is missing or broken)."""


def _resolve(entry: str) -> Any:
    """The callable named `module:attribute`; raises MeasurementUnavailable naming it."""
    module_name, attr = entry.split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            raise MeasurementUnavailable(f"{module_name} does not exist yet (inspection, issue 5)") from None
        raise MeasurementUnavailable(f"{module_name} cannot be imported: {exc}") from exc
    except Exception as exc:  # noqa: BLE001 — a broken module is reported, not hidden
        raise MeasurementUnavailable(f"{module_name} cannot be imported: {type(exc).__name__}: {exc}") from exc
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise MeasurementUnavailable(f"{module_name} has no function {attr}() yet (inspection, issue 5)")
    return fn


def cad_faces(program: PartProgram) -> dict[str, str] | str:
    """The CAD model's faces as label -> surface type, through the inspection CAD loader;
    a string saying why when the loader is not available."""
    try:
        load = _resolve(CAD_ENTRY)
    except MeasurementUnavailable as exc:
        return str(exc)
    model = load(program.cad_path, mesh_unit=program.mesh_unit)
    return {f.label: f.type for f in model.faces}


class InspectionMeasurement:
    """The adapter onto `inspection`: per view, the session's cloud is registered to the
    CAD model, segmented by face and evaluated (`INSPECT_ENTRY` on `LOAD_ENTRY`); the report is
    kept in the session's outputs; each characteristic takes its value from the view
    with the most points on its face."""

    name = "inspection"

    def __init__(self) -> None:
        self._models: dict[tuple[Path, str], Any] = {}  # (CAD path, unit) -> CadModel, loaded once

    def unavailable(self) -> str | None:
        try:
            for entry in (CAD_ENTRY, LOAD_ENTRY, INSPECT_ENTRY):
                _resolve(entry)
        except MeasurementUnavailable as exc:
            return str(exc)
        return None

    def _model(self, program: PartProgram) -> Any:
        key = (program.cad_path, program.mesh_unit)
        if key not in self._models:
            self._models[key] = _resolve(CAD_ENTRY)(program.cad_path, mesh_unit=program.mesh_unit)
        return self._models[key]

    def measure(self, sessions: Sequence[Session], program: PartProgram) -> MeasurementResult:
        from inspection.errors import InspectionError  # the adapter is the one importer of inspection

        load, inspect = _resolve(LOAD_ENTRY), _resolve(INSPECT_ENTRY)
        model = self._model(program)
        tables: list[dict[str, dict[str, Any]]] = []
        details: dict[str, Any] = {}
        paths: list[Path] = []
        for k, session in enumerate(sessions):
            try:
                report = inspect(load(session.root), model)
            except InspectionError as exc:
                return MeasurementResult(False, message=f"session {session.root}: {exc}", details=details)
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
    if value is None or not np.isfinite(float(value)):
        reason = row.get("note") or row.get("status") or f"no {column} in the report"
        return MeasuredValue(c.name, None, int(row["points"]), k, note=f"face {c.face}: {reason}")
    return MeasuredValue(c.name, float(value), int(row["points"]), k)
