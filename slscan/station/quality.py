"""Verdicts and running statistics: measured values judged against the part program.

The verdict of a part: `fail` when any characteristic is out of tolerance, else `error`
when any could not be measured (a part is never passed on a value it does not have), else
`pass`. Statistics are over the last stored cycle of each serial number with a verdict:
control charts with limits from the parts that passed, Western Electric rules and
capability (`slscan.station.spc`).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from slscan.station.measure import MeasurementResult
from slscan.station.program import Characteristic, PartProgram
from slscan.station.results import ResultRow, ValueRecord
from slscan.station.spc import (
    MIN_LIMIT_POINTS,
    Capability,
    ControlChart,
    capability,
    individuals_limits,
    subgroup_limits,
    western_electric,
)


def judge(program: PartProgram, result: MeasurementResult) -> tuple[str, list[ValueRecord], str]:
    """(status, one record per characteristic, message) of one measured part."""
    if not result.ok:
        return "error", [], f"not measured: {result.message}"
    records = []
    for c in program.characteristics:
        m = result.value(c.name)
        value = None if m is None else m.value_mm
        note = "not in the measurement" if m is None else m.note
        records.append(ValueRecord(c.name, c.kind, c.face, value, c.tolerance_mm,
                                   None if value is None else c.conforms(value), 0 if m is None else m.points, note))
    bad = [r.characteristic for r in records if r.conforms is False]
    missing = [r.characteristic for r in records if r.conforms is None]
    if bad:
        return "fail", records, "out of tolerance: " + ", ".join(bad)
    if missing:
        return "error", records, "not measured: " + ", ".join(missing)
    return "pass", records, ""


@dataclass(frozen=True)
class ChartPoint:
    """One part's value of one characteristic: result id, serial, time stored, value (mm;
    None: not measured) and the part's verdict (pass, fail, error)."""

    result_id: int
    serial: str
    time: dt.datetime
    value_mm: float | None
    status: str


@dataclass(frozen=True)
class CharacteristicStats:
    """One characteristic over the parts (each serial's last cycle with a verdict, in time
    order): the chart's points; `plotted` the measured ones, and per plotted point (or
    subgroup) the chart statistic, its Western Electric flags and whether it is in the
    baseline (every part in it passed); the spread statistic (moving or subgroup ranges)
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
        return sum(p.status != "pass" for p in self.plotted)

    @property
    def not_measured(self) -> int:
        return len(self.points) - len(self.plotted)


@dataclass(frozen=True)
class RunningStats:
    """Parts with a verdict (last cycle per serial), how many passed, and per characteristic."""

    parts: int
    passed: int
    failed: int
    errors: int
    characteristics: tuple[CharacteristicStats, ...]

    @property
    def yield_percent(self) -> float | None:
        judged = self.passed + self.failed
        return 100.0 * self.passed / judged if judged else None


def latest_per_serial(rows: Sequence[ResultRow]) -> list[ResultRow]:
    """The last cycle with a verdict (pass, fail, error) of each serial, oldest first."""
    last: dict[str, ResultRow] = {}
    for r in rows:
        if r.status in ("pass", "fail", "error"):
            last.pop(r.serial, None)
            last[r.serial] = r
    return list(last.values())


def chart_series(program: PartProgram, rows: Sequence[ResultRow],
                 values: dict[int, list[ValueRecord]]) -> dict[str, list[ChartPoint]]:
    """Per characteristic, every part (each serial's last cycle with a verdict) in time
    order, with its value or None when that characteristic was not measured."""
    out: dict[str, list[ChartPoint]] = {c.name: [] for c in program.characteristics}
    for r in latest_per_serial(rows):
        got = {v.characteristic: v.value_mm for v in values.get(r.id, [])}
        for name, series in out.items():
            series.append(ChartPoint(r.id, r.serial, r.finished_at or r.started_at, got.get(name), r.status))
    return out


def characteristic_stats(c: Characteristic, points: Sequence[ChartPoint], subgroup: int = 1) -> CharacteristicStats:
    """Control chart and capability of one characteristic (see `slscan.station.spc`)."""
    plotted = [p for p in points if p.value_mm is not None]
    x = np.array([p.value_mm for p in plotted], dtype=float)
    ok = np.array([p.status == "pass" for p in plotted], dtype=bool)
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
    count = {s: sum(r.status == s for r in parts) for s in ("pass", "fail", "error")}
    return RunningStats(len(parts), count["pass"], count["fail"], count["error"], chars)
