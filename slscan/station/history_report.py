"""The station's HTML report for one part program: running statistics, control limits,
capability (Cp/Cpk, Pp/Ppk with confidence intervals, normality, the model read) and
Nelson flags per characteristic, the values the user left out and why, the control charts
(matplotlib PNG files beside the page) and every stored cycle with its values and session
folder. The page prints on A4 and Letter (tables wrap, headings stay with their content)."""

from __future__ import annotations

import datetime as dt
import html
from collections.abc import Sequence
from pathlib import Path

from inspection.report_header import HEADER_CSS, ReportHeader, file_sha256, header_html
from inspection.tolerances import CONFORMING, DECISION_RULES, NON_CONFORMING, UNCERTAIN
from scanner import __version__
from scanner.session import write_atomic
from slscan.station.calib import FACTORY_PREFIX
from slscan.station.charts import write_charts
from slscan.station.program import PartProgram
from slscan.station.quality import (
    DECISION_MARKS,
    SPC_DEFAULTS,
    CharacteristicStats,
    SpcOptions,
    latest_per_serial,
    running_stats,
)
from slscan.station.results import ResultRow, ValueRecord
from slscan.station.spc import MIN_CAPABILITY_N, MIN_INDIVIDUALS, MIN_SUBGROUPS, NELSON_RULES, Index

REPORT_FILE = "report.html"
DECISION_CLASSES = {CONFORMING: "pass", NON_CONFORMING: "fail", UNCERTAIN: "uncertain"}  # a value cell's style
_STYLE = """body{font-family:sans-serif;margin:1.5em;color:#222}table{border-collapse:collapse;margin:.5em 0 1.5em}
.scroll{overflow-x:auto;max-width:100%}
td,th{border:1px solid #ccc;padding:3px 6px;text-align:right;font-size:13px}th{background:#f0f0f0}
td.l,th.l{text-align:left}
.pass{color:#1a7a1a;font-weight:bold}.fail{color:#c01818;font-weight:bold}.error,.aborted,.incomplete,
.in_progress,.warn{color:#b06000;font-weight:bold}.uncertain{color:#7b2fbf;font-weight:bold}
img{display:block;margin:.3em 0 1em;max-width:100%}
@media print{body{margin:0;font-size:10px}.scroll{overflow:visible}table{width:100%;table-layout:auto}
td,th{font-size:8px;padding:1px 3px}td{white-space:nowrap}td.l{white-space:normal;overflow-wrap:anywhere}
thead{display:table-header-group}
tr,img{break-inside:avoid}h2,h3{break-after:avoid}}
@page{margin:12mm 10mm 14mm;@bottom-right{content:"page " counter(page) " of " counter(pages);font-size:9px}}"""


def _f(v: float | None, digits: int = 4) -> str:
    return "" if v is None else f"{v:.{digits}f}"


def _cell(text: str, cls: str = "") -> str:
    return f"<td class='{cls}'>{html.escape(text)}</td>"


def _flags(s: CharacteristicStats) -> str:
    """Which plotted points (part or subgroup numbers, 1-based) broke which rules."""
    unit = "part" if s.subgroup == 1 else "subgroup"
    hits = [f"{unit} {k + 1}: {','.join(map(str, sorted(f)))}" for k, f in enumerate(s.location_flags) if f]
    return "; ".join(hits) or "none"


def _index(i: Index | None) -> str:
    return "" if i is None else i.text()


def _table(head: list[tuple[str, str]], rows: list[str]) -> str:
    """A table with a repeated header row when printed over pages; `head` (title, class)."""
    cells = "".join(f"<th class='{c}'>{t}</th>" for t, c in head)
    return f"<div class='scroll'><table><thead><tr>{cells}</tr></thead><tbody>{''.join(rows)}</tbody></table></div>"


def _limits_table(stats: Sequence[CharacteristicStats]) -> str:
    head = [("characteristic", "l"), ("tolerance (mm)", ""), ("n", ""), ("below limit", ""), ("left out", ""),
            ("not measured", ""), ("mean (mm)", ""), ("max (mm)", ""), ("chart", "l"), ("limits", "l"),
            ("centre (mm)", ""), ("LCL (mm)", ""), ("UCL (mm)", ""), ("&sigma; within (mm)", ""),
            ("rules flagged", "l")]
    rows = []
    for st in stats:
        lim = st.chart.location if st.chart else None
        lcl = _f(lim.lcl) + (" (bound)" if lim is not None and lim.lcl_clipped else "") if lim else ""
        rows.append(f"<tr>{_cell(st.name, 'l')}{_cell(_f(st.tolerance_mm, 3))}{_cell(str(st.n))}"
                    f"{_cell(str(st.below_limit))}{_cell(str(st.excluded))}{_cell(str(st.not_measured))}"
                    f"{_cell(_f(st.mean_mm))}{_cell(_f(st.max_mm))}"
                    f"{_cell(st.chart.kind if st.chart else ('I-MR' if st.subgroup == 1 else 'Xbar-R'), 'l')}"
                    f"{_cell(st.limits_note, 'l' if st.chart else 'warn l')}"
                    f"{_cell(_f(lim.centre if lim else None))}{_cell(lcl)}{_cell(_f(lim.ucl if lim else None))}"
                    f"{_cell(_f(st.chart.sigma_within if st.chart else None, 5))}{_cell(_flags(st), 'l')}</tr>")
    return _table(head, rows)


def _capability_table(stats: Sequence[CharacteristicStats]) -> str:
    head = [("characteristic", "l"), ("n", ""), ("mean (mm)", ""), ("&sigma; overall (mm)", ""),
            ("Cp, 0..tol. [95 %]", ""), ("Cpk [95 %]", ""), ("Pp, 0..tol. [95 %]", ""), ("Ppk [95 %]", ""),
            ("normality", "l"), ("Weibull Pp / Ppk", ""), ("read", "l"), ("note", "l")]
    rows = []
    for st in stats:
        cap = st.capability
        if cap is None:
            why = st.limits_note if not st.chart else "no spread"
            rows.append(f"<tr>{_cell(st.name, 'l')}{_cell(str(st.n))}" + "<td></td>" * 8
                        + f"{_cell('none', 'l')}{_cell(why, 'warn l')}</tr>")
            continue
        weibull = f"{_index(cap.weibull_pp)} / {_index(cap.weibull_ppk)}"
        rows.append(f"<tr>{_cell(st.name, 'l')}{_cell(str(cap.n))}{_cell(_f(cap.mean))}"
                    f"{_cell(_f(cap.sigma_overall, 5))}{_cell(cap.cp.text())}{_cell(cap.cpk.text())}"
                    f"{_cell(cap.pp.text())}{_cell(cap.ppk.text())}{_cell(cap.normality, 'l')}{_cell(weibull)}"
                    f"{_cell(cap.model, 'l')}"
                    f"{_cell('; '.join(t for t in (cap.method, cap.warning) if t), 'warn l' if cap.warning else 'l')}"
                    "</tr>")
    return _table(head, rows)


def _exclusions(rows: Sequence[ResultRow], options: SpcOptions) -> str:
    if not options.exclusions:
        return "<p>No value was left out: every measured value is in the limits and the capability.</p>"
    serial = {r.id: r.serial for r in rows}
    body = [f"<tr>{_cell(str(rid))}{_cell(serial.get(rid, '(not among these results)'), 'l')}{_cell(why, 'l')}</tr>"
            for rid, why in sorted(options.exclusions.items())]
    return _table([("result id", ""), ("serial", "l"), ("reason given", "l")], body)


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
        operator=seen([r.operator for r in rows]), date=f"{dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M:%S}",
        rig=seen([r.rig for r in rows]), calibration_id=seen([r.calibration_id for r in rows]),
        calibration_date=seen(dates) or ("undated (factory geometry)" if rows and all(
            (r.calibration_id or "").startswith(FACTORY_PREFIX) for r in rows) else ""),
        software_version=seen([f"slscan {r.software_version}" for r in rows]) or f"slscan {__version__}")


def _method(program: PartProgram, options: SpcOptions) -> str:
    """How the statistics were computed, said once on the page."""
    rules = ", ".join(f"{r} ({NELSON_RULES[r]})" for r in options.rules)
    baseline = (f" Limits from the baseline of {len(options.baseline)} chosen results only."
                if options.baseline is not None else "")
    frozen = f" Limits frozen: {html.escape(options.frozen_source)}." if options.frozen else ""
    return (f"<p>Each value is decided by ISO 14253-1 under the program's rule ({html.escape(program.decision_rule)}: "
            f"{html.escape(DECISION_RULES[program.decision_rule])}): conforming, non-conforming or uncertain, with its "
            "expanded uncertainty U (k = 2) as value &plusmn; U; a figure below its detection limit is shown as "
            "&lt; limit. A part passes when every value is conforming and fails when any is non-conforming; a part "
            "with an uncertain value is <span class='uncertain'>UNCERTAIN</span>: neither passed nor failed, it is "
            "set aside to be re-measured (a new attempt of the same serial) and never passed on that measurement.</p>"
            "<p>Statistics use every measured value of a characteristic, whatever the part's verdict; values are "
            "left out only by the user (listed below with the reason). A value below its detection limit is "
            "censored: charted at its limit (hollow triangle), and in the centre, the mean and the overall &sigma; by "
            "maximum likelihood; moving ranges with a censored value are unknown and left out of &sigma; within. "
            f"Limits need {MIN_INDIVIDUALS} values (I-MR) or {MIN_SUBGROUPS} subgroups (X-bar R): fewer give none. An "
            "LCL below 0 is set to 0, the natural bound of a zone width or a height. Every characteristic has an upper "
            "limit (its tolerance) and the natural lower bound 0: Cp = tolerance / 6&sigma;<sub>within</sub>, Cpk = "
            "(tolerance &minus; mean) / 3&sigma;<sub>within</sub>; Pp and Ppk the same with "
            "&sigma;<sub>overall</sub> (the sample SD). Minitab leaves Cp and Pp out when the lower end is a "
            "natural bound; here they compare the spread with the whole band 0..tolerance, so Cpk exceeds Cp when "
            "the process sits in the band's lower half (where a form error should be). 95 % intervals "
            "(chi-squared for Cp and Pp, Bissell for Cpk and Ppk). Normality by the Anderson-Darling test; when it "
            "rejects the normal at 5 % (or, with censored values, the Weibull fits better) read the Weibull model's "
            "Pp / Ppk (ISO 22514-2 percentile method). "
            f"Fewer than {MIN_CAPABILITY_N} values: the indices are marked as too uncertain. Nelson rules used: "
            f"{rules}."
            f"{baseline}{frozen}</p>")


def write_report(folder: Path, program: PartProgram, rows: Sequence[ResultRow],
                 values: dict[int, list[ValueRecord]], source: str, options: SpcOptions = SPC_DEFAULTS) -> Path:
    """Write `folder/report.html` and `folder/charts/*.png`; returns the page's path.
    `source` names where the results came from (shown on the page)."""
    folder.mkdir(parents=True, exist_ok=True)
    stats = running_stats(program, rows, values, options)
    charts = write_charts(folder / "charts", program, stats)
    e = html.escape
    out = [f"<!doctype html><html><head><meta charset='utf-8'><title>{e(program.name)} results</title>"
           f"<style>{_STYLE}{HEADER_CSS}</style></head><body>",
           f"<h1>{e(program.name)} v{e(program.version)} — results</h1>", header_html(station_header(program, rows)),
           f"<p>Program {e(str(program.path))} [{e(program.fingerprint)}], CAD {e(program.cad_path.name)}; results "
           f"from {e(source)}; written {dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M:%S} UTC by slscan "
           f"{__version__}.</p>",
           "<section><h2>Running statistics</h2>",
           f"<p>{stats.parts} parts (last cycle per serial): {stats.passed} pass, {stats.failed} fail, "
           f"{stats.uncertain} uncertain (re-measure), {stats.errors} not measured"
           + (f"; yield {stats.yield_percent:.1f} %" if stats.yield_percent is not None else "") + ".</p>",
           _method(program, options), "</section>",
           f"<section><h2>Control limits</h2>{_limits_table(stats.characteristics)}</section>",
           f"<section><h2>Capability</h2>{_capability_table(stats.characteristics)}</section>",
           f"<section><h2>Values left out by the user</h2>{_exclusions(latest_per_serial(rows), options)}</section>",
           "<h2>Control charts</h2>"]
    for c in program.characteristics:
        out.append(f"<section id='chart-{e(charts[c.name].stem)}'><h3>{e(c.name)}</h3>"
                   f"<img src='charts/{e(charts[c.name].name)}' "
                   f"alt='{e(c.name)} control chart'></section>")
    names = [c.name for c in program.characteristics]
    out.append("<h2>Cycles</h2><div class='scroll'><table><thead><tr><th>id</th><th class='l'>serial</th>"
               "<th>attempt</th><th class='l'>status</th>" + "".join(f"<th>{e(n)} (mm)</th>" for n in names)
               + "<th class='l'>finished (UTC)</th><th class='l'>operator</th><th class='l'>calibration</th>"
                 "<th class='l'>message</th><th class='l'>part folder</th></tr></thead><tbody>")
    for r in rows:
        by_name = {v.characteristic: v for v in values.get(r.id, [])}
        cells = []
        for n in names:
            v = by_name.get(n)
            cells.append(_cell(f"{v.shown()} {DECISION_MARKS.get(v.decision, v.decision)}" if v else "",
                               DECISION_CLASSES.get(v.decision, "") if v else ""))
        when = f"{r.finished_at:%Y-%m-%d %H:%M:%S}" if r.finished_at else ""
        out.append(f"<tr>{_cell(str(r.id))}{_cell(r.serial, 'l')}{_cell(str(r.attempt))}"
                   f"{_cell(r.status.upper(), r.status + ' l')}{''.join(cells)}{_cell(when, 'l')}"
                   f"{_cell(r.operator, 'l')}{_cell(r.calibration_id or '', 'l')}{_cell(r.message, 'l')}"
                   f"{_cell(r.part_path, 'l')}</tr>")
    out.append("</tbody></table></div></body></html>\n")
    path = folder / REPORT_FILE
    write_atomic(path, "\n".join(out).encode())
    return path
