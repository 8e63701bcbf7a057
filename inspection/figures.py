"""The inspection figures, written down once: every figure a face's form evaluation gives
(`inspection.form.FaceForm`), what it applies to and how the report, the tolerance files,
the part programs and the station name it.

A `Figure` says: its `name` (the `FaceForm` attribute and the stem of its report columns),
its `unit`, the surface types it is evaluated on, whether it is tested against zero (then a
value the noise alone could read is reported as null with its detection limit), the part
program's `kind` and `method` that ask for it and the tolerance key that limits it (a
figure without a `kind` is reported, never toleranced), and how people read it (`title`,
the report's headings). Report columns (`inspection.json`, `.csv`): `<name>_mm`,
`<name>_u_mm` (U, k = 2), `<name>_limit_mm` (the detection limit, when reported below it);
a toleranced face adds `tolerance_<key>` and `verdict_<characteristic>`.

Adding a figure is one entry in `FIGURES` plus its computation (`inspection.form`):
docs/architecture.md, "Adding a figure".
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from inspection.uncertainty import Estimate

MINIMUM_ZONE, LEAST_SQUARES = "minimum_zone", "least_squares"
FORM_METHODS = (MINIMUM_ZONE, LEAST_SQUARES)  # how a zone is fitted; a part program's default: the first
FORM, DEVIATION = "form", "deviation"  # the report's two groups of figures: form and texture; deviations


@dataclass(frozen=True)
class Figure:
    """One figure of a face (module docstring). `surfaces`: the surface types it is
    evaluated on (None: every face); `zero_tested`: it has a detection limit; `group`: FORM
    or DEVIATION (the report's all-figures tables); `heading` its column there; `abbrev` its
    column in the text table ("": not there); `kind`, `method`: the part program's
    characteristic that asks for it ("": none; method None: the kind has one figure);
    `characteristic`: the stem of its tolerance key and verdict column; `raw_of`: the form
    surface's figure this one is the raw points' counterpart of ("": none)."""

    name: str
    title: str
    heading: str
    group: str
    surfaces: tuple[str, ...] | None
    zero_tested: bool
    abbrev: str = ""
    kind: str = ""
    method: str | None = None
    characteristic: str = ""
    raw_of: str = ""
    unit: str = "mm"

    @property
    def value_column(self) -> str:
        return f"{self.name}_{self.unit}"

    @property
    def u_column(self) -> str:
        """The column of the value's expanded uncertainty U (k = 2)."""
        return f"{self.name}_u_{self.unit}"

    @property
    def limit_column(self) -> str:
        """The column of the detection limit (only written when there is one)."""
        return f"{self.name}_limit_{self.unit}"

    @property
    def tolerance_key(self) -> str:
        """The key that limits the figure in a tolerance file and in the report's
        `tolerance_<key>` column ("" when it is not toleranced)."""
        return f"{self.characteristic}_{self.unit}" if self.characteristic else ""

    @property
    def tolerance_column(self) -> str:
        return f"tolerance_{self.tolerance_key}"

    @property
    def verdict_column(self) -> str:
        return f"verdict_{self.characteristic}"

    def applies_to(self, surface: str) -> bool:
        return self.surfaces is None or surface in self.surfaces

    def fields(self, e: Estimate | None) -> dict[str, float | None]:
        """The report columns of an estimate of this figure (None: not measured, value and
        U null); the limit only when the estimate has one."""
        if e is None:
            return {self.value_column: None, self.u_column: None}
        return {self.value_column: e.value, self.u_column: e.U,
                **({self.limit_column: e.limit} if e.limit is not None else {})}


PLANE, CYLINDER = ("plane",), ("cylinder",)
TEXTURED = ("plane", "cylinder", "cone")  # faces with surface coordinates to filter on (`form._SURFACE_FORMS`)

FIGURES = (
    Figure("flatness_ls", "flatness (least squares)", "flatness LS", FORM, PLANE, True,
           kind="flatness", method=LEAST_SQUARES, characteristic="flatness_ls"),
    Figure("flatness_mz", "flatness (minimum zone)", "flatness MZ", FORM, PLANE, True, "flat MZ",
           kind="flatness", method=MINIMUM_ZONE, characteristic="flatness"),
    Figure("cylindricity_ls", "cylindricity (least squares)", "cylindricity LS", FORM, CYLINDER, True,
           kind="cylindricity", method=LEAST_SQUARES, characteristic="cylindricity_ls"),
    Figure("cylindricity_mz", "cylindricity (minimum zone)", "cylindricity MZ", FORM, CYLINDER, True, "cyl MZ",
           kind="cylindricity", method=MINIMUM_ZONE, characteristic="cylindricity"),
    Figure("sq", "Sq after noise removal", "Sq", FORM, TEXTURED, True, "Sq", kind="sq", characteristic="sq"),
    Figure("profile", "profile of a surface", "profile", FORM, None, True, "profile", kind="profile",
           characteristic="profile"),
    Figure("deviation_min", "deviation min", "deviation min", DEVIATION, None, True, "dev min"),
    Figure("deviation_max", "deviation max", "deviation max", DEVIATION, None, True, "dev max"),
    Figure("deviation_mean", "deviation mean", "deviation mean", DEVIATION, None, False),
    Figure("deviation_rms", "deviation RMS", "deviation RMS", DEVIATION, None, False),
    Figure("raw_deviation_min", "raw points' deviation min", "deviation raw points min", DEVIATION, None, True,
           raw_of="deviation_min"),
    Figure("raw_deviation_max", "raw points' deviation max", "deviation raw points max", DEVIATION, None, True,
           raw_of="deviation_max"),
)
"""Every figure, in report order."""

_BY_NAME = {f.name: f for f in FIGURES}
_BY_KEY = {f.tolerance_key: f for f in FIGURES if f.characteristic}
_BY_KIND = {(f.kind, f.method): f for f in FIGURES if f.kind}
TOLERANCE_KEYS = tuple(_BY_KEY)
"""The keys a tolerance file may limit a face by."""
KINDS = tuple(dict.fromkeys(f.kind for f in FIGURES if f.kind))
"""The kinds of characteristic a part program may ask for."""


def _unknown(what: str, name: object, known: Iterable[object]) -> KeyError:
    return KeyError(f"unknown {what} {name!r}; known: {', '.join(map(str, known))}")


def figure(name: str) -> Figure:
    """The figure called `name` (refused, listing the known ones, when there is none)."""
    if name not in _BY_NAME:
        raise _unknown("figure", name, _BY_NAME)
    return _BY_NAME[name]


def limited_by(key: str) -> Figure:
    """The figure a tolerance key ("flatness_mm", ...: `TOLERANCE_KEYS`) limits."""
    if key not in _BY_KEY:
        raise _unknown("tolerance key", key, TOLERANCE_KEYS)
    return _BY_KEY[key]


def methods(kind: str) -> tuple[str, ...]:
    """The methods a part program's `kind` takes (empty: the kind has one figure)."""
    if kind not in KINDS:
        raise _unknown("kind", kind, KINDS)
    return tuple(m for k, m in _BY_KIND if k == kind and m is not None)


def asked_by(kind: str, method: str | None) -> Figure:
    """The figure a part program's characteristic of `kind` and `method` measures."""
    if (kind, method) not in _BY_KIND:
        raise _unknown("kind and method", (kind, method), _BY_KIND)
    return _BY_KIND[(kind, method)]
