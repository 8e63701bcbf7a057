"""The inspection report as one self-contained HTML page (images embedded as data URIs),
laid out as a metrology lab issues one and printable to PDF (`inspection.report_pdf`):

    header       part, serial, program and its SHA-256, operator, date, rig, calibration
                 id and date, software version; the overall verdict and the decision rule
    views        the part from four sides coloured by signed deviation, colour bar in mm,
                 callouts naming each toleranced face with its verdict
    table        one row per characteristic: face, characteristic, nominal, tolerance,
                 value, U (k = 2), detection limit, verdict; units in every header
    histogram    the signed deviations of every point on a face
    raw/filtered the form surface's figures beside the raw points' where they differ
    close-ups    each toleranced face in its own surface coordinates
    all figures  every face's figures (µm, value ± U or < limit), and how to read them

Element ids (`#header`, `#verdict`, `#views`, `#characteristics`, `#histogram`,
`#raw-filtered`, `#face-<id>`, `#figures`) are what the browser test checks."""

from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import Any, Iterable

from inspection.form import FIGURES
from inspection.report_figures import deviation_histogram, face_closeup, part_views
from inspection.report_header import HEADER_CSS, header_html
from inspection.tolerances import DECISION_RULES, FIGURE_OF, TITLES
from inspection.uncertainty import Estimate

STYLE = """
body{font-family:"DejaVu Sans",Arial,sans-serif;color:#222;margin:0;background:#fff}
main{max-width:1120px;margin:0 auto;padding:16px 24px}
h1{font-size:22px;margin:8px 0}h2{font-size:17px;margin:22px 0 8px;border-bottom:1px solid #bbb}
.scroll{overflow-x:auto;max-width:100%}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}
th{background:#eef0f3}td.l,th.l{text-align:left}
.conforming{background:#d6f5d6}.non-conforming{background:#f8d0d0}.uncertain{background:#fdf0c2}
.not-measured{background:#e4e4e4}.limit{color:#666}
#verdict{font-size:18px;padding:8px 12px;border:2px solid #888;display:inline-block;margin:6px 0}
img{max-width:100%;height:auto;display:block}
.faces{display:flex;flex-wrap:wrap;gap:12px}.faces section{flex:1 1 480px;max-width:100%}
p.note,span.note{font-size:12px;color:#444}
@media print{main{max-width:none;padding:0}h2{break-after:avoid}img,table{break-inside:avoid}}
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
            e = r.form.figure(FIGURE_OF[key]) if r.form.status == "ok" else None
            rows.append({"face": r.title, "characteristic": TITLES[key], "nominal_mm": 0.0, "tolerance_mm": tol,
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
                    f"<td>{'&plusmn; ' + _mm(c['u_mm']) if c['value_mm'] is not None else ''}</td>"
                    f"<td>{_mm(c['limit_mm'])}</td><td class='l {_css(c['verdict'])}'>{html.escape(c['verdict'])}"
                    f"</td></tr>")
    return f"<div class='scroll'><table>{head}{''.join(body)}</table></div>"


def _raw_filtered(report: Any) -> str:
    """Per measured face, the form surface's figure beside the raw points' one where the
    two differ as printed (µm)."""
    pairs = (("deviation min", "deviation_min", "raw_deviation_min"),
             ("deviation max", "deviation_max", "raw_deviation_max"))
    rows = []
    for r in report.faces:
        m = r.form
        if m.status != "ok":
            continue
        for what, filtered, raw in pairs:
            a, b = _um_cell(m.figure(filtered)), _um_cell(m.figure(raw))
            if a != b:
                rows.append(f"<tr><td class='l'>{html.escape(r.title)}</td><td class='l'>{what}</td>{a}{b}</tr>")
        if m.sq_raw_mm is not None and m.sq_noise_mm is not None:
            rows.append(f"<tr><td class='l'>{html.escape(r.title)}</td><td class='l'>Sq</td>{_um_cell(m.sq)}"
                        f"<td>{m.sq_raw_mm * 1e3:.1f} (noise {m.sq_noise_mm * 1e3:.1f})</td></tr>")
    if not rows:
        return "<p>The filtered and raw figures agree on every face.</p>"
    return ("<div class='scroll'><table><tr><th class='l'>face</th><th class='l'>figure</th>"
            "<th>form surface, noise removed (µm)</th><th>raw points, noise included (µm)</th></tr>"
            + "".join(rows) + "</table></div>")


def _all_figures(report: Any) -> str:
    heads = {"flatness_mz": "flatness MZ", "flatness_ls": "flatness LS", "cylindricity_mz": "cylindricity MZ",
             "cylindricity_ls": "cylindricity LS", "sq": "Sq", "profile": "profile", "deviation_min": "dev min",
             "deviation_max": "dev max", "deviation_mean": "dev mean", "deviation_rms": "dev RMS",
             "raw_deviation_min": "raw points min", "raw_deviation_max": "raw points max"}
    body = "".join(
        f"<tr><td class='l'>{html.escape(r.title)}</td><td class='l'>{r.type}</td><td>{r.form.points}</td>"
        + "".join(_um_cell(r.form.figure(n)) for n in FIGURES)
        + f"<td class='l'>{html.escape(r.form.noise_source or r.form.status)}</td></tr>" for r in report.faces)
    return ("<div class='scroll'><table><tr><th class='l'>face</th><th class='l'>type</th><th>points</th>"
            + "".join(f"<th>{heads[n]} (µm)</th>" for n in FIGURES) + "<th class='l'>noise model</th></tr>"
            + body + "</table></div>")


def _header(report: Any) -> str:
    return header_html(report.header, [("Scan", report.source), ("CAD model", f"{report.model} ({report.unit})"),
                                       ("Calibration uncertainty", report.calibration)])


def closeup_faces(report: Any) -> Iterable[Any]:
    """The faces that get a close-up: toleranced faces with points."""
    return [r for r in report.faces if r.verdicts and r.form.points > 0]


def render(report: Any, limit: float, noise_note: str, deviation_png: bytes | None = None) -> str:
    """The whole page (module docstring); `limit` (mm) the colour scale's ends, as the
    recording's deviation maps; `noise_note` how noise was treated, said once."""
    e = html.escape
    rows = characteristic_rows(report)
    profiles = {r.title: t for r in report.faces for k, (t, _) in r.verdicts.items() if k == "profile_mm"}
    s = report.form_settings
    closeups = "".join(
        f"<section id='face-{e(r.label.lstrip('#'))}'><h3>{e(r.title)}</h3>{_img(face_closeup(report, r, limit), r.title)}"
        f"</section>" for r in closeup_faces(report))
    camera = (f"<h2>Deviation map in the camera image</h2>{_img(deviation_png, 'deviation map in the camera image')}"
              f"<p class='note'>blue: inside the material, red: outside, over ±{limit:.4f} mm; grey: part points on "
              f"no face; dark: not the part.</p>" if deviation_png else "")
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
        f"limit x (the scanner's noise alone could read that much). Conforming only when value + U is within the "
        f"tolerance; non-conforming when value − U is beyond it; otherwise uncertain. Nominal 0: a form tolerance "
        f"limits the zone width about the ideal form, a profile tolerance the zone about the CAD surface.</p>"
        f"<h2>The part, coloured by deviation</h2><section id='views'>{_img(part_views(report, limit), 'part views')}"
        f"</section>"
        f"<h2>Deviation histogram</h2><section id='histogram'>"
        f"{_img(deviation_histogram(report, profiles), 'deviation histogram')}</section>"
        f"<h2>Filtered and raw figures</h2><section id='raw-filtered'>{_raw_filtered(report)}"
        f"<p class='note'>Zones, profile and deviations are those of the form surface (ISO 16610-61 Gaussian, "
        f"cut-off {s.form_cutoff_mm} mm, noise bias removed); the raw points' extremes include the noise; Sq "
        f"has the noise's mean square subtracted (roughness cut-off {s.roughness_cutoff_mm} mm).</p></section>"
        f"<h2>Faces</h2><div class='faces'>{closeups}</div>{camera}"
        f"<h2>All face figures</h2><section id='figures'>{_all_figures(report)}</section>"
        f"<p class='note'>{e(noise_note)}</p></main></body></html>")
