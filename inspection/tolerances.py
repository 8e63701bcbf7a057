"""Tolerance files: per-face limits for the inspection report (`config/tolerances/`).

    # tolerances of config/parts/demo_part.step (mm)
    [faces."#657"]              # a face by its label: "#<STEP ADVANCED_FACE id>" or "F<index>" (meshes)
    flatness_mm = 0.05          # minimum-zone flatness (ISO 1101), planes
    sq_mm = 0.10                # Sq roughness (ISO 25178-2)
    [faces."#17"]
    cylindricity_mm = 0.05      # minimum-zone cylindricity, cylinders
    profile_mm = 0.4            # profile of a surface: every point within +-profile/2 of nominal
    [default]                   # optional: limits for every face without its own table
    profile_mm = 1.0

Verdicts follow the decision rule of ISO 14253-1: "pass" when the value plus its noise
uncertainty is within the limit, "fail" when the value minus it is beyond, else
"uncertain" — a measurement the scanner's noise cannot decide is never called a pass.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from inspection.errors import ToleranceError
from scanner.schema import nearest

CHARACTERISTICS = {"flatness_mm": ("plane",), "cylindricity_mm": ("cylinder",), "sq_mm": None, "profile_mm": None}


@dataclass(frozen=True)
class Tolerances:
    """Limits (mm) by face label, and defaults for faces without their own."""

    faces: dict[str, dict[str, float]]
    default: dict[str, float]
    path: Path | None = None

    def for_face(self, label: str) -> dict[str, float]:
        return {**self.default, **self.faces.get(label, {})}


def load_tolerances(path: str | Path, labels: dict[str, str]) -> Tolerances:
    """A tolerance TOML checked against the model's faces (`labels`: label -> type)."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ToleranceError(f"{path}: no such tolerance file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ToleranceError(f"{path}: unreadable tolerance file: {exc}") from None
    unknown = set(raw) - {"faces", "default"}
    if unknown:
        raise ToleranceError(f"{path}: unknown table(s) {sorted(unknown)}; expected [faces.\"#id\"] and [default]")
    if not isinstance(raw.get("faces", {}), dict):
        raise ToleranceError(f"{path}: faces must be a table of [faces.\"#id\"] tables")

    def limits(table: object, where: str, face_type: str | None) -> dict[str, float]:
        if not isinstance(table, dict):
            raise ToleranceError(f"{path}: {where} must be a table")
        out = {}
        for key, value in table.items():
            if key not in CHARACTERISTICS:
                guess = nearest(key, CHARACTERISTICS)
                raise ToleranceError(f"{path}: {where}.{key}: unknown characteristic; "
                                     + (f"did you mean '{guess}'?" if guess else f"use {sorted(CHARACTERISTICS)}"))
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
                raise ToleranceError(f"{path}: {where}.{key}: a tolerance must be a finite number > 0 (mm), "
                                     f"got {value!r}")
            types = CHARACTERISTICS[key]
            if face_type is not None and types is not None and face_type not in types:
                raise ToleranceError(f"{path}: {where}.{key}: face is a {face_type}; {key} applies to {types[0]}s")
            out[key] = float(value)
        return out

    faces = {}
    for label, table in raw.get("faces", {}).items():
        if label not in labels:
            raise ToleranceError(f"{path}: faces.\"{label}\": the model has no such face (labels look like "
                                 f"{next(iter(labels))})")
        faces[label] = limits(table, f"faces.\"{label}\"", labels[label])
    return Tolerances(faces, limits(raw.get("default", {}), "default", None), path)


def verdict(value: float | None, limit: float, uncertainty: float) -> str:
    """ISO 14253-1 decision: "pass", "fail", "uncertain", or "not measured"."""
    if value is None:
        return "not measured"
    if value + uncertainty <= limit:
        return "pass"
    if value - uncertainty > limit:
        return "fail"
    return "uncertain"
