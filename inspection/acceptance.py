"""The acceptance and reverification test of VDI/VDE 2634 Part 2 (optical 3D measuring
systems with area scanning): where the artefacts go, what is measured at each position,
and the quality parameters against their maximum permissible errors (MPE).

What this implements (lengths in mm; the measuring volume is a box of `size_mm` centred on
the camera axis at the rig's working distance, L0 its diagonal):

- probing error, with a sphere of calibrated diameter (0.1-0.2 L0) at 10 places: the
  centre of the volume, its 8 corners (inset so the whole sphere is inside) and the centre
  of its near face. A least-squares sphere with free radius is fitted to each scan
  (`inspection.artefacts.fit_sphere`), less a band of `EDGE_MARGIN_PX` pixels along its
  silhouette (`find_spheres`). Probing error form PF = the range of the radial
  distances of the points from it, the 0.3 % of points furthest from it left out (the
  guideline allows up to 0.3 %); probing error size PS = measured diameter - calibrated
  diameter. The reported PF and PS are the largest (PS: largest in magnitude) over the places.
- sphere-spacing error, with a ball bar (two spheres, calibrated centre distance >= 0.3 L0)
  in 7 positions through the centre of the volume: along its 4 space diagonals, its width,
  its height and the diagonal of its horizontal (x-z) face. SD = measured - calibrated
  centre distance. Length measurement error E = the same for the outer length, centre
  distance plus both radii (as a two-point measurement across both spheres would take
  it): SD plus the spheres' size errors.
- flatness measurement error, with a flat of calibrated flatness (length >= 0.5 L0) in 6
  positions: facing the camera at the centre (long side across and, once, upright), at the
  near and far quarter of the depth, and tilted 30 degrees about each of its axes at the
  centre. F = the range of the signed distances from the least-squares plane, the 0.3 % of
  points furthest from it left out, over the flat less a band of `EDGE_MARGIN_PX` pixels
  along its outline (those pixels see the flat's edge and what lies behind it at once).

Each parameter is judged against its MPE from the rig file's [acceptance.mpe] table with an
ISO 14253-1 decision rule (`inspection.tolerances.decide`). The uncertainty of a test
value is that of the artefact's certificate (U of the diameter, the length, the flatness;
the artefact's own certified form enters PF and F as a systematic and is added to their
U); the scanner's own errors are what the test measures and are not in it. Each
position also reports the measured figure's own uncertainty from the scanner's model
(`inspection.uncertainty`), so the figure's error can be read against it.
"""

from __future__ import annotations

import html
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from inspection.artefact_file import ArtefactSet
from inspection.artefacts import (
    ArtefactError,
    BallBarResult,
    PlaneResult,
    SphereResult,
    measure_ball_bar,
    measure_plane,
    measure_sphere,
)
from inspection.tolerances import CONFORMING, DECISION_RULES, GUARD_BANDED, NOT_MEASURED, decide
from inspection.uncertainty import ScanUncertainty
from scanner.config import get, get_table, get_vector, resolve
from scanner.errors import ConfigError

PARAMETERS = ("PF", "PS", "SD", "F", "E")
NAMES = {"PF": "probing error form", "PS": "probing error size", "SD": "sphere-spacing error",
         "F": "flatness measurement error", "E": "length measurement error"}
SIGNED = {"PS", "SD", "E"}  # judged by magnitude, within +-MPE
PLANE_TILT_DEG = 30.0
MAX_STEP_MM = 1.0  # neighbouring pixels further apart than this belong to different surfaces
EDGE_MARGIN_PX = 3  # the flat's pixels this close to its outline are left out (mixed with what lies behind)


# ------------------------------------------------------------------- volume and MPEs


@dataclass(frozen=True)
class Acceptance:
    """The rig file's [acceptance] table: the measuring volume, the MPEs, the decision
    rule and the artefact file.

        [acceptance]
        volume_mm = [130.0, 110.0, 80.0]      # width, height, depth of the measuring volume
        artefacts = "../artefacts/sim_bench.toml"
        decision_rule = "guard-banded"        # or "plain" (inspection.tolerances.DECISION_RULES)
        [acceptance.mpe]                      # maximum permissible errors (mm)
        PF_mm = 0.100
        PS_mm = 0.005
        SD_mm = 0.010
        F_mm = 0.100
        E_mm = 0.012
    """

    size_mm: tuple[float, float, float]
    centre_mm: tuple[float, float, float]
    mpe: dict[str, float]
    decision_rule: str = GUARD_BANDED
    artefacts: Path | None = None

    @property
    def L0_mm(self) -> float:
        return float(np.linalg.norm(self.size_mm))

    @classmethod
    def from_rig(cls, raw: dict[str, Any], path: Path, working_distance_mm: float) -> Acceptance:
        """From a rig TOML's content (`RigConfig.raw`); errors name the file and key."""
        if "acceptance" not in raw:
            raise ConfigError(path, "acceptance", "the rig has no [acceptance] table: give its measuring volume "
                                                  "and the MPEs to verify it against (see config/rigs/sim_bench.toml)")
        t = get_table(raw, "acceptance", path)
        known = {"volume_mm", "artefacts", "decision_rule", "mpe"}
        for k in t:
            if k not in known:
                raise ConfigError(path, f"acceptance.{k}", f"unknown key; expected one of {sorted(known)}")
        size = tuple(get_vector(t, "volume_mm", 3, path, prefix="acceptance"))
        if not all(s > 0 for s in size):
            raise ConfigError(path, "acceptance.volume_mm", f"sizes must be > 0, got {list(size)}")
        rule = get(t, "decision_rule", str, path, GUARD_BANDED, "acceptance")
        if rule not in DECISION_RULES:
            raise ConfigError(path, "acceptance.decision_rule", f"{rule!r}: use one of {sorted(DECISION_RULES)}")
        m = get_table(t, "mpe", path, prefix="acceptance")
        mpe = {}
        for k, v in m.items():
            name = k.removesuffix("_mm")
            if name not in PARAMETERS or not k.endswith("_mm"):
                raise ConfigError(path, f"acceptance.mpe.{k}", f"unknown parameter; use {[p + '_mm' for p in PARAMETERS]}")
            value = get(m, k, float, path, prefix="acceptance.mpe")
            if not 0 < value < np.inf:
                raise ConfigError(path, f"acceptance.mpe.{k}", f"an MPE must be a finite number > 0 (mm), got {value}")
            mpe[name] = value
        art = get(t, "artefacts", str, path, None, "acceptance")
        return cls(size, (0.0, 0.0, working_distance_mm), mpe, rule, resolve(path, art) if art else None)  # type: ignore[arg-type]


# ------------------------------------------------------------------------- positions


@dataclass(frozen=True)
class Position:
    """One placement of an artefact: `kind` (sphere, ball_bar, plane), its `pose`
    (artefact frame -> the rig's world frame, mm: a sphere's centre at the origin; a ball
    bar's centre at the origin, its spheres at +-length/2 along x; a plane's centre at
    the origin, its long side along x, its normal along z) and what to tell an operator."""

    kind: str
    index: int
    pose: np.ndarray
    description: str

    @property
    def name(self) -> str:
        return f"{self.kind}-{self.index + 1}"


def pose_of(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def frame_along(direction: np.ndarray) -> np.ndarray:
    """A rotation whose x axis is `direction` and whose z axis points as much toward the
    camera (-z of the world) as it can."""
    x = direction / np.linalg.norm(direction)
    z = np.array([0.0, 0.0, -1.0]) - x * (-x[2])
    if np.linalg.norm(z) < 1e-6:
        z = np.array([0.0, -1.0, 0.0])
    z /= np.linalg.norm(z)
    return np.column_stack([x, np.cross(z, x), z])


def _where(offset: np.ndarray, half: np.ndarray) -> str:
    words = []
    for value, h, (neg, pos) in zip(offset, half, (("left", "right"), ("top", "bottom"), ("near", "far"))):
        if abs(value) > 0.25 * h:
            words.append(pos if value > 0 else neg)
    if words in (["near"], ["far"]):
        return f"centre of the {words[0]} face"
    return "-".join(words) if words else "centre"


def positions(acceptance: Acceptance, artefacts: ArtefactSet) -> list[Position]:
    """The test's positions for the artefacts given (see the module docstring)."""
    c = np.array(acceptance.centre_mm)
    half = np.array(acceptance.size_mm) / 2.0
    out: list[Position] = []
    if artefacts.sphere is not None:
        inset = half - artefacts.sphere.radius_mm - 2.0
        if (inset <= 0).any():
            raise ConfigError(artefacts.path or "artefacts", "sphere.diameter_mm",
                              f"a sphere of {artefacts.sphere.diameter_mm} mm does not fit the measuring volume "
                              f"{list(acceptance.size_mm)} mm")
        places = [np.zeros(3)] + [inset * np.array(s) for s in np.ndindex(2, 2, 2) for s in [np.array(s) * 2 - 1]] \
            + [np.array([0.0, 0.0, -inset[2]])]
        for i, p in enumerate(places):
            out.append(Position("sphere", i, pose_of(np.eye(3), c + p),
                                f"sphere at the {_where(p, half)} of the measuring volume, its centre at "
                                f"({', '.join(f'{v:.0f}' for v in c + p)}) mm"))
    if artefacts.ball_bar is not None:
        L = artefacts.ball_bar.length_mm
        dirs = [("space diagonal, top-left-near to bottom-right-far", half * [1, 1, 1]),
                ("space diagonal, top-right-near to bottom-left-far", half * [-1, 1, 1]),
                ("space diagonal, bottom-left-near to top-right-far", half * [1, -1, 1]),
                ("space diagonal, bottom-right-near to top-left-far", half * [-1, -1, 1]),
                ("across, left to right", np.array([1.0, 0.0, 0.0])),
                ("upright, top to bottom", np.array([0.0, 1.0, 0.0])),
                ("diagonal of the horizontal face, left-near to right-far", half * [1, 0, 1])]
        for i, (words, d) in enumerate(dirs):
            R = frame_along(np.asarray(d, dtype=np.float64))
            reach = np.abs(R[:, 0]) * (L / 2 + artefacts.ball_bar.radius_mm)
            if (reach > half + 1e-9).any():
                raise ConfigError(artefacts.path or "artefacts", "ball_bar.length_mm",
                                  f"a ball bar of {L} mm does not fit the measuring volume {list(acceptance.size_mm)} "
                                  f"mm along its {words}")
            out.append(Position("ball_bar", i, pose_of(R, c), f"ball bar through the centre, {words}"))
    if artefacts.plane is not None:
        a, b = artefacts.plane.size_mm
        t = np.radians(PLANE_TILT_DEG)
        places = [("facing the camera at the centre, long side across", np.eye(3), np.zeros(3)),
                  ("facing the camera at the centre, long side upright",
                   cv2.Rodrigues(np.array([0.0, 0.0, np.pi / 2]))[0], np.zeros(3)),
                  ("facing the camera a quarter of the depth nearer", np.eye(3), np.array([0, 0, -half[2] / 2])),
                  ("facing the camera a quarter of the depth farther", np.eye(3), np.array([0, 0, half[2] / 2])),
                  (f"at the centre, tilted {PLANE_TILT_DEG:g} degrees about its long side",
                   cv2.Rodrigues(np.array([t, 0.0, 0.0]))[0], np.zeros(3)),
                  (f"at the centre, tilted {PLANE_TILT_DEG:g} degrees about its short side",
                   cv2.Rodrigues(np.array([0.0, t, 0.0]))[0], np.zeros(3))]
        for i, (words, R, p) in enumerate(places):
            corners = np.array([[sx * a / 2, sy * b / 2, 0.0] for sx in (-1, 1) for sy in (-1, 1)]) @ R.T + p
            if (np.abs(corners) > half + 1e-9).any():
                raise ConfigError(artefacts.path or "artefacts", "plane.size_mm",
                                  f"a flat of {a} x {b} mm does not fit the measuring volume "
                                  f"{list(acceptance.size_mm)} mm {words}")
            out.append(Position("plane", i, pose_of(R, c + p), f"flat {words}"))
    return out


# ------------------------------------------------------------------------ evaluation


def regions(points: np.ndarray, max_step_mm: float = MAX_STEP_MM) -> tuple[np.ndarray, np.ndarray]:
    """Connected surfaces of an organised cloud (H, W, 3), NaN invalid: (labels (H, W),
    pixel counts per label, label 0 = invalid or a depth step)."""
    valid = np.isfinite(points).all(axis=2)
    z = np.where(valid, points[..., 2], np.nan)
    ok = valid.copy()
    with np.errstate(invalid="ignore"):
        for axis in (0, 1):
            jump = np.abs(np.diff(z, axis=axis)) > max_step_mm
            if axis == 0:
                ok[:-1] &= ~jump
                ok[1:] &= ~jump
            else:
                ok[:, :-1] &= ~jump
                ok[:, 1:] &= ~jump
    n, labels, stats, _ = cv2.connectedComponentsWithStats(ok.view(np.uint8), connectivity=4)
    return labels, stats[:, cv2.CC_STAT_AREA]


@dataclass(frozen=True, eq=False)
class ScanData:
    """What evaluating one position needs: the organised cloud (H, W, 3) in the rig's
    world frame, and a function giving the ScanUncertainty of the points at pixels (N, 2)
    (column, row)."""

    points: np.ndarray
    uncertainties: Callable[[np.ndarray], ScanUncertainty]


def inner_pixels(surface: np.ndarray) -> np.ndarray:
    """The pixels (H, W) bool of a `surface` mask less the band of `EDGE_MARGIN_PX` along its
    outline, whose blurred images mix the surface with what lies beside it."""
    kernel = np.ones((2 * EDGE_MARGIN_PX + 1,) * 2, np.uint8)
    return cv2.erode(surface.view(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


def find_spheres(points: np.ndarray, radius_mm: float, count: int) -> list[np.ndarray]:
    """Pixels (N, 2) (column, row) of the `count` largest surfaces of an organised cloud
    (H, W, 3) whose least-squares sphere has about `radius_mm` (within 10 %), less their
    outline band (`inner_pixels`): at a sphere's silhouette the camera's blur mixes its
    fringes with the dark beyond and moves the decoded phase outward (on the simulator's
    bench rig, camera blur σ 0.6 px, the band made the radius of a 25 mm sphere read
    +0.56 µm on noise-free scans; without it, +0.01 µm, as with no blur)."""
    from inspection.artefacts import fit_sphere

    labels, sizes = regions(points)
    found = []
    for k in np.argsort(sizes[1:])[::-1] + 1:
        if sizes[k] < 100 or len(found) == count:
            break
        rows, cols = np.nonzero(labels == k)
        try:
            fit = fit_sphere(points[rows, cols].astype(np.float64))
        except ArtefactError:
            continue
        if abs(fit.radius - radius_mm) < 0.1 * radius_mm:
            rows, cols = np.nonzero(inner_pixels(labels == k))
            found.append(np.stack([cols, rows], axis=1))
    if len(found) < count:
        raise ArtefactError(f"{len(found)} of {count} sphere(s) of radius {radius_mm:g} mm found in the scan")
    return found


@dataclass(frozen=True)
class PositionResult:
    """One position's measured figures (`values`: parameter -> mm), each figure's own
    uncertainty from the scanner's model (`model_u`: parameter -> U, about 95 %, mm), and the
    fit behind them."""

    position: Position
    values: dict[str, float]
    model_u: dict[str, float]
    detail: dict[str, Any]
    error: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.position.name, "kind": self.position.kind, "description": self.position.description,
                "pose": self.position.pose.tolist(), **{f"{k}_mm": v for k, v in self.values.items()},
                **{f"{k}_model_u_mm": v for k, v in self.model_u.items()}, "detail": self.detail,
                **({"error": self.error} if self.error else {})}


def evaluate(position: Position, data: ScanData, artefacts: ArtefactSet) -> PositionResult:
    """The figures of one position's scan; an artefact not found gives a result with
    `error` set (and no figures), which fails the test."""
    try:
        if position.kind == "sphere":
            s = artefacts.sphere
            assert s is not None
            (px,) = find_spheres(data.points, s.radius_mm, 1)
            _, res = measure_sphere(data.points[px[:, 1], px[:, 0]].astype(np.float64), data.uncertainties(px),
                                    s.radius_mm)
            return _sphere_result(position, res, s.diameter_mm)
        if position.kind == "ball_bar":
            b = artefacts.ball_bar
            assert b is not None
            pxs = find_spheres(data.points, b.radius_mm, 2)
            bar = measure_ball_bar(tuple(data.points[p[:, 1], p[:, 0]].astype(np.float64) for p in pxs),  # type: ignore[arg-type]
                                   tuple(data.uncertainties(p) for p in pxs), b.radius_mm)  # type: ignore[arg-type]
            return _bar_result(position, bar, b.length_mm, b.diameter_mm)
        p = artefacts.plane
        assert p is not None
        labels, sizes = regions(data.points)
        if len(sizes) < 2:
            raise ArtefactError("no surface in the scan")
        k = int(np.argmax(sizes[1:])) + 1
        plane = measure_plane(data.points[inner_pixels(labels == k)].astype(np.float64), band_mm=1.0)
        return _plane_result(position, plane)
    except ArtefactError as exc:
        return PositionResult(position, {}, {}, {}, str(exc))


def _sphere_result(position: Position, res: SphereResult, diameter_mm: float) -> PositionResult:
    return PositionResult(position, {"PF": res.form_range_mm, "PS": 2.0 * res.radius.value - diameter_mm},  # type: ignore[operator]
                          {"PS": 2.0 * res.radius.U}, res.as_dict())


def _bar_result(position: Position, bar: BallBarResult, length_mm: float, diameter_mm: float) -> PositionResult:
    return PositionResult(position, {"SD": bar.distance.value - length_mm,  # type: ignore[operator]
                                     "E": bar.outer_length.value - length_mm - diameter_mm},  # type: ignore[operator]
                          {"SD": bar.distance.U, "E": bar.outer_length.U}, bar.as_dict())


def _plane_result(position: Position, plane: PlaneResult) -> PositionResult:
    return PositionResult(position, {"F": plane.flatness_range_mm}, {}, plane.as_dict())


# ---------------------------------------------------------------------------- report


def test_uncertainty(parameter: str, artefacts: ArtefactSet) -> float:
    """U (k = 2, mm) of a test value from the artefact's certificate (module docstring)."""
    s, b, p = artefacts.sphere, artefacts.ball_bar, artefacts.plane
    if parameter == "PF" and s is not None:
        return s.form_mm + s.diameter_u_mm / 2.0
    if parameter == "PS" and s is not None:
        return s.diameter_u_mm
    if parameter == "SD" and b is not None:
        return b.length_u_mm
    if parameter == "E" and b is not None:
        return float(np.hypot(b.length_u_mm, b.diameter_u_mm)) + b.form_mm
    if parameter == "F" and p is not None:
        return p.flatness_mm + p.flatness_u_mm
    return 0.0


@dataclass(frozen=True)
class AcceptanceReport:
    """The test: every position's figures, each parameter's test value (the largest over
    its positions, by magnitude for signed ones), U, MPE and verdict, and whether the rig
    passed (every parameter with an MPE conforming under the decision rule)."""

    rig: str
    calibration: str
    acceptance: Acceptance
    artefacts: ArtefactSet
    results: tuple[PositionResult, ...]
    notes: dict[str, str] = field(default_factory=dict)

    def value(self, parameter: str) -> float | None:
        vals = [r.values[parameter] for r in self.results if parameter in r.values]
        if not vals:
            return None
        return float(max(vals, key=abs)) if parameter in SIGNED else float(max(vals))

    def verdict(self, parameter: str) -> str:
        mpe = self.acceptance.mpe.get(parameter)
        v = self.value(parameter)
        if mpe is None:
            return "no MPE"
        if v is None or any(r.error for r in self.results if _measures(r.position.kind, parameter)):
            return NOT_MEASURED
        U = test_uncertainty(parameter, self.artefacts)
        return decide(v, U, mpe, -mpe if parameter in SIGNED else None, self.acceptance.decision_rule)

    @property
    def passed(self) -> bool:
        checked = [p for p in PARAMETERS if p in self.acceptance.mpe and self.value(p) is not None]
        return bool(checked) and all(self.verdict(p) == CONFORMING for p in self.acceptance.mpe) \
            and not any(r.error for r in self.results)

    def as_dict(self) -> dict[str, Any]:
        return {**{f"{p}_mm": self.value(p) for p in PARAMETERS},
                **{f"{p}_u_mm": test_uncertainty(p, self.artefacts) for p in PARAMETERS},
                "mpe": {f"{p}_mm": v for p, v in self.acceptance.mpe.items()},
                "verdicts": {p: self.verdict(p) for p in PARAMETERS}, "pass": self.passed,
                "decision_rule": self.acceptance.decision_rule, "rule": DECISION_RULES[self.acceptance.decision_rule],
                "rig": self.rig, "calibration": self.calibration,
                "volume_mm": list(self.acceptance.size_mm), "L0_mm": self.acceptance.L0_mm,
                "artefacts": self.artefacts.as_dict(), "notes": self.notes,
                "positions": [r.as_dict() for r in self.results]}

    def table(self) -> str:
        """Per position and overall, in µm, for the terminal."""
        lines = [f"{'position':<12} {'PF':>9} {'PS':>9} {'SD':>9} {'E':>9} {'F':>9}   model U (PS/SD/E)   what"]
        for r in self.results:
            cells = [f"{r.values[p] * 1e3:9.1f}" if p in r.values else f"{'-':>9}" for p in ("PF", "PS", "SD", "E", "F")]
            mu = "/".join(f"{r.model_u[p] * 1e3:.1f}" for p in ("PS", "SD", "E") if p in r.model_u) or "-"
            lines.append(f"{r.position.name:<12} {' '.join(cells)}   {mu:>17}   "
                         + (f"NOT MEASURED: {r.error}" if r.error else r.position.description))
        lines.append("")
        lines.append(f"{'parameter':<32} {'value':>9} {'U':>7} {'MPE':>8}  verdict")
        for p in PARAMETERS:
            v, mpe = self.value(p), self.acceptance.mpe.get(p)
            value = f"{v * 1e3:9.1f}" if v is not None else f"{'-':>9}"
            limit = f"{mpe * 1e3:8.1f}" if mpe else f"{'-':>8}"
            lines.append(f"{NAMES[p] + ' ' + p:<32} {value} {test_uncertainty(p, self.artefacts) * 1e3:7.1f} "
                         f"{limit}  {self.verdict(p)}")
        lines.append(f"(µm; U of the test value from the artefact certificates, k = 2; decision rule "
                     f"{self.acceptance.decision_rule}: {DECISION_RULES[self.acceptance.decision_rule]})")
        lines.append(f"{'PASS' if self.passed else 'FAIL'}: rig {self.rig}, {self.calibration}")
        return "\n".join(lines)

    def html(self) -> str:
        d = self.as_dict()
        rows = "".join(
            f"<tr><td>{html.escape(r.position.name)}</td>"
            + "".join(f"<td>{r.values[p] * 1e3:.1f}</td>" if p in r.values else "<td>-</td>"
                      for p in ("PF", "PS", "SD", "E", "F"))
            + f"<td>{html.escape(r.error or r.position.description)}</td></tr>" for r in self.results)
        def um(x: float | None) -> str:
            return "-" if x is None else f"{x * 1e3:.1f}"

        summary = "".join(f"<tr><td>{NAMES[p]} {p}</td><td>{um(d[f'{p}_mm'])}</td><td>{um(d[f'{p}_u_mm'])}</td>"
                          f"<td>{um(self.acceptance.mpe.get(p))}</td><td class='{d['verdicts'][p]}'>"
                          f"{d['verdicts'][p]}</td></tr>" for p in PARAMETERS)
        return (f"<!doctype html><html><head><meta charset='utf-8'><title>Acceptance test {html.escape(self.rig)}</title>"
                f"<style>body{{font-family:sans-serif}}td,th{{padding:2px 8px;text-align:right}}"
                f".conforming{{background:#cfc}}.non-conforming{{background:#fcc}}.uncertain{{background:#ffc}}"
                f"</style></head><body><h1>Acceptance test (VDI/VDE 2634 Part 2): {'PASS' if self.passed else 'FAIL'}"
                f"</h1><p>rig {html.escape(self.rig)}; {html.escape(self.calibration)}; measuring volume "
                f"{' x '.join(f'{s:g}' for s in self.acceptance.size_mm)} mm (L0 {self.acceptance.L0_mm:.0f} mm); "
                f"artefacts {html.escape(self.artefacts.name)}</p>"
                f"<h2>Quality parameters</h2><table><tr><th>parameter</th><th>value (µm)</th><th>U (µm, k = 2)</th>"
                f"<th>MPE (µm)</th><th>verdict</th></tr>{summary}</table>"
                f"<p>Decision rule {html.escape(self.acceptance.decision_rule)}: "
                f"{html.escape(DECISION_RULES[self.acceptance.decision_rule])}. U of a test value: the artefact "
                f"certificate's.</p><h2>Positions</h2><table><tr><th>position</th><th>PF</th><th>PS</th><th>SD</th>"
                f"<th>E</th><th>F</th><th>placement</th></tr>{rows}</table><p>µm.</p>"
                + "".join(f"<p>{html.escape(k)}: {html.escape(v)}</p>" for k, v in self.notes.items())
                + "</body></html>")


MEASURED_BY = {"sphere": ("PF", "PS"), "ball_bar": ("SD", "E"), "plane": ("F",)}


def _measures(kind: str, parameter: str) -> bool:
    return parameter in MEASURED_BY[kind]
