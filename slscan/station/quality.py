"""Verdicts and running statistics: measured values judged against the part program.

The verdict of a part: `fail` when any characteristic is out of tolerance, else `error`
when any could not be measured (a part is never passed on a value it does not have), else
`pass`. Statistics are over the last stored cycle of each serial number with a verdict.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from slscan.station.measure import MeasurementResult
from slscan.station.program import PartProgram
from slscan.station.results import ResultRow, ValueRecord


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
class CharacteristicStats:
    """Values (mm) of one characteristic over the parts: count, mean, standard deviation,
    maximum, and Cpu = (tolerance - mean) / 3 sigma (None below 2 values or at zero spread)."""

    name: str
    tolerance_mm: float
    n: int
    mean_mm: float | None
    std_mm: float | None
    max_mm: float | None
    cpu: float | None


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


def running_stats(program: PartProgram, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]]) -> RunningStats:
    """Statistics of the program's parts from stored results (`rows` of this program)."""
    parts = latest_per_serial(rows)
    chars = []
    for c in program.characteristics:
        vals = np.array([v.value_mm for r in parts for v in values.get(r.id, [])
                         if v.characteristic == c.name and v.value_mm is not None], dtype=float)
        n = len(vals)
        mean = float(vals.mean()) if n else None
        std = float(vals.std(ddof=1)) if n >= 2 else None
        cpu = (c.tolerance_mm - mean) / (3 * std) if mean is not None and std else None
        chars.append(CharacteristicStats(c.name, c.tolerance_mm, n, mean, std, float(vals.max()) if n else None, cpu))
    count = {s: sum(r.status == s for r in parts) for s in ("pass", "fail", "error")}
    return RunningStats(len(parts), count["pass"], count["fail"], count["error"], tuple(chars))
