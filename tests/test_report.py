"""The inspection report (issue 14): one source of tolerances (the part program), face
names wherever a face is shown, and the HTML page checked in a real browser (headless
Chromium: elements present and drawn, nothing wider than the window), not by pixels.

The page under test is rendered from a report built here with known figures: the high top
of the demo part (a plane, z = 22 mm) bowed by a known amount, so the drawn colours, the
table's values and verdicts have an independent truth (the numbers put in, ISO 14253-1's
rule written out in the test)."""

from __future__ import annotations

import html
import json
import os
import re
import shutil
import tomllib
from functools import cache
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from inspection.form import FaceForm, FormSettings
from inspection.report import FaceRow, InspectionReport
from inspection.report_header import ReportHeader, file_sha256
from inspection.report_pdf import chromium, dump_dom, print_pdf, screenshot
from inspection.segmentation import Segmentation
from inspection.uncertainty import Estimate
from scanner.config import CONFIG_DIR
from scanner.errors import ConfigError
from slscan.commands.inspect import load_tolerance_source
from slscan.station.program import load_program, program_tolerances

PROGRAM = CONFIG_DIR / "parts" / "demo_part.toml"
TOLERANCE_FILE = Path(__file__).parent / "data" / "tolerance_file.toml"
DEMO_LABELS = {"#17": "cylinder", "#105": "cone", "#158": "plane", "#270": "plane", "#305": "plane", "#375": "plane",
               "#480": "plane", "#575": "plane", "#602": "cylinder", "#657": "plane", "#684": "plane",
               "#711": "plane", "#718": "plane"}  # `slscan cad config/parts/demo_part.step`
WIDTH, HEIGHT = 1280, 900
needs_chromium = pytest.mark.skipif(chromium() is None, reason="headless Chromium not installed (Debian: chromium)")


# ------------------------------------------------------------------ one source of tolerances

def test_the_program_is_the_tolerance_source() -> None:
    """The demo program's characteristics, read here from the TOML itself, are the limits the
    inspection applies, face by face, with the program's face names."""
    raw = tomllib.loads(PROGRAM.read_text())
    want: dict[str, dict[str, float]] = {}
    for c in raw["characteristic"]:
        key = f"{c['kind']}_ls_mm" if c.get("method") == "least_squares" else f"{c['kind']}_mm"
        want.setdefault(c["face"], {})[key] = c["tolerance_mm"]
    tol, program = load_tolerance_source(PROGRAM, DEMO_LABELS)
    assert program is not None and program.name == raw["program"]["name"]
    assert tol.faces == want and tol.default == {} and tol.decision_rule == "guard-banded"
    assert tol.names == raw["faces"] and tol.name("#657") == "high top"
    assert program_tolerances(load_program(PROGRAM)).faces == want


def test_a_tolerance_file_is_still_read() -> None:
    tol, program = load_tolerance_source(TOLERANCE_FILE, DEMO_LABELS)
    assert program is None and tol.names == {}
    assert tol.faces["#17"] == {"cylindricity_ls_mm": 0.05} and tol.default == {"profile_mm": 0.1}


def test_a_program_naming_a_face_the_model_lacks_is_refused(tmp_path: Path) -> None:
    text = PROGRAM.read_text().replace('cad = "demo_part.step"', f'cad = "{CONFIG_DIR / "parts" / "demo_part.step"}"')
    text = text.replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR / "patterns"}/')
    bad = tmp_path / "p.toml"
    bad.write_text(text.replace('"#711" = "base"', '"#999" = "base"'))
    with pytest.raises(ConfigError, match=r'p\.toml.*faces\."#999"'):
        load_tolerance_source(bad, DEMO_LABELS)
    bad.write_text(text + '\n[[characteristic]]\nname = "again"\nface = "#657"\nkind = "flatness"\n'
                          'tolerance_mm = 0.1\n')
    with pytest.raises(ConfigError, match="second flatness of face #657"):
        load_tolerance_source(bad, DEMO_LABELS)


# ------------------------------------------------------------------ a report with known figures

BOW_MM = 0.012  # the high top's bow: deviation BOW at its centre, 0 at its corners
HIGH_TOP = SimpleNamespace(label="#657", step_id=657, type="plane", index=9)
BOSS = SimpleNamespace(label="#17", step_id=17, type="cylinder", index=0)


@cache
def demo_cad() -> object:
    """The demo part's CAD model (STEP, ~1-6 s to load)."""
    from inspection.cad import load_cad

    return load_cad(CONFIG_DIR / "parts" / "demo_part.step")


MARGIN_MM = 1.0  # the edge band the figures leave out


def known_report(cad: bool = False) -> InspectionReport:
    """The high top (35 x 60 mm at z = 22) bowed by BOW_MM, and the boss's side (r 12 mm),
    with figures and verdicts as given (not computed by the code under test); the form
    surface the figures are taken from is the bow without the noise, inside MARGIN_MM of
    the top's border (the points outside are not in the figures); with `cad` the demo
    part's CAD model, drawn behind the points."""
    rng = np.random.default_rng(1)
    u, v = rng.uniform(-45, -10, 20000), rng.uniform(-30, 30, 20000)
    r2 = ((u + 27.5) / 17.5) ** 2 + (v / 30.0) ** 2
    surface = BOW_MM * (1 - r2 / 2)
    inner = (np.abs(u + 27.5) <= 17.5 - MARGIN_MM) & (np.abs(v) <= 30 - MARGIN_MM)
    top_dev = surface + rng.normal(0, 0.002, len(u))
    a, h = rng.uniform(-np.pi, np.pi, 6000), rng.uniform(10, 33, 6000)
    side = np.column_stack([20 + 12 * np.cos(a), 12 * np.sin(a), h])
    foot = np.vstack([np.column_stack([u, v, np.full_like(u, 22.0)]), side])
    dev = np.concatenate([top_dev, rng.normal(0, 0.002, len(a))])
    face = np.concatenate([np.full(len(u), HIGH_TOP.index), np.full(len(a), BOSS.index)])
    uv = np.vstack([np.column_stack([u, v]), np.column_stack([a, h])])
    normal = np.vstack([np.tile([0, 0, 1.0], (len(u), 1)), np.column_stack([np.cos(a), np.sin(a), 0 * a])])
    seg = Segmentation(face, dev, foot, normal, uv)
    top = FaceForm(int(inner.sum()), "ok", flatness_mz=Estimate(0.0123, 0.001), flatness_ls=Estimate(0.0131, 0.001),
                   sq=Estimate(None, 0.002, 0.0046), profile=Estimate(0.0254, 0.002),
                   deviation_min=Estimate(-0.0007, 0.001), deviation_max=Estimate(0.0127, 0.001),
                   raw_deviation_min=Estimate(-0.0081, 0.004), raw_deviation_max=Estimate(0.0199, 0.004),
                   sq_raw_mm=0.0031, sq_noise_mm=0.0029, noise_source="decoder and sensor model",
                   deviation_source="form surface", surface_mm=np.where(inner, surface, np.nan))
    boss = FaceForm(len(a), "ok", cylindricity_mz=Estimate(0.048, 0.003), noise_source="decoder and sensor model",
                    deviation_source="form surface", surface_mm=np.zeros(len(a)))
    rows = (FaceRow.of(HIGH_TOP, top, {"flatness_mm": (0.05, "conforming"), "profile_mm": (0.1, "conforming"),
                                       "sq_mm": (0.03, "conforming")}, "high top"),
            FaceRow.of(BOSS, boss, {"cylindricity_mm": (0.05, "uncertain")}, "boss side"))
    reg = SimpleNamespace(fitness=0.99, rmse_mm=0.013, method="test", ambiguous=False, as_dict=lambda: {})
    header = ReportHeader(part="demo-part", serial="SN-0042", program=f"{PROGRAM} (version 2.0)",
                          program_sha256=file_sha256(PROGRAM), operator="A. Inspector", date="2026-12-01 21:00:00",
                          rig="sim-bench", calibration_id="factory-sim-bench", calibration_date="undated",
                          software_version="slscan 0.1.0")
    return InspectionReport(model=str(CONFIG_DIR / "parts" / "demo_part.step"), unit="mm", source="known",
                            scan_points=len(foot), part_points=len(foot), assigned_points=len(foot), registration=reg,
                            faces=rows, form_settings=FormSettings(), timings_s={}, part_mask=np.ones(len(foot), bool),
                            segmentation=seg, calibration="none", header=header, cad=demo_cad() if cad else None)


def iso_14253(value: float, U: float, tol: float) -> str:
    """The guard-banded rule, written out: conforming when value + U <= tol, non-conforming
    when value - U > tol, otherwise uncertain."""
    return "conforming" if value + U <= tol else "non-conforming" if value - U > tol else "uncertain"


def test_table_text_and_json_name_the_faces() -> None:
    rep = known_report()
    text = rep.table()
    assert "high top #657" in text and "boss side #17" in text and "flat MZ µm" in text
    data = json.loads(json.dumps(rep.as_dict(), default=str))
    assert {r["label"]: r["name"] for r in data["faces"]} == {"#657": "high top", "#17": "boss side"}
    assert data["header"]["serial"] == "SN-0042" and len(data["header"]["program_sha256"]) == 64


def test_characteristic_table_has_units_values_and_verdicts() -> None:
    rep = known_report()
    page = rep.html()
    table = page[page.index("id='characteristics'"):page.index("</table>", page.index("id='characteristics'"))]
    heads = re.findall(r"<th[^>]*>(.*?)</th>", table)
    assert all("(mm)" in h for h in heads if h not in ("face", "characteristic", "verdict (ISO 14253-1)"))
    rows = [r for r in re.findall(r"<tr>(.*?)</tr>", table) if "<td" in r]
    cells = {re.sub("<.*?>", "", r.split("</td>")[1]): [re.sub("<.*?>", "", c) for c in r.split("</td>")[:-1]]
             for r in rows}
    flat = cells["flatness (minimum zone)"]
    assert flat[0] == "high top #657" and flat[3:6] == ["0.0500", "0.0123", "&plusmn; 0.0020"]
    assert flat[7] == iso_14253(0.0123, 0.002, 0.05) == "conforming"
    sq = cells["Sq after noise removal"]  # below its limit: < L, with the U at the limit its verdict uses
    assert sq[4] == "&lt; 0.0046" and sq[5] == "&plusmn; 0.0040" and sq[6] == "0.0046"
    assert cells["cylindricity (minimum zone)"][7] == iso_14253(0.048, 0.006, 0.05) == "uncertain"
    # raw and filtered side by side: the raw extremes differ from the form surface's
    raw = page[page.index("id='raw-filtered'"):]
    assert "-0.7 &plusmn; 2.0" in raw and "-8.1 &plusmn; 8.0" in raw
    # header: every field, the program's SHA-256 as computed here from the file
    for want in ("SN-0042", "A. Inspector", "factory-sim-bench", "slscan 0.1.0", file_sha256(PROGRAM)):
        assert want in page


# ------------------------------------------------------------------ in a real browser

PROBE = """<script>
window.addEventListener('load', () => {
  const out = {scrollWidth: document.documentElement.scrollWidth, innerWidth: window.innerWidth,
               scrollHeight: document.documentElement.scrollHeight, boxes: {}, images: []};
  for (const el of document.querySelectorAll('[id]')) {
    const r = el.getBoundingClientRect();
    out.boxes[el.id] = [r.left, r.top + window.scrollY, r.width, r.height];
  }
  for (const img of document.images) out.images.push([img.alt, img.naturalWidth, img.naturalHeight]);
  const pre = document.createElement('pre'); pre.id = 'layout-probe'; pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
</script>"""


def layout(page: Path, tmp: Path) -> dict:
    """The page as Chromium lays it out at WIDTH px: the probe's measurements."""
    probed = page.parent / f"probe-{page.name}"  # beside it: its relative links still resolve
    probed.write_text(page.read_text().replace("</body>", PROBE + "</body>"))
    dom = dump_dom(probed, WIDTH, HEIGHT)
    assert dom is not None, "chromium --dump-dom failed"
    return json.loads(re.search(r"<pre id=\"layout-probe\">(.*?)</pre>", dom, re.S).group(1).replace("&quot;", '"'))


def check_in_browser(page: Path, tmp: Path, ids: tuple[str, ...], closeup: str | None,
                     save: Path | None = None, stem: str = "inspection") -> None:
    """Chromium lays the page out with every element in `ids` present and non-empty, every
    image decoded, nothing wider than the window; its screenshot is drawn (not blank) in
    every element's box. With `save`, the first page and (unless None) the close-up of
    element `closeup` are saved there as PNG."""
    import cv2

    box = layout(page, tmp)
    assert box["scrollWidth"] <= box["innerWidth"] == WIDTH, f"page overflows: {box['scrollWidth']} px"
    for i in ids:
        assert i in box["boxes"], f"no #{i}"
        assert box["boxes"][i][2] > 100 and box["boxes"][i][3] > 20, f"#{i} is empty: {box['boxes'][i]}"
        assert box["boxes"][i][0] + box["boxes"][i][2] <= WIDTH + 0.5, f"#{i} overflows"
    assert box["images"] and all(w > 0 and h > 0 for _, w, h in box["images"]), box["images"]
    full = tmp / f"{stem}-full.png"
    assert screenshot(page, full, WIDTH, int(box["scrollHeight"]) + 20) is not None
    img = cv2.imread(str(full))
    for i in ids:
        x, y, w, h = (round(t) for t in box["boxes"][i])
        crop = img[y:y + h, x:x + w]
        assert crop.size and (crop < 200).any(axis=2).mean() > 0.002, f"#{i} is blank in the screenshot"
    if save is not None:
        save.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(save / f"{stem}-first-page.png"), img[:HEIGHT])
        if "views" in box["boxes"]:
            x, y, w, h = (round(t) for t in box["boxes"]["views"])
            cv2.imwrite(str(save / f"{stem}-views.png"), img[max(y - 30, 0):y + h + 10, x:x + w])
        if closeup is None:
            return
        x, y, w, h = (round(t) for t in box["boxes"][closeup])
        what = "face-closeup" if closeup.startswith("face-") else closeup
        cv2.imwrite(str(save / f"{stem}-{what}.png"), img[max(y - 30, 0):y + h + 10, x:x + w])


def saved_screenshots() -> Path | None:
    """Where to keep the screenshots (SLSCAN_SCREENSHOTS, e.g. docs/screenshots), or None."""
    where = os.environ.get("SLSCAN_SCREENSHOTS")
    return Path(where) if where else None


@needs_chromium
def test_report_in_a_browser(tmp_path: Path) -> None:
    rep = known_report(cad=True)
    paths = rep.write(tmp_path, pdf=True)
    page = tmp_path / "inspection.html"
    assert "src=\"data:image/png;base64," in page.read_text() and "src=\"http" not in page.read_text()
    sections = ("header", "verdict", "characteristics", "views", "histogram", "raw-filtered", "face-657", "face-17",
                "figures")
    check_in_browser(page, tmp_path, sections, "face-657", saved_screenshots(), "known-report")
    pdf = tmp_path / "inspection.pdf"
    assert pdf in paths and pdf.read_bytes()[:5] == b"%PDF-" and pdf.stat().st_size > 50_000


needs_poppler = pytest.mark.skipif(shutil.which("pdftoppm") is None or shutil.which("pdftotext") is None,
                                   reason="poppler-utils not installed (pdftoppm, pdftotext)")
PAPER_PT = {"A4": (595, 842), "Letter": (612, 792)}  # page sizes in points (1/72 in)


def pdf_pages(pdf: Path, folder: Path) -> list[tuple[np.ndarray, list[tuple[str, float, float]]]]:
    """The PDF's pages as (grey image at 50 dpi, its text lines as (text, top, bottom) in
    points from the page's top), by poppler."""
    import subprocess

    import cv2

    subprocess.run(["pdftoppm", "-r", "50", "-gray", "-png", str(pdf), str(folder / "page")], check=True)
    pages = []
    for k, png in enumerate(sorted(folder.glob("page-*.png"), key=lambda p: int(p.stem.split("-")[1])), 1):
        box = subprocess.run(["pdftotext", "-bbox", "-f", str(k), "-l", str(k), str(pdf), "-"], check=True,
                             capture_output=True, text=True).stdout
        lines: dict[float, list[tuple[float, str, float]]] = {}
        for x, top, bottom, word in re.findall(r'<word xMin="([\d.]+)" yMin="([\d.]+)" xMax="[\d.]+" '
                                               r'yMax="([\d.]+)">(.*?)</word>', box):
            lines.setdefault(round(float(top), 1), []).append((float(x), html.unescape(word), float(bottom)))
        text = [(" ".join(w for _, w, _ in sorted(words)), top, max(b for _, _, b in words))
                for top, words in sorted(lines.items())]
        pages.append((cv2.imread(str(png), cv2.IMREAD_GRAYSCALE), text))
    return pages


@needs_chromium
@needs_poppler
def test_the_pdf_prints_whole_on_a4_and_letter(tmp_path: Path) -> None:
    """Printed on A4 and on Letter and rendered back to pixels: nothing is drawn in the
    outer 6 mm of any page (3 mm at the foot, where the page number is), every page is
    numbered "page k of N", every heading has content under it on its page (text or a
    figure: at least 30 pt of ink between it and the page number), and every word of every
    table header is in the PDF's text (Chromium drops what it cuts at the margin: the
    issue's PDF lost the "dev RMS", "raw points" and "noise model" columns)."""
    import subprocess

    rep = known_report(cad=True)
    rep.write(tmp_path, pdf=False)
    page = tmp_path / "inspection.html"
    headings = {html.unescape(re.sub("<.*?>", "", h)).strip()
                for h in re.findall(r"<h[23][^>]*>(.*?)</h[23]>", page.read_text())}
    assert {"All face figures", "Deviations from nominal", "high top #657"} <= headings
    header_words = {w for th in re.findall(r"<th[^>]*>(.*?)</th>", page.read_text())
                    for w in re.split(r"[\s-]+", html.unescape(re.sub("<.*?>", "", th))) if w}  # may wrap at a hyphen
    for paper, (w_pt, h_pt) in PAPER_PT.items():
        out = tmp_path / paper
        out.mkdir()
        pdf = print_pdf(page, out / "report.pdf", paper)
        assert pdf is not None
        info = subprocess.run(["pdfinfo", str(pdf)], capture_output=True, text=True, check=True).stdout
        size = re.search(r"Page size:\s+([\d.]+) x ([\d.]+) pts", info)
        assert abs(float(size.group(1)) - w_pt) < 1 and abs(float(size.group(2)) - h_pt) < 1, info
        pages = pdf_pages(pdf, out)
        px = 50 / 72  # pixels per point
        strip = round(6 / 25.4 * 50)  # 6 mm at 50 dpi
        for k, (img, lines) in enumerate(pages, 1):
            for edge in (img[:, :strip], img[:, -strip:], img[:strip], img[-strip // 2:]):  # the number sits low
                assert edge.min() > 200, f"{paper} page {k}: something drawn within 6 mm of the paper's edge"
            number = [top for text, top, _ in lines if text == f"page {k} of {len(pages)}"]
            assert number, f"{paper} page {k} has no page number"
            heads = [bottom for text, _, bottom in lines if text in headings]
            if heads:
                rows = img[int((max(heads) + 4) * px):int((number[0] - 4) * px)]
                assert (rows.min(axis=1) < 200).sum() * 72 / 50 > 30, f"{paper} page {k} ends with a heading"
        words = {w for _, lines in pages for t, _, _ in lines for w in re.split(r"[\s-]+", t) if w}
        assert not header_words - words, f"{paper}: table headers cut off: {sorted(header_words - words)}"
        assert {"decoder", "sensor", "noise", "model"} <= words  # the deviation table's last column


def test_the_colour_scale_is_tied_to_the_tolerance() -> None:
    """The known report's smallest profile tolerance is 0.1 mm: green within +-0.05 mm
    (inside the zone), warm above and cool below it up to 0.1 mm, dark beyond; its legend
    (the recording's swatches and the camera map's strip) shows those colours."""
    from inspection.deviation_colours import legend_strip, scale_of

    scale = scale_of(known_report())
    assert scale.h_mm == pytest.approx(0.05) and "profile tolerance 0.100 mm of high top #657" in scale.source
    r, g, b = scale.rgb(np.array([0.0, 0.049, -0.049, 0.075, -0.075, 0.2, -0.2, np.nan])).T
    assert (g[:3] > r[:3]).all() and (g[:3] > b[:3]).all()  # inside: green
    assert r[3] > b[3] + 0.5 and r[3] > g[3] and b[4] > r[4] + 0.4 and b[4] > g[4]  # outside: warm above, cool below
    assert max(r[5], g[5], b[5]) < 0.5 and r[5] > b[5] and b[6] > r[6] and max(r[6], g[6], b[6]) < 0.5  # dark
    assert r[7] == g[7] == b[7]  # no deviation: grey
    strip = legend_strip(scale, 480)
    for d, _ in scale.legend():  # every step's colour is on the strip
        want = np.round(scale.rgb(np.array([d]))[0] * 255)
        assert (np.abs(strip.reshape(-1, 3).astype(int) - want).max(axis=1) <= 1).any(), d


def test_face_closeup_shows_the_bow() -> None:
    """On a zone of +-8 um the high top's close-up is warm (outside the zone, above: red
    over blue, more red than green) at its centre, where the bow is +12 um, and green
    (inside the zone) at its corners, where it is 0: the map follows the form surface put
    in, not the noise (2 um, which would speckle a map of raw points)."""
    import cv2

    from inspection.deviation_colours import ColourScale
    from inspection.report_figures import CLOSEUP_AXES, face_closeup

    rep = known_report()
    png = face_closeup(rep, rep.faces[0], ColourScale(0.008, "test zone"))
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(int)
    h, w = img.shape[:2]
    left, bottom, width, height = CLOSEUP_AXES
    x0, x1 = int(w * left) + 6, int(w * (left + width)) - 6
    y0, y1 = int(h * (1 - bottom - height)) + 6, int(h * (1 - bottom)) - 6

    def colour(x: int, y: int) -> np.ndarray:
        return img[y - 3:y + 4, x - 3:x + 4].reshape(-1, 3).mean(axis=0)[::-1]  # RGB

    r, g, b = colour((x0 + x1) // 2, (y0 + y1) // 2)
    assert r - b > 120 and r > g + 60, (r, g, b)
    for x, y in ((x0 + 4, y0 + 4), (x1 - 4, y0 + 4), (x0 + 4, y1 - 4), (x1 - 4, y1 - 4)):
        r, g, b = colour(x, y)
        assert g > r + 10 and g > b + 10, (r, g, b)


def test_the_face_map_counts_the_points_the_table_counts() -> None:
    """The close-up shows the points the figures are taken over (the edge band left out),
    and says how many: the table's count."""
    from inspection.deviation_colours import shown_count, shown_deviations

    rep = known_report()
    top = rep.faces[0]
    assert shown_count(rep, top) == top.form.points < 20000
    shown = shown_deviations(rep)
    on_top = rep.segmentation.face == HIGH_TOP.index
    assert np.isfinite(shown[on_top]).sum() == top.form.points
    assert np.allclose(shown[on_top][np.isfinite(shown[on_top])], top.form.surface_mm[np.isfinite(top.form.surface_mm)])
    page = rep.html()
    assert f"{top.form.points} points, those the figures count ({top.form.points} in the table)" in page


def test_every_view_calls_out_the_faces_that_face_it() -> None:
    """Callouts on every view, by geometry worked out here: the high top (normal +z) faces
    all four views (each looks down at 12 degrees or more); the boss's side (normals
    horizontal) faces every view but the one from straight above, where it is seen edge-on."""
    from inspection.report_figures import VIEWS, callout_views

    assert [elev for _, elev, _ in VIEWS] == [30.0, 30.0, 90.0, 12.0]  # the views this truth is for
    rep = known_report()
    top, boss = (rep.faces.index(r) for r in rep.faces)
    assert callout_views(rep) == {0: [top, boss], 1: [top, boss], 2: [top], 3: [top, boss]}


def test_the_view_from_above_has_no_z_axis_labels(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seen straight down z, matplotlib draws the z axis's ticks and label on one point (a
    black blob with "z (mm)" in the view's corner): that view has none, the others have them."""
    import matplotlib.pyplot as plt

    from inspection import report_figures
    from inspection.deviation_colours import ColourScale

    figures = []
    monkeypatch.setattr(report_figures, "_png", lambda fig: figures.append(fig) or b"")
    report_figures.part_views(known_report(), ColourScale(0.02, "test"))
    views = [ax for ax in figures[0].axes if ax.name == "3d"]
    labelled = [bool(ax.get_zlabel()) and len(ax.get_zticks()) > 0 for ax in views]
    assert labelled == [elev < 90.0 for _, elev, _ in report_figures.VIEWS] == [True, True, False, True]
    plt.close(figures[0])


def test_the_cad_model_is_drawn_behind_the_points() -> None:
    """With the CAD model the views show the part's unscanned faces as a grey shaded mesh:
    far more grey pixels (R = G = B, not white) than without it, where only the axes' grid
    lines, ticks and labels are grey."""
    import cv2

    from inspection.deviation_colours import ColourScale
    from inspection.report_figures import part_views

    def grey_share(png: bytes) -> float:
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(int)
        flat = (img.max(axis=2) - img.min(axis=2)) <= 6
        return float((flat & (img.mean(axis=2) > 90) & (img.mean(axis=2) < 235)).mean())

    scale = ColourScale(0.02, "test")
    bare, drawn = grey_share(part_views(known_report(), scale)), grey_share(part_views(known_report(cad=True), scale))
    assert bare < 0.06 and drawn > bare + 0.08, (bare, drawn)  # measured: 4 % and 16 % of the figure


def test_pdf_skipped_without_chromium(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(shutil, "which", lambda name: None)
    page = tmp_path / "p.html"
    page.write_text("<html><body>x</body></html>")
    assert print_pdf(page, tmp_path / "p.pdf") is None and not (tmp_path / "p.pdf").exists()


# ------------------------------------------------------------------ the station's report

def station_cycles(n: int = 12) -> tuple[list, dict]:
    """n stored cycles of the demo program: each characteristic's value drawn about a
    quarter of its tolerance with U = 5 % of the tolerance, every fifth part's high-top
    flatness out of tolerance and the eighth part's at its tolerance (uncertain); decisions
    by the ISO 14253-1 rule written out here."""
    import datetime as dt

    from slscan.station.results import ResultRow, ValueRecord

    program = load_program(PROGRAM)
    rng = np.random.default_rng(3)
    rows, values = [], {}
    t0 = dt.datetime(2026, 12, 1, 8, 0, tzinfo=dt.UTC)
    for k in range(n):
        vals = []
        for c in program.characteristics:
            v = abs(rng.normal(c.tolerance_mm / 4, c.tolerance_mm / 20))
            if c.name == "high_top_flatness" and k % 5 == 4:
                v = 3 * c.tolerance_mm
            if c.name == "high_top_flatness" and k == 7:
                v = c.tolerance_mm
            U = 0.05 * c.tolerance_mm
            decision = iso_14253(v, U, c.tolerance_mm)
            vals.append(ValueRecord(c.name, c.kind, c.face, v, c.tolerance_mm,
                                    {"conforming": True, "non-conforming": False}.get(decision), 1000, "", U, None,
                                    decision, "guard-banded"))
        decisions = {v.decision for v in vals}
        status = "fail" if "non-conforming" in decisions else "uncertain" if "uncertain" in decisions else "pass"
        rows.append(ResultRow(program.name, program.version, program.fingerprint, f"SN-{k + 1:04d}", "ana", "bench-1",
                              "sim-bench", "factory-sim-bench", "0.1.0", "cad", f"/parts/{k}",
                              t0 + dt.timedelta(minutes=k),
                              id=k + 1, attempt=1, status=status, finished_at=t0 + dt.timedelta(minutes=k, seconds=40)))
        values[k + 1] = vals
    return rows, values


@needs_chromium
def test_station_report_has_the_header_in_a_browser(tmp_path: Path) -> None:
    from slscan.station.history_report import write_report

    rows, values = station_cycles()
    page = write_report(tmp_path / "station", load_program(PROGRAM), rows, values, "test cycles")
    text = page.read_text()
    for want in ("12 serials", "SN-0001", "ana", "sim-bench", "factory-sim-bench", "undated (factory geometry)",
                 "slscan 0.1.0", file_sha256(PROGRAM), "9 pass, 2 fail, 1 uncertain (re-measure)",
                 "0.0500 ± 0.0025 UNCERTAIN", "<td class='uncertain l'>UNCERTAIN</td>"):
        assert want in text, want
    check_in_browser(page, tmp_path, ("header", "chart-high_top_flatness"), "chart-high_top_flatness",
                     saved_screenshots(), "station-report")


@pytest.mark.slow
@needs_chromium
def test_demo_report_in_a_browser(tmp_path: Path, capsys) -> None:
    """`slscan demo` (slow: a scan and an inspection, ~1 min CPU) inspects with the demo
    part's program: face names from the program in the table, the report with its header,
    its PDF, and the page laid out in Chromium. SLSCAN_SCREENSHOTS=docs/screenshots keeps
    the screenshots (first page, the high top's close-up)."""
    from slscan import cli

    out = tmp_path / "demo"
    assert cli.main(["demo", "--out", str(out)]) == 4  # no decision: the boss side's cylindricity not measured
    text = capsys.readouterr().out
    assert "high top #657" in text and "low top #158" in text and "flatness 50 conforming" in text
    # seen from straight above the boss's side is grazing: its cylindricity is not measured, and said so
    assert "boss side #17" in text and "cylindricity 50 not measured" in text
    last = text.strip().splitlines()[-1]  # the verdict, why, and what to run next
    assert last.startswith("RESULT    NOT MEASURED: boss side #17 cylindricity not measured: ")
    assert "Next: slscan " in last
    data = json.loads((out / "outputs" / "inspection.json").read_text())
    assert data["header"]["program_sha256"] == file_sha256(PROGRAM) and data["verdict"] == "not measured"
    rows = {r["label"]: r for r in data["faces"]}
    assert rows["#657"]["name"] == "high top" and rows["#657"]["verdict_flatness"] == "conforming"
    assert (out / "outputs" / "inspection.pdf").read_bytes()[:5] == b"%PDF-"
    from scanner.recording_reader import read_component

    [(_, context)] = read_component(out / "recording.rrd", "world/inspection/faces", "AnnotationContext:context", None)
    labels = {c["class_description"]["info"]["label"] for c in context}
    assert {"high top #657 plane", "low top #158 plane", "boss side #17 cylinder"} <= labels  # the recording's labels
    [(_, legend)] = read_component(out / "recording.rrd", "world/inspection/deviation_legend", "Points3D:labels", None)
    assert any("inside the zone" in str(t) and "profile tolerance 0.100 mm of high top #657" in str(t) for t in legend)
    check_in_browser(out / "outputs" / "inspection.html", tmp_path, ("header", "verdict", "characteristics", "views",
                                                                      "histogram", "raw-filtered", "face-657",
                                                                      "figures"), "face-657", saved_screenshots())


def test_the_demo_ends_with_the_verdict_why_and_what_next(tmp_path: Path) -> None:
    """One line, last: the verdict, the characteristics that decide it with their values
    (the figures put into the known report), and a command to run."""
    from dataclasses import replace

    from slscan.commands.scan import DEMO_TURNTABLE, demo_conclusion

    rep = known_report()
    line = demo_conclusion(rep, tmp_path / "demo")
    assert line.startswith("RESULT    UNCERTAIN: boss side #17 cylindricity 0.0480 ± 0.0060 mm is within its U of "
                           "0.050 mm") and "Next: re-measure: slscan demo" in line and "\n" not in line
    unseen = FaceForm(210, "too few points", "fewer than 50 grid cells of 0.243 mm left inside the 1.0 mm edge margin")
    boss = replace(rep.faces[1], form=unseen, verdicts={"cylindricity_mm": (0.05, "not measured")})
    line = demo_conclusion(replace(rep, faces=(rep.faces[0], boss)), tmp_path / "demo")
    assert line.startswith("RESULT    NOT MEASURED: boss side #17 cylindricity not measured: 210 points from the "
                           "demo's one view (fewer than 50 grid cells")
    assert line.endswith(f"Next: slscan station {os.path.relpath(DEMO_TURNTABLE[0])} --config "
                         f"{os.path.relpath(DEMO_TURNTABLE[1])} --auto --parts 1")
    top = replace(rep.faces[0], verdicts={"flatness_mm": (0.01, "non-conforming")})
    line = demo_conclusion(replace(rep, faces=(top,)), tmp_path / "demo")
    assert line.startswith("RESULT    NON-CONFORMING: high top #657 flatness 0.0123 ± 0.0020 mm > 0.010 mm.")


def test_inspect_without_cad_needs_a_program(tmp_path: Path) -> None:
    from slscan.commands.inspect import inspect_source

    with pytest.raises(ConfigError, match="give --cad FILE, or a part program"):
        inspect_source(tmp_path / "cloud.ply", None, tolerances=TOLERANCE_FILE)
