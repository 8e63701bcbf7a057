"""The calibration procedure: capture (on a rig) or read (from disk), solve, validate, write.

On a rig (`calibrate_rig`), with a `Bench` that places things in front of it — an
operator told what to do, or the simulator moving them:

  1. the board at its first pose: flat grey levels measure the projector's response (gamma);
  2. board poses, each captured under white, black and fringes in both orientations
     (pre-compensated with the measured gamma), decoded and checked at once: the corners
     found, their projector pixels, the coverage of both images and the tilts so far, and
     what poses are still needed, on the terminal and in Rerun;
  3. the solution (camera, projector, joint refinement) and its reprojection limits;
  4. a plate on a stage at known heights (phase-to-height, Eq. 17), once more at the
     reference height without gamma compensation (to show what it is worth);
  5. the validation artefact, scanned and measured with the new calibration;
  6. the calibration file, only if every limit is met.

From disk (`calibrate_capture`, `calibrate_views`) the same steps run on what was captured
before; whatever a capture lacks (gamma, plate, artefact) is reported as not measured.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from itertools import pairwise
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from calibration.board import Board
from calibration.calibration_recording import CalibrationRecording
from calibration.capture import capture_fringes, capture_pose, capture_uncompensated, show_images
from calibration.coverage import Coverage, needed_poses, tilt_deg
from calibration.errors import CalibrationError, CalibrationRejected, DetectionError, NotEnoughData
from calibration.fit import fit_plane, plane_rms
from calibration.gamma import DEFAULT_LEVELS, GammaFit, fit_gamma, flat_images, phase_error_rad
from calibration.intrinsics import calibrate_device
from calibration.phase_height import PhaseHeightFit, evaluate, fit_phase_to_height, local_pitch_range_mm
from calibration.solve import (
    OUTLIER_ALPHA,
    OUTLIER_GATE,
    CalibrationSettings,
    Solution,
    Stability,
    check_limits,
    leave_one_out,
    solve,
    without_view,
)
from calibration.stereo import RIG_PARAMETERS
from calibration.store import CaptureSet, CaptureWriter, decode_pose, pose_view
from calibration.validate import Artefact, Validation, measure_sphere_pair
from calibration.views import Correspondence, View, correspond
from scanner.calibration_file import write_calibration
from scanner.config import CONFIG_DIR, resolve
from scanner.decode import DecodeResult
from scanner.errors import ConfigError
from scanner.geometry import RigModel
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator, triangulate
from scanner.rig import Rig, RigConfig

DEFAULT_BOARD = CONFIG_DIR / "boards" / "sim_chess_9x7.toml"
DEFAULT_HEIGHTS_MM = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0)
DEFAULT_ARTEFACT = Artefact(radius_mm=10.0, distance_mm=50.0)
SHARE_SHOWN = ("camera.fx", "camera.cx", "camera.cy", "projector.fx", "projector.cx", "projector.cy", "extrinsic.rx",
               "extrinsic.ry", "extrinsic.tx", "extrinsic.tz")  # the report's source split of the variance
CALIBRATION_SETTINGS = tuple(CalibrationSettings.__dataclass_fields__)  # solver keys of [calibrate] and overrides

Say = Callable[[str], None]


class Bench(Protocol):
    """Places things in front of the rig; each call returns once they are in place."""

    def place_board(self, index: int, needed: list[str]) -> bool:
        """Put the board at pose `index` (advice: what is still needed); False: no more poses."""

    def place_plate(self, height_mm: float) -> None:
        """Put the flat plate at `height_mm` on the stage (0: the reference plane)."""

    def place_artefact(self) -> None:
        """Put the validation artefact in view, in front of the plate."""


@dataclass(frozen=True)
class Procedure:
    """What a calibration does: the board, how many poses, the solver settings and limits,
    the plate heights (empty: no phase-to-height) and the validation artefact (None: none).
    Read from the rig TOML's optional [calibrate] table:

        [calibrate]
        board = "../boards/sim_chess_9x7.toml"   # relative to the rig TOML
        poses = 12
        plate_heights_mm = [0, 5, 10, 15, 20, 25, 30]   # first = reference plane
        artefact = { type = "sphere_pair", radius_mm = 10.0, distance_mm = 50.0 }
        max_camera_rms_px = 0.5      # and max_projector_rms_px, max_validation_mm,
        fix_k3 = false               # drop_outliers, min_views, max_joint_camera_std
                                     # (see CalibrationSettings)
    """

    board: Board
    patterns: PatternSet
    poses: int = 12
    settings: CalibrationSettings = field(default_factory=CalibrationSettings)
    plate_heights_mm: tuple[float, ...] = DEFAULT_HEIGHTS_MM
    artefact: Artefact | None = DEFAULT_ARTEFACT
    gamma_levels: np.ndarray = field(default_factory=lambda: DEFAULT_LEVELS.copy())

    @classmethod
    def for_rig(cls, config: RigConfig, **overrides: Any) -> Procedure:
        """From the rig's [calibrate] table; `overrides` (None = keep) take precedence:
        board (a path), poses, plate_heights_mm, artefact and any CalibrationSettings field."""
        p, table = config.path, config.file.calibrate
        given = {k: v for k, v in table.model_dump(exclude_none=True).items() if k in CALIBRATION_SETTINGS}
        o = {k: v for k, v in overrides.items() if v is not None}
        board_path = o.pop("board", None) or (resolve(p, table.board) if table.board is not None else DEFAULT_BOARD)
        try:
            solver = CalibrationSettings(**{**given, **{k: o.pop(k) for k in CALIBRATION_SETTINGS if k in o}})
        except ValueError as exc:
            raise ConfigError(p, "calibrate", str(exc)) from None
        written = DEFAULT_HEIGHTS_MM if table.plate_heights_mm is None else table.plate_heights_mm
        heights = tuple(float(h) for h in o.pop("plate_heights_mm", written))
        artefact = o.pop("artefact", None) or (Artefact.of(table.artefact) if table.artefact is not None
                                               else DEFAULT_ARTEFACT)
        if heights and (heights[0] != 0.0 or any(b <= a for a, b in pairwise(heights))):
            raise ConfigError(p, "calibrate.plate_heights_mm", f"{list(heights)}: start at 0 (the reference plane) "
                                                               f"and increase")
        poses = int(o.pop("poses", 12 if table.poses is None else table.poses))
        if o:
            raise ConfigError(p, "calibrate", f"unknown overrides {sorted(o)}")
        if poses < solver.min_views:
            raise ConfigError(p, "calibrate.poses", f"{poses} poses is below min_views = {solver.min_views}")
        base = PatternSet.load(config.patterns_path)
        return cls(Board.load(board_path), replace(base, orientations=("vertical", "horizontal")), poses, solver,
                   heights, artefact)


@dataclass(frozen=True, eq=False)
class Plate:
    """One plate scan: stage height, projector gamma it was taken with, decoded maps."""

    height_mm: float
    gamma: float
    decoded: DecodeResult


@dataclass(eq=False)
class CalibrationResult:
    """Everything a calibration produced (see `report` for the file, `lines` for people)."""

    rig_name: str
    board: Board
    settings: CalibrationSettings
    solution: Solution
    gamma: GammaFit | None = None
    failures: dict[str, str] = field(default_factory=dict)
    phase_height: PhaseHeightFit | None = None
    gamma_check: dict[str, float] = field(default_factory=dict)  # what the gamma compensation is worth
    validation: Validation | None = None
    stability: Stability | None = None

    @property
    def model(self) -> RigModel:
        s = self.solution.stereo
        return RigModel(s.camera, s.projector, s.cam_from_proj, projector_gamma=self.gamma.gamma if self.gamma else 1.0,
                        phase_to_height=self.phase_height.model if self.phase_height else None)

    def report(self) -> dict[str, Any]:
        """The calibration file's report sections (see `scanner.calibration_file`)."""
        sol, s = self.solution, self.solution.stereo
        views = [{"name": n, "camera_rms_px": float(c), "projector_rms_px": float(p),
                  "camera_points": len(corr.camera), "projector_points": len(corr.projector),
                  # decoded projector pixels about each corner's local fit: the decoding's noise
                  "projector_fit_rms_px": float(np.nanmedian(corr.projector_corners.fit_rms_px)),
                  "pixels_per_corner": int(np.median(corr.projector_corners.pixels_used))}
                 for n, c, p, corr in zip(sol.names, s.per_view_rms_px("camera"), s.per_view_rms_px("projector"),
                                          sol.correspondences)]
        separate = {d.name: {**d.pinhole.to_dict(), "rms_px": d.rms_px, "std": d.std}
                    for d in (sol.camera, sol.projector)}
        return {
            "board": self.board.to_dict(),
            "rms_px": {"camera": s.camera_rms_px, "projector": s.projector_rms_px, "stereo": s.rms_px},
            "uncertainty": s.std,
            "covariance": {"parameters": list(RIG_PARAMETERS), "matrix": s.covariance.tolist(),
                           "decoding_matrix": s.decoding_covariance.tolist(), "noise_model": s.noise.to_dict()},
            "camera_intrinsics": asdict(sol.camera_choice), "views": views,
            "dropped_views": {**sol.dropped, **self.failures},
            "outlier_corners": {"test": f"a corner whose camera or projector point's standardised residuals (squared, "
                                        f"summed) exceed {OUTLIER_GATE:.1f}, the chi-square (2 dof) point a point "
                                        f"following the noise model exceeds with probability {OUTLIER_ALPHA:g}",
                                "failed": {name: {str(k): v for k, v in ids.items()}
                                             for name, ids in sol.outlier_corners.items()}},
            "outlier_views": self.outliers(),
            "coverage": {name: {"fraction": c.fraction, "cells": c.counts.tolist(), "uncovered": c.empty_zones()}
                         for name, c in self.coverage().items()},
            "separate": separate, "gamma": self.gamma.to_dict() if self.gamma else None,
            "phase_to_height": self.phase_height.to_dict() if self.phase_height else None,
            "gamma_check": self.gamma_check or None,
            "validation": self.validation.to_dict() if self.validation else None,
            "stability": ({"values": self.stability.values, "leave_one_out": self.stability.spread}
                          if self.stability else None),
            "limits": {"camera_rms_px": self.settings.max_camera_rms_px,
                       "projector_rms_px": self.settings.max_projector_rms_px,
                       "validation_mm": self.settings.max_validation_mm}}

    def coverage(self) -> dict[str, Coverage]:
        """Where the points of the views in use fell, per device."""
        out = {}
        for name, pinhole in (("camera", self.solution.stereo.camera), ("projector", self.solution.stereo.projector)):
            cov = out[name] = Coverage(pinhole.size)
            for corr in self.solution.correspondences:
                cov.add(getattr(corr, name).image_points)
        return out

    def outliers(self) -> dict[str, str]:
        """Views in use whose joint error stands out (name -> figures), worst first."""
        s, factor = self.solution.stereo, self.settings.outlier_factor
        bad = dict.fromkeys(self.solution.outliers("camera", factor) + self.solution.outliers("projector", factor))
        return {self.solution.names[i]: f"camera {s.per_view_rms_px('camera')[i]:.4f} px, projector "
                                        f"{s.per_view_rms_px('projector')[i]:.4f} px RMS" for i in bad}

    def lines(self) -> list[str]:
        """The report for the terminal."""
        sol, s = self.solution, self.solution.stereo
        std = s.std
        Kc, Kp = s.camera.K, s.projector.K
        left_out = {**sol.dropped, **self.failures}
        outliers = self.outliers()
        share = s.decoding_share()
        left_out_text = "; ".join(f"{k} ({v})" for k, v in left_out.items())
        out = [f"views     {len(sol.names)} used" + (f", left out: {left_out_text}" if left_out else ""),
               *([f"corners   fail the outlier test (a good corner fails it with probability {OUTLIER_ALPHA:g}; kept): "
                  + "; ".join(f"{name} {', '.join(str(k) for k in ids)}" for name, ids in sol.outlier_corners.items())]
                 if sol.outlier_corners else []),
               *([f"outliers  {'; '.join(f'{k} ({v})' for k, v in outliers.items())} stand out (over "
                  f"{self.settings.outlier_factor:g} x the median view): re-take them, or solve with --drop-outliers"]
                 if outliers else []),
               f"camera    fx {Kc[0, 0]:.2f} ± {std['camera.fx']:.2f}  fy {Kc[1, 1]:.2f} ± {std['camera.fy']:.2f}  "
               f"cx {Kc[0, 2]:.2f} ± {std['camera.cx']:.2f}  cy {Kc[1, 2]:.2f} ± {std['camera.cy']:.2f} px   "
               f"RMS {s.camera_rms_px:.4f} px",
               f"          intrinsics from the {sol.camera_choice.source}: {sol.camera_choice.reason}",
               f"projector fx {Kp[0, 0]:.2f} ± {std['projector.fx']:.2f}  fy {Kp[1, 1]:.2f} ± {std['projector.fy']:.2f}"
               f"  cx {Kp[0, 2]:.2f} ± {std['projector.cx']:.2f}  cy {Kp[1, 2]:.2f} ± {std['projector.cy']:.2f} px   "
               f"RMS {s.projector_rms_px:.4f} px",
               "coverage  " + ", ".join(f"{name} {c.fraction:.0%} of the image" + (
                   f" (not covered: {', '.join(c.empty_zones())})" if c.empty_zones() else "")
                   for name, c in self.coverage().items()),
               f"stereo    baseline {np.linalg.norm(s.cam_from_proj[:3, 3]):.3f} mm "
               f"(± {std['extrinsic.translation_mm']:.4f} mm), rotation ± {std['extrinsic.rotation_deg']:.4f} deg, "
               f"RMS {s.rms_px:.4f} px",
               f"          the ± are one sigma from the {s.noise.summary()}; a projector corner carries its camera "
               f"corner's error through the local fit, and the fit is weighted by that model",
               "          share of each variance from the decoding's own error (the rest from the camera corners'): "
               + ", ".join(f"{n} {share[n]:.0%}" for n in SHARE_SHOWN if n in share),
               f"          {sol.camera.summary()} (own views, before the joint refinement)",
               f"          {sol.projector.summary()} (own views, before the joint refinement)"]
        out.append(f"gamma     {self.gamma.summary()}" if self.gamma else "gamma     not measured (1.0 assumed)")
        if self.phase_height:
            m = self.phase_height.model
            held = self.phase_height.rms(True)
            which = "held-out" if np.isfinite(held[0]) else "fitted"
            rms3 = held if which == "held-out" else self.phase_height.rms(False)
            lo, hi = self.phase_height.pitch_range_mm
            out += [f"Eq. 17    l {m.l_mm:.3f} mm (camera to plate {m.plane[3]:.3f} mm), d {m.d_mm:.3f} mm, pitch "
                    f"{m.pitch_mm:.4f} mm (local pitch {lo:.4f} .. {hi:.4f} mm over the plate)",
                    *("          " + line for line in self.phase_height.lines()),
                    f"          {which} heights RMS: Eq. 17 {rms3[0] * 1e3:.1f} um, per-pixel {rms3[1] * 1e3:.1f} um, "
                    f"triangulation {rms3[2] * 1e3:.1f} um"]
        else:
            out.append("Eq. 17    not calibrated (no plate scans)")
        g = self.gamma_check
        if "ripple_uncompensated_mm" in g:
            out.append(f"          uncompensated, these fringes would carry up to "
                       f"{g['phase_error_uncompensated_rad']:.4f} rad of phase error per frequency "
                       f"(up to {g['ripple_uncompensated_mm'] * 1e3:.1f} um of depth "
                       f"ripple on this rig); compensated {g['phase_error_compensated_rad']:.4f} rad "
                       f"({g['ripple_compensated_mm'] * 1e3:.2f} um)")
        if "flatness_compensated_mm" in g:
            out.append(f"plate     flatness RMS {g['flatness_compensated_mm'] * 1e3:.1f} um with gamma compensation"
                       + (f", {g['flatness_uncompensated_mm'] * 1e3:.1f} um without"
                          if "flatness_uncompensated_mm" in g else ""))
        out.append(f"validate  {self.validation.summary()}" if self.validation else "validate  no artefact scanned")
        if self.stability:
            out += ["stability (leave one view out):", *("          " + line for line in self.stability.lines())]
        return out


class OperatorBench:
    """A `Bench` for a person at a real rig: says what to place and waits for Enter
    (answering 'q' ends the board poses)."""

    def __init__(self, say: Say, ask: Callable[[str], str] = input) -> None:
        self.say = say
        self.ask = ask

    def place_board(self, index: int, needed: list[str]) -> bool:
        self.say(f"pose {index}: place the board, still and whole in view of camera and projector"
                 + (f"; still needed: {'; '.join(needed)}" if needed else ""))
        return self.ask("press Enter to capture, q and Enter when there are enough poses: ").strip().lower() != "q"

    def place_plate(self, height_mm: float) -> None:
        self.ask(f"put the flat plate on the stage at {height_mm:g} mm (0 = reference plane), then press Enter: ")

    def place_artefact(self) -> None:
        self.ask("put the sphere pair in view in front of the plate, then press Enter: ")


# ---------------------------------------------------------------------------- steps


def correspond_all(board: Board, views: list[View], strict: bool,
                   say: Say) -> tuple[list[Correspondence], dict[str, str]]:
    """Correspondences of every view. `strict`: a view without the board or the projector
    pattern is an error; otherwise it is reported and left out."""
    found, failures = [], {}
    for i, view in enumerate(views):
        try:
            found.append(correspond(board, view, i))
        except DetectionError as exc:
            if strict:
                raise
            failures[view.name] = str(exc)
            say(f"left out: {exc}")
    return found, failures


def triangulated_points(decoded: DecodeResult, triangulator: Triangulator) -> np.ndarray:
    """Camera-frame points (H, W, 3) of a decoded scan, NaN where invalid."""
    return triangulate(decoded, triangulator, with_normals=False).points


def _valid_points(points: np.ndarray) -> np.ndarray:
    """The finite points (N, 3) float64 of an organised cloud (H, W, 3)."""
    return points[np.isfinite(points).all(axis=2)].astype(np.float64)


def gamma_effect(fit: GammaFit, decoded: DecodeResult, triangulator: Triangulator) -> dict[str, float]:
    """The largest phase error of this pattern set through the measured projector response,
    without and with compensation, and the depth ripple it makes on this rig: phase error /
    2π x fringe period (projector px) x median depth sensitivity (mm per projector px) over
    the decoded scan."""
    m = decoded.maps["vertical"] if "vertical" in decoded.maps else next(iter(decoded.maps.values()))
    _, dz_dc = triangulator.depth_scale(m.coordinate, m.orientation, sensitivity=True)
    mm_per_rad = m.period_px / (2.0 * np.pi) * float(np.nanmedian(dz_dc))
    out = {}
    for kind, compensated in (("uncompensated", False), ("compensated", True)):
        err = phase_error_rad(fit.gamma, decoded.patterns.steps, compensated)
        out[f"phase_error_{kind}_rad"] = err
        out[f"ripple_{kind}_mm"] = err * mm_per_rad
    return out


def phase_to_height(plates: list[Plate], triangulator: Triangulator) -> PhaseHeightFit:
    """Eq. 17 from plate scans taken with the calibrated gamma; every other non-zero height
    is held out of the fit (when there are at least four) to measure the model between them."""
    plates = sorted(plates, key=lambda p: p.height_mm)
    heights = [p.height_mm for p in plates]
    n = len(heights)
    fit_mask = [k == 0 or n < 5 or k % 2 == 0 for k in range(n)]
    phases = [p.decoded.maps["vertical"].phase for p in plates]
    points = [triangulated_points(p.decoded, triangulator) for p in plates]
    plane = fit_plane(_valid_points(points[0]))
    camera = triangulator.rig.camera
    m = fit_phase_to_height(heights, phases, plane, camera, fit_mask)
    return PhaseHeightFit(m, evaluate(heights, fit_mask, phases, points, m),
                          local_pitch_range_mm(phases[0], plane, camera))


def blame_for_validation(solution: Solution, decoded: DecodeResult, artefact: Artefact, gamma: float,
                         settings: CalibrationSettings) -> list[int]:
    """Views whose removal improves the artefact measurement most, best improvement first."""
    errors = []
    for i in range(len(solution.names)):
        s = without_view(solution, i, settings)
        model = RigModel(s.camera, s.projector, s.cam_from_proj, projector_gamma=gamma)
        try:
            errors.append(measure_sphere_pair(triangulated_points(decoded, Triangulator(model)), artefact).error_mm)
        except CalibrationError:  # a view whose removal breaks the measurement is not the one to blame
            errors.append(np.inf)
    return [int(i) for i in np.argsort(errors)[:3]]


def finish(result: CalibrationResult, plates: list[Plate], artefact: tuple[Artefact, DecodeResult] | None, say: Say,
           recording: CalibrationRecording | None = None) -> CalibrationResult:
    """Limits, phase-to-height, validation and stability of a solved calibration; raises
    CalibrationRejected when a limit is exceeded."""
    check_limits(result.solution, result.settings)
    gamma = result.gamma.gamma if result.gamma else 1.0
    triangulator = Triangulator(result.model)
    compensated = [p for p in plates if abs(p.gamma - gamma) < 1e-9]
    if len(compensated) >= 3:
        say("fitting the phase-to-height model (Eq. 17) to the plate scans")
        result.phase_height = phase_to_height(compensated, triangulator)
        if recording:
            recording.phase_height(result.phase_height)
    reference = [p for p in plates if p.height_mm == min(q.height_mm for q in plates)] if plates else []
    for p in reference:
        kind = "compensated" if abs(p.gamma - gamma) < 1e-9 else "uncompensated"
        points = _valid_points(triangulated_points(p.decoded, triangulator))
        result.gamma_check[f"flatness_{kind}_mm"] = plane_rms(points)
    if result.gamma is not None and compensated:
        result.gamma_check.update(gamma_effect(result.gamma, compensated[0].decoded, triangulator))
    if artefact is not None:
        description, decoded = artefact
        say("measuring the validation artefact")
        cloud = triangulate(decoded, triangulator, with_normals=False)
        result.validation = measure_sphere_pair(cloud.points, description)
        if recording:
            recording.artefact(cloud, result.model)
        if result.validation.error_mm > result.settings.max_validation_mm:
            blame = blame_for_validation(result.solution, decoded, description, gamma, result.settings)
            names = ", ".join(result.solution.names[i] for i in blame)
            raise CalibrationRejected(
                f"validation error {result.validation.error_mm:.4f} mm exceeds the limit "
                f"{result.settings.max_validation_mm:.4f} mm ({result.validation.summary()}); the views whose removal "
                f"improves it most: {names}. Check the board's square size and the artefact's certified distance, "
                f"re-take those poses, or raise the limit", blame)
    if len(result.solution.names) > result.settings.min_views:
        say("leave-one-view-out stability")
        result.stability = leave_one_out(result.solution, result.settings)
    return result


def write_result(result: CalibrationResult, path: str | Path) -> Path:
    """The calibration JSON and its phase-to-height maps (when phase-to-height was calibrated)."""
    return write_calibration(path, result.model, result.report(), result.rig_name)


def solve_views(board: Board, correspondences: list[Correspondence], failures: dict[str, str],
                *, camera_size: tuple[int, int], projector_size: tuple[int, int], settings: CalibrationSettings,
                rig_name: str, gamma: GammaFit | None, say: Say,
                recording: CalibrationRecording | None = None) -> CalibrationResult:
    say(f"solving from {len(correspondences)} views")
    solution = solve(correspondences, camera_size, projector_size, settings)
    result = CalibrationResult(rig_name, board, settings, solution, gamma, failures)
    if recording:
        recording.solution(solution, result.model)
    return result


# ---------------------------------------------------------------------------- entry points


def calibrate_views(board: Board, views: list[View], projector_size: tuple[int, int], settings: CalibrationSettings,
                    rig_name: str, say: Say, *, recording: CalibrationRecording | None = None,
                    strict: bool = True) -> CalibrationResult:
    """Calibrate from decoded views alone (e.g. another tool's Gray-code captures)."""
    if not views:
        raise NotEnoughData("no views to calibrate from")
    corr, failures = correspond_all(board, views, strict, say)
    camera_size = views[0].size
    _log_views(recording, views, corr, camera_size, projector_size)
    result = solve_views(board, corr, failures, camera_size=camera_size, projector_size=projector_size,
                         settings=settings, rig_name=rig_name, gamma=None, say=say,
                         recording=recording)
    return finish(result, [], None, say, recording)


def calibrate_capture(capture: CaptureSet, settings: CalibrationSettings, rig_name: str, say: Say,
                      *, recording: CalibrationRecording | None = None, strict: bool = True,
                      board: Board | None = None) -> CalibrationResult:
    """Calibrate from a capture folder written by `calibrate_rig`; `board` replaces the
    board description the capture was made with (e.g. to correct it)."""
    board, patterns, bits = board or capture.board, capture.patterns, capture.bit_depth
    psize, csize = capture.projector_size, capture.camera_size
    gamma = None
    g = capture.gamma()
    if g is not None:
        gamma = fit_gamma(g[0], g[1], float(2 ** bits - 1))
        say(gamma.summary())
        if recording:
            recording.gamma(gamma)
    views = capture.views()
    corr, failures = correspond_all(board, views, strict, say)
    _log_views(recording, views, corr, csize, psize)
    result = solve_views(board, corr, failures, camera_size=csize, projector_size=psize, settings=settings,
                         rig_name=rig_name, gamma=gamma, say=say, recording=recording)
    plates = [Plate(h, gm, decode_pose(f"plate at {h} mm", f, patterns, bits, psize,  # 1.0 beside a fitted gamma:
                                       judged=gamma is None or abs(gm - 1.0) > 1e-9))  # uncompensated on purpose
              for h, gm, f in capture.plates()]
    art = capture.artefact()
    art_decoded = None
    if art is not None:
        description = Artefact.from_dict(art[0], capture.root)
        art_decoded = (description, decode_pose("artefact", art[1], patterns, bits, psize))
    return finish(result, plates, art_decoded, say, recording)


def _log_views(recording: CalibrationRecording | None, views: list[View], corr: list[Correspondence],
               camera_size: tuple[int, int], projector_size: tuple[int, int]) -> None:
    if recording is None:
        return
    cam, proj = Coverage(camera_size), Coverage(projector_size)
    by_name = {c.name: c for c in corr}
    for i, v in enumerate(views):
        c = by_name.get(v.name)
        if c is not None:
            cam.add(c.camera.image_points)
            proj.add(c.projector.image_points)
        recording.view(i, v.image, c, cam, proj)


def calibrate_rig(rig: Rig, procedure: Procedure, bench: Bench, out: Path, say: Say,
                  recording: CalibrationRecording | None = None) -> CalibrationResult:
    """The guided calibration of an open rig (see the module docstring); the raw captures
    go to `out` (a new folder), so `calibrate_capture` can solve them again."""
    cam, proj = rig.camera, rig.projector
    csize, psize = (cam.width, cam.height), (proj.width, proj.height)
    with CaptureWriter(out, procedure.board, procedure.patterns, camera_size=csize, projector_size=psize,
                       bit_depth=cam.bit_depth,
                       rig_name=rig.config.name) as writer:
        gamma, corr, failures = capture_board_poses(rig, procedure, bench, say, writer, recording)
        result = solve_views(procedure.board, corr, failures, camera_size=csize, projector_size=psize,
                             settings=procedure.settings, rig_name=rig.config.name,
                             gamma=gamma, say=say, recording=recording)
        check_limits(result.solution, result.settings)  # before spending time on the plate and artefact
        plates, artefact = _capture_checks(rig, procedure, bench, writer, gamma.gamma, say)
    return finish(result, plates, artefact, say, recording)


def capture_board_poses(rig: Rig, procedure: Procedure, bench: Bench, say: Say, writer: CaptureWriter | None = None,
                        recording: CalibrationRecording | None = None
                        ) -> tuple[GammaFit, list[Correspondence], dict[str, str]]:
    """Gamma, then board poses until enough are usable (at most twice as many attempts);
    the frames go to `writer` when given."""
    board, patterns = procedure.board, procedure.patterns
    cam, proj = rig.camera, rig.projector
    csize, psize = (cam.width, cam.height), (proj.width, proj.height)
    cover_c, cover_p = Coverage(csize), Coverage(psize)
    corr: list[Correspondence] = []
    failures: dict[str, str] = {}
    tilts: list[tuple[float, float]] = []

    def needed() -> list[str]:
        return needed_poses(cover_c, cover_p, tilts, len(corr), procedure.poses)

    if not bench.place_board(0, ["the board facing the camera, in the middle of the view"]):
        raise NotEnoughData("no board pose was placed")
    say("measuring the projector response (flat grey levels)")
    levels = procedure.gamma_levels
    flats = show_images(rig, flat_images(levels, proj.width, proj.height))
    if writer is not None:
        writer.add_gamma(levels, flats)
    gamma = fit_gamma(levels, flats, float(2 ** cam.bit_depth - 1))
    say(gamma.summary())
    if recording:
        recording.gamma(gamma)
    index = 0
    while len(corr) < procedure.poses and index < 2 * procedure.poses:
        if index > 0 and not bench.place_board(index, needed()):
            break
        frames = capture_pose(rig, patterns, gamma.gamma)
        name = writer.add_pose(frames, gamma.gamma) if writer is not None else f"pose_{index:03d}"
        found = None
        try:
            found = correspond(board, pose_view(name, frames, patterns, cam.bit_depth, psize), index)
        except DetectionError as exc:
            failures[name] = str(exc)
            say(f"pose {index}: not usable, take it again: {exc}")
        if found is not None:
            corr.append(found)
            cover_c.add(found.camera.image_points)
            cover_p.add(found.projector.image_points)
            if len(corr) >= 3:  # a quick camera solve gives the board tilts for the advice
                quick = calibrate_device("camera", [c.camera for c in corr], csize)
                tilts = [tilt_deg(T) for T in quick.poses]
            say(f"pose {index} ({name}): {len(found.camera)} corners, {len(found.projector)} with projector "
                f"pixels; coverage camera {cover_c.fraction:.0%}, projector {cover_p.fraction:.0%}")
            advice = needed()
            say("still needed: " + "; ".join(advice) if advice else "the pose set is complete")
        if recording:
            recording.view(index, frames.white, found, cover_c, cover_p)
        index += 1
    return gamma, corr, failures


def _capture_checks(rig: Rig, procedure: Procedure, bench: Bench, writer: CaptureWriter, gamma: float,
                    say: Say) -> tuple[list[Plate], tuple[Artefact, DecodeResult] | None]:
    """The plate at each stage height (at the first also without gamma compensation), then
    the validation artefact."""
    patterns, bits = procedure.patterns, rig.camera.bit_depth
    psize = (rig.projector.width, rig.projector.height)
    plates = []
    for h in procedure.plate_heights_mm:
        bench.place_plate(h)
        takes = [gamma, 1.0] if h == procedure.plate_heights_mm[0] and abs(gamma - 1.0) > 1e-9 else [gamma]
        for g in takes:
            say(f"plate at {h:g} mm" + ("" if g == gamma else " without gamma compensation"))
            fringes = capture_fringes(rig, patterns, g) if g == gamma else capture_uncompensated(rig, patterns)
            writer.add_plate(h, fringes, g)
            decoded = decode_pose(f"plate at {h} mm", fringes, patterns, bits, psize, judged=g == gamma)
            plates.append(Plate(h, g, decoded))
    if procedure.artefact is None:
        return plates, None
    bench.place_artefact()
    say("artefact")
    fringes = capture_fringes(rig, patterns, gamma)
    writer.add_artefact(fringes, procedure.artefact.to_dict(), gamma)
    return plates, (procedure.artefact, decode_pose("artefact", fringes, patterns, bits, psize))
