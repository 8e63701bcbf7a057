"""The deviation colour scale of every view of an inspection (the report's part views and
close-ups, the camera-image deviation map, the Rerun recording), tied to the tolerance:

    |d| <= h         inside the tolerance zone: green (pale at 0, deeper towards the zone's edge)
    h < |d| <= 2h    outside: graded, yellow to red above nominal (excess material), cyan to
                     blue below (missing material)
    |d| > 2h         far outside: saturated dark red / dark blue

d the signed deviation from nominal (mm, + excess material) and h the half-width of the
zone it is judged in (`scale_of`): the smallest profile tolerance of the part's faces, t/2
(ISO 1101: a zone of width t centred on the nominal surface); without one, the smallest
form tolerance's t/2 as a reference zone about nominal; without any tolerance, the 99th
percentile of |d|, said so on every legend. Points on no face, or left out of the figures,
are grey.

What is coloured is the deviation the figures are taken from (`shown_deviations`): on a
face with a form surface (ISO 16610-61 filter, `inspection.form`) the form surface's
deviation at each point, the scanner's noise filtered out; on a face measured from its raw
points, the raw deviation; points outside the figures (the edge margin, spikes, faces too
small to evaluate) are not coloured, so the points a map shows are the points its figures
count."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

GREY = 0.6  # the grey of a point with no deviation shown (0..1)
EXTENT = 2.5  # a colour bar runs over +-EXTENT h: the saturated ends show
# the scale's anchors, t = d / h, and their RGB (0..1); colours between anchors are interpolated
_T = np.array([-2.0, -1.0, -1.0 + 1e-6, 0.0, 1.0 - 1e-6, 1.0, 2.0])
_RGB = np.array([(0.08, 0.16, 0.55), (0.45, 0.85, 0.95), (0.20, 0.62, 0.25), (0.60, 0.86, 0.56), (0.20, 0.62, 0.25),
                 (0.98, 0.88, 0.25), (0.75, 0.05, 0.05)])
_SATURATED = {-1: (0.05, 0.08, 0.35), 1: (0.45, 0.0, 0.0)}


@dataclass(frozen=True)
class ColourScale:
    """The zone half-width `h_mm` colours are tied to and what it is (`source`, e.g.
    "profile tolerance 0.100 mm of high top #657")."""

    h_mm: float
    source: str

    def rgb(self, deviation_mm: np.ndarray) -> np.ndarray:
        """RGB (N, 3) in 0..1 of signed deviations (mm); grey where NaN."""
        d = np.asarray(deviation_mm, float)
        t = np.nan_to_num(d) / max(self.h_mm, 1e-12)
        rgb = np.stack([np.interp(np.clip(t, -2.0, 2.0), _T, _RGB[:, k]) for k in range(3)], axis=1)
        for side, colour in _SATURATED.items():
            rgb[side * t > 2.0] = colour
        rgb[~np.isfinite(d)] = GREY
        return rgb

    def legend(self) -> list[tuple[float, str]]:
        """(deviation mm, text) at the scale's steps, from below nominal to above."""
        h = self.h_mm
        return [(-2.5 * h, f"< {-2 * h:+.3f} mm: far below (saturated)"), (-1.5 * h, f"{-2 * h:+.3f}..{-h:+.3f} mm: "
                "below the zone"), (0.0, f"within ±{h:.3f} mm: inside the zone"),
                (1.5 * h, f"{h:+.3f}..{2 * h:+.3f} mm: above the zone"),
                (2.5 * h, f"> {2 * h:+.3f} mm: far above (saturated)")]

    def colormap(self) -> tuple[Any, Any]:
        """(matplotlib colormap, norm) over +-EXTENT h for colour bars, the same colours."""
        from matplotlib.colors import ListedColormap, Normalize

        d = np.linspace(-EXTENT * self.h_mm, EXTENT * self.h_mm, 501)
        return ListedColormap(self.rgb(d)), Normalize(-EXTENT * self.h_mm, EXTENT * self.h_mm)

    @property
    def caption(self) -> str:
        return (f"green: within ±{self.h_mm:.3f} mm ({self.source}); yellow to red above, cyan to blue below, "
                f"up to twice that; dark beyond")


def scale_of(report: Any) -> ColourScale:
    """The report's colour scale (module docstring)."""
    profiles = [(t, r.title) for r in report.faces for k, (t, _) in r.verdicts.items() if k == "profile_mm"]
    if profiles:
        t, title = min(profiles)
        return ColourScale(t / 2, f"profile tolerance {t:.3f} mm of {title}")
    forms = [(t, k.removesuffix("_mm").removesuffix("_ls").replace("_", " "), r.title) for r in report.faces
             for k, (t, _) in r.verdicts.items() if k.startswith(("flatness", "cylindricity"))]
    if forms:
        t, kind, title = min(forms)
        return ColourScale(t / 2, f"half the {kind} tolerance {t:.3f} mm of {title}, as a zone about nominal")
    d = shown_deviations(report)
    h = float(np.nanpercentile(np.abs(d), 99)) if np.isfinite(d).any() else 1.0
    return ColourScale(h, "no tolerance given: the 99th percentile of |deviation|")


def shown_deviations(report: Any) -> np.ndarray:
    """Per part point (the segmentation's order), the deviation the figures are taken from
    (mm), NaN where none is (module docstring)."""
    seg = report.segmentation
    out = np.full(len(seg.face), np.nan)
    for row in report.faces:
        surface = row.form.surface_mm
        if surface is None or row.index < 0:
            continue
        idx = np.flatnonzero(seg.face == row.index)
        if len(idx) != len(surface):
            raise ValueError(f"{row.title}: {len(surface)} form-surface values for its {len(idx)} points")
        out[idx] = surface
    return out


def shown_count(report: Any, row: Any) -> int:
    """The points of a face the views colour (those its figures are taken over)."""
    s = row.form.surface_mm
    return int(np.isfinite(s).sum()) if s is not None else 0


def legend_strip(scale: ColourScale, height: int) -> np.ndarray:
    """An RGB uint8 panel (height, width, 3) with the scale's swatches and their meaning,
    for images that carry their own legend (the camera-image deviation map); its lettering
    grows with the image, so it reads at the size the image is shown."""
    import cv2

    k = max(height / 700.0, 0.6)  # lettering scale: about 0.6 of a line per 1 % of the image's height

    def at(v: float) -> int:
        return round(v * k)

    panel = np.full((max(height, at(330)), at(380), 3), 255, np.uint8)
    font, size, thick = cv2.FONT_HERSHEY_SIMPLEX, 0.45 * k, max(1, at(1.2))
    cv2.putText(panel, "deviation from nominal (mm)", (at(10), at(24)), font, size * 1.1, (0, 0, 0), thick,
                cv2.LINE_AA)
    rows = [(d, text, scale.rgb(np.array([d]))[0]) for d, text in reversed(scale.legend())]
    rows.append((np.nan, "no deviation shown (not in the figures)", np.full(3, GREY)))
    for j, (_, text, rgb) in enumerate(rows):
        y = at(44 + 30 * j)
        cv2.rectangle(panel, (at(10), y), (at(34), y + at(20)), tuple(round(255 * c) for c in rgb), -1)
        cv2.rectangle(panel, (at(10), y), (at(34), y + at(20)), (90, 90, 90), 1)
        cv2.putText(panel, text, (at(42), y + at(15)), font, size, (0, 0, 0), thick, cv2.LINE_AA)
    y = at(44 + 30 * len(rows) + 20)
    for j, line in enumerate(_wrap(f"tied to {scale.source}", 40)):
        cv2.putText(panel, line, (at(10), y + at(20) * j), font, size, (60, 60, 60), thick, cv2.LINE_AA)
    return panel[:height] if height >= len(panel) else panel


def _wrap(text: str, width: int) -> list[str]:
    lines, line = [], ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    return lines + [line]


def deviation_image(report: Any, scan: Any, scale: ColourScale | None = None) -> np.ndarray:
    """RGB uint8 image of the shown deviations (`shown_deviations`) in `scale` (default the
    report's): the camera image for organised scans, else a view along the cloud's z axis;
    dark grey for scan points that are not the part; the legend to its right."""
    scale = scale or scale_of(report)
    colours = np.full((len(scan), 3), 0.25)
    colours[report.part_mask] = scale.rgb(shown_deviations(report))
    if scan.pixels is not None:
        px, (h, w) = scan.pixels, scan.image_shape
    else:
        xy = scan.points[:, :2]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        res = 1000.0 / max(float((hi - lo).max()), 1e-9)
        px = np.floor((xy - lo) * res).astype(np.int64)
        w, h = (px.max(axis=0) + 1).tolist()
    img = np.zeros((h, w, 3), np.uint8)
    img[px[:, 1], px[:, 0]] = np.round(colours * 255).astype(np.uint8)
    strip = legend_strip(scale, h)
    if len(strip) < h:
        strip = np.vstack([strip, np.full((h - len(strip), strip.shape[1], 3), 255, np.uint8)])
    return np.hstack([img, strip[:h]])
