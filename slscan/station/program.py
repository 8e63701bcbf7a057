"""Part programs (`config/parts/*.toml`): what to measure on a part and how to scan it.

    [program]
    name = "demo-part"                  # the part number results are filed under
    version = "1.0"                     # stored with every result
    cad = "demo_part.step"              # STEP or mesh, relative to this file
    mesh_unit = "mm"                    # optional, mesh CAD only: the unit its coordinates are in
    description = "..."                 # optional

    [scan]
    patterns = "../patterns/heterodyne_3x4.toml"   # pattern set TOML, relative to this file
    exposure_s = 0.010                  # optional: camera exposure (default: the rig's)
    views = 1                           # scans per part (the part is turned between views)

    [calibration]
    id = "factory-sim-bench"            # the calibration the program was proven with
    max_age_days = 180                  # optional: stricter than the station's expiry

    [control]                           # optional: control charts
    subgroup_size = 1                   # parts per subgroup: 1 = individuals/moving range (I-MR),
                                        # 2..10 = X-bar and R charts of consecutive parts

    [[characteristic]]                  # one table per characteristic, in report order
    name = "high_top_flatness"          # unique; results and charts are filed under it
    face = "#657"                       # CAD face: "#<STEP ADVANCED_FACE id>" (`slscan cad FILE` lists
                                        # them with their types), or "F<index>" of a mesh
    kind = "flatness"                   # flatness | cylindricity | sq | profile
    method = "minimum_zone"             # flatness, cylindricity: minimum_zone (default) | least_squares
    tolerance_mm = 0.05                 # upper limit of the measured value

Every measured value is a width or a height in mm and conforms when it is <= its
tolerance: flatness and cylindricity are zone widths (ISO 1101), `sq` the root-mean-square
height of the face's roughness (ISO 25178), and `profile` the width of the zone centred on
the nominal surface that holds every point, 2 max|signed deviation| (ISO 1101 profile of a
surface, tolerance zone t = ±t/2 about nominal).

Loading validates every key (errors name the file and the key) and, through the inspection
CAD loader, that each face exists in the CAD model and has a surface type the
characteristic applies to.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Mapping

from scanner.config import get, get_table, load_toml, resolve
from scanner.errors import ConfigError
from scanner.patterns import PatternSet
from slscan.station.spc import MAX_SUBGROUP
from slscan.station.station_config import check_keys

KINDS = ("flatness", "cylindricity", "sq", "profile")
FORM_METHODS = ("minimum_zone", "least_squares")
# Surface types each characteristic can be evaluated on (profile: any face, its deviations).
# A mesh face of no known surface type ("mesh") has no form or texture to evaluate.
SURFACE_KINDS = {"flatness": ("plane",), "cylindricity": ("cylinder",), "sq": ("plane", "cylinder", "cone")}

_TOP_KEYS = {"program", "scan", "calibration", "control", "characteristic"}
_CONTROL_KEYS = {"subgroup_size"}
_PROGRAM_KEYS = {"name", "version", "cad", "mesh_unit", "description"}
_SCAN_KEYS = {"patterns", "exposure_s", "views"}
_CALIBRATION_KEYS = {"id", "max_age_days"}
_CHARACTERISTIC_KEYS = {"name", "face", "kind", "method", "tolerance_mm"}


@dataclass(frozen=True)
class Characteristic:
    """One measured characteristic of one CAD face; lengths in mm."""

    name: str
    face: str
    kind: str
    tolerance_mm: float
    method: str | None = None  # flatness, cylindricity only

    def conforms(self, value_mm: float) -> bool:
        """Whether a measured value is within tolerance (every kind is an upper limit)."""
        return value_mm <= self.tolerance_mm

    @property
    def label(self) -> str:
        """Short human-readable description, e.g. 'flatness (minimum zone) F2 <= 0.050 mm'."""
        how = f" ({self.method.replace('_', ' ')})" if self.method else ""
        return f"{self.kind}{how} {self.face} <= {self.tolerance_mm:.3f} mm"


@dataclass(frozen=True)
class ScanSettings:
    """Pattern set file, exposure (s; None = the rig's) and views per part."""

    patterns_path: Path
    exposure_s: float | None
    views: int

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

    def characteristic(self, name: str) -> Characteristic:
        for c in self.characteristics:
            if c.name == name:
                return c
        raise KeyError(f"{self.path}: no characteristic named {name!r}")


def load_program(path: str | Path, faces: Callable[[PartProgram], Mapping[str, str]] | None = None) -> PartProgram:
    """Parse and validate a part program. With `faces` (a program -> {face label: surface
    type} lister, e.g. `measure.cad_faces`), every characteristic's face is checked in the
    CAD model."""
    path = Path(path)
    raw = load_toml(path)
    check_keys(raw, _TOP_KEYS, path)
    prog = get_table(raw, "program", path)
    check_keys(prog, _PROGRAM_KEYS, path, "program")
    version = get(prog, "version", (str, int, float), path, prefix="program")
    cad = resolve(path, get(prog, "cad", str, path, prefix="program"))
    if not cad.is_file():
        raise ConfigError(path, "program.cad", f"CAD file not found: {cad}")
    scan = _scan_settings(get_table(raw, "scan", path), path)
    cal = get_table(raw, "calibration", path)
    check_keys(cal, _CALIBRATION_KEYS, path, "calibration")
    max_age = get(cal, "max_age_days", float, path, None, "calibration")
    if max_age is not None and max_age <= 0:
        raise ConfigError(path, "calibration.max_age_days", f"must be > 0 days, got {max_age}")
    chars = _characteristics(raw, path)
    control = get_table(raw, "control", path, required=False)
    check_keys(control, _CONTROL_KEYS, path, "control")
    subgroup = get(control, "subgroup_size", int, path, 1, "control")
    if not 1 <= subgroup <= MAX_SUBGROUP:
        raise ConfigError(path, "control.subgroup_size", f"must be 1..{MAX_SUBGROUP} parts, got {subgroup}")
    program = PartProgram(
        path=path, name=get(prog, "name", str, path, prefix="program"), version=str(version), cad_path=cad,
        mesh_unit=get(prog, "mesh_unit", str, path, "mm", "program"),
        description=get(prog, "description", str, path, "", "program"), scan=scan,
        calibration_id=get(cal, "id", str, path, prefix="calibration"), max_calibration_age_days=max_age,
        characteristics=chars, fingerprint=hashlib.sha256(path.read_bytes()).hexdigest()[:12],
        face_check="not checked", subgroup_size=subgroup)
    if faces is None:
        return program
    found = faces(program)
    validate_faces(program, found)
    return replace(program, face_check=f"{len(found)} faces in {cad.name}, all {len(chars)} characteristics found")


def validate_faces(program: PartProgram, faces: Mapping[str, str]) -> None:
    """Refuse a characteristic whose face is not in the CAD model (`faces`: label -> surface
    type) or whose surface type the characteristic does not apply to."""
    for i, c in enumerate(program.characteristics):
        key = f"characteristic[{i}].face"
        if c.face not in faces:
            some = ", ".join(list(faces)[:12]) + (" ..." if len(faces) > 12 else "")
            raise ConfigError(program.path, key, f"face {c.face!r} ({c.name}) is not in {program.cad_path.name}; "
                                                 f"its faces are {some}")
        allowed = SURFACE_KINDS.get(c.kind)
        kind = faces[c.face]
        if allowed and kind not in allowed:
            raise ConfigError(program.path, key, f"{c.kind} applies to {' or '.join(allowed)} faces; "
                                                 f"face {c.face} of {program.cad_path.name} is a {kind}"
                                                 + (" face (a mesh face of no known surface type: use a STEP "
                                                    "model)" if kind == "mesh" else ""))


def _scan_settings(table: dict[str, Any], path: Path) -> ScanSettings:
    check_keys(table, _SCAN_KEYS, path, "scan")
    patterns = resolve(path, get(table, "patterns", str, path, prefix="scan"))
    try:
        PatternSet.load(patterns)
    except ConfigError as exc:
        raise ConfigError(path, "scan.patterns", str(exc)) from None
    exposure = get(table, "exposure_s", float, path, None, "scan")
    if exposure is not None and not 0 < exposure < 10:
        raise ConfigError(path, "scan.exposure_s", f"{exposure} s is not a plausible exposure")
    views = get(table, "views", int, path, 1, "scan")
    if not 1 <= views <= 16:
        raise ConfigError(path, "scan.views", f"views per part must be 1..16, got {views}")
    return ScanSettings(patterns, exposure, views)


def _characteristics(raw: dict[str, Any], path: Path) -> tuple[Characteristic, ...]:
    items = get(raw, "characteristic", list, path)
    if not items:
        raise ConfigError(path, "characteristic", "a program needs at least one [[characteristic]]")
    out: list[Characteristic] = []
    for i, t in enumerate(items):
        pre = f"characteristic[{i}]"
        if not isinstance(t, dict):
            raise ConfigError(path, pre, "expected a table ([[characteristic]])")
        check_keys(t, _CHARACTERISTIC_KEYS, path, pre)
        name = get(t, "name", str, path, prefix=pre)
        if not name.strip() or name in {c.name for c in out}:
            raise ConfigError(path, f"{pre}.name", f"names must be non-empty and unique; {name!r} is not")
        kind = get(t, "kind", str, path, prefix=pre)
        if kind not in KINDS:
            raise ConfigError(path, f"{pre}.kind", f"'{kind}' is not one of {KINDS}")
        method = get(t, "method", str, path, None, pre)
        if kind in ("flatness", "cylindricity"):
            method = method or FORM_METHODS[0]
            if method not in FORM_METHODS:
                raise ConfigError(path, f"{pre}.method", f"'{method}' is not one of {FORM_METHODS}")
        elif method is not None:
            raise ConfigError(path, f"{pre}.method", f"{kind} takes no method")
        tol = get(t, "tolerance_mm", float, path, prefix=pre)
        if not 0 < tol < math.inf:
            raise ConfigError(path, f"{pre}.tolerance_mm", f"must be a finite number > 0 mm, got {tol}")
        face = get(t, "face", str, path, prefix=pre)
        out.append(Characteristic(name=name, face=face, kind=kind, tolerance_mm=tol, method=method))
    return tuple(out)
