"""Repeat-scan studies of the uncertainty model (`inspection.uncertainty`): how often the
true value lies within ±U.

Each trial places the artefact somewhere new in the rig's measuring volume (so the fringe
systematics, fixed for one placement, are drawn afresh as the model assumes), renders it
with fresh noise, decodes it and measures it with the same estimator `slscan verify` uses,
on the camera window around the artefact (`sim.artefact_scenes.window_renderer`: the same
pixels, fewer of them to render). With a `calibration`, each trial also reconstructs with
a rig whose parameters are drawn from that covariance (the simulator still renders with
the true one), and U includes the calibration term. `noise_scale` scales the noise model
the U is computed from (not the simulated noise): below 1 it underestimates it.
"""

from __future__ import annotations

import multiprocessing
import time
from dataclasses import dataclass, replace
from typing import Callable, Iterator, TypeVar

import numpy as np

from inspection.acceptance import Acceptance, Position, find_spheres, frame_along, pose_of
from inspection.artefact_file import ArtefactSet
from inspection.artefacts import measure_ball_bar, measure_sphere
from inspection.uncertainty import (
    CalibrationUncertainty,
    Estimate,
    FringeError,
    ScanUncertainty,
    defocus_corrected,
    fringe_error,
    perturbed,
    scan_uncertainty,
)
from scanner.decode import DecodeResult
from scanner.geometry import RigModel
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator, triangulate
from scanner.rig import RigConfig
from sim.artefact_scenes import artefact_objects, quick_scan, window_renderer
from sim.render import Renderer, SensorModel


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
                f"(95 %); {self.seconds:.0f} s")


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

    def sensor_noise(self, mean_dn: np.ndarray) -> np.ndarray:
        """The camera's intensity noise (DN, one sigma) at a mean signal (DN)."""
        return self.sensor.noise_sigma_dn(mean_dn, self.bit_depth)

    def scan(self, renderer: Renderer, rng: np.random.Generator, defocus: bool = False) -> DecodeResult:
        """One decoded scan of `renderer`'s scene with fresh noise; with `defocus`, its
        coordinates corrected for the camera's stated blur (`defocus_corrected`)."""
        decoded = quick_scan(renderer, self.patterns, self.model.projector_gamma, self.exposure_s, self.bit_depth, rng)
        return defocus_corrected(decoded, self.sensor.blur_sigma_px) if defocus else decoded


Measure = Callable[[np.ndarray, Callable[[np.ndarray], ScanUncertainty]], Estimate]
TrialFunction = Callable[[int], tuple[Trial, ...]]  # trial k -> one Trial per figure
T = TypeVar("T")

_JOB: Callable[[int], object] | None = None  # the study being run, inherited by forked workers


def _run_job(k: int) -> object:
    assert _JOB is not None
    return _JOB(k)


def map_trials(job: Callable[[int], T], n: int, processes: int = 1) -> Iterator[T]:
    """job(0..n-1) in order, on `processes` forked workers (each job draws everything from
    its own seed, so the results do not depend on how they are shared out)."""
    global _JOB
    if processes <= 1:
        yield from (job(k) for k in range(n))
        return
    _JOB = job
    try:
        with multiprocessing.get_context("fork").Pool(processes) as pool:
            yield from pool.imap(_run_job, range(n))  # type: ignore[misc]
    finally:
        _JOB = None


def run_trials(figures: tuple[str, ...], trial: TrialFunction, n: int, processes: int = 1,
               progress: Callable[[str], None] | None = None) -> tuple[CoverageResult, ...]:
    """Trials 0..n-1 of a study (`map_trials`), with a line to `progress` every tenth of
    the way."""
    done: list[tuple[Trial, ...]] = []
    step = max(1, n // 10)
    for r in map_trials(trial, n, processes):
        done.append(r)
        if progress is not None and (len(done) % step == 0 or len(done) == n):
            progress("; ".join(f"{f}: {CoverageResult(f, tuple(t[i] for t in done)).fraction:.1%}"
                               for i, f in enumerate(figures)) + f" inside ±U after {len(done)} of {n}")
    return tuple(CoverageResult(f, tuple(t[i] for t in done)) for i, f in enumerate(figures))


def _trial(bench: Bench, position: Position, artefacts: ArtefactSet, measure: Measure, truth: float,
           rng: np.random.Generator, calibration: CalibrationUncertainty | None, noise_scale: float) -> Trial:
    t0 = time.perf_counter()
    renderer = window_renderer(bench.model, artefact_objects(position, artefacts), bench.sensor, bench.projector_blur_px)
    decoded = bench.scan(renderer, rng)
    used = renderer.model
    if calibration is not None:
        used = perturbed(used, calibration.draw(rng))
    points = triangulate(decoded, Triangulator(used), with_normals=False).points
    cal = calibration or CalibrationUncertainty.none("the simulator's exact geometry")

    def uncertainties(pixels: np.ndarray) -> ScanUncertainty:
        unc = scan_uncertainty(decoded, used, bench.sensor_noise, bench.fringe, cal, pixels)
        return replace(unc, noise=unc.noise.scaled(noise_scale))  # type: ignore[union-attr]

    return Trial(measure(points, uncertainties), truth, time.perf_counter() - t0)


def sphere_radius(bench: Bench, artefacts: ArtefactSet, n: int, seed: int = 0,
                  calibration: CalibrationUncertainty | None = None, noise_scale: float = 1.0,
                  processes: int = 1, progress: Callable[[str], None] | None = None) -> CoverageResult:
    """Coverage of the sphere radius: the artefact set's sphere at random places."""
    s = artefacts.sphere
    assert s is not None
    half = np.array(bench.acceptance.size_mm) / 2 - s.radius_mm - 2.0
    c0 = np.array(bench.acceptance.centre_mm)

    def measure(points: np.ndarray, unc: Callable[[np.ndarray], ScanUncertainty]) -> Estimate:
        (px,) = find_spheres(points, s.radius_mm, 1)
        return measure_sphere(points[px[:, 1], px[:, 0]].astype(np.float64), unc(px), s.radius_mm)[1].radius

    def trial(k: int) -> tuple[Trial]:
        rng = np.random.default_rng((seed, k))
        return (_trial(bench, Position("sphere", k, pose_of(np.eye(3), c0 + rng.uniform(-half, half)), ""),
                       artefacts, measure, s.radius_mm, rng, calibration, noise_scale),)

    return run_trials(("sphere radius",), trial, n, processes, progress)[0]


def ball_bar_length(bench: Bench, artefacts: ArtefactSet, n: int, seed: int = 0,
                    calibration: CalibrationUncertainty | None = None, noise_scale: float = 1.0,
                    processes: int = 1, progress: Callable[[str], None] | None = None) -> CoverageResult:
    """Coverage of the ball bar's centre distance: random directions (kept inside the
    measuring volume) through random places near its centre."""
    b = artefacts.ball_bar
    assert b is not None
    half = np.array(bench.acceptance.size_mm) / 2
    c0 = np.array(bench.acceptance.centre_mm)

    def measure(points: np.ndarray, unc: Callable[[np.ndarray], ScanUncertainty]) -> Estimate:
        pxs = find_spheres(points, b.radius_mm, 2)
        bar = measure_ball_bar(tuple(points[p[:, 1], p[:, 0]].astype(np.float64) for p in pxs),  # type: ignore[arg-type]
                               tuple(unc(p) for p in pxs), b.radius_mm)  # type: ignore[arg-type]
        return bar.distance

    def trial(k: int) -> tuple[Trial]:
        rng = np.random.default_rng((seed, k))
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
        return (_trial(bench, Position("ball_bar", k, pose, ""), artefacts, measure, b.length_mm, rng, calibration,
                       noise_scale),)

    return run_trials(("ball-bar length",), trial, n, processes, progress)[0]


# ------------------------------------------------------------------- flatness and Sq


PLATE_MM = (40.0, 30.0)
PLATE_STEP_MM = 0.1  # mesh spacing: 0.1 mm, below the camera's 0.125 mm pixels


@dataclass(frozen=True)
class Plate:
    """A flat plate of `PLATE_MM` whose surface has a bow (quadratic dome of `bow_mm`
    from the middle to the corners) and a random texture of RMS `texture_mm` at
    wavelengths of `wavelengths_mm` (sim.parts.Roughness), as a height-field mesh."""

    bow_mm: float = 0.030
    texture_mm: float = 0.008
    wavelengths_mm: tuple[float, float] = (1.5, 4.0)

    def mesh(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        from sim.parts import Roughness

        w, h = PLATE_MM
        x, y = np.meshgrid(np.arange(-w / 2, w / 2 + 1e-9, PLATE_STEP_MM), np.arange(-h / 2, h / 2 + 1e-9, PLATE_STEP_MM))
        p = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
        z = self.bow_mm * (1.0 - (p[:, 0] ** 2 + p[:, 1] ** 2) / ((w / 2) ** 2 + (h / 2) ** 2))
        z += Roughness(0, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), self.texture_mm, self.wavelengths_mm, seed=seed).height(p)
        p[:, 2] = z
        rows, cols = x.shape
        k = np.arange(rows * cols).reshape(rows, cols)[:-1, :-1].ravel()
        tris = np.concatenate([np.stack([k, k + 1, k + cols], 1), np.stack([k + 1, k + cols + 1, k + cols], 1)])
        return p, tris.astype(np.int32)


def _plate_face() -> object:
    from inspection.surfaces import Plane

    class Face:
        type = "plane"
        surface = Plane(np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]))

    return Face()


def registered(measured: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid move (R, t) that best lays `measured` points (N, 3) on the true ones of
    the same pixels (least squares, Kabsch): an inspection's registration, made ideal. It
    takes out what a calibration error does to the plate as a whole (on the bench rig
    ~10 µm and ~0.03 mrad), which registration takes out of an inspection too; left in,
    it re-bins the points on the form grid and moves the flatness by up to ~1 µm,
    more than its calibration term, in a way no inspection sees."""
    a, b = measured.mean(axis=0), truth.mean(axis=0)
    u, _, vt = np.linalg.svd((measured - a).T @ (truth - b))
    R = (u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt).T
    return R, b - R @ a


def _plate_renderer(bench: Bench, plate: Plate, seed: int, k: int,
                    rng: np.random.Generator) -> tuple[Renderer, np.ndarray]:
    """Placement k of the plate (its own texture, a random place in the measuring volume,
    tilted up to 20 degrees) on the camera window around it: (renderer, plate pose 4x4)."""
    from sim.calibration_bench import rotation
    from sim.scene import SceneObject

    half = np.array(bench.acceptance.size_mm) / 2 - [PLATE_MM[0] / 2, PLATE_MM[1] / 2, 8.0]
    c0 = np.array(bench.acceptance.centre_mm)
    vertices, triangles = plate.mesh(seed * 100003 + k)
    pose = pose_of(rotation(*rng.uniform(-20.0, 20.0, 2), rng.uniform(0.0, 360.0)), c0 + rng.uniform(-half, half))
    obj = SceneObject("plate", "mesh", pose, 0.7, vertices=vertices, triangles=triangles)
    return window_renderer(bench.model, (obj,), bench.sensor, bench.projector_blur_px), pose


def plate_figures(bench: Bench, n: int, seed: int = 0, calibration: CalibrationUncertainty | None = None,
                  noise_scale: float = 1.0, plate: Plate = Plate(), draws: int = 32, processes: int = 1,
                  progress: Callable[[str], None] | None = None) -> tuple[CoverageResult, CoverageResult]:
    """Coverage of the minimum-zone flatness and of Sq of a textured, bowed plate
    (`Plate`) placed at random in the measuring volume, tilted up to 20 degrees: the
    plate's points taken into its own frame with its true pose after an ideal registration
    (`registered`: registration is not what is studied here), evaluated as an inspection evaluates a plane face
    (`inspection.form.evaluate_face`), the decoded coordinates corrected for the camera's
    stated blur (`defocus_corrected`: not yet in the scan pipeline). The truth: the same
    evaluation of the noise-free surface points the same pixels see, over the points the
    measurement's figures were taken over (`FaceForm.region`: the silhouette's mixed
    pixels, up to ~0.1 mm off, fail the spike test and the edge margin is counted from
    what is left, so a truth taken over every pixel held corner cells the measurement did
    not and read up to 4 µm wider) and binned on the measurement's grid (the true heights
    at the measured points' in-plane places, a few µm from their own: a grid started at
    the true points' corner moves the border cells, where the form filter's end effects
    and the bow's slope are largest, by up to a cell)."""
    from inspection.form import FormSettings, evaluate_face

    face = _plate_face()
    cal = calibration or CalibrationUncertainty.none("the simulator's exact geometry")
    settings = FormSettings(draws=draws)

    def trial(k: int) -> tuple[Trial, Trial]:
        rng = np.random.default_rng((seed, k))
        t0 = time.perf_counter()
        renderer, pose = _plate_renderer(bench, plate, seed, k, rng)
        decoded = bench.scan(renderer, rng, defocus=True)
        used = renderer.model if calibration is None else perturbed(renderer.model, calibration.draw(rng))
        points = triangulate(decoded, Triangulator(used), with_normals=False).points
        gt = renderer.ground_truth
        ok = np.isfinite(points).all(axis=2) & (gt.object_id == 2)
        rows, cols = np.nonzero(ok)
        px = np.stack([cols, rows], axis=1)
        unc = scan_uncertainty(decoded, used, bench.sensor_noise, bench.fringe, cal, px)
        inv = np.linalg.inv(pose)
        true_pts = gt.points[rows, cols] @ inv[:3, :3].T + inv[:3, 3]
        R, t = registered(points[rows, cols].astype(np.float64), gt.points[rows, cols].astype(np.float64))
        R, t = inv[:3, :3] @ R, inv[:3, :3] @ t + inv[:3, 3]
        measured = points[rows, cols].astype(np.float64) @ R.T + t
        normals = np.tile([0.0, 0.0, 1.0], (len(measured), 1))
        moves = unc.shifts(points[rows, cols].astype(np.float64))
        got = evaluate_face(face, measured, measured[:, 2], measured[:, :2], settings, seed=k,
                            noise=unc.noise.rotated(R).scaled(noise_scale), normals=normals,  # type: ignore[union-attr]
                            shifts=None if moves is None else moves @ R.T)
        true_pts = np.column_stack([measured[:, :2], true_pts[:, 2]])  # on the measurement's grid (its cells)
        truth = evaluate_face(face, true_pts, true_pts[:, 2], true_pts[:, :2], FormSettings(draws=2), seed=k,
                              noise=unc.noise.rotated(R).scaled(0.0), normals=normals,  # type: ignore[union-attr]
                              region=got.region)
        dt_s = time.perf_counter() - t0
        return (Trial(got.flatness_mz, truth.flatness_mz.value, dt_s / 2),  # type: ignore[union-attr,arg-type]
                Trial(got.sq, truth.sq.value, dt_s / 2))  # type: ignore[union-attr,arg-type]

    flat, sq = run_trials(("flatness (minimum zone)", "Sq"), trial, n, processes, progress)
    return flat, sq


@dataclass(frozen=True)
class NoiseModelCheck:
    """How well the decoder-and-sensor noise model (`inspection.uncertainty.depth_noise`)
    predicts the depth noise: per placement, the standard deviation of the difference of
    two scans' depths over sqrt(2) times the predicted sigma_z (`ratios`), and the same
    from two interleaved halves of the pixels (`halves`, (n, 2)), whose difference gives
    each ratio's statistical precision."""

    ratios: np.ndarray
    halves: np.ndarray
    pixels: int

    @property
    def precision(self) -> float:
        """Statistical standard deviation of one placement's ratio."""
        return float(np.std(self.halves[:, 0] - self.halves[:, 1], ddof=1) / 2.0)

    def rel_u_bound(self) -> float:
        """A 95 % upper bound of the model's own relative error (RMS over placements): the
        ratios' mean square deviation from 1 at its upper confidence limit (chi-square, n
        degrees of freedom), less each ratio's statistical variance."""
        from scipy.stats import chi2

        n = len(self.ratios)
        ms_hi = float(np.sum((self.ratios - 1.0) ** 2)) / chi2.ppf(0.05, n)
        return float(np.sqrt(max(ms_hi - self.precision ** 2, 0.0)))

    def summary(self) -> str:
        return (f"noise model: measured/predicted depth noise {np.mean(self.ratios):.4f} mean, "
                f"{np.std(self.ratios, ddof=1):.4f} std over {len(self.ratios)} placements (statistical precision of "
                f"one {self.precision:.4f}, ~{self.pixels} pixels each); the model's relative error below "
                f"{self.rel_u_bound():.2%} (95 %)")


def noise_model_check(bench: Bench, n: int, seed: int = 99, plate: Plate = Plate(),
                      processes: int = 1) -> NoiseModelCheck:
    """`NoiseModelCheck` over n placements of the textured plate (two scans each, pixels
    more than 8 px inside its outline: the silhouette's mixed pixels are not noise)."""
    from scipy import ndimage

    def placement(k: int) -> tuple[float, float, float, int]:
        rng = np.random.default_rng((seed, k))
        renderer, _ = _plate_renderer(bench, plate, seed, k, rng)
        scans = [bench.scan(renderer, rng, defocus=True) for _ in range(2)]
        z = [triangulate(d, Triangulator(renderer.model), with_normals=False).points[..., 2].astype(np.float64)
             for d in scans]
        inside = np.isfinite(z[0]) & np.isfinite(z[1]) & (renderer.ground_truth.object_id == 2)
        inside = ndimage.binary_erosion(inside, np.ones((17, 17)))
        rows, cols = np.nonzero(inside)
        unc = scan_uncertainty(scans[0], renderer.model, bench.sensor_noise, None, CalibrationUncertainty.none("not studied"),
                               np.stack([cols, rows], axis=1))
        r = (z[0] - z[1])[rows, cols] / (np.sqrt(2.0) * unc.noise.sigma_z)  # type: ignore[union-attr]
        even = (rows + cols) % 2 == 0
        return float(np.std(r)), float(np.std(r[even])), float(np.std(r[~even])), len(r)

    done = np.array(list(map_trials(placement, n, processes)))
    return NoiseModelCheck(done[:, 0], done[:, 1:3], int(np.median(done[:, 3])))
