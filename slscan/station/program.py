"""Part programs (`config/parts/*.toml`): what to measure on a part and how to scan it.

    [program]
    name = "demo-part"                  # the part number results are filed under
    version = "1.0"                     # stored with every result
    cad = "demo_part.step"              # STEP or mesh, relative to this file
    mesh_unit = "mm"                    # optional, mesh CAD only: the unit its coordinates are in
    description = "..."                 # optional
    decision_rule = "guard-banded"      # optional: how U enters the verdicts (ISO 14253-1, below)

    [scan]
    patterns = "../patterns/heterodyne_3x4.toml"   # pattern set TOML, relative to this file
    exposure_s = 0.010                  # optional: camera exposure (default: the rig's)
    views = 1                           # scans per part: N, the operator turns the part between views
                                        # (each view measured alone), or a list of stage angles in
                                        # degrees, [0, 90, 180, 270]: the rig's [stage] turns the part,
                                        # the views are fused and the whole part measured at once

    [inspection]                        # optional
    edge_margin_mm = 1.0                # band along every face's measured border left out of the
                                        # figures (default 1 mm; a narrow face, e.g. a 1.5 mm chamfer,
                                        # needs less)

    [calibration]
    id = "factory-sim-bench"            # the calibration the program was proven with
    max_age_days = 180                  # optional: stricter than the station's expiry

    [control]                           # optional: control charts
    subgroup_size = 1                   # parts per subgroup: 1 = individuals/moving range (I-MR),
                                        # 2..10 = X-bar and R charts of consecutive parts

    [faces]                             # optional: the faces' names, shown wherever a face is
    "#657" = "high top"                 # (reports, tables, the recording)

    [[characteristic]]                  # one table per characteristic, in report order
    name = "high_top_flatness"          # unique; results and charts are filed under it
    face = "#657"                       # CAD face: "#<STEP ADVANCED_FACE id>" (`slscan cad FILE` lists
                                        # them with their types), or "F<index>" of a mesh
    kind = "flatness"                   # flatness | cylindricity | sq | profile (`inspection.figures`)
    method = "minimum_zone"             # flatness, cylindricity: minimum_zone (default) | least_squares
    tolerance_mm = 0.05                 # upper limit of the measured value

Every measured value is a width or a height in mm with an upper limit, its tolerance:
flatness and cylindricity are zone widths (ISO 1101), `sq` the root-mean-square height of
the face's roughness (ISO 25178), and `profile` the width of the zone centred on the
nominal surface that holds every point, 2 max|signed deviation| (ISO 1101 profile of a
surface, tolerance zone t = ±t/2 about nominal). A measured value is decided by ISO
14253-1 under the program's `decision_rule` (`Characteristic.decide`, through
`inspection.tolerances.decide`): "guard-banded" (the default) calls it conforming only when
value + U <= tolerance, non-conforming when value - U > tolerance, else uncertain; "plain"
compares the value alone (U still recorded). A figure below its detection limit is
conforming when that limit is within the tolerance, else uncertain.

Loading validates the file on the project's schema layer (`scanner.schema`: unknown keys
refused with the nearest valid name, types, ranges, finite numbers; errors name the file
and the key), then the files it names and, through the inspection CAD loader, that each
face exists in the CAD model and has a surface type the characteristic applies to.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, field_validator

from inspection.cad import MESH_UNITS_MM
from inspection.figures import FORM_METHODS, KINDS, asked_by, methods
from inspection.tolerances import CONFORMING, DECISION_RULES, GUARD_BANDED, PLAIN, Tolerances, decide
from scanner import schema
from scanner.config import resolve
from scanner.errors import ConfigError
from scanner.patterns import PatternSet
from slscan.station.spc import MAX_SUBGROUP

if TYPE_CHECKING:
    from inspection.form import FormSettings

Name = Annotated[schema.Str, Field(min_length=1, pattern=r"\S")]  # plain text, not empty, not blank


class ProgramTable(schema.Schema):
    name: Name
    version: schema.Str | schema.Int | schema.Float
    cad: schema.Str
    mesh_unit: Literal[tuple(MESH_UNITS_MM)] = "mm"  # type: ignore[valid-type]  # Literal built from the registry
    description: schema.Str = ""
    decision_rule: Literal[tuple(DECISION_RULES)] = GUARD_BANDED  # type: ignore[valid-type]  # from the registry


MAX_VIEWS = 16


class ScanTable(schema.Schema):
    patterns: schema.Str
    exposure_s: Annotated[float, Field(strict=True, gt=0, lt=10)] | None = None
    views: int | list[float] = 1  # a number of views or stage angles in degrees (`_views`)

    @field_validator("views", mode="before")
    @classmethod
    def _views(cls, v: object) -> object:
        """1..MAX_VIEWS views, or a list of 1..MAX_VIEWS finite stage angles (deg)."""
        want = f"a number of views 1..{MAX_VIEWS} or a list of 1..{MAX_VIEWS} stage angles in degrees"
        number = (int, float)
        if isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_VIEWS:
            return v
        if (isinstance(v, list) and 1 <= len(v) <= MAX_VIEWS
                and all(isinstance(a, number) and not isinstance(a, bool) and math.isfinite(a) for a in v)):
            return [float(a) for a in v]
        raise ValueError(f"expected {want}, got {v!r}")


class InspectionTable(schema.Schema):
    edge_margin_mm: Annotated[float, Field(strict=True, ge=0, le=10)] = 1.0


class CalibrationTable(schema.Schema):
    id: schema.Str
    max_age_days: schema.PositiveFloat | None = None


class ControlTable(schema.Schema):
    subgroup_size: Annotated[int, Field(strict=True, ge=1, le=MAX_SUBGROUP)] = 1


class CharacteristicTable(schema.Schema):
    name: Name
    face: schema.Str
    kind: Literal[KINDS]  # type: ignore[valid-type]  # Literal built from the figures registry
    method: Literal[FORM_METHODS] | None = None  # type: ignore[valid-type]  # from the figures registry
    tolerance_mm: schema.PositiveFloat  # finite: the base schema refuses inf and NaN


class ProgramFile(schema.Schema):
    """A part program TOML (module docstring)."""

    program: ProgramTable
    scan: ScanTable
    calibration: CalibrationTable
    control: ControlTable = ControlTable()
    inspection: InspectionTable = InspectionTable()
    faces: dict[str, Name] = Field(default_factory=dict)
    characteristic: Annotated[list[CharacteristicTable], Field(min_length=1)]


@dataclass(frozen=True)
class Characteristic:
    """One measured characteristic of one CAD face; lengths in mm."""

    name: str
    face: str
    kind: str
    tolerance_mm: float
    method: str | None = None  # flatness, cylindricity only

    def conforms(self, value_mm: float) -> bool:
        """Whether a true value (exact, no uncertainty: the simulator's) is within
        tolerance (every kind is an upper limit)."""
        return decide(value_mm, 0.0, self.tolerance_mm, rule=PLAIN) == CONFORMING

    def decide(self, value_mm: float | None, u_mm: float | None, limit_mm: float | None = None,
               rule: str = GUARD_BANDED) -> str:
        """The ISO 14253-1 decision on a measured value (mm) with its expanded uncertainty
        U (mm; None: not known, taken as 0 and so only the value is judged) against this
        characteristic's tolerance; `limit_mm` the detection limit of a value too small to
        tell from zero (value None). One of conforming, non-conforming, uncertain, not measured."""
        return decide(value_mm, u_mm or 0.0, self.tolerance_mm, None, rule, limit_mm)

    @property
    def label(self) -> str:
        """Short human-readable description, e.g. 'flatness (minimum zone) F2 <= 0.050 mm'."""
        how = f" ({self.method.replace('_', ' ')})" if self.method else ""
        return f"{self.kind}{how} {self.face} <= {self.tolerance_mm:.3f} mm"


@dataclass(frozen=True)
class ScanSettings:
    """Pattern set file, exposure (s; None = the rig's) and views per part; with
    `stage_angles_deg` (a `views` list) the rig's stage turns the part to each angle (deg)
    and `views` is their number, else the operator turns it between `views` scans."""

    patterns_path: Path
    exposure_s: float | None
    views: int
    stage_angles_deg: tuple[float, ...] | None = None

    def pattern_set(self) -> PatternSet:
        return PatternSet.load(self.patterns_path)


@dataclass(frozen=True)
class PartProgram:
    """A validated part program. `fingerprint` is the first 12 hex digits of the file's
    SHA-256 (stored with results beside `version`, so an edit without a version bump shows);
    `face_check` says how the faces were checked against the CAD."""

    path: Path
    name: str
    version: str
    cad_path: Path
    mesh_unit: str
    description: str
    scan: ScanSettings
    calibration_id: str
    max_calibration_age_days: float | None
    characteristics: tuple[Characteristic, ...]
    fingerprint: str
    face_check: str
    subgroup_size: int = 1
    face_names: Mapping[str, str] = field(default_factory=dict)
    decision_rule: str = GUARD_BANDED
    edge_margin_mm: float = 1.0  # the inspection's band left out along every face's border

    def form_settings(self) -> FormSettings:
        """The form figures' settings this program asks for (its edge margin)."""
        from inspection.form import FormSettings  # scipy: not at the command line's start

        return FormSettings(edge_margin_mm=self.edge_margin_mm)

    def characteristic(self, name: str) -> Characteristic:
        for c in self.characteristics:
            if c.name == name:
                return c
        raise KeyError(f"{self.path}: no characteristic named {name!r}")


def load_program(path: str | Path, faces: Callable[[PartProgram], Mapping[str, str]] | None = None) -> PartProgram:
    """Parse and validate a part program (`ProgramFile`; then the files it names, and the
    rules across characteristics). With `faces` (a program -> {face label: surface type}
    lister, e.g. `measure.cad_faces`), every characteristic's face is checked in the CAD model."""
    path = Path(path)
    f = schema.load(ProgramFile, path)
    cad = resolve(path, f.program.cad)
    if not cad.is_file():
        raise ConfigError(path, "program.cad", f"CAD file not found: {cad}")
    patterns = resolve(path, f.scan.patterns)
    try:
        PatternSet.load(patterns)
    except ConfigError as exc:
        raise ConfigError(path, "scan.patterns", str(exc)) from None
    chars = _characteristics(f.characteristic, path)
    views = f.scan.views
    angles = None if isinstance(views, int) else tuple(views)
    count = views if isinstance(views, int) else len(views)
    program = PartProgram(
        path=path, name=f.program.name, version=str(f.program.version), cad_path=cad, mesh_unit=f.program.mesh_unit,
        description=f.program.description,
        scan=ScanSettings(patterns, f.scan.exposure_s, count, angles),
        calibration_id=f.calibration.id, max_calibration_age_days=f.calibration.max_age_days,
        characteristics=chars, fingerprint=hashlib.sha256(path.read_bytes()).hexdigest()[:12],
        face_check="not checked", subgroup_size=f.control.subgroup_size, face_names=dict(f.faces),
        decision_rule=f.program.decision_rule, edge_margin_mm=f.inspection.edge_margin_mm)
    if faces is None:
        return program
    found = faces(program)
    validate_faces(program, found)
    return replace(program, face_check=f"{len(found)} faces in {cad.name}, all {len(chars)} characteristics found")


def validate_faces(program: PartProgram, faces: Mapping[str, str]) -> None:
    """Refuse a characteristic whose face is not in the CAD model (`faces`: label -> surface
    type) or whose surface type the characteristic does not apply to, and a name given to
    a face the model does not have."""
    for i, c in enumerate(program.characteristics):
        key = f"characteristic[{i}].face"
        if c.face not in faces:
            some = ", ".join(list(faces)[:12]) + (" ..." if len(faces) > 12 else "")
            raise ConfigError(program.path, key, f"face {c.face!r} ({c.name}) is not in {program.cad_path.name}; "
                                                 f"its faces are {some}")
        allowed = asked_by(c.kind, c.method).surfaces  # None: any face (a mesh face of no known surface
        kind = faces[c.face]                           # type, "mesh", has no form or texture to evaluate)
        if allowed and kind not in allowed:
            raise ConfigError(program.path, key, f"{c.kind} applies to {' or '.join(allowed)} faces; "
                                                 f"face {c.face} of {program.cad_path.name} is a {kind}"
                                                 + (" face (a mesh face of no known surface type: use a STEP "
                                                    "model)" if kind == "mesh" else ""))
    for label in program.face_names:
        if label not in faces:
            raise ConfigError(program.path, f'faces."{label}"', f"{program.cad_path.name} has no face {label!r}")


def _characteristics(items: Sequence[CharacteristicTable], path: Path) -> tuple[Characteristic, ...]:
    """The characteristics, with the rules the schema cannot see: unique names, a method
    only where the kind has one (the form kinds default to minimum zone)."""
    out: list[Characteristic] = []
    for i, t in enumerate(items):
        pre = f"characteristic[{i}]"
        if t.name in {c.name for c in out}:
            raise ConfigError(path, f"{pre}.name", f"names must be unique; {t.name!r} is used twice")
        method = t.method
        if methods(t.kind):
            method = method or FORM_METHODS[0]
        elif method is not None:
            raise ConfigError(path, f"{pre}.method", f"{t.kind} takes no method")
        out.append(Characteristic(name=t.name, face=t.face, kind=t.kind, tolerance_mm=t.tolerance_mm, method=method))
    return tuple(out)


def program_tolerances(program: PartProgram) -> Tolerances:
    """The program's characteristics as the inspection's per-face limits (the one source of
    a part's tolerances: `slscan inspect --tolerances PROGRAM` and the demo use this), with
    the program's face names and decision rule (ISO 14253-1). Two
    characteristics of one kind and method on one face cannot be told apart by the
    inspection report, so they are refused."""
    faces: dict[str, dict[str, float]] = {}
    for i, c in enumerate(program.characteristics):
        key = asked_by(c.kind, c.method).tolerance_key
        limits = faces.setdefault(c.face, {})
        if key in limits:
            raise ConfigError(program.path, f"characteristic[{i}]", f"a second {c.kind} of face {c.face} ({c.name}); "
                                                                    f"one per face, kind and method")
        limits[key] = c.tolerance_mm
    return Tolerances(faces, {}, program.path, program.decision_rule, dict(program.face_names))
