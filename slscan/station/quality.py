"""Verdicts and running statistics: measured values judged against the part program.

Each characteristic is decided by ISO 14253-1 under the program's decision rule
(`Characteristic.decide`: conforming, non-conforming, uncertain or not measured; see
`slscan.station.program`). The verdict of a part from its characteristics':

    fail       any characteristic is non-conforming (proven out, even allowing for U)
    error      else any could not be measured (a part is never passed on a value it does not have)
    uncertain  else any is uncertain: its value lies within U of its tolerance, so this
               measurement can neither accept nor reject the part
    pass       every characteristic is conforming (proven in, allowing for U)

An uncertain part is neither passed nor failed: the station puts it in a separate bin,
"uncertain - re-measure". The operator re-scans it (a new attempt of the same serial; the
last attempt with a verdict is the part's); if it stays uncertain, the part goes to a
more accurate instrument or to the quality engineer's decision — the station never
passes it. `slscan station --auto` exits 1 when any part is not passed.

Statistics are over the last stored cycle of each serial number with a verdict: control
charts, Nelson's rules and capability (`slscan.station.spc`) over every value of a
characteristic, whatever the part's verdict (a part out on one characteristic is a real
sample of the others, and a value out of tolerance is a real sample of its process). A
value below its detection limit is a censored value: kept, at its limit. Values are left
out of the limits and the capability only by the user (`Exclusions`: the result id and
the reason, shown in the report and exported with the values); limits may be computed
from a baseline of results only, or frozen (`ControlChart` from an earlier report). The
yield is the passed share of the judged parts (pass, fail, uncertain): an uncertain part
has not passed.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from inspection.tolerances import CONFORMING, NON_CONFORMING, NOT_MEASURED, UNCERTAIN
from slscan.station.measure import MeasurementResult
from slscan.station.program import Characteristic, PartProgram
from slscan.station.results import VERDICTS, ResultRow, ValueRecord
from slscan.station.spc import (
    DEFAULT_RULES,
    Capability,
    ControlChart,
    capability,
    individuals_limits,
    minimum_points,
    nelson,
    subgroup_limits,
)

# a part's status from its characteristics' decisions, most severe first, and its message's opening
PART_STATUS = ((NON_CONFORMING, "fail", "out of tolerance"), (NOT_MEASURED, "error", "not measured"),
               (UNCERTAIN, "uncertain", "uncertain (within U of the tolerance; re-measure)"))
# a value's `conforms` column from its decision (None: neither proven)
CONFORMS = {CONFORMING: True, NON_CONFORMING: False}
# a decision as one short word on a text line (terminal, TUI)
DECISION_MARKS = {CONFORMING: "ok", NON_CONFORMING: "OUT", UNCERTAIN: "UNCERTAIN", NOT_MEASURED: "--"}


def judge(program: PartProgram, result: MeasurementResult) -> tuple[str, list[ValueRecord], str]:
    """(status, one record per characteristic, message) of one measured part (the module
    docstring): every value decided with `Characteristic.decide` under the program's rule."""
    if not result.ok:
        return "error", [], f"not measured: {result.message}"
    records = []
    rule = program.decision_rule
    for c in program.characteristics:
        m = result.value(c.name)
        if m is None:
            decision = NOT_MEASURED
            records.append(ValueRecord(c.name, c.kind, c.face, None, c.tolerance_mm, None, 0,
                                       "not in the measurement", decision=decision, rule=rule))
            continue
        decision = c.decide(m.value_mm, m.u_mm, m.limit_mm, rule)
        records.append(ValueRecord(c.name, c.kind, c.face, m.value_mm, c.tolerance_mm, CONFORMS.get(decision),
                                   m.points, m.note, m.u_mm, m.limit_mm, decision, rule))
    for decision, status, said in PART_STATUS:
        names = [r.characteristic for r in records if r.decision == decision]
        if names:
            return status, records, f"{said}: " + ", ".join(names)
    return "pass", records, ""


@dataclass(frozen=True)
class ChartPoint:
    """One part's value of one characteristic: result id, serial, time stored, value (mm;
    None: not measured, or below its detection limit `limit_mm`), the part's verdict
    (pass, fail, uncertain, error), this value's decision (ISO 14253-1; "" when not
    stored) and why the user left it out ("": not left out)."""

    result_id: int
    serial: str
    time: dt.datetime
    value_mm: float | None
    status: str
    decision: str = ""
    limit_mm: float | None = None
    excluded: str = ""

    @property
    def censored(self) -> bool:
        """Below its detection limit: the true value is in [0, limit_mm]."""
        return self.value_mm is None and self.limit_mm is not None

    @property
    def charted_mm(self) -> float | None:
        """The value as charted: the measured value, or the detection limit of a censored one."""
        return self.limit_mm if self.censored else self.value_mm


@dataclass(frozen=True)
class CharacteristicStats:
    """One characteristic over the parts (each serial's last cycle with a verdict, in time
    order): the chart's points; `plotted` those with a value or a detection limit, and per
    plotted point (or subgroup) the chart statistic (a censored value at its limit), its
    Nelson flags and whether it went into the limits (`in_limits`: not left out by the
    user, in the baseline when one was chosen); `censored` per location point (it holds a
    value below its detection limit); the spread statistic (moving or subgroup ranges,
    NaN where a censored value makes it unknown) and its flags; the limits (None below the
    minimum sample, `limits_note` says why, or how they were obtained) and the capability
    over every value not left out by the user."""

    name: str
    tolerance_mm: float
    points: tuple[ChartPoint, ...]
    subgroup: int
    plotted: tuple[ChartPoint, ...]
    location: tuple[float, ...]
    location_flags: tuple[frozenset[int], ...]
    in_limits: tuple[bool, ...]
    censored: tuple[bool, ...]
    spread: tuple[float, ...]
    spread_flags: tuple[frozenset[int], ...]
    chart: ControlChart | None
    capability: Capability | None
    limits_note: str = ""
    rules: tuple[int, ...] = DEFAULT_RULES

    @property
    def n(self) -> int:
        """Parts with a value or a detection limit."""
        return len(self.plotted)

    @property
    def values_mm(self) -> list[float]:
        """The charted values (a censored one at its limit), in time order."""
        return [v for p in self.plotted if (v := p.charted_mm) is not None]  # every plotted point has one

    @property
    def mean_mm(self) -> float | None:
        """Mean of the measured values (censored ones at their limit; the capability's
        mean treats them by maximum likelihood)."""
        return float(np.mean(self.values_mm)) if self.plotted else None

    @property
    def max_mm(self) -> float | None:
        return max(self.values_mm) if self.plotted else None

    @property
    def excluded(self) -> int:
        """Values the user left out of the limits and the capability."""
        return sum(bool(p.excluded) for p in self.plotted)

    @property
    def below_limit(self) -> int:
        """Values below their detection limit (censored)."""
        return sum(p.censored for p in self.plotted)

    @property
    def uncertain(self) -> int:
        """Values of this characteristic decided uncertain."""
        return sum(p.decision == UNCERTAIN for p in self.plotted)

    @property
    def not_measured(self) -> int:
        return len(self.points) - len(self.plotted)


@dataclass(frozen=True)
class RunningStats:
    """Parts with a verdict (last cycle per serial), how many passed, failed, were
    uncertain or not measured, and per characteristic."""

    parts: int
    passed: int
    failed: int
    errors: int
    characteristics: tuple[CharacteristicStats, ...]
    uncertain: int = 0

    @property
    def yield_percent(self) -> float | None:
        judged = self.passed + self.failed + self.uncertain
        return 100.0 * self.passed / judged if judged else None


def latest_per_serial(rows: Sequence[ResultRow]) -> list[ResultRow]:
    """The last cycle with a verdict (pass, fail, uncertain, error) of each serial, oldest first."""
    last: dict[str, ResultRow] = {}
    for r in rows:
        if r.status in VERDICTS:
            last.pop(r.serial, None)
            last[r.serial] = r
    return list(last.values())


def chart_series(program: PartProgram, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]],
                 exclusions: Mapping[int, str] | None = None) -> dict[str, list[ChartPoint]]:
    """Per characteristic, every part (each serial's last cycle with a verdict) in time
    order, with its value, or its detection limit, or neither when that characteristic
    was not measured; `exclusions` result id -> the user's reason to leave it out."""
    out: dict[str, list[ChartPoint]] = {c.name: [] for c in program.characteristics}
    for r in latest_per_serial(rows):
        got = {v.characteristic: v for v in values.get(r.id, [])}
        why = (exclusions or {}).get(r.id, "")
        for name, series in out.items():
            v = got.get(name)
            series.append(ChartPoint(r.id, r.serial, r.finished_at or r.started_at, v.value_mm if v else None,
                                     r.status, (v.decision or "") if v else "", v.limit_mm if v else None, why))
    return out


def characteristic_stats(c: Characteristic, points: Sequence[ChartPoint], subgroup: int = 1, *,
                         rules: Sequence[int] = DEFAULT_RULES, frozen: ControlChart | None = None,
                         baseline: Collection[int] | None = None, frozen_source: str = "") -> CharacteristicStats:
    """Control chart and capability of one characteristic (see `slscan.station.spc`):
    limits from the values the user did not leave out (of the `baseline` result ids only,
    when given), or the `frozen` ones; the capability over every value not left out."""
    plotted = [p for p in points if p.charted_mm is not None]
    x = np.array([p.charted_mm for p in plotted], dtype=float)
    cens = np.array([p.censored for p in plotted], dtype=bool)
    kept = np.array([not p.excluded for p in plotted], dtype=bool)
    use = kept & np.array([baseline is None or p.result_id in baseline for p in plotted], dtype=bool)
    if subgroup == 1:
        location, location_cens, in_limits = x, cens, use
        spread = np.where(cens[1:] | cens[:-1], np.nan, np.abs(np.diff(x)))
        groups = None
    else:
        k = len(x) // subgroup
        groups = x[:k * subgroup].reshape(k, subgroup)
        group_cens = cens[:k * subgroup].reshape(k, subgroup)
        location, location_cens = groups.mean(axis=1), np.any(group_cens, axis=1)
        in_limits = use[:k * subgroup].reshape(k, subgroup).all(axis=1)
        spread = np.where(location_cens, np.nan, np.ptp(groups, axis=1))
    need = minimum_points(subgroup)
    unit = "values" if subgroup == 1 else f"subgroups of {subgroup}"
    chart, note = frozen, f"limits frozen ({frozen_source or 'given'})" if frozen is not None else ""
    if frozen is None:
        have = int(in_limits.sum())
        if use.any() and cens[use].all():
            note = (f"no limits: all {int(use.sum())} values below their detection limit (<= {x[use].max():.4f} mm), "
                    "no spread to estimate: the process is well inside the tolerance")
        elif have < need:
            note = f"no limits: {have} {unit}, limits need {need} (AIAG minimum)"
        else:
            try:
                chart = (individuals_limits(x[use], cens[use]) if groups is None
                         else subgroup_limits(groups[in_limits], group_cens[in_limits]))
                note = f"limits from {have} {unit}" + (" of the baseline" if baseline is not None else "")
            except ValueError as exc:  # too few ranges of measured values among them
                note = f"no limits: {exc}"
    none: frozenset[int] = frozenset()
    location_flags = [frozenset(f) for f in nelson(location, chart.location, rules)] if chart else \
        [none] * len(location)
    spread_flags = [frozenset({1}) if chart and r > chart.spread.ucl else none for r in spread]
    cap = capability(x[kept], c.tolerance_mm, chart.sigma_within, cens[kept], chart.dof) if chart else None
    return CharacteristicStats(c.name, c.tolerance_mm, tuple(points), subgroup, tuple(plotted),
                               tuple(float(v) for v in location), tuple(location_flags),
                               tuple(bool(b) for b in in_limits), tuple(bool(b) for b in location_cens),
                               tuple(float(v) for v in spread), tuple(spread_flags), chart, cap, note, tuple(rules))


@dataclass(frozen=True)
class SpcOptions:
    """The user's choices for the statistics: result id -> reason for values left out,
    the Nelson rules, the baseline result ids the limits come from (None: every value),
    and frozen limits per characteristic name with where they came from."""

    exclusions: Mapping[int, str] = dataclasses.field(default_factory=dict)
    rules: tuple[int, ...] = DEFAULT_RULES
    baseline: frozenset[int] | None = None
    frozen: Mapping[str, ControlChart] = dataclasses.field(default_factory=dict)
    frozen_source: str = ""


SPC_DEFAULTS = SpcOptions()  # nothing left out, the default rules, limits from every value


def running_stats(program: PartProgram, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]],
                  options: SpcOptions = SPC_DEFAULTS) -> RunningStats:
    """Statistics of the program's parts from stored results (`rows` of this program)."""
    parts = latest_per_serial(rows)
    series = chart_series(program, rows, values, options.exclusions)
    chars = tuple(characteristic_stats(c, series[c.name], program.subgroup_size, rules=options.rules,
                                       frozen=options.frozen.get(c.name), baseline=options.baseline,
                                       frozen_source=options.frozen_source)
                  for c in program.characteristics)
    count = {s: sum(r.status == s for r in parts) for s in VERDICTS}
    return RunningStats(len(parts), count["pass"], count["fail"], count["error"], chars, count["uncertain"])
