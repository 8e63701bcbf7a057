"""Repeat-scan studies of the uncertainty model (`inspection.uncertainty`): how often the
true value lies within ±U.

Each trial places the artefact somewhere new in the rig's measuring volume (so the fringe
systematics, fixed for one placement, are drawn afresh as the model assumes), renders it
with fresh noise, decodes it and measures it with the same estimator `slscan verify` uses,
on the camera window around the artefact (`sim.artefacts.window_renderer`: the same
pixels, fewer of them to render). With a `calibration`, each trial also reconstructs with
a rig whose parameters are drawn from that covariance (the simulator still renders with
the true one), and U includes the calibration term. `noise_scale` scales the noise model
the U is computed from (not the simulated noise): below 1 it underestimates it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from inspection.acceptance import Acceptance, Position, find_spheres, frame_along, pose_of
from inspection.artefact_file import ArtefactSet
from inspection.artefacts import measure_ball_bar, measure_sphere
from inspection.uncertainty import (
    CalibrationUncertainty,
    Estimate,
    FringeError,
    ScanUncertainty,
    fringe_error,
    perturbed,
    scan_uncertainty,
)
from scanner.geometry import RigModel
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator, triangulate
from scanner.rig import RigConfig
from sim.artefacts import artefact_objects, quick_scan, window_renderer
from sim.render import SensorModel


@dataclass(frozen=True)
class Trial:
    """One repeat: the estimate, the truth (mm) and the seconds it took."""

    estimate: Estimate
    truth: float
    seconds: float

    @property
    def inside(self) -> bool:
        return self.estimate.value is not None and abs(self.estimate.value - self.truth) <= self.estimate.U


@dataclass(frozen=True)
class CoverageResult:
    """Trials of one figure; `fraction` of them with the truth within ±U."""

    figure: str
    trials: tuple[Trial, ...]

    @property
    def fraction(self) -> float:
        return float(np.mean([t.inside for t in self.trials]))

    @property
    def seconds(self) -> float:
        return float(sum(t.seconds for t in self.trials))

    def summary(self) -> str:
        err = np.array([t.estimate.value - t.truth for t in self.trials if t.estimate.value is not None])
        U = np.array([t.estimate.U for t in self.trials])
        return (f"{self.figure}: truth within ±U in {self.fraction:.1%} of {len(self.trials)} trials; error mean "
                f"{err.mean() * 1e3:+.3f} µm, std {err.std(ddof=1) * 1e3:.3f} µm; median U {np.median(U) * 1e3:.3f} µm "
                f"(k = 2); {self.seconds:.0f} s")


@dataclass(frozen=True, eq=False)
class Bench:
    """The simulated rig of a study: its true geometry, sensor, pattern set and the
    fringe error of its projector."""

    model: RigModel
    sensor: SensorModel
    patterns: PatternSet
    projector_blur_px: float
    exposure_s: float
    bit_depth: int
    fringe: FringeError
    acceptance: Acceptance

    @classmethod
    def of(cls, config: RigConfig) -> Bench:
        model = config.nominal_model()
        patterns = PatternSet.load(config.patterns_path)
        blur = float(config.projector.get("blur_sigma_px", 0.0))
        return cls(model, SensorModel.from_config(config), patterns, blur,
                   float(config.camera.get("exposure_s", 0.01)), int(config.camera.get("bit_depth", 12)),
                   fringe_error(patterns, model.projector.width, model.projector_gamma, blur),
                   Acceptance.from_rig(config.raw, config.path, config.working_distance_mm))


Measure = Callable[[np.ndarray, Callable[[np.ndarray], ScanUncertainty]], Estimate]


def _trial(bench: Bench, position: Position, artefacts: ArtefactSet, measure: Measure, truth: float,
           rng: np.random.Generator, calibration: CalibrationUncertainty | None, noise_scale: float) -> Trial:
    t0 = time.perf_counter()
    renderer = window_renderer(bench.model, artefact_objects(position, artefacts), bench.sensor, bench.projector_blur_px)
    decoded = quick_scan(renderer, bench.patterns, bench.model.projector_gamma, bench.exposure_s, bench.bit_depth, rng)
    used = renderer.model
    if calibration is not None:
        used = perturbed(used, calibration.draw(rng))
    points = triangulate(decoded, Triangulator(used), with_normals=False).points
    cal = calibration or CalibrationUncertainty.none("the simulator's exact geometry")

    def uncertainties(pixels: np.ndarray) -> ScanUncertainty:
        unc = scan_uncertainty(decoded, used, lambda a: bench.sensor.noise_sigma_dn(a, bench.bit_depth), bench.fringe,
                               cal, pixels)
        return replace(unc, noise=unc.noise.scaled(noise_scale))  # type: ignore[union-attr]

    return Trial(measure(points, uncertainties), truth, time.perf_counter() - t0)


def sphere_radius(bench: Bench, artefacts: ArtefactSet, n: int, seed: int = 0,
                  calibration: CalibrationUncertainty | None = None, noise_scale: float = 1.0) -> CoverageResult:
    """Coverage of the sphere radius: the artefact set's sphere at random places."""
    s = artefacts.sphere
    assert s is not None
    rng = np.random.default_rng(seed)
    half = np.array(bench.acceptance.size_mm) / 2 - s.radius_mm - 2.0
    c0 = np.array(bench.acceptance.centre_mm)

    def measure(points: np.ndarray, unc: Callable[[np.ndarray], ScanUncertainty]) -> Estimate:
        (px,) = find_spheres(points, s.radius_mm, 1)
        return measure_sphere(points[px[:, 1], px[:, 0]].astype(np.float64), unc(px), s.radius_mm)[1].radius

    trials = [_trial(bench, Position("sphere", k, pose_of(np.eye(3), c0 + rng.uniform(-half, half)), ""), artefacts,
                     measure, s.radius_mm, rng, calibration, noise_scale) for k in range(n)]
    return CoverageResult("sphere radius", tuple(trials))


def ball_bar_length(bench: Bench, artefacts: ArtefactSet, n: int, seed: int = 0,
                    calibration: CalibrationUncertainty | None = None, noise_scale: float = 1.0) -> CoverageResult:
    """Coverage of the ball bar's centre distance: random directions (kept inside the
    measuring volume) through random places near its centre."""
    b = artefacts.ball_bar
    assert b is not None
    rng = np.random.default_rng(seed)
    half = np.array(bench.acceptance.size_mm) / 2
    c0 = np.array(bench.acceptance.centre_mm)

    def measure(points: np.ndarray, unc: Callable[[np.ndarray], ScanUncertainty]) -> Estimate:
        pxs = find_spheres(points, b.radius_mm, 2)
        bar = measure_ball_bar(tuple(points[p[:, 1], p[:, 0]].astype(np.float64) for p in pxs),  # type: ignore[arg-type]
                               tuple(unc(p) for p in pxs), b.radius_mm)  # type: ignore[arg-type]
        return bar.distance

    trials = []
    for k in range(n):
        while True:  # a direction and a place whose spheres fit the volume and do not hide each other
            d = rng.normal(size=3)
            d[2] = abs(d[2]) * 0.6
            R = frame_along(d / np.linalg.norm(d))
            reach = np.abs(R[:, 0]) * (b.length_mm / 2 + b.radius_mm)
            room = half - reach
            lateral = np.hypot(R[0, 0], R[1, 0]) * b.length_mm
            if (room > 0).all() and lateral > 2.2 * b.radius_mm:
                break
        pose = pose_of(R, c0 + rng.uniform(-room, room))
        trials.append(_trial(bench, Position("ball_bar", k, pose, ""), artefacts, measure, b.length_mm, rng,
                             calibration, noise_scale))
    return CoverageResult("ball-bar length", tuple(trials))
