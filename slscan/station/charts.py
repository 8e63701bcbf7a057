"""Control charts: PNG images drawn with matplotlib (for the HTML report) and a Rerun series.

Per characteristic, one figure of two panels sharing the part axis (see
`slscan.station.spc`): the individuals (or subgroup means) with the centre line, the
control limits from the baseline and the tolerance; below, the moving ranges (or subgroup
ranges) with theirs. Parts in the baseline are blue dots, failed or partly measured parts
red crosses (shown, left out of the limits), parts where the characteristic was not
measured grey ticks on the axis; a value decided uncertain (within its U of the
tolerance, ISO 14253-1) is marked with a purple triangle; a point flagged by a Western Electric rule is ringed in
orange with the rule numbers. The title carries Cp and Cpk with their 95 % intervals and
the small-sample warning.

The station-level Rerun recording gets every stored value as a scalar on the `scan`
timeline (the result id as the sequence number), beside its tolerance:

    metrics/control/<characteristic>/value_mm        the measured value (mm)
    metrics/control/<characteristic>/u_mm            its expanded uncertainty U (k = 2, mm), when known
    metrics/control/<characteristic>/tolerance_mm    the upper limit (mm)
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Any, Sequence

from inspection.tolerances import UNCERTAIN
from scanner.session_lock import folder_lock
from scanner.session_recording import SessionRecording
from slscan.station.paths import child
from slscan.station.program import Characteristic, PartProgram
from slscan.station.quality import CharacteristicStats, RunningStats, latest_per_serial
from slscan.station.results import ResultRow, ValueRecord

FIGURE_IN = (9.6, 4.8)  # width, height in inches; at DPI: 960 x 480 px
DPI = 100
_BLUE, _RED, _GREY, _ORANGE, _GREEN, _PURPLE = "#1f5fa8", "#c01818", "#8a8a8a", "#e07b00", "#1a7a1a", "#7b2fbf"


def capability_text(s: CharacteristicStats) -> str:
    """Cp and Cpk with their intervals, and the warning, in one line."""
    cap = s.capability
    if cap is None:
        return "capability: too few parts that passed"
    text = (f"Cp {cap.cp:.2f} [{cap.cp_ci[0]:.2f}, {cap.cp_ci[1]:.2f}]  "
            f"Cpk {cap.cpk:.2f} [{cap.cpk_ci[0]:.2f}, {cap.cpk_ci[1]:.2f}] (95 %, n = {cap.n})")
    return text + (f"  WARNING: {cap.warning}" if cap.warning else "")


def draw_chart(c: Characteristic, s: CharacteristicStats) -> Any:
    """The control chart figure of one characteristic (matplotlib, not shown)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=FIGURE_IN, dpi=DPI, layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    chart = s.chart
    if s.subgroup == 1:
        x = [i + 1 for i, p in enumerate(s.points) if p.value_mm is not None]
        spread_x = x[1:]
        names = ("value (mm)", "moving range (mm)")
        missing = [i + 1 for i, p in enumerate(s.points) if p.value_mm is None]
    else:
        x = list(range(1, len(s.location) + 1))
        spread_x = x
        names = (f"mean of {s.subgroup} (mm)", f"range of {s.subgroup} (mm)")
        missing = []
    for ax, ys, flags, xs, limits in ((top, s.location, s.location_flags, x, chart.location if chart else None),
                                      (bottom, s.spread, s.spread_flags, spread_x, chart.spread if chart else None)):
        base = s.baseline if ax is top else [True] * len(ys)
        ax.plot(xs, ys, color=_GREY, linewidth=0.8, zorder=1)
        ax.scatter([a for a, b in zip(xs, base) if b], [y for y, b in zip(ys, base) if b], s=18, color=_BLUE,
                   zorder=3, label="in the limits' baseline")
        ax.scatter([a for a, b in zip(xs, base) if not b], [y for y, b in zip(ys, base) if not b], s=30,
                   marker="x", color=_RED, zorder=3, label="failed or partly measured part (not in the limits)")
        for a, y, f in zip(xs, ys, flags):
            if f:
                ax.scatter([a], [y], s=110, facecolors="none", edgecolors=_ORANGE, linewidths=1.5, zorder=4)
                ax.annotate(",".join(str(r) for r in sorted(f)), (a, y), textcoords="offset points", xytext=(6, 6),
                            color=_ORANGE, fontsize=8)
        if limits is not None:
            ax.axhline(limits.centre, color=_GREEN, linewidth=1)
            for v in (limits.lcl, limits.ucl):
                ax.axhline(v, color=_GREEN, linestyle="--", linewidth=1)
            ax.annotate(f"UCL {limits.ucl:.4f}", (1, limits.ucl), xycoords=("axes fraction", "data"),
                        xytext=(-4, 3), textcoords="offset points", ha="right", fontsize=8, color=_GREEN)
        ax.grid(True, color="#dddddd", linewidth=0.6)
        ax.set_ylabel(names[0] if ax is top else names[1])
    if s.subgroup == 1 and s.uncertain:
        top.scatter([a for a, p in zip(x, s.plotted) if p.decision == UNCERTAIN],
                    [p.value_mm for p in s.plotted if p.decision == UNCERTAIN], s=60, marker="^",
                    facecolors="none", edgecolors=_PURPLE, linewidths=1.4, zorder=5,
                    label="uncertain: within U of the tolerance (re-measure)")
    top.axhline(c.tolerance_mm, color=_RED, linewidth=1.5, label=f"tolerance {c.tolerance_mm:.3f} mm")
    if missing:
        top.plot(missing, [top.get_ylim()[0]] * len(missing), "|", color=_GREY, markersize=12,
                 label="not measured")
    top.legend(loc="upper left", fontsize=7, framealpha=0.8)
    bottom.set_xlabel("part (each serial's last cycle, in time order)" if s.subgroup == 1 else "subgroup")
    kind = "individuals / moving range" if s.subgroup == 1 else f"X-bar / R (subgroups of {s.subgroup})"
    fig.suptitle(f"{c.name}: {c.label} - {kind}\n{capability_text(s)}", fontsize=9)
    return fig


def write_charts(folder: Path, program: PartProgram, stats: RunningStats) -> dict[str, Path]:
    """One PNG per characteristic in `folder` (each written atomically; names made safe);
    returns name -> file."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for c, s in zip(program.characteristics, stats.characteristics):
        path = child(folder, c.name, ".png")
        tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
        draw_chart(c, s).savefig(tmp, format="png")
        tmp.replace(path)
        out[c.name] = path
    return out


def control_metric(name: str, what: str) -> str:
    """The metric name of a characteristic's chart series (under `metrics/`)."""
    return f"control/{name}/{what}"


class ChartRecording:
    """The control charts as a Rerun recording at `path`. While the station runs it is
    written under a name of this process's own (`control_charts.<pid>.rrd`, a live view of
    what this station measured); closing with the results history (`close(rows, values)`)
    writes `path` afresh from that history, the database's, under a folder lock, so two
    stations sharing a data folder never lose each other's parts: whichever closes last
    writes every part both stored. Closed without a history (the database unreachable),
    the own file is kept beside `path`, which is left as it was. `live=False`: written at
    `path` itself (the history's own writer)."""

    def __init__(self, path: Path, program: PartProgram, recording_id: str, *, live: bool = True) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.program = program
        self.path = path
        self.recording_id = recording_id
        self._own = path.with_name(f"{path.stem}.{os.getpid()}{path.suffix}") if live else path
        self.rec = SessionRecording(self._own, recording_id, send_blueprint=False)

    def __enter__(self) -> ChartRecording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self, rows: Sequence[ResultRow] | None = None,
              values: dict[int, list[ValueRecord]] | None = None) -> None:
        self.rec.close()
        if rows is None or self._own == self.path:
            return
        with folder_lock(self.path.parent):
            whole = self.path.with_name(f".{self.path.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}{self.path.suffix}")
            try:
                with ChartRecording(whole, self.program, self.recording_id, live=False) as history:
                    history.log_history(rows, values or {})
                whole.replace(self.path)
            finally:
                whole.unlink(missing_ok=True)
        self._own.unlink(missing_ok=True)

    def log(self, result_id: int, values: Sequence[ValueRecord]) -> None:
        """One part's measured values at `scan` = its result id, with their tolerances."""
        scalars = {}
        for v in values:
            if v.value_mm is not None:
                scalars[control_metric(v.characteristic, "value_mm")] = v.value_mm
                scalars[control_metric(v.characteristic, "tolerance_mm")] = v.tolerance_mm
                if v.u_mm is not None:
                    scalars[control_metric(v.characteristic, "u_mm")] = v.u_mm
        if scalars:
            self.rec.log_metrics(scalars, scan=result_id)

    def log_history(self, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]]) -> None:
        """Earlier parts from the results database (each serial's last cycle), so the
        charts start with the history."""
        for r in latest_per_serial(rows):
            self.log(r.id, values.get(r.id, []))
