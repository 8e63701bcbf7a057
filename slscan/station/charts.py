"""Control charts: PNG images drawn with matplotlib (for the HTML report) and a Rerun series.

Per characteristic, one figure (see `slscan.station.spc`): left, the individuals (or
subgroup means) over the moving ranges (or subgroup ranges), sharing the part axis (whole
numbers), with the centre lines, the control limits and the tolerance; right, the
distribution of the values with the tolerance and the fitted normal and Weibull densities,
and under it the legend, where it covers no point. Values in the limits are blue dots;
values below their detection limit are hollow down-triangles at the limit (the true value
is below); values the user left out are grey crosses; parts where the characteristic was not
measured grey ticks on the axis; a value decided uncertain (within its U of the tolerance,
ISO 14253-1) is ringed by a purple triangle; a point flagged by a Nelson rule is ringed in
orange with the rule numbers. Without limits (too few values) the panel says so. The title
carries Cp/Cpk and Pp/Ppk with their 95 % intervals, the model read and the warnings.

The station-level Rerun recording gets every stored value as a scalar on the `scan`
timeline (the result id as the sequence number), beside its tolerance:

    metrics/control/<characteristic>/value_mm        the measured value (mm)
    metrics/control/<characteristic>/below_limit_mm  a value below its detection limit: that limit (mm)
    metrics/control/<characteristic>/u_mm            its expanded uncertainty U (k = 2, mm), when known
    metrics/control/<characteristic>/tolerance_mm    the upper limit (mm)
"""

from __future__ import annotations

import hashlib
import os
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from inspection.tolerances import UNCERTAIN
from scanner.session_lock import folder_lock
from scanner.session_recording import SessionRecording
from slscan.station.paths import child
from slscan.station.program import Characteristic, PartProgram
from slscan.station.quality import CharacteristicStats, RunningStats, latest_per_serial
from slscan.station.results import ResultRow, ValueRecord

FIGURE_IN = (11.0, 5.4)  # width, height in inches; at DPI: 1100 x 540 px
DPI = 100
PNG_FAST = {"compress_level": 3}  # zlib level 3: the same pixels, a 5 % larger file, encoded in half the time of 6
_BLUE, _RED, _GREY, _ORANGE, _GREEN, _PURPLE = "#1f5fa8", "#c01818", "#8a8a8a", "#e07b00", "#1a7a1a", "#7b2fbf"


def capability_lines(s: CharacteristicStats) -> list[str]:
    """Cp/Cpk, Pp/Ppk with their 95 % intervals, the model read, and the warning."""
    cap = s.capability
    if cap is None:
        return ["capability: none (no limits)" if s.chart is None else "capability: none (no spread)"]
    lines = [f"Cp {cap.cp.text()}  Cpk {cap.cpk.text()}  Pp {cap.pp.text()}  Ppk {cap.ppk.text()} (normal, 95 %, "
             f"n = {cap.n}" + (f", {cap.censored} below the detection limit" if cap.censored else "") + ")"]
    if cap.model == "Weibull" and cap.weibull_ppk is not None and cap.weibull_pp is not None:
        lines.append(f"read the Weibull model: Pp {cap.weibull_pp.text()}  Ppk {cap.weibull_ppk.text()}")
    return lines + ([f"WARNING: {cap.warning}"] if cap.warning else [])


def _xy(xs: Sequence[int], ys: Sequence[float], keep: Sequence[bool]) -> tuple[list[int], list[float]]:
    return [a for a, k in zip(xs, keep) if k], [y for y, k in zip(ys, keep) if k]


def _points(ax: Any, xs: list[int], ys: Sequence[float], *, in_limits: Sequence[bool], censored: Sequence[bool],
            flags: Sequence[frozenset[int]], limited: bool) -> None:
    """The chart's points by kind (module docstring), their connecting line and the rule
    flags; `limited`: the chart has limits (the values' label says they are in them)."""
    ax.plot(xs, ys, color=_GREY, linewidth=0.8, zorder=1)
    measured = [b and not c for b, c in zip(in_limits, censored)]
    ax.scatter(*_xy(xs, ys, measured), s=18, color=_BLUE, zorder=3,
               label="value (in the limits)" if limited else "value")
    below = [b and c for b, c in zip(in_limits, censored)]
    if any(below):
        ax.scatter(*_xy(xs, ys, below), s=34, marker="v", facecolors="none", edgecolors=_BLUE, linewidths=1.2,
                   zorder=3, label="below its detection limit (at the limit)")
    if not all(in_limits):
        ax.scatter(*_xy(xs, ys, [not b for b in in_limits]), s=30, marker="x", color=_GREY, zorder=3,
                   label="not in the limits (left out by the user, or outside the baseline)")
    for a, y, f in zip(xs, ys, flags):
        if f:
            ax.scatter([a], [y], s=110, facecolors="none", edgecolors=_ORANGE, linewidths=1.5, zorder=4)
            ax.annotate(",".join(str(r) for r in sorted(f)), (a, y), textcoords="offset points", xytext=(6, 6),
                        color=_ORANGE, fontsize=8)


def _limit_lines(ax: Any, limits: Any) -> None:
    """Centre and control limits, labelled at the right (none: the title says why)."""
    if limits is None:
        return
    ax.axhline(limits.centre, color=_GREEN, linewidth=1)
    for v in (limits.lcl, limits.ucl):
        ax.axhline(v, color=_GREEN, linestyle="--", linewidth=1)
    lcl = f"LCL {limits.lcl:.4f}" + (" (natural bound)" if limits.lcl_clipped else "")
    for v, text, va in ((limits.ucl, f"UCL {limits.ucl:.4f}", "bottom"), (limits.lcl, lcl, "top")):
        ax.annotate(text, (1, v), xycoords=("axes fraction", "data"), xytext=(-4, 2 if va == "bottom" else -2),
                    textcoords="offset points", ha="right", va=va, fontsize=7, color=_GREEN)


def _distribution(ax: Any, c: Characteristic, s: CharacteristicStats) -> None:
    """Histogram of the values in the capability (censored ones at their limit, hatched),
    the tolerance, and the two fitted densities."""
    from scipy import stats

    keep = [not p.excluded for p in s.plotted]
    x = np.array([p.charted_mm for p, k in zip(s.plotted, keep) if k], float)
    cens = np.array([p.censored for p, k in zip(s.plotted, keep) if k], bool)
    hi = max(c.tolerance_mm, float(x.max()) if len(x) else 0.0) * 1.08
    bins = np.linspace(0.0, hi, 25)
    if len(x):
        ax.hist(x[~cens], bins=bins, orientation="horizontal", color=_BLUE, alpha=0.55, density=False)
        if cens.any():
            ax.hist(x[cens], bins=bins, orientation="horizontal", facecolor="none", edgecolor=_BLUE, hatch="///")
    ax.axhline(c.tolerance_mm, color=_RED, linewidth=1.5)
    cap = s.capability
    if cap is not None and len(x):
        y = np.linspace(0.0, hi, 200)
        scale = len(x) * (bins[1] - bins[0])  # density -> count per bin
        ax.plot(stats.norm.pdf(y, cap.mean, cap.sigma_overall) * scale, y, color=_GREEN, linewidth=1.2,
                label="normal fit" + (" (read)" if cap.model == "normal" else ""))
        if cap.weibull_shape is not None:
            ax.plot(stats.weibull_min.pdf(y, cap.weibull_shape, 0, cap.weibull_scale) * scale, y, color=_PURPLE,
                    linewidth=1.2, linestyle="--", label="Weibull fit" + (" (read)" if cap.model == "Weibull" else ""))
    ax.set_xlabel("values per bin", fontsize=8)
    ax.set_title(cap.normality if cap is not None else "distribution", fontsize=7)
    ax.tick_params(labelsize=7)
    ax.grid(True, color="#dddddd", linewidth=0.6)


def draw_chart(c: Characteristic, s: CharacteristicStats) -> Any:
    """The control chart figure of one characteristic (matplotlib, not shown)."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=FIGURE_IN, dpi=DPI, layout="constrained")
    grid = fig.add_gridspec(2, 2, width_ratios=(3.2, 1), height_ratios=(2, 1))
    top = fig.add_subplot(grid[0, 0])
    bottom = fig.add_subplot(grid[1, 0], sharex=top)
    dist = fig.add_subplot(grid[0, 1], sharey=top)
    legend_cell = fig.add_subplot(grid[1, 1])
    legend_cell.axis("off")
    chart = s.chart
    if s.subgroup == 1:
        x = [i + 1 for i, p in enumerate(s.points) if p.charted_mm is not None]
        spread_x = x[1:]
        names = ("value (mm)", "moving range (mm)")
        missing = [i + 1 for i, p in enumerate(s.points) if p.charted_mm is None]
    else:
        x = list(range(1, len(s.location) + 1))
        spread_x = x
        names = (f"mean of {s.subgroup} (mm)", f"range of {s.subgroup} (mm)")
        missing = []
    _points(top, x, s.location, in_limits=s.in_limits, censored=s.censored, flags=s.location_flags,
            limited=chart is not None)
    _limit_lines(top, chart.location if chart else None)
    known = [not np.isnan(r) for r in s.spread]
    _points(bottom, spread_x, s.spread, in_limits=known, censored=[False] * len(s.spread), flags=s.spread_flags,
            limited=chart is not None)
    _limit_lines(bottom, chart.spread if chart else None)
    if s.subgroup == 1 and s.uncertain:
        top.scatter([a for a, p in zip(x, s.plotted) if p.decision == UNCERTAIN],
                    [v for v, p in zip(s.values_mm, s.plotted) if p.decision == UNCERTAIN], s=60, marker="^",
                    facecolors="none", edgecolors=_PURPLE, linewidths=1.4, zorder=5,
                    label="uncertain: within U of the tolerance (re-measure)")
    top.axhline(c.tolerance_mm, color=_RED, linewidth=1.5, label=f"tolerance {c.tolerance_mm:.3f} mm")
    if chart is not None:
        frozen = " (frozen)" if s.limits_note.startswith("limits frozen") else ""
        top.plot([], [], color=_GREEN, linestyle="--", label="control limits" + frozen)
    top.set_ylim(bottom=0.0)
    if missing:
        top.plot(missing, [0.0] * len(missing), "|", color=_GREY, markersize=12, label="not measured",
                 clip_on=False)
    for ax, name in ((top, names[0]), (bottom, names[1])):
        ax.grid(True, color="#dddddd", linewidth=0.6)
        ax.set_ylabel(name)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    top.tick_params(labelbottom=False)
    bottom.set_xlabel("part (each serial's last cycle, in time order)" if s.subgroup == 1 else "subgroup")
    _distribution(dist, c, s)
    dist.tick_params(labelleft=False)
    handles = top.get_legend_handles_labels()
    more = dist.get_legend_handles_labels()
    flagged = ([top.scatter([], [], s=110, facecolors="none", edgecolors=_ORANGE, linewidths=1.5)],
               [f"flagged by a Nelson rule (rules used: {','.join(map(str, s.rules))})"])
    legend_cell.legend([*handles[0], *more[0], *flagged[0]], [*handles[1], *more[1], *flagged[1]],
                       loc="upper left", fontsize=7, frameon=False)
    kind = "individuals / moving range" if s.subgroup == 1 else f"X-bar / R (subgroups of {s.subgroup})"
    head = f"{c.name}: {c.label} - {kind}; {s.limits_note}"
    fig.suptitle("\n".join([head] + capability_lines(s)), fontsize=9)
    return fig


def _write_png(fig: Any, path: Path) -> None:
    """The figure as a PNG file with the pixels `savefig` gives, for about 10 % less: the
    constrained layout done, then one draw (`savefig` draws twice with a layout engine,
    the first time only to lay out), encoded at `PNG_FAST`."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.image import imsave

    canvas = FigureCanvasAgg(fig)
    fig.get_layout_engine().execute(fig)
    fig.set_layout_engine("none")
    canvas.draw()
    imsave(path, canvas.buffer_rgba(), format="png", dpi=fig.dpi, pil_kwargs=PNG_FAST)


def _stamp(path: Path) -> tuple[int, int, int] | None:
    """The file's inode, size and modification time (ns); None when it is not there."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


# chart file -> (digest of the characteristic and statistics it shows, its stamp) as this process wrote it
_DRAWN: dict[Path, tuple[bytes, tuple[int, int, int] | None]] = {}


def write_charts(folder: Path, program: PartProgram, stats: RunningStats) -> dict[str, Path]:
    """One PNG per characteristic in `folder` (each written atomically; names made safe);
    returns name -> file. A file this process wrote from the same characteristic and
    statistics, and nobody replaced since, is kept, not drawn again (about 0.3 s a chart):
    the station rewrites the report after every stored cycle, also after one that changes
    no chart (aborted), and `--auto` once more after its last cycle."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for c, s in zip(program.characteristics, stats.characteristics):
        path = child(folder, c.name, ".png")
        digest = hashlib.sha256(repr((c, s)).encode()).digest()
        if _DRAWN.get(path) != (digest, _stamp(path)):
            tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
            _write_png(draw_chart(c, s), tmp)
            tmp.replace(path)
            _DRAWN[path] = digest, _stamp(path)
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
                if v.u_mm is not None:
                    scalars[control_metric(v.characteristic, "u_mm")] = v.u_mm
            elif v.limit_mm is not None:
                scalars[control_metric(v.characteristic, "below_limit_mm")] = v.limit_mm
            if v.value_mm is not None or v.limit_mm is not None:
                scalars[control_metric(v.characteristic, "tolerance_mm")] = v.tolerance_mm
        if scalars:
            self.rec.log_metrics(scalars, scan=result_id)

    def log_history(self, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]]) -> None:
        """Earlier parts from the results database (each serial's last cycle), so the
        charts start with the history."""
        for r in latest_per_serial(rows):
            self.log(r.id, values.get(r.id, []))
