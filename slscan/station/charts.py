"""Control charts: each characteristic's value per part over time, with its tolerance line.

Two outputs from the same series: PNG images drawn with OpenCV (for the HTML report), and
a station-level Rerun recording where every stored value is a scalar on the `scan`
timeline (the result id as the sequence number), beside its tolerance:

    metrics/control/<characteristic>/value_mm        the measured value (mm)
    metrics/control/<characteristic>/tolerance_mm    the upper limit (mm)
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from scanner.session_recording import SessionRecording
from slscan.station.program import Characteristic, PartProgram
from slscan.station.quality import latest_per_serial
from slscan.station.results import ResultRow, ValueRecord

CHART_SIZE = (960, 320)  # width, height in px
_MARGIN = (80, 20, 40, 50)  # left, right, top, bottom
_WHITE, _GREY, _BLACK = (255, 255, 255), (200, 200, 200), (40, 40, 40)
_RED, _GREEN, _BLUE = (40, 40, 220), (40, 160, 40), (200, 110, 30)  # BGR


@dataclass(frozen=True)
class ChartPoint:
    """One part's value of one characteristic: result id, serial, time stored, value (mm)."""

    result_id: int
    serial: str
    time: dt.datetime
    value_mm: float
    conforms: bool


def chart_series(program: PartProgram, rows: Sequence[ResultRow],
                 values: dict[int, list[ValueRecord]]) -> dict[str, list[ChartPoint]]:
    """Per characteristic, the measured values of each serial's last cycle, in time order."""
    out: dict[str, list[ChartPoint]] = {c.name: [] for c in program.characteristics}
    for r in latest_per_serial(rows):
        for v in values.get(r.id, []):
            if v.characteristic in out and v.value_mm is not None:
                out[v.characteristic].append(ChartPoint(r.id, r.serial, r.finished_at or r.started_at, v.value_mm,
                                                        bool(v.conforms)))
    return out


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.45, color: tuple[int, int, int] = _BLACK,
          right: bool = False) -> None:
    if right:
        (w, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        org = (org[0] - w, org[1])
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def draw_chart(c: Characteristic, points: Sequence[ChartPoint], size: tuple[int, int] = CHART_SIZE) -> np.ndarray:
    """A BGR control chart: value per part (green conforming, red not), the tolerance as a
    red line, the mean as a blue line, axes in mm; time of the first and last part below."""
    w, h = size
    left, right, top, bottom = _MARGIN
    img = np.full((h, w, 3), _WHITE, np.uint8)
    vals = np.array([p.value_mm for p in points], dtype=float)
    y_max = max(c.tolerance_mm * 1.25, float(vals.max()) * 1.1 if len(vals) else 0.0)
    x0, x1, y0, y1 = left, w - right, h - bottom, top

    def y_of(v: float) -> int:
        return int(round(y0 - (y0 - y1) * v / y_max))

    def x_of(i: int) -> int:
        return int(round(x0 + (x1 - x0) * (i + 0.5) / max(len(points), 1)))

    for k in range(6):  # grid and y labels
        v = y_max * k / 5
        cv2.line(img, (x0, y_of(v)), (x1, y_of(v)), _GREY, 1)
        _text(img, f"{v:.3f}", (x0 - 6, y_of(v) + 4), right=True)
    cv2.rectangle(img, (x0, y1), (x1, y0), _BLACK, 1)
    tol_y = y_of(c.tolerance_mm)
    cv2.line(img, (x0, tol_y), (x1, tol_y), _RED, 2)
    _text(img, f"tolerance {c.tolerance_mm:.3f} mm", (x1 - 4, tol_y - 6), color=_RED, right=True)
    if len(vals):
        mean_y = y_of(float(vals.mean()))
        cv2.line(img, (x0, mean_y), (x1, mean_y), _BLUE, 1, cv2.LINE_AA)
        _text(img, f"mean {vals.mean():.4f} mm", (x0 + 6, mean_y - 6), color=_BLUE)
        xy = [(x_of(i), y_of(v)) for i, v in enumerate(vals)]
        if len(xy) > 1:
            cv2.polylines(img, [np.array(xy, np.int32)], False, _GREY, 1, cv2.LINE_AA)
        for p, (x, y) in zip(points, xy):
            cv2.circle(img, (x, y), 5, _GREEN if p.conforms else _RED, -1, cv2.LINE_AA)
        _text(img, f"{points[0].time:%Y-%m-%d %H:%M:%S}", (x0, y0 + 18))
        _text(img, f"{points[-1].time:%Y-%m-%d %H:%M:%S}  ({len(points)} parts)", (x1, y0 + 18), right=True)
    else:
        _text(img, "no measured parts yet", (x0 + 10, (y0 + y1) // 2))
    _text(img, f"{c.name}: {c.label}", (x0, top - 10), 0.55)
    _text(img, "mm", (8, top - 10))
    return img


def write_charts(folder: Path, program: PartProgram, series: dict[str, list[ChartPoint]]) -> dict[str, Path]:
    """One PNG per characteristic in `folder`; returns name -> file."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for c in program.characteristics:
        path = folder / f"{c.name}.png"
        if not cv2.imwrite(str(path), draw_chart(c, series[c.name])):
            raise OSError(f"{path}: could not write the chart image")
        out[c.name] = path
    return out


def control_metric(name: str, what: str) -> str:
    """The metric name of a characteristic's chart series (under `metrics/`)."""
    return f"control/{name}/{what}"


class ChartRecording:
    """The control charts as a Rerun recording (`<path>`, written as `.part` until closed)."""

    def __init__(self, path: Path, program: PartProgram, recording_id: str) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.program = program
        self.rec = SessionRecording(path, recording_id, send_blueprint=False)

    def __enter__(self) -> ChartRecording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.rec.close()

    def log(self, result_id: int, values: Sequence[ValueRecord]) -> None:
        """One part's measured values at `scan` = its result id, with their tolerances."""
        scalars = {}
        for v in values:
            if v.value_mm is not None:
                scalars[control_metric(v.characteristic, "value_mm")] = v.value_mm
                scalars[control_metric(v.characteristic, "tolerance_mm")] = v.tolerance_mm
        if scalars:
            self.rec.log_metrics(scalars, scan=result_id)

    def log_history(self, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]]) -> None:
        """Earlier parts from the results database (each serial's last cycle), so the
        charts start with the history."""
        for r in latest_per_serial(rows):
            self.log(r.id, values.get(r.id, []))
