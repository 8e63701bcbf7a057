"""The inspection report: a per-face table (the layout of paper 000's Table 3, plus
minimum-zone figures, noise floors, tolerances and verdicts) as JSON, CSV, text and a
human-readable HTML page with the deviation map.

Columns (mm): flatness / cylindricity by least squares (paper 000 Eq. 20-22) and minimum
zone (ISO 1101), both on the form surface (ISO 16610-61 Gaussian, cut-off in the report);
the raw zone of the unfiltered points; the noise floor (the zone the filtered scanner
noise alone spans); Sq (ISO 25178-2) with the estimated noise removed in quadrature;
signed deviations from nominal (positive = excess material).
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from inspection.form import FaceForm, FormSettings

NOISE_NOTE = ("Scanner noise (sigma_n per point, estimated from the data) would widen a zone evaluated on raw "
              "points by several sigma_n and add sigma_n^2 to Sq^2: zones are evaluated on the form surface "
              "(noise divided by the filter), reported with the zone the filtered noise alone spans (noise floor), "
              "Sq has sigma_n removed in quadrature, the profile zone (2 max|deviation|) is taken on the form surface "
              "(the raw points' extremes, 4-5 sigma_n of noise each side, are listed apart), and a tolerance the "
              "noise floor cannot decide is 'uncertain'.")


@dataclass(frozen=True)
class FaceRow:
    """One face of the report: its label, STEP id and type, and its figures."""

    label: str
    id: int | None
    type: str
    form: FaceForm
    verdicts: dict[str, tuple[float, str]] = field(default_factory=dict)

    @classmethod
    def of(cls, face: Any, form: FaceForm, verdicts: dict[str, tuple[float, str]]) -> FaceRow:
        return cls(face.label, face.step_id, face.type, form, verdicts)

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"label": self.label, "id": self.id, "type": self.type, **self.form.as_dict()}
        for key, (limit, v) in self.verdicts.items():
            d[f"tolerance_{key}"] = limit
            d[f"verdict_{key.removesuffix('_mm')}"] = v
        return d


@dataclass(frozen=True, eq=False)
class InspectionReport:
    """The result of `pipeline.inspect`. `registration` is a `registration.Registration`;
    `part_mask` which scan points are the part, `segmentation` their faces."""

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

    @property
    def fitness(self) -> float:
        return float(self.registration.fitness)

    @property
    def rmse_mm(self) -> float:
        return float(self.registration.rmse_mm)

    @property
    def verdict(self) -> str:
        """"fail" if any limit fails, "uncertain" if any cannot be decided, "pass" if all
        pass, "no tolerances" without limits."""
        vs = [v for row in self.faces for _, v in row.verdicts.values()]
        for word in ("fail", "uncertain", "not measured"):
            if word in vs:
                return word
        return "pass" if vs else "no tolerances"

    def as_dict(self) -> dict[str, Any]:
        return {"status": "ok", "model": self.model, "unit": self.unit, "source": self.source,
                "fitness": self.fitness, "rmse_mm": self.rmse_mm, "verdict": self.verdict,
                "registration": self.registration.as_dict(),
                "points": {"scan": self.scan_points, "part": self.part_points, "assigned": self.assigned_points,
                           "unassigned": self.part_points - self.assigned_points},
                "form_settings": asdict(self.form_settings), "noise_treatment": NOISE_NOTE,
                "timings_s": self.timings_s, "faces": [row.as_dict() for row in self.faces]}

    def table(self) -> str:
        """The per-face table as text (values in mm; MZ = minimum zone, LS = least squares;
        deviations and profile of the form surface; each limit with its verdict)."""
        head = (f"{'face':>8} {'type':<9} {'points':>8} {'flat MZ':>9} {'flat LS':>9} {'cyl MZ':>9} {'cyl LS':>9} "
                f"{'Sq':>8} {'floor':>7} {'dev min':>8} {'dev max':>8} {'profile':>8}  tolerance verdicts")
        lines = [head, "-" * len(head)]

        def f(x: float | None, w: int = 9) -> str:
            return f"{x:{w}.4f}" if x is not None else f"{'-':>{w}}"

        for row in self.faces:
            m = row.form
            v = ", ".join(f"{k.removesuffix('_mm')} {lim:.3f} {w}" for k, (lim, w) in row.verdicts.items())
            lines.append(f"{row.label:>8} {row.type:<9} {m.points:>8} {f(m.flatness_mz_mm)} {f(m.flatness_ls_mm)} "
                         f"{f(m.cylindricity_mz_mm)} {f(m.cylindricity_ls_mm)} {f(m.sq_mm, 8)} "
                         f"{f(m.noise_floor_mm, 7)} {f(m.deviation_min_mm, 8)} {f(m.deviation_max_mm, 8)} {f(m.profile_mm, 8)}  "
                         f"{v or m.status if m.status != 'ok' else v}")
        s = self.form_settings
        lines.append(f"registration fitness {self.fitness:.3f}, RMSE {self.rmse_mm * 1e3:.1f} um "
                     f"({self.registration.method}{', AMBIGUOUS pose' if self.registration.ambiguous else ''}); "
                     f"{self.assigned_points}/{self.part_points} part points on faces; form filter ISO 16610-61 "
                     f"cut-off {s.form_cutoff_mm} mm (2nd-order regression), roughness cut-off "
                     f"{s.roughness_cutoff_mm} mm, edge margin {s.edge_margin_mm} mm; verdict {self.verdict}")
        return "\n".join(lines)

    def write(self, folder: str | Path, stem: str = "inspection", deviation_png: bytes | None = None) -> list[Path]:
        """inspection.json, inspection.csv and inspection.html (with the deviation map) in
        `folder`; returns their paths."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        paths = [folder / f"{stem}.json", folder / f"{stem}.csv", folder / f"{stem}.html"]
        _atomic(paths[0], json.dumps(self.as_dict(), indent=1, default=_plain).encode())
        rows = [r.as_dict() for r in self.faces]
        keys = list(dict.fromkeys(k for r in rows for k in r))
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
        _atomic(paths[1], buf.getvalue().encode())
        _atomic(paths[2], self.html(deviation_png).encode())
        return paths

    def html(self, deviation_png: bytes | None = None) -> str:
        d = self.as_dict()
        cols = ["label", "type", "points", "flatness_mz_mm", "flatness_ls_mm", "cylindricity_mz_mm",
                "cylindricity_ls_mm", "raw_zone_mm", "noise_floor_mm", "sq_mm", "deviation_min_mm",
                "deviation_max_mm", "profile_mm", "raw_deviation_min_mm", "raw_deviation_max_mm", "status"]
        vcols = sorted({k for r in d["faces"] for k in r if k.startswith(("tolerance_", "verdict_"))})

        def cell(v: Any) -> str:
            if isinstance(v, float):
                return f"<td>{v:.4f}</td>"
            cls = f' class="{v}"' if v in ("pass", "fail", "uncertain") else ""
            return f"<td{cls}>{html.escape('' if v is None else str(v))}</td>"

        body = "".join("<tr>" + "".join(cell(r.get(c)) for c in cols + vcols) + "</tr>" for r in d["faces"])
        img = (f'<h2>Deviation map</h2><p>signed deviation from nominal (blue: inside the material, red: '
               f'outside; grey: part points on no face)</p><img src="data:image/png;base64,'
               f'{base64.b64encode(deviation_png).decode()}">' if deviation_png else "")
        return (f"<!doctype html><html><head><meta charset='utf-8'><title>Inspection of {html.escape(self.source)}"
                f"</title><style>body{{font-family:sans-serif}}td,th{{padding:2px 8px;text-align:right}}"
                f".pass{{background:#cfc}}.fail{{background:#fcc}}.uncertain{{background:#ffc}}</style></head><body>"
                f"<h1>Inspection: {html.escape(Path(self.model).name)}</h1>"
                f"<p>scan {html.escape(self.source)}; model {html.escape(self.model)} ({html.escape(self.unit)}); "
                f"verdict <b>{self.verdict}</b></p>"
                f"<p>registration: fitness {self.fitness:.3f}, RMSE {self.rmse_mm * 1e3:.1f} &micro;m, "
                f"{html.escape(self.registration.method)}; points: {self.assigned_points} of {self.part_points} "
                f"on faces</p><table><tr>{''.join(f'<th>{c}</th>' for c in cols + vcols)}</tr>{body}</table>"
                f"<p>All lengths in mm. {html.escape(NOISE_NOTE)}</p>{img}</body></html>")


def deviation_colours(dev: np.ndarray, limit_mm: float) -> np.ndarray:
    """RGB (N, 3) in 0..1: blue (inside the material) - white - red (outside) over
    +-limit_mm; grey where the deviation is NaN (a point on no face)."""
    t = np.clip(np.nan_to_num(dev) / max(limit_mm, 1e-9), -1.0, 1.0)
    rgb = np.stack([np.where(t > 0, 1.0, 1.0 + t), 1.0 - np.abs(t), np.where(t < 0, 1.0, 1.0 - t)], axis=1)
    rgb[~np.isfinite(dev)] = 0.6
    return rgb


def colour_limit(report: InspectionReport) -> float:
    """The colour scale of deviation maps: the 99th percentile of |deviation| (mm)."""
    dev = report.segmentation.deviation_mm
    return float(np.nanpercentile(np.abs(dev), 99)) if np.isfinite(dev).any() else 1.0


def deviation_image(report: InspectionReport, scan: Any) -> np.ndarray:
    """RGB uint8 image of the signed deviations (`deviation_colours`, `colour_limit`): the
    camera image for organised scans, else a view along the cloud's z axis; dark grey
    for scan points that are not the part."""
    colours = np.full((len(scan), 3), 0.25)
    colours[report.part_mask] = deviation_colours(report.segmentation.deviation_mm, colour_limit(report))
    if scan.pixels is not None:
        px, (h, w) = scan.pixels, scan.image_shape
    else:
        xy = scan.points[:, :2]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        scale = 1000.0 / max(float((hi - lo).max()), 1e-9)
        px = np.floor((xy - lo) * scale).astype(np.int64)
        w, h = (px.max(axis=0) + 1).tolist()
    img = np.zeros((h, w, 3), np.uint8)
    img[px[:, 1], px[:, 0]] = np.round(colours * 255).astype(np.uint8)
    return img


def png(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", image[..., ::-1])
    return buf.tobytes() if ok else b""


def _atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_bytes(data)
    tmp.replace(path)


def _plain(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)
