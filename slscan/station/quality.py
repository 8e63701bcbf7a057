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
charts with limits from the parts that passed or were uncertain (a part proven out, or
not fully measured, is an assignable cause and left out; an uncertain value is a real
measurement of the process and stays in), Western Electric rules and capability
(`slscan.station.spc`). The yield is the passed share of the judged parts (pass, fail,
uncertain): an uncertain part has not passed.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from inspection.tolerances import CONFORMING, NON_CONFORMING, NOT_MEASURED, UNCERTAIN
from slscan.station.measure import MeasurementResult
from slscan.station.program import Characteristic, PartProgram
from slscan.station.results import VERDICTS, ResultRow, ValueRecord
from slscan.station.spc import (
    MIN_LIMIT_POINTS,
    Capability,
    ControlChart,
    capability,
    individuals_limits,
    subgroup_limits,
    western_electric,
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
    None: not measured), the part's verdict (pass, fail, uncertain, error) and this
    value's decision (ISO 14253-1; "" when not stored)."""

    result_id: int
    serial: str
    time: dt.datetime
    value_mm: float | None
    status: str
    decision: str = ""


@dataclass(frozen=True)
class CharacteristicStats:
    """One characteristic over the parts (each serial's last cycle with a verdict, in time
    order): the chart's points; `plotted` the measured ones, and per plotted point (or
    subgroup) the chart statistic, its Western Electric flags and whether it is in the
    baseline (every part in it passed or was uncertain); the spread statistic (moving or subgroup ranges)
    and its flags; the limits from the baseline (None with too few) and the capability."""

    name: str
    tolerance_mm: float
    points: tuple[ChartPoint, ...]
    subgroup: int
    plotted: tuple[ChartPoint, ...]
    location: tuple[float, ...]
    location_flags: tuple[frozenset[int], ...]
    baseline: tuple[bool, ...]
    spread: tuple[float, ...]
    spread_flags: tuple[frozenset[int], ...]
    chart: ControlChart | None
    capability: Capability | None

    @property
    def n(self) -> int:
        """Parts with a value."""
        return len(self.plotted)

    @property
    def mean_mm(self) -> float | None:
        return float(np.mean([p.value_mm for p in self.plotted])) if self.plotted else None

    @property
    def max_mm(self) -> float | None:
        return max(p.value_mm for p in self.plotted) if self.plotted else None  # type: ignore[type-var]

    @property
    def excluded(self) -> int:
        """Measured parts left out of the limits and the capability (their part failed or
        was not fully measured)."""
        return sum(not _in_baseline(p) for p in self.plotted)

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


def chart_series(program: PartProgram, rows: Sequence[ResultRow],
                 values: dict[int, list[ValueRecord]]) -> dict[str, list[ChartPoint]]:
    """Per characteristic, every part (each serial's last cycle with a verdict) in time
    order, with its value or None when that characteristic was not measured."""
    out: dict[str, list[ChartPoint]] = {c.name: [] for c in program.characteristics}
    for r in latest_per_serial(rows):
        got = {v.characteristic: v for v in values.get(r.id, [])}
        for name, series in out.items():
            v = got.get(name)
            series.append(ChartPoint(r.id, r.serial, r.finished_at or r.started_at, v.value_mm if v else None,
                                     r.status, (v.decision or "") if v else ""))
    return out


def characteristic_stats(c: Characteristic, points: Sequence[ChartPoint], subgroup: int = 1) -> CharacteristicStats:
    """Control chart and capability of one characteristic (see `slscan.station.spc`)."""
    plotted = [p for p in points if p.value_mm is not None]
    x = np.array([p.value_mm for p in plotted], dtype=float)
    ok = np.array([_in_baseline(p) for p in plotted], dtype=bool)
    chart = None
    if subgroup == 1:
        location, baseline = x, ok
        spread = np.abs(np.diff(x))
        if ok.sum() >= MIN_LIMIT_POINTS:
            chart = individuals_limits(x[ok])
    else:
        k = len(x) // subgroup
        groups, group_ok = x[:k * subgroup].reshape(k, subgroup), ok[:k * subgroup].reshape(k, subgroup).all(axis=1)
        location, baseline, spread = groups.mean(axis=1), group_ok, np.ptp(groups, axis=1)
        if group_ok.sum() >= MIN_LIMIT_POINTS:
            chart = subgroup_limits(groups[group_ok])
    none: frozenset[int] = frozenset()
    location_flags = [frozenset(f) for f in western_electric(location, chart.location)] if chart else \
        [none] * len(location)
    spread_flags = [frozenset({1}) if chart and r > chart.spread.ucl else none for r in spread]
    cap = capability(x[ok], c.tolerance_mm, chart.sigma_within) if chart else None
    return CharacteristicStats(c.name, c.tolerance_mm, tuple(points), subgroup, tuple(plotted),
                               tuple(float(v) for v in location), tuple(location_flags),
                               tuple(bool(b) for b in baseline), tuple(float(v) for v in spread), tuple(spread_flags),
                               chart, cap)


def running_stats(program: PartProgram, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]]) -> RunningStats:
    """Statistics of the program's parts from stored results (`rows` of this program)."""
    parts = latest_per_serial(rows)
    series = chart_series(program, rows, values)
    chars = tuple(characteristic_stats(c, series[c.name], program.subgroup_size) for c in program.characteristics)
    count = {s: sum(r.status == s for r in parts) for s in VERDICTS}
    return RunningStats(len(parts), count["pass"], count["fail"], count["error"], chars, count["uncertain"])


def _in_baseline(p: ChartPoint) -> bool:
    """Whether a part's value goes into the control limits and capability (module docstring)."""
    return p.status in ("pass", "uncertain")
