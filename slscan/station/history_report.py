"""The station's HTML report for one part program: running statistics, the control charts
(PNG files beside the page) and every stored cycle with its values and session folder."""

from __future__ import annotations

import datetime as dt
import html
from pathlib import Path
from typing import Sequence

from scanner import __version__
from scanner.session import write_atomic
from slscan.station.charts import chart_series, write_charts
from slscan.station.program import PartProgram
from slscan.station.quality import running_stats
from slscan.station.results import ResultRow, ValueRecord

REPORT_FILE = "report.html"
_STYLE = """body{font-family:sans-serif;margin:1.5em;color:#222}table{border-collapse:collapse;margin:.5em 0 1.5em}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}th{background:#f0f0f0}td.l,th.l{text-align:left}
.pass{color:#1a7a1a;font-weight:bold}.fail{color:#c01818;font-weight:bold}.error,.aborted,.incomplete,
.in_progress{color:#b06000;font-weight:bold}img{display:block;margin:.3em 0 1em;max-width:100%}"""


def _f(v: float | None, digits: int = 4) -> str:
    return "" if v is None else f"{v:.{digits}f}"


def _cell(text: str, cls: str = "") -> str:
    return f"<td class='{cls}'>{html.escape(text)}</td>"


def write_report(folder: Path, program: PartProgram, rows: Sequence[ResultRow],
                 values: dict[int, list[ValueRecord]], source: str) -> Path:
    """Write `folder/report.html` and `folder/charts/*.png`; returns the page's path.
    `source` names where the results came from (shown on the page)."""
    folder.mkdir(parents=True, exist_ok=True)
    charts = write_charts(folder / "charts", program, chart_series(program, rows, values))
    stats = running_stats(program, rows, values)
    e = html.escape
    out = [f"<!doctype html><html><head><meta charset='utf-8'><title>{e(program.name)} results</title>"
           f"<style>{_STYLE}</style></head><body>",
           f"<h1>{e(program.name)} v{e(program.version)} — results</h1>",
           f"<p>Program {e(str(program.path))} [{e(program.fingerprint)}], CAD {e(program.cad_path.name)}; results "
           f"from {e(source)}; written {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M:%S} UTC by slscan "
           f"{__version__}.</p>",
           "<h2>Running statistics</h2>",
           f"<p>{stats.parts} parts (last cycle per serial): {stats.passed} pass, {stats.failed} fail, "
           f"{stats.errors} not measured"
           + (f"; yield {stats.yield_percent:.1f} %" if stats.yield_percent is not None else "") + ".</p>",
           "<table><tr><th class='l'>characteristic</th><th>tolerance (mm)</th><th>n</th><th>mean (mm)</th>"
           "<th>std (mm)</th><th>max (mm)</th><th>Cpu</th></tr>"]
    for s in stats.characteristics:
        out.append(f"<tr>{_cell(s.name, 'l')}{_cell(_f(s.tolerance_mm, 3))}{_cell(str(s.n))}{_cell(_f(s.mean_mm))}"
                   f"{_cell(_f(s.std_mm))}{_cell(_f(s.max_mm))}{_cell(_f(s.cpu, 2))}</tr>")
    out.append("</table><h2>Control charts</h2>")
    for c in program.characteristics:
        out.append(f"<h3>{e(c.name)}</h3><img src='charts/{e(charts[c.name].name)}' alt='{e(c.name)} control chart'>")
    names = [c.name for c in program.characteristics]
    out.append("<h2>Cycles</h2><table><tr><th>id</th><th class='l'>serial</th><th>attempt</th><th class='l'>status</th>"
               + "".join(f"<th>{e(n)} (mm)</th>" for n in names)
               + "<th class='l'>finished (UTC)</th><th class='l'>operator</th><th class='l'>calibration</th>"
                 "<th class='l'>message</th><th class='l'>part folder</th></tr>")
    for r in rows:
        by_name = {v.characteristic: v for v in values.get(r.id, [])}
        cells = []
        for n in names:
            v = by_name.get(n)
            cls = "" if v is None or v.conforms is None else ("pass" if v.conforms else "fail")
            cells.append(_cell(_f(v.value_mm) if v else "", cls))
        when = f"{r.finished_at:%Y-%m-%d %H:%M:%S}" if r.finished_at else ""
        out.append(f"<tr>{_cell(str(r.id))}{_cell(r.serial, 'l')}{_cell(str(r.attempt))}"
                   f"{_cell(r.status.upper(), r.status + ' l')}{''.join(cells)}{_cell(when, 'l')}"
                   f"{_cell(r.operator, 'l')}{_cell(r.calibration_id or '', 'l')}{_cell(r.message, 'l')}"
                   f"{_cell(r.part_path, 'l')}</tr>")
    out.append("</table></body></html>\n")
    path = folder / REPORT_FILE
    write_atomic(path, "\n".join(out).encode())
    return path
