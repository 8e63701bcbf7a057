"""The station's HTML report for one part program: running statistics, control limits,
capability with its confidence intervals and Western Electric flags per characteristic,
the control charts (matplotlib PNG files beside the page) and every stored cycle with its
values and session folder."""

from __future__ import annotations

import datetime as dt
import html
from pathlib import Path
from typing import Sequence

from inspection.report_header import HEADER_CSS, ReportHeader, file_sha256, header_html
from scanner import __version__
from scanner.session import write_atomic
from slscan.station.calib import FACTORY_PREFIX
from slscan.station.charts import capability_text, write_charts
from slscan.station.program import PartProgram
from slscan.station.quality import CharacteristicStats, running_stats
from slscan.station.results import ResultRow, ValueRecord
from slscan.station.spc import MIN_CAPABILITY_N

REPORT_FILE = "report.html"
_STYLE = """body{font-family:sans-serif;margin:1.5em;color:#222}table{border-collapse:collapse;margin:.5em 0 1.5em}
table{display:block;overflow-x:auto;max-width:100%}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}th{background:#f0f0f0}td.l,th.l{text-align:left}
.pass{color:#1a7a1a;font-weight:bold}.fail{color:#c01818;font-weight:bold}.error,.aborted,.incomplete,
.in_progress,.warn{color:#b06000;font-weight:bold}img{display:block;margin:.3em 0 1em;max-width:100%}"""


def _f(v: float | None, digits: int = 4) -> str:
    return "" if v is None else f"{v:.{digits}f}"


def _cell(text: str, cls: str = "") -> str:
    return f"<td class='{cls}'>{html.escape(text)}</td>"


def _flags(s: CharacteristicStats) -> str:
    """Which plotted points (part or subgroup numbers, 1-based) broke which rules."""
    unit = "part" if s.subgroup == 1 else "subgroup"
    hits = [f"{unit} {k + 1}: {','.join(map(str, sorted(f)))}" for k, f in enumerate(s.location_flags) if f]
    return "; ".join(hits) or "none"


def station_header(program: PartProgram, rows: Sequence[ResultRow]) -> ReportHeader:
    """The inspection report's header for a program's results: each field lists what its
    cycles recorded (distinct values), the program's file with its SHA-256, written now."""
    def seen(values: Sequence[str | None]) -> str:
        return ", ".join(dict.fromkeys(v for v in values if v))

    dates = [c.split("@", 1)[1][:10] for c in (r.calibration_id or "" for r in rows) if "@" in c]
    return ReportHeader(
        part=f"{program.name} — {program.description}" if program.description else program.name,
        serial=f"{len({r.serial for r in rows})} serials: " + seen([r.serial for r in rows]) if rows else "",
        program=f"{program.path} (version {program.version})", program_sha256=file_sha256(program.path),
        operator=seen([r.operator for r in rows]), date=f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M:%S}",
        rig=seen([r.rig for r in rows]), calibration_id=seen([r.calibration_id for r in rows]),
        calibration_date=seen(dates) or ("undated (factory geometry)" if rows and all(
            (r.calibration_id or "").startswith(FACTORY_PREFIX) for r in rows) else ""),
        software_version=seen([f"slscan {r.software_version}" for r in rows]) or f"slscan {__version__}")


def write_report(folder: Path, program: PartProgram, rows: Sequence[ResultRow],
                 values: dict[int, list[ValueRecord]], source: str) -> Path:
    """Write `folder/report.html` and `folder/charts/*.png`; returns the page's path.
    `source` names where the results came from (shown on the page)."""
    folder.mkdir(parents=True, exist_ok=True)
    stats = running_stats(program, rows, values)
    charts = write_charts(folder / "charts", program, stats)
    e = html.escape
    out = [f"<!doctype html><html><head><meta charset='utf-8'><title>{e(program.name)} results</title>"
           f"<style>{_STYLE}{HEADER_CSS}</style></head><body>",
           f"<h1>{e(program.name)} v{e(program.version)} — results</h1>", header_html(station_header(program, rows)),
           f"<p>Program {e(str(program.path))} [{e(program.fingerprint)}], CAD {e(program.cad_path.name)}; results "
           f"from {e(source)}; written {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M:%S} UTC by slscan "
           f"{__version__}.</p>",
           "<h2>Running statistics</h2>",
           f"<p>{stats.parts} parts (last cycle per serial): {stats.passed} pass, {stats.failed} fail, "
           f"{stats.errors} not measured"
           + (f"; yield {stats.yield_percent:.1f} %" if stats.yield_percent is not None else "") + ".</p>",
           "<p>Control limits come from the parts that passed (failed or partly measured parts are shown on the "
           "charts, marked, and left out of the limits and the capability). Every characteristic has an upper "
           "limit (its tolerance) and the natural lower bound 0: Cpk = (tolerance - mean) / 3&sigma;, Cp = "
           f"tolerance / 6&sigma;, &sigma; the within sigma of the chart; 95 % intervals. Fewer than "
           f"{MIN_CAPABILITY_N} values: the indices are marked as too uncertain. Rules: Western Electric 1 (beyond "
           "3&sigma;), 2 (2 of 3 beyond 2&sigma;), 3 (4 of 5 beyond 1&sigma;), 4 (8 on one side).</p>",
           "<table><tr><th class='l'>characteristic</th><th>tolerance (mm)</th><th>n</th><th>left out</th>"
           "<th>mean (mm)</th><th>max (mm)</th><th class='l'>chart</th><th>centre (mm)</th><th>LCL (mm)</th>"
           "<th>UCL (mm)</th><th>&sigma; within (mm)</th><th class='l'>capability</th>"
           "<th class='l'>rules flagged</th></tr>"]
    for st in stats.characteristics:
        lim = st.chart.location if st.chart else None
        out.append(f"<tr>{_cell(st.name, 'l')}{_cell(_f(st.tolerance_mm, 3))}{_cell(str(st.n))}"
                   f"{_cell(str(st.excluded + st.not_measured))}{_cell(_f(st.mean_mm))}{_cell(_f(st.max_mm))}"
                   f"{_cell(st.chart.kind if st.chart else 'too few parts', 'l')}"
                   f"{_cell(_f(lim.centre if lim else None))}{_cell(_f(lim.lcl if lim else None))}"
                   f"{_cell(_f(lim.ucl if lim else None))}"
                   f"{_cell(_f(st.chart.sigma_within if st.chart else None, 5))}"
                   f"{_cell(capability_text(st), 'warn l' if st.capability and st.capability.warning else 'l')}"
                   f"{_cell(_flags(st), 'l')}</tr>")
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
