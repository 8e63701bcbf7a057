"""The inspection report: a per-face table (the layout of paper 000's Table 3, plus
minimum-zone figures, uncertainties, detection limits, tolerances and ISO 14253-1 verdicts)
as JSON, CSV, text and a human-readable HTML page with the deviation map.

Figures (mm in files, µm in the text table): flatness / cylindricity by least squares
(paper 000 Eq. 20-22) and minimum zone (ISO 1101), both on the form surface (a
second-order Gaussian regression filter, cut-off in the report); Sq after noise removal
(`sq_mm`) beside ISO 25178-2's Sq of the measured surface, noise included (`sq_raw_mm`);
signed deviations from nominal
(positive = excess material) and the profile zone of the form surface; the raw points'
extremes. In JSON and CSV every figure `x_mm` has `x_u_mm`, its expanded uncertainty
(k = 2); a figure that cannot be told from zero is null with `x_limit_mm`, its detection
limit (the text table prints `< limit`). Each toleranced characteristic has
`tolerance_x_mm` and `verdict_x`: conforming, non-conforming or uncertain under the
recorded decision rule. The figures and their column names: `inspection.figures`. How to
read them: README, "Reading the figures".
"""

from __future__ import annotations

import csv
import io
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from inspection.deviation_colours import deviation_image, scale_of  # noqa: F401 (deviation_image: the commands')
from inspection.figures import FIGURES, limited_by
from inspection.form import FaceForm, FormSettings
from inspection.pose_uncertainty import PoseUncertainty
from inspection.report_header import ReportHeader
from inspection.report_html import render
from inspection.report_pdf import print_pdf
from inspection.tolerances import DECISION_RULES, DECISION_STATUS, GUARD_BANDED, NOT_MEASURED, overall
from inspection.uncertainty import Estimate
from scanner.csv_cells import csv_cell
from scanner.session import write_atomic, write_json

NOISE_NOTE = ("Every figure is given with its expanded uncertainty U (k = 2): scanner noise predicted per point "
              "by the decoder and the sensor model (or, without one, estimated from the data), the fringe error "
              "of the projector's quantised patterns, and the calibration's covariance where the rig has one. "
              "Noise adds to zones and to Sq: each zone, the profile, the deviation extremes and Sq are reported "
              "with that noise bias removed (zones and profile: the mean shift of the same figure over noise "
              "draws; Sq: the noise's mean square subtracted, beside ISO 25178-2's Sq of the measured surface). "
              "A figure is reported as a number only when it exceeds its detection limit (a truly flat, smooth "
              "face reads above it in at most 5 % of scans); otherwise as < limit, which conforms only when "
              "the limit plus its U is within the tolerance. Zones, deviations and the "
              "profile are those of the form surface (features longer than the form cut-off); the raw points' "
              "extremes include the noise.")

TABLE = tuple(f for f in FIGURES if f.abbrev)  # the text table's figures


def cell_text(e: Estimate | None, width: int = 13) -> str:
    """A figure for the text table, in µm: "12.3±2.1", "<6.1", or "-"."""
    if e is None:
        text = "-"
    elif e.value is None:
        text = f"<{e.limit * 1e3:.1f}" if e.limit is not None else "n/m"
    else:
        text = f"{e.value * 1e3:.1f}±{e.U * 1e3:.1f}"
    return f"{text:>{width}}"


@dataclass(frozen=True)
class FaceRow:
    """One face of the report: its label, STEP id and type, its figures and verdicts
    (characteristic -> (tolerance mm, verdict)); `name` the part program's name of the face
    ("" without one), `index` the face's index in the CAD model (segmentation's labels)."""

    label: str
    id: int | None
    type: str
    form: FaceForm
    verdicts: dict[str, tuple[float, str]] = field(default_factory=dict)
    name: str = ""
    index: int = -1

    @classmethod
    def of(cls, face: Any, form: FaceForm, verdicts: dict[str, tuple[float, str]], name: str = "") -> FaceRow:
        return cls(face.label, face.step_id, face.type, form, verdicts, name, face.index)

    @property
    def title(self) -> str:
        """The face as people read it: "high top #657", or the label alone without a name."""
        return f"{self.name} {self.label}" if self.name else self.label

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"label": self.label, "name": self.name, "id": self.id, "type": self.type,
                             **self.form.as_dict()}
        for key, (limit, v) in self.verdicts.items():
            figure = limited_by(key)
            d[figure.tolerance_column] = limit
            d[figure.verdict_column] = v
        return d


@dataclass(frozen=True, eq=False)
class InspectionReport:
    """The result of `pipeline.inspect`. `registration` is a `registration.Registration`;
    `part_mask` which scan points are the part, `segmentation` their faces;
    `decision_rule` how verdicts used U; `calibration` where the calibration term came from;
    `pose_u` the registration pose's uncertainty (None: not known); `header` who, what, when and with what
    (`inspection.report_header`), filled by the command that inspects; `cad` the CAD model
    inspected against (an `inspection.cad.CadModel`, drawn behind the points in the report's
    views; None: not kept); `status` the registration's: "ok", "ambiguous" when another pose
    explains the scan as well (then nothing is measured), "free" when the view leaves a
    motion free (the faces it moves are not measured); `status_note` says why."""

    model: str
    unit: str
    source: str
    scan_points: int
    part_points: int
    assigned_points: int
    registration: Any
    faces: tuple[FaceRow, ...]
    form_settings: FormSettings
    timings_s: dict[str, float]
    part_mask: np.ndarray = field(repr=False)
    segmentation: Any = field(repr=False)
    decision_rule: str = GUARD_BANDED
    calibration: str = ""
    pose_u: PoseUncertainty | None = None
    header: ReportHeader = field(default_factory=ReportHeader)
    cad: Any = field(default=None, repr=False)
    status: str = "ok"
    status_note: str = ""

    @property
    def fitness(self) -> float:
        return float(self.registration.fitness)

    @property
    def rmse_mm(self) -> float:
        return float(self.registration.rmse_mm)

    @property
    def verdict(self) -> str:
        """non-conforming if any characteristic is, else uncertain / not measured if any is,
        conforming if all are, "no tolerances" without limits; "not measured" whatever the
        limits when the pose is ambiguous."""
        if self.status == "ambiguous":
            return NOT_MEASURED
        return overall([v for row in self.faces for _, v in row.verdicts.values()])

    def as_dict(self) -> dict[str, Any]:
        return {"status": DECISION_STATUS[self.verdict], "pose_status": self.status,
                **({"status_note": self.status_note} if self.status_note else {}),
                "header": self.header.as_dict(), "model": self.model, "unit": self.unit, "source": self.source,
                "fitness": self.fitness, "rmse_mm": self.rmse_mm, "verdict": self.verdict,
                "decision_rule": self.decision_rule, "rule": DECISION_RULES[self.decision_rule],
                "coverage_factor": 2.0, "calibration_uncertainty": self.calibration,
                "registration": {**self.registration.as_dict(), **(self.pose_u.as_dict() if self.pose_u else {})},
                "points": {"scan": self.scan_points, "part": self.part_points, "assigned": self.assigned_points,
                           "unassigned": self.part_points - self.assigned_points},
                "form_settings": asdict(self.form_settings), "noise_treatment": NOISE_NOTE,
                "timings_s": self.timings_s, "faces": [row.as_dict() for row in self.faces]}

    def table(self) -> str:
        """The per-face table as text, every length in µm: figures as value ± U (k = 2), or
        < detection limit; each limit with its verdict."""
        width = max([8] + [len(r.title) for r in self.faces])
        head = (f"{'face':<{width}} {'type':<9} {'points':>7} " + " ".join(f"{f.abbrev + ' µm':>13}" for f in TABLE)
                + "  tolerance µm, verdict")
        lines = [head, "-" * len(head)]
        for row in self.faces:
            m = row.form
            v = ", ".join(f"{limited_by(k).characteristic} {lim * 1e3:g} {w}" for k, (lim, w) in row.verdicts.items())
            cells = " ".join(cell_text(m.figure(f.name)) for f in TABLE)
            lines.append(f"{row.title:<{width}} {row.type:<9} {m.points:>7} {cells}  "
                         f"{v or m.status if m.status != 'ok' else v}")
        s = self.form_settings
        lines.append(f"µm, value ± U (k = 2); < x: below the detection limit x (noise alone could read that much). "
                     f"Zones, profile and deviations of the form surface (second-order Gaussian regression "
                     f"filter, cut-off {s.form_cutoff_mm} mm); Sq after noise removal (ISO 25178-2 Sq of the "
                     f"measured surface: "
                     f"sq_raw_mm), roughness cut-off {s.roughness_cutoff_mm} mm; noise bias removed; "
                     f"edge margin {s.edge_margin_mm} mm.")
        lines.append(f"registration fitness {self.fitness:.3f}, RMSE {self.rmse_mm * 1e3:.1f} um "
                     f"({self.registration.method}{', AMBIGUOUS pose' if self.registration.ambiguous else ''}"
                     + (f"; {self.pose_u.text()}" if self.pose_u is not None else "")
                     + "".join(f"; free: {m.describe()}" for m in getattr(self.registration, "free", ())) + "); "
                     f"{self.assigned_points}/{self.part_points} part points on faces; "
                     f"calibration: {self.calibration}; "
                     f"decision rule {self.decision_rule}; verdict {self.verdict}")
        if self.status_note:
            lines.append(self.status_note)
        return "\n".join(lines)

    def write(self, folder: str | Path, stem: str = "inspection", deviation_png: bytes | None = None,
              pdf: bool = False, paper: str | None = None) -> list[Path]:
        """inspection.json, inspection.csv and inspection.html (with the deviation map) in
        `folder`, and with `pdf` inspection.pdf printed from the page on `paper` (A4 or
        Letter; default `report_pdf.on_paper`'s, else A4) by headless Chromium when it is installed; returns
        the paths written."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        paths = [folder / f"{stem}.json", folder / f"{stem}.csv", folder / f"{stem}.html"]
        write_json(paths[0], self.as_dict())
        rows = [{k: v for k, v in r.as_dict().items() if k != "u_components_mm"} for r in self.faces]
        keys = list(dict.fromkeys(k for r in rows for k in r))
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=keys)
        w.writeheader()
        w.writerows([{k: csv_cell(v) for k, v in r.items()} for r in rows])  # names from the part program: text
        write_atomic(paths[1], buf.getvalue().encode())
        write_atomic(paths[2], self.html(deviation_png).encode())
        if pdf and print_pdf(paths[2], folder / f"{stem}.pdf", paper) is not None:
            paths.append(folder / f"{stem}.pdf")
        return paths

    def html(self, deviation_png: bytes | None = None) -> str:
        """The self-contained HTML report (`inspection.report_html`)."""
        return render(self, scale_of(self), NOISE_NOTE, deviation_png)


def png(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", image[..., ::-1])
    return buf.tobytes() if ok else b""
