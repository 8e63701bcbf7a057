"""The inspection report as one self-contained HTML page (images embedded as data URIs),
laid out as a metrology lab issues one and printable to PDF (`inspection.report_pdf`):

    header       part, serial, program and its SHA-256, operator, date, rig, calibration
                 id and date, software version; the overall verdict and the decision rule
    views        the part from four sides coloured by deviation on the tolerance-tied scale
                 (`inspection.deviation_colours`), colour bar in mm, callouts naming each
                 toleranced face with its values and verdicts
    table        one row per characteristic: face, characteristic, nominal, tolerance,
                 value, U (k = 2), detection limit, verdict; units in every header
    histogram    the signed deviations of every point on a face
    raw/filtered the form surface's figures beside the raw points' where they differ
    close-ups    each toleranced face in its own surface coordinates
    all figures  every face's figures (µm, value ± U or < limit) in two tables (form and
                 texture; deviations), and how to read them

Each table is in one unit, named in every header. Printed (A4 or Letter,
`inspection.report_pdf`), tables wrap and repeat their header row on each page, headings
stay with what follows them, and every page is numbered "page n of N".

Element ids (`#header`, `#verdict`, `#views`, `#characteristics`, `#histogram`,
`#raw-filtered`, `#face-<id>`, `#figures`) are what the browser test checks."""

from __future__ import annotations

import base64
import html
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from inspection.deviation_colours import ColourScale, shown_count
from inspection.figures import DEVIATION, FIGURES, FORM, figure, limited_by
from inspection.report_figures import deviation_histogram, face_closeup, part_views
from inspection.report_header import HEADER_CSS, header_html
from inspection.tolerances import DECISION_RULES
from inspection.uncertainty import Estimate

STYLE = """
body{font-family:"DejaVu Sans",Arial,sans-serif;color:#222;margin:0;background:#fff}
main{max-width:1120px;margin:0 auto;padding:16px 24px}
h1{font-size:22px;margin:8px 0}h2{font-size:17px;margin:22px 0 8px;border-bottom:1px solid #bbb}
.scroll{overflow-x:auto;max-width:100%}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}
thead{display:table-header-group}
th{background:#eef0f3}td.l,th.l{text-align:left}
.conforming{background:#d6f5d6}.non-conforming{background:#f8d0d0}.uncertain{background:#fdf0c2}
.not-measured{background:#e4e4e4}.limit{color:#666}
#verdict{font-size:18px;padding:8px 12px;border:2px solid #888;display:inline-block;margin:6px 0}
img{max-width:100%;height:auto;display:block}
.faces{display:flex;flex-wrap:wrap;gap:12px}.faces section{flex:1 1 480px;max-width:100%}
p.note,span.note{font-size:12px;color:#444}
.keep{break-inside:avoid}
@media print{main{max-width:none;padding:0}h1{font-size:18px}h2,h3{break-after:avoid}tr,img{break-inside:avoid}
.scroll{overflow:visible}table{font-size:9px;width:100%}td,th{padding:1px 3px}td{white-space:nowrap}
td.l,th,td .note{white-space:normal;overflow-wrap:break-word}
img{max-height:230mm;width:auto;max-width:100%}.faces{display:block}}
@page{margin:12mm 10mm 14mm;@bottom-right{content:"page " counter(page) " of " counter(pages);font-size:9px}}
"""


def _img(data: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def _css(verdict: str) -> str:
    return verdict.replace(" ", "-")


def _mm(x: float | None) -> str:
    return "" if x is None else f"{x:.4f}"


def _um_cell(e: Estimate | None) -> str:
    """A figure in µm for the all-figures table."""
    if e is None:
        return "<td></td>"
    if e.value is None:
        return f"<td class='limit'>&lt; {e.limit * 1e3:.1f}</td>" if e.limit is not None else "<td>n/m</td>"
    return f"<td>{e.value * 1e3:.1f} &plusmn; {e.U * 1e3:.1f}</td>"


def characteristic_rows(report: Any) -> list[dict[str, Any]]:
    """One row per toleranced characteristic: face title, characteristic, nominal (mm, 0:
    an ideal form or the nominal surface itself), tolerance, value, U, limit (mm, None
    where not known), verdict."""
    rows = []
    for r in report.faces:
        for key, (tol, verdict) in r.verdicts.items():
            limited = limited_by(key)
            e = r.form.figure(limited.name) if r.form.status == "ok" else None
            rows.append({"face": r.title, "characteristic": limited.title, "nominal_mm": 0.0, "tolerance_mm": tol,
                         "value_mm": None if e is None else e.value, "u_mm": None if e is None else e.U,
                         "limit_mm": None if e is None else e.limit, "verdict": verdict,
                         "note": "" if r.form.status == "ok" else f"{r.form.status}: {r.form.note}"})
    return rows


def _characteristics_table(rows: list[dict[str, Any]]) -> str:
    head = ("<tr><th class='l'>face</th><th class='l'>characteristic</th><th>nominal (mm)</th>"
            "<th>tolerance (mm)</th><th>measured value (mm)</th><th>U, k = 2 (mm)</th>"
            "<th>detection limit (mm)</th><th class='l'>verdict (ISO 14253-1)</th></tr>")
    body = []
    for c in rows:
        value = (_mm(c["value_mm"]) if c["value_mm"] is not None
                 else f"&lt; {_mm(c['limit_mm'])}" if c["limit_mm"] is not None
                 else f"<span class='note'>{html.escape(c['note'] or '—')}</span>")
        body.append(f"<tr><td class='l'>{html.escape(c['face'])}</td><td class='l'>{html.escape(c['characteristic'])}"
                    f"</td><td>{_mm(c['nominal_mm'])}</td><td>{_mm(c['tolerance_mm'])}</td><td>{value}</td>"
                    f"<td>{'&plusmn; ' + _mm(c['u_mm']) if c['u_mm'] is not None else ''}</td>"
                    f"<td>{_mm(c['limit_mm'])}</td><td class='l {_css(c['verdict'])}'>{html.escape(c['verdict'])}"
                    f"</td></tr>")
    return f"<div class='scroll'><table>{head}{''.join(body)}</table></div>"


def _raw_filtered(report: Any) -> str:
    """Per measured face, the form surface's figure beside the raw points' one where the
    two differ as printed (µm)."""
    pairs = [(figure(raw.raw_of), raw) for raw in FIGURES if raw.raw_of]
    rows = []
    for r in report.faces:
        m = r.form
        if m.status != "ok":
            continue
        for filtered, raw in pairs:
            a, b = _um_cell(m.figure(filtered.name)), _um_cell(m.figure(raw.name))
            if a != b:
                rows.append(f"<tr><td class='l'>{html.escape(r.title)}</td><td class='l'>{filtered.heading}</td>"
                            f"{a}{b}</tr>")
        if m.sq_raw_mm is not None and m.sq_noise_mm is not None:
            rows.append(f"<tr><td class='l'>{html.escape(r.title)}</td><td class='l'>Sq</td>{_um_cell(m.sq)}"
                        f"<td>{m.sq_raw_mm * 1e3:.1f} (noise {m.sq_noise_mm * 1e3:.1f})</td></tr>")
    if not rows:
        return "<p>The filtered and raw figures agree on every face.</p>"
    return ("<div class='scroll'><table><tr><th class='l'>face</th><th class='l'>figure</th>"
            "<th>form surface, noise removed (µm)</th><th>raw points, noise included (µm)</th></tr>"
            + "".join(rows) + "</table></div>")


def _figures_table(report: Any, group: str, last: tuple[str, Any]) -> str:
    """One table of every face's figures of `group` (µm, `inspection.figures`) with the
    `last` (header, row -> text) column."""
    shown = [f for f in FIGURES if f.group == group]
    body = "".join(
        f"<tr><td class='l'>{html.escape(r.title)}</td><td class='l'>{r.type}</td><td>{r.form.points}</td>"
        + "".join(_um_cell(r.form.figure(f.name)) for f in shown)
        + f"<td class='l'>{html.escape(last[1](r))}</td></tr>" for r in report.faces)
    return ("<div class='scroll'><table><thead><tr><th class='l'>face</th><th class='l'>type</th><th>points</th>"
            + "".join(f"<th>{f.heading} (µm)</th>" for f in shown) + f"<th class='l'>{last[0]}</th></tr></thead>"
            f"<tbody>{body}</tbody></table></div>")


def _all_figures(report: Any) -> str:
    """Every face's figures in two tables that fit a printed page: form and texture, then
    the deviations from nominal."""
    return ("<h3>Form and texture</h3>"
            + _figures_table(report, FORM, ("status", lambda r: r.form.status if r.form.status != "ok"
                                            else r.form.note or "ok"))
            + "<h3>Deviations from nominal</h3>"
            + _figures_table(report, DEVIATION, ("noise model", lambda r: r.form.noise_source or r.form.status)))


def _header(report: Any) -> str:
    return header_html(report.header, [("Scan", report.source), ("CAD model", f"{report.model} ({report.unit})"),
                                       ("Calibration uncertainty", report.calibration)])


def closeup_faces(report: Any) -> Iterable[Any]:
    """The faces that get a close-up: toleranced faces with points in their figures."""
    return [r for r in report.faces if r.verdicts and shown_count(report, r) > 0]


def _no_closeup(report: Any) -> str:
    """A line naming the toleranced faces without a close-up, and why."""
    rows = [r for r in report.faces if r.verdicts and shown_count(report, r) == 0]
    return "".join(f"<p class='note'>{html.escape(r.title)}: no close-up, no figures ({html.escape(r.form.status)}"
                   f"{': ' + html.escape(r.form.note) if r.form.note else ''}; {r.form.points} points).</p>"
                   for r in rows)


def render(report: Any, scale: ColourScale, noise_note: str, deviation_png: bytes | None = None) -> str:
    """The whole page (module docstring); `scale` the deviation colour scale of every view,
    as the recording's; `noise_note` how noise was treated, said once."""
    e = html.escape
    rows = characteristic_rows(report)
    profiles = {r.title: t for r in report.faces for k, (t, _) in r.verdicts.items() if limited_by(k).name == "profile"}
    s = report.form_settings
    closeups = [
        f"<section class='keep' id='face-{e(r.label.lstrip('#'))}'><h3>{e(r.title)}</h3>"
        f"{_img(face_closeup(report, r, scale), r.title)}<p class='note'>{shown_count(report, r)} points, those the "
        f"figures count ({r.form.points} in the table)</p></section>" for r in closeup_faces(report)]
    faces = (f"<div class='keep'><h2>Faces</h2>{_no_closeup(report)}{''.join(closeups[:1])}</div>"  # heading kept
             f"<div class='faces'>{''.join(closeups[1:])}</div>")  # with the first close-up
    camera = (f"<section class='keep'><h2>Deviation map in the camera image</h2>"
              f"{_img(deviation_png, 'deviation map in the camera image')}"
              f"<p class='note'>{e(scale.caption)}; grey: part points the figures do not use; dark: not the part."
              f"</p></section>" if deviation_png else "")
    title = report.header.part or Path(report.model).name
    return (
        f"<!doctype html><html><head><meta charset='utf-8'><title>Inspection report: {e(title)}</title>"
        f"<style>{STYLE}{HEADER_CSS}</style></head><body><main>"
        f"<h1>Inspection report: {e(title)}</h1>{_header(report)}"
        f"<p id='verdict' class='{_css(report.verdict)}'>Verdict: <b>{e(report.verdict)}</b> "
        + (f"<br><b>{e(report.status_note)}</b><br>" if report.status_note else "")
        + f"({len(rows)} characteristics; decision rule {e(report.decision_rule)}: "
        f"{e(DECISION_RULES[report.decision_rule])})</p>"
        f"<p>Registration: fitness {report.fitness:.3f}, RMSE {report.rmse_mm * 1e3:.1f} µm "
        f"({e(report.registration.method)}); {report.assigned_points} of {report.part_points} part points on faces"
        + "".join(f"; free: {e(m.describe())}" for m in getattr(report.registration, "free", ())) + ".</p>"
        f"<h2>Characteristics</h2><section id='characteristics'>{_characteristics_table(rows)}</section>"
        f"<p class='note'>Value ± U: U is the expanded uncertainty (k = 2, about 95 %). &lt; x: below the detection "
        f"limit x (the scanner's noise alone reads that much on a truly flat, smooth face in 5 % of scans); its "
        f"U is the figure's U at the limit. Conforming only when value + U (&lt; x: x + U) is within the "
        f"tolerance; non-conforming when value − U is beyond it; otherwise uncertain. Nominal 0: a form tolerance "
        f"limits the zone width about the ideal form, a profile tolerance the zone about the CAD surface.</p>"
        f"<section class='keep'><h2>The part, coloured by deviation</h2><div id='views'>"
        f"{_img(part_views(report, scale), 'part views')}</div><p class='note'>{e(scale.caption)}. Colour: the "
        f"deviation the figures are taken from (the form surface's, the scanner's noise filtered out), at the points "
        f"the figures count; grey: the CAD model.</p></section>"
        f"<section class='keep'><h2>Deviation histogram</h2><div id='histogram'>"
        f"{_img(deviation_histogram(report, profiles), 'deviation histogram')}</div></section>"
        f"<section class='keep'><h2>Filtered and raw figures</h2><div id='raw-filtered'>{_raw_filtered(report)}"
        f"<p class='note'>Zones, profile and deviations are those of the form surface (second-order Gaussian "
        f"regression filter, cut-off {s.form_cutoff_mm} mm, noise bias removed); the raw points' extremes include "
        f"the noise; Sq is after noise removal: ISO 25178-2's Sq of the measured surface less the noise's mean "
        f"square (roughness cut-off {s.roughness_cutoff_mm} mm).</p></div></section>"
        f"{faces}{camera}"
        f"<h2>All face figures</h2><section id='figures'>{_all_figures(report)}</section>"
        f"<p class='note'>{e(noise_note)}</p></main></body></html>")
