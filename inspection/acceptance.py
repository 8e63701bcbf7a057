"""The acceptance and reverification test of VDI/VDE 2634 Part 2 (optical 3D measuring
systems with area scanning): where the artefacts go, what is measured at each position,
and the quality parameters against their maximum permissible errors (MPE).

What this implements (lengths in mm; the measuring volume is a box of `size_mm` centred on
the camera axis at the rig's working distance, L0 its diagonal):

- probing error, with a sphere of calibrated diameter (0.1-0.2 L0) at 10 places: the
  centre of the volume, its 8 corners (inset so the whole sphere is inside) and the centre
  of its near face. A least-squares sphere with free radius is fitted to every point of
  the sphere's surface in the scan (its connected region, `find_spheres`), the 0.3 % of
  points furthest from it left out and the sphere fitted again (the guideline allows up to
  0.3 %). Probing error form PF = the range of the radial distances of the points from it;
  probing error size PS = measured diameter - calibrated diameter. The reported PF and PS
  are the largest (PS: largest in magnitude) over the places.
- sphere-spacing error, with a ball bar (two spheres, calibrated centre distance >= 0.3 L0)
  in 7 positions through the centre of the volume: along its 4 space diagonals, its width,
  its height and the diagonal of its horizontal (x-z) face. SD = measured - calibrated
  centre distance, both spheres fitted as for PS.
- flatness measurement error, with a flat of calibrated flatness (length >= 0.5 L0) in 6
  positions: facing the camera at the centre (long side across and, once, upright), at the
  near and far quarter of the depth, and tilted 30 degrees about each of its axes at the
  centre. F = the range of the signed distances from the least-squares plane of every
  point of the flat, the 0.3 % furthest left out (and the plane fitted again).

Beside the guideline's parameters, and judged against the same MPEs but named apart:
- OL, the ball bar's outer-length error: the centre distance plus both fitted radii less
  the certified distance plus diameter, as a two-point measurement across both spheres
  would read it; it is SD plus both spheres' size errors from the same fits. VDI/VDE
  2634-2 has no such parameter (its length measurement error E belongs to Part 3, and ISO
  10360-13's E is not implemented here), so it is not called E.

A named variant, "inner" (`INNER`), is reported beside every position and never decides
the test: the same fits over the artefact's inner region only, a band of `EDGE_MARGIN_PX`
pixels along each outline left out (the camera's blur mixes a surface's fringes there with
what lies beyond: on the simulator it made a 25 mm sphere's radius read +0.56 µm), sphere
points facing the camera at more than 75 degrees and further than 0.1 R from a first fit,
and flat points further than 1 mm from a first plane. The scanner's own uncertainty model
(`inspection.uncertainty`) holds there, so the variant's figures carry its U (`model_u`).

The test is complete only when every prescribed position was measured. A position the
operator skips (or that a stop leaves) is "not tested"; a parameter with a position not
tested has no verdict ("incomplete"), and the test's result is "incomplete", never a pass,
whatever the other positions read. An artefact not found in a position's scan makes its
parameters "not measured", and the test fails.

Each parameter is judged against its MPE from the rig file's [acceptance.mpe] table with an
ISO 14253-1 decision rule (`inspection.tolerances.decide`). The uncertainty of a test
value is that of the artefact's certificate (U of the diameter, the length, the flatness;
the artefact's own certified form enters PF and F as a systematic and is added to their
U); the scanner's own errors are what the test measures and are not in it.
"""

from __future__ import annotations

import html
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

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
from scanner.config import resolve
from scanner.errors import ConfigError
from scanner.rig_schema import AcceptanceTable

if TYPE_CHECKING:
    from scanner.rig import RigConfig

PARAMETERS = ("PF", "PS", "SD", "F", "OL")
NAMES = {"PF": "probing error form", "PS": "probing error size", "SD": "sphere-spacing error",
         "F": "flatness measurement error", "OL": "ball-bar outer-length error (not VDI/VDE 2634-2)"}
SIGNED = {"PS", "SD", "OL"}  # judged by magnitude, within +-MPE
INNER = ("inner: the fits over each artefact's inner region (a 3 px band along its outline, sphere points facing "
         "the camera at more than 75 degrees or beyond 0.1 R of a first fit, flat points beyond 1 mm of a first "
         "plane left out; then the 0.3 %); reported beside the guideline's figures, never deciding the test")
NOT_TESTED, INCOMPLETE = "not tested", "incomplete"
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
        OL_mm = 0.012                         # the ball bar's outer-length error (not a guideline parameter)
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
    def for_rig(cls, config: RigConfig) -> Acceptance:
        """From a rig's [acceptance] table (validated at load); errors name the file and key."""
        return cls.of(config.file.acceptance, config.path, config.working_distance_mm)

    @classmethod
    def of(cls, table: AcceptanceTable | None, path: Path, working_distance_mm: float) -> Acceptance:
        """From a rig file's [acceptance] table, the volume centred at `working_distance_mm`."""
        if table is None:
            raise ConfigError(path, "acceptance", "the rig has no [acceptance] table: give its measuring volume "
                                                  "and the MPEs to verify it against (see config/rigs/sim_bench.toml)")
        if table.decision_rule not in DECISION_RULES:
            raise ConfigError(path, "acceptance.decision_rule", f"{table.decision_rule!r}: use one of "
                                                                f"{sorted(DECISION_RULES)}")
        if table.mpe is None:
            raise ConfigError(path, "acceptance.mpe", "required key is missing")
        mpe = {k.removesuffix("_mm"): v for k, v in table.mpe.model_dump(exclude_none=True).items()}
        sx, sy, sz = table.volume_mm
        return cls((sx, sy, sz), (0.0, 0.0, working_distance_mm), mpe, table.decision_rule,
                   resolve(path, table.artefacts) if table.artefacts else None)


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
        places = [np.zeros(3)] + [inset * (np.array(s) * 2 - 1) for s in np.ndindex(2, 2, 2)] \
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
    _, labels, stats, _ = cv2.connectedComponentsWithStats(ok.view(np.uint8), connectivity=4)
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
    (H, W, 3) whose least-squares sphere has about `radius_mm` (within 10 %): every pixel
    of each (the guideline's fits take them all; `inner_pixels` gives the inner variant's)."""
    from inspection.artefacts import fit_sphere

    labels, sizes = regions(points)
    found: list[np.ndarray] = []
    for k in np.argsort(sizes[1:])[::-1] + 1:
        if sizes[k] < 100 or len(found) == count:
            break
        rows, cols = np.nonzero(labels == k)
        try:
            fit = fit_sphere(points[rows, cols].astype(np.float64))
        except ArtefactError:
            continue
        if abs(fit.radius - radius_mm) < 0.1 * radius_mm:
            found.append(np.stack([cols, rows], axis=1))
    if len(found) < count:
        raise ArtefactError(f"{len(found)} of {count} sphere(s) of radius {radius_mm:g} mm found in the scan")
    return found


def inner_of(pixels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The pixels (M, 2) of a surface's `pixels` (N, 2) (column, row) in an image of
    `shape` (H, W) less its outline band (`inner_pixels`)."""
    mask = np.zeros(shape, bool)
    mask[pixels[:, 1], pixels[:, 0]] = True
    rows, cols = np.nonzero(inner_pixels(mask))
    return np.stack([cols, rows], axis=1)


@dataclass(frozen=True)
class PositionResult:
    """One prescribed position: `tested` False when it was not scanned (skipped, or the
    test stopped before it: "not tested"); the guideline's figures (`values`: parameter ->
    mm), the inner variant's (`inner`, `INNER`) with each one's U from the scanner's own
    model (`model_u`: parameter -> U, about 95 %, mm), and the fits behind them; `error`:
    the artefact was not found."""

    position: Position
    values: dict[str, float]
    model_u: dict[str, float]
    detail: dict[str, Any]
    error: str = ""
    inner: dict[str, float] = field(default_factory=dict)
    tested: bool = True

    @classmethod
    def not_tested(cls, position: Position) -> PositionResult:
        return cls(position, {}, {}, {}, tested=False)

    @property
    def status(self) -> str:
        return NOT_TESTED if not self.tested else NOT_MEASURED if self.error else "measured"

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.position.name, "kind": self.position.kind, "description": self.position.description,
                "status": self.status, "pose": self.position.pose.tolist(),
                **{f"{k}_mm": v for k, v in self.values.items()},
                "inner": {**{f"{k}_mm": v for k, v in self.inner.items()},
                          **{f"{k}_model_u_mm": v for k, v in self.model_u.items()}},
                "detail": self.detail, **({"error": self.error} if self.error else {})}


def evaluate(position: Position, data: ScanData, artefacts: ArtefactSet) -> PositionResult:
    """The figures of one position's scan, the guideline's and the inner variant's; an
    artefact not found gives a result with `error` set (and no figures), which fails the
    test."""
    shape = data.points.shape[:2]

    def points_at(px: np.ndarray) -> np.ndarray:
        return data.points[px[:, 1], px[:, 0]].astype(np.float64)

    try:
        if position.kind == "sphere":
            s = artefacts.sphere
            assert s is not None
            (px,) = find_spheres(data.points, s.radius_mm, 1)
            inner_px = inner_of(px, shape)
            _, whole = measure_sphere(points_at(px), data.uncertainties(px), s.radius_mm, inner=False)
            _, inner = measure_sphere(points_at(inner_px), data.uncertainties(inner_px), s.radius_mm)
            return _sphere_result(position, whole, inner, s.diameter_mm)
        if position.kind == "ball_bar":
            b = artefacts.ball_bar
            assert b is not None
            pxs = find_spheres(data.points, b.radius_mm, 2)
            inner_pxs = [inner_of(p, shape) for p in pxs]
            def bar(sets: list[np.ndarray], inner: bool) -> BallBarResult:
                first, second = sets
                return measure_ball_bar((points_at(first), points_at(second)),
                                        (data.uncertainties(first), data.uncertainties(second)),
                                        b.radius_mm, inner=inner)

            bar_whole, bar_inner = bar(pxs, False), bar(inner_pxs, True)
            return _bar_result(position, bar_whole, bar_inner, b.length_mm, b.diameter_mm)
        p = artefacts.plane
        assert p is not None
        labels, sizes = regions(data.points)
        if len(sizes) < 2:
            raise ArtefactError("no surface in the scan")
        k = int(np.argmax(sizes[1:])) + 1
        plane_whole = measure_plane(data.points[labels == k].astype(np.float64))
        plane_inner = measure_plane(data.points[inner_pixels(labels == k)].astype(np.float64), band_mm=1.0)
        return _plane_result(position, plane_whole, plane_inner)
    except ArtefactError as exc:
        return PositionResult(position, {}, {}, {}, str(exc))


def _sphere_result(position: Position, whole: SphereResult, inner: SphereResult, diameter_mm: float) -> PositionResult:
    def figures(s: SphereResult) -> dict[str, float]:
        return {"PF": s.form_range_mm, "PS": 2.0 * s.radius.value_or_raise() - diameter_mm}

    return PositionResult(position, figures(whole), {"PS": 2.0 * inner.radius.U},
                          {"sphere": whole.as_dict(), "inner": inner.as_dict()}, inner=figures(inner))


def _bar_figures(bar: BallBarResult, length_mm: float, diameter_mm: float) -> dict[str, float]:
    return {"SD": bar.distance.value_or_raise() - length_mm,
            "OL": bar.outer_length.value_or_raise() - length_mm - diameter_mm}


def _bar_result(position: Position, whole: BallBarResult, inner: BallBarResult, length_mm: float,
                diameter_mm: float) -> PositionResult:
    return PositionResult(position, _bar_figures(whole, length_mm, diameter_mm),
                          {"SD": inner.distance.U, "OL": inner.outer_length.U},
                          {"ball_bar": whole.as_dict(), "inner": inner.as_dict()},
                          inner=_bar_figures(inner, length_mm, diameter_mm))


def _plane_result(position: Position, whole: PlaneResult, inner: PlaneResult) -> PositionResult:
    return PositionResult(position, {"F": whole.flatness_range_mm}, {}, {"plane": whole.as_dict(),
                                                                          "inner": inner.as_dict()},
                          inner={"F": inner.flatness_range_mm})


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
    if parameter == "OL" and b is not None:
        return float(np.hypot(b.length_u_mm, b.diameter_u_mm)) + b.form_mm
    if parameter == "F" and p is not None:
        return p.flatness_mm + p.flatness_u_mm
    return 0.0


@dataclass(frozen=True)
class AcceptanceReport:
    """The test: every prescribed position's figures (`results`, one per position of
    `positions(acceptance, artefacts)`, in order; a position missing counts as not
    tested), each parameter's test value (the largest over its positions, by magnitude
    for signed ones), U, MPE and verdict, and the test's `status`: "pass" (every position
    measured, every parameter with an MPE conforming under the decision rule),
    "incomplete" (a prescribed position not tested) or "fail"."""

    rig: str
    calibration: str
    acceptance: Acceptance
    artefacts: ArtefactSet
    results: tuple[PositionResult, ...]
    notes: dict[str, str] = field(default_factory=dict)

    @property
    def all_results(self) -> tuple[PositionResult, ...]:
        """A result for every prescribed position: the ones given, the others not tested."""
        given = {r.position.name: r for r in self.results}
        return tuple(given.get(p.name) or PositionResult.not_tested(p)
                     for p in positions(self.acceptance, self.artefacts))

    def not_tested(self) -> list[str]:
        return [r.position.name for r in self.all_results if not r.tested]

    def value(self, parameter: str, inner: bool = False) -> float | None:
        vals = [(r.inner if inner else r.values)[parameter] for r in self.all_results
                if parameter in (r.inner if inner else r.values)]
        if not vals:
            return None
        return float(max(vals, key=abs)) if parameter in SIGNED else float(max(vals))

    def verdict(self, parameter: str) -> str:
        mpe = self.acceptance.mpe.get(parameter)
        if mpe is None:
            return "no MPE"
        mine = [r for r in self.all_results if _measures(r.position.kind, parameter)]
        if not mine or all(not r.tested for r in mine):
            return NOT_TESTED
        if any(not r.tested for r in mine):
            return INCOMPLETE
        v = self.value(parameter)
        if v is None or any(r.error for r in mine):
            return NOT_MEASURED
        U = test_uncertainty(parameter, self.artefacts)
        return decide(v, U, mpe, -mpe if parameter in SIGNED else None, self.acceptance.decision_rule)

    @property
    def status(self) -> str:
        if self.not_tested():
            return INCOMPLETE
        ok = all(self.verdict(p) == CONFORMING for p in self.acceptance.mpe) and not any(r.error for r in self.results)
        return "pass" if ok and any(self.value(p) is not None for p in self.acceptance.mpe) else "fail"

    @property
    def passed(self) -> bool:
        return self.status == "pass"

    def headline(self) -> str:
        missing = self.not_tested()
        total = len(self.all_results)
        if missing:
            return (f"INCOMPLETE: {total - len(missing)} of {total} prescribed positions tested; not tested: "
                    f"{', '.join(missing)} (no verdict)")
        return "PASS" if self.passed else "FAIL"

    def as_dict(self) -> dict[str, Any]:
        return {**{f"{p}_mm": self.value(p) for p in PARAMETERS},
                **{f"{p}_u_mm": test_uncertainty(p, self.artefacts) for p in PARAMETERS},
                "mpe": {f"{p}_mm": v for p, v in self.acceptance.mpe.items()},
                "verdicts": {p: self.verdict(p) for p in PARAMETERS}, "status": self.status, "pass": self.passed,
                "positions_prescribed": len(self.all_results), "positions_not_tested": self.not_tested(),
                "names": {p: NAMES[p] for p in PARAMETERS},
                "inner": {"definition": INNER, **{f"{p}_mm": self.value(p, inner=True) for p in PARAMETERS}},
                "decision_rule": self.acceptance.decision_rule, "rule": DECISION_RULES[self.acceptance.decision_rule],
                "rig": self.rig, "calibration": self.calibration,
                "volume_mm": list(self.acceptance.size_mm), "L0_mm": self.acceptance.L0_mm,
                "artefacts": self.artefacts.as_dict(), "notes": self.notes,
                "positions": [r.as_dict() for r in self.all_results]}

    def table(self) -> str:
        """Per position and overall, in µm, for the terminal."""
        order = ("PF", "PS", "SD", "OL", "F")
        lines = [f"{'position':<12} " + " ".join(f"{p:>9}" for p in order) + "   inner variant (model U)   what"]
        for r in self.all_results:
            cells = [f"{r.values[p] * 1e3:9.1f}" if p in r.values else f"{'-':>9}" for p in order]
            inner = ", ".join(f"{p} {v * 1e3:.1f}" + (f"±{r.model_u[p] * 1e3:.1f}" if p in r.model_u else "")
                              for p, v in r.inner.items()) or "-"
            what = ("NOT TESTED" if not r.tested else f"NOT MEASURED: {r.error}" if r.error
                    else r.position.description)
            lines.append(f"{r.position.name:<12} {' '.join(cells)}   {inner:<24}  {what}")
        lines.append("")
        lines.append(f"{'parameter':<52} {'value':>9} {'U':>7} {'MPE':>8}  verdict")
        for p in PARAMETERS:
            v, mpe = self.value(p), self.acceptance.mpe.get(p)
            value = f"{v * 1e3:9.1f}" if v is not None else f"{'-':>9}"
            limit = f"{mpe * 1e3:8.1f}" if mpe else f"{'-':>8}"
            lines.append(f"{NAMES[p] + ' ' + p:<52} {value} {test_uncertainty(p, self.artefacts) * 1e3:7.1f} "
                         f"{limit}  {self.verdict(p)}")
        lines.append(f"(µm; U of the test value from the artefact certificates, k = 2; decision rule "
                     f"{self.acceptance.decision_rule}: {DECISION_RULES[self.acceptance.decision_rule]}; "
                     f"{INNER})")
        lines.append(f"{self.headline()}: rig {self.rig}, {self.calibration}")
        return "\n".join(lines)

    def html(self) -> str:
        d = self.as_dict()
        order = ("PF", "PS", "SD", "OL", "F")

        def um(x: float | None) -> str:
            return "-" if x is None else f"{x * 1e3:.1f}"

        rows = "".join(
            f"<tr class='{'not-tested' if not r.tested else ''}'><td>{html.escape(r.position.name)}</td>"
            + "".join(f"<td>{um(r.values.get(p))}</td>" for p in order)
            + "".join(f"<td>{um(r.inner.get(p))}</td>" for p in order)
            + f"<td>{html.escape('NOT TESTED' if not r.tested else r.error or r.position.description)}</td></tr>"
            for r in self.all_results)
        summary = "".join(f"<tr><td>{html.escape(NAMES[p])} {p}</td><td>{um(d[f'{p}_mm'])}</td>"
                          f"<td>{um(d[f'{p}_u_mm'])}</td><td>{um(self.acceptance.mpe.get(p))}</td>"
                          f"<td class='{d['verdicts'][p].replace(' ', '-')}'>{d['verdicts'][p]}</td></tr>"
                          for p in PARAMETERS)
        return (f"<!doctype html><html><head><meta charset='utf-8'>"
                f"<title>Acceptance test {html.escape(self.rig)}</title>"
                f"<style>body{{font-family:sans-serif}}td,th{{padding:2px 8px;text-align:right}}"
                f".conforming{{background:#cfc}}.non-conforming{{background:#fcc}}.uncertain{{background:#ffc}}"
                f".incomplete,.not-tested,tr.not-tested{{background:#ddd}}"
                f"</style></head><body><h1>Acceptance test (VDI/VDE 2634 Part 2): {html.escape(self.headline())}"
                f"</h1><p>rig {html.escape(self.rig)}; {html.escape(self.calibration)}; measuring volume "
                f"{' x '.join(f'{s:g}' for s in self.acceptance.size_mm)} mm (L0 {self.acceptance.L0_mm:.0f} mm); "
                f"artefacts {html.escape(self.artefacts.name)}</p>"
                f"<h2>Quality parameters</h2><table><tr><th>parameter</th><th>value (µm)</th><th>U (µm, k = 2)</th>"
                f"<th>MPE (µm)</th><th>verdict</th></tr>{summary}</table>"
                f"<p>Decision rule {html.escape(self.acceptance.decision_rule)}: "
                f"{html.escape(DECISION_RULES[self.acceptance.decision_rule])}. U of a test value: the artefact "
                f"certificate's. A position not tested leaves its parameters without a verdict and the test "
                f"incomplete.</p><h2>Positions</h2><table><tr><th>position</th>"
                + "".join(f"<th>{p}</th>" for p in order) + "".join(f"<th>{p} inner</th>" for p in order)
                + f"<th>placement</th></tr>{rows}</table><p>µm. {html.escape(INNER)}.</p>"
                + "".join(f"<p>{html.escape(k)}: {html.escape(v)}</p>" for k, v in self.notes.items())
                + "</body></html>")


MEASURED_BY = {"sphere": ("PF", "PS"), "ball_bar": ("SD", "OL"), "plane": ("F",)}


def _measures(kind: str, parameter: str) -> bool:
    return parameter in MEASURED_BY[kind]
