"""Tolerance files: per-face limits for the inspection report. A part's tolerances live in
its part program (`config/parts/*.toml`, `slscan.station.program`), which `slscan inspect
--tolerances` and the demo read and turn into `Tolerances`; this file format is for a model
without a program:

    # tolerances of config/parts/demo_part.step (mm)
    decision_rule = "guard-banded"   # optional: how verdicts use U (see DECISION_RULES)
    [faces."#657"]              # a face by its label: "#<STEP ADVANCED_FACE id>" or "F<index>" (meshes)
    flatness_mm = 0.05          # minimum-zone flatness (ISO 1101), planes (flatness_ls_mm: least squares)
    sq_mm = 0.10                # Sq after noise removal (the true surface's ISO 25178-2 Sq, estimated)
    [faces."#17"]
    cylindricity_mm = 0.05      # minimum-zone cylindricity, cylinders (cylindricity_ls_mm: least squares)
    profile_mm = 0.4            # profile of a surface: every point within +-profile/2 of nominal
    [default]                   # optional: limits for every face without its own table
    profile_mm = 1.0

The keys, the figure each limits and the surface types it applies to are
`inspection.figures`' (`TOLERANCE_KEYS`, `limited_by`).

Verdicts follow ISO 14253-1 (`decide`): with the default "guard-banded" rule a
characteristic is "conforming" when conformance is proven (its value plus its expanded
uncertainty U is within the limit), "non-conforming" when non-conformance is proven (the
value minus U is beyond it), else "uncertain" — a measurement its uncertainty cannot decide
is never called conforming. The "plain" rule judges the value alone (U is still reported).
A figure below its detection limit ("< L": the measurement could not tell it from zero) is
judged like any value, with the interval [0, L + U] in place of [value - U, value + U]: its
true value lies below about L, and L is itself uncertain by the figure's U there
(`inspection.uncertainty.Estimate`). So it is conforming only when L + U is within the
upper limit (and 0 above any lower one), non-conforming when L + U is below a lower limit,
else uncertain; the plain rule judges L alone.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inspection.errors import ToleranceError
from inspection.figures import TOLERANCE_KEYS, limited_by
from scanner.schema import nearest


@dataclass(frozen=True)
class Tolerances:
    """Limits (mm) by face label, and defaults for faces without their own; `names` the
    faces' names by label (a part program's [faces] table), shown wherever a face is."""

    faces: dict[str, dict[str, float]]
    default: dict[str, float]
    path: Path | None = None
    decision_rule: str = "guard-banded"
    names: dict[str, str] = field(default_factory=dict)

    def name(self, label: str) -> str:
        return self.names.get(label, "")

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
    unknown = set(raw) - {"faces", "default", "decision_rule"}
    if unknown:
        raise ToleranceError(f"{path}: unknown table(s) {sorted(unknown)}; expected [faces.\"#id\"], [default] and "
                             f"decision_rule")
    if not isinstance(raw.get("faces", {}), dict):
        raise ToleranceError(f"{path}: faces must be a table of [faces.\"#id\"] tables")
    rule = raw.get("decision_rule", GUARD_BANDED)
    if rule not in DECISION_RULES:
        raise ToleranceError(f"{path}: decision_rule {rule!r}: use one of {sorted(DECISION_RULES)}")

    def limits(table: object, where: str, face_type: str | None) -> dict[str, float]:
        if not isinstance(table, dict):
            raise ToleranceError(f"{path}: {where} must be a table")
        out = {}
        for key, value in table.items():
            if key not in TOLERANCE_KEYS:
                guess = nearest(key, TOLERANCE_KEYS)
                raise ToleranceError(f"{path}: {where}.{key}: unknown characteristic; "
                                     + (f"did you mean '{guess}'?" if guess else f"use {sorted(TOLERANCE_KEYS)}"))
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
                raise ToleranceError(f"{path}: {where}.{key}: a tolerance must be a finite number > 0 (mm), "
                                     f"got {value!r}")
            figure = limited_by(key)
            if face_type is not None and not figure.applies_to(face_type):
                raise ToleranceError(f"{path}: {where}.{key}: face is a {face_type}; {key} applies to "
                                     f"{' or '.join(f'{t}s' for t in figure.surfaces or ())}")
            out[key] = float(value)
        return out

    faces = {}
    for label, table in raw.get("faces", {}).items():
        if label not in labels:
            raise ToleranceError(f"{path}: faces.\"{label}\": the model has no such face (labels look like "
                                 f"{next(iter(labels))})")
        faces[label] = limits(table, f"faces.\"{label}\"", labels[label])
    return Tolerances(faces, limits(raw.get("default", {}), "default", None), path, rule)


CONFORMING, NON_CONFORMING, UNCERTAIN, NOT_MEASURED = "conforming", "non-conforming", "uncertain", "not measured"
NO_TOLERANCES = "no tolerances"  # a part without limits: measured, nothing to decide
GUARD_BANDED, PLAIN = "guard-banded", "plain"
DECISION_RULES = {
    GUARD_BANDED: "ISO 14253-1: conforming when value + U is within the limit, non-conforming when value - U is "
                  "beyond it, otherwise uncertain; a figure below its detection limit L (< L) as the value L: "
                  "conforming only when L + U is within the limit",
    PLAIN: "the value against the limit (simple acceptance; a figure < L judged by L); U reported but not applied",
}


def decide(value: float | None, U: float, upper: float, lower: float | None = None, rule: str = GUARD_BANDED,
           limit: float | None = None) -> str:
    """The ISO 14253-1 verdict of a measured figure against its specification [lower,
    upper] (mm; `lower` None: an upper limit only, as for form tolerances): "conforming",
    "non-conforming", "uncertain" or "not measured" (see the module docstring). `U`: the
    value's expanded uncertainty (for a figure below its detection limit, the figure's U
    at that limit); `limit`: its detection limit when `value` is None because the figure
    could not be told from zero (a figure >= 0: zones, Sq, magnitudes)."""
    if rule not in DECISION_RULES:
        raise ValueError(f"unknown decision rule {rule!r}; use one of {sorted(DECISION_RULES)}")
    band = U if rule == GUARD_BANDED else 0.0
    lo = -np.inf if lower is None else lower
    if value is None:
        if limit is None:
            return NOT_MEASURED
        top = limit + band  # the measurement says the figure lies in [0, top]
        if lo <= 0.0 and top <= upper:
            return CONFORMING
        if top < lo:
            return NON_CONFORMING
        return UNCERTAIN
    if lo + band <= value <= upper - band:
        return CONFORMING
    if value - band > upper or value + band < lo:
        return NON_CONFORMING
    return UNCERTAIN


DECISION_STATUS = {CONFORMING: "ok", NO_TOLERANCES: "ok", NON_CONFORMING: "failed", UNCERTAIN: "no decision",
                   NOT_MEASURED: "no decision"}
"""The `status` of a result by its overall verdict, as its exit code says it
(`slscan.exit_codes`: 0, 1 and 4)."""


def overall(verdicts: list[str]) -> str:
    """A part's verdict from its characteristics': non-conforming if any is, else
    uncertain or not measured if any is, else conforming ("no tolerances" without any)."""
    for word in (NON_CONFORMING, UNCERTAIN, NOT_MEASURED):
        if word in verdicts:
            return word
    return CONFORMING if verdicts else NO_TOLERANCES
