"""Repeat-scan studies of the uncertainty model (`inspection.uncertainty`): how often the
true value lies within ±U, measured on the product's own code path (`slscan coverage`).

Each trial places an artefact somewhere new in the rig's measuring volume (so the fringe
systematics, fixed for one placement, are drawn afresh as the model assumes), renders it
with fresh noise on the camera window around it (`sim.artefact_scenes.window_renderer`:
the same pixels as a full frame, fewer of them rendered), decodes it with the decoder
`slscan scan` runs (`quick_scan`: `scanner.decode.decode`, default settings),
triangulates it with the rig model in use and measures it with what the command measures
it with, the measurement model made as the commands make it (`Bench.measurement`, from
`slscan.measurement_model.rig_measurement`):
  - sphere radius, ball-bar length: `inspection.acceptance.evaluate`, as `slscan verify`
    (the inner variant's fit, which carries the scanner model's U);
  - flatness and Sq of a plate: `inspection.inspect_scan.measure_face`, as `slscan
    inspect` measures a face, with its defocus correction, after an ideal registration
    (`registered`; the registration is the pose case's);
  - the pose of the demo part and the mean deviation of one of its plane faces:
    `inspection.inspect_scan.inspect`, as reported (`demo_part_coverage`).
A correction either ships in those functions or is not used here.

Truths come from the simulator's geometry only: the artefacts' certificates (the
simulator makes them exactly), the plate's ray-cast surface points (its rendered mesh)
at the pixels the measurement used, filtered and zoned by the figures' definitions
(`plate_truth`, not `evaluate_face`), and the part's pose in the scene (its faces where
the CAD has them: a face's mean deviation is 0).

Calibration errors: with `rigs` (`MeasuringRig.from_calibration`: the results of
independent simulated calibrations, `slscan calibrate --seed`), trial k reconstructs with
rigs[k mod len(rigs)] and its U holds that calibration's covariance; the simulator
renders with the true geometry. Trials sharing a calibration share its error: the
calibrations, not the trials, are the independent draws of it.
"""

from __future__ import annotations

import json
import multiprocessing
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from inspection.acceptance import Acceptance, Position, ScanData, evaluate, frame_along, pose_of
from inspection.artefact_file import ArtefactSet
from inspection.uncertainty import CalibrationUncertainty, Estimate, MeasurementModel
from scanner.decode import DecodeResult
from scanner.geometry import Pinhole, RigModel
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator, triangulate
from scanner.rig import RigConfig
from sim.artefact_scenes import artefact_objects, quick_scan, window_renderer
from sim.render import Renderer, SensorModel

if TYPE_CHECKING:
    from inspection.report import InspectionReport


@dataclass(frozen=True)
class Trial:
    """One repeat: the estimate (value with U, or below its detection limit), the truth
    (mm) and the seconds it took; not `measured` when the command states no figure with a
    U to cover (a pose not proven), left out of the coverage."""

    estimate: Estimate
    truth: float
    seconds: float
    measured: bool = True

    @property
    def inside(self) -> bool:
        """The truth within ±U of the value; for a figure below its limit L, within [0, L + U]
        (what `inspection.tolerances.decide` takes it to say)."""
        e = self.estimate
        if e.value is None:
            return e.limit is not None and self.truth <= e.limit + e.U
        return abs(e.value - self.truth) <= e.U


@dataclass(frozen=True)
class CoverageResult:
    """Trials of one figure; `fraction` of them with the truth within ±U; `not_measured`
    the trials left out as giving no figure to cover (a pose not proven)."""

    figure: str
    trials: tuple[Trial, ...]
    not_measured: int = 0

    @property
    def fraction(self) -> float:
        return float(np.mean([t.inside for t in self.trials])) if self.trials else float("nan")

    @property
    def seconds(self) -> float:
        return float(sum(t.seconds for t in self.trials))

    def errors(self) -> np.ndarray:
        return np.array([t.estimate.value - t.truth for t in self.trials if t.estimate.value is not None])

    def as_json(self, case: str) -> dict[str, Any]:
        """The figures `slscan coverage --json` prints."""
        err = self.errors()
        return {"case": case, "scans": len(self.trials), "inside": int(sum(t.inside for t in self.trials)),
                "coverage": self.fraction, "error_mean_mm": float(err.mean()) if len(err) else None,
                "error_sd_mm": float(err.std(ddof=1)) if len(err) > 1 else None,
                "median_U_mm": float(np.median([t.estimate.U for t in self.trials])) if self.trials else None,
                "seconds": self.seconds,
                "reported": len(err), "below_limit": int(len(self.trials) - len(err)),
                "not_measured": self.not_measured}

    def summary(self) -> str:
        err = self.errors()
        U = np.array([t.estimate.U for t in self.trials])
        errors = "no value reported"
        if len(err) > 1:
            t = err.mean() / (err.std(ddof=1) / np.sqrt(len(err)))
            errors = f"error mean {err.mean() * 1e3:+.3f} µm (t = {t:+.1f}), std {err.std(ddof=1) * 1e3:.3f} µm"
        return (f"{self.figure}: truth within ±U in {self.fraction:.1%} of {len(self.trials)} trials; {errors}; "
                f"median U {np.median(U) * 1e3:.3f} µm (95 %); {len(self.trials) - len(err)} below their limit; "
                + (f"{self.not_measured} not measured; " if self.not_measured else "") + f"{self.seconds:.0f} s")


@dataclass(frozen=True, eq=False)
class Bench:
    """The simulated rig of a study: its true geometry, sensor, pattern set, and the
    measurement model its commands use (`measurement`, made by the caller with
    `slscan.measurement_model.rig_measurement`, the calibration term as the rig has it)."""

    model: RigModel
    sensor: SensorModel
    patterns: PatternSet
    projector_blur_px: float
    exposure_s: float
    bit_depth: int
    acceptance: Acceptance
    measurement: MeasurementModel

    @classmethod
    def of(cls, config: RigConfig, measurement: MeasurementModel) -> Bench:
        return cls(config.nominal_model(), SensorModel.from_config(config), PatternSet.load(config.patterns_path),
                   config.devices["projector"].settings.blur_sigma_px, config.camera.exposure_s or 0.01,
                   config.camera.bit_depth or 12, Acceptance.for_rig(config), measurement)

    def scan(self, renderer: Renderer, rng: np.random.Generator) -> DecodeResult:
        """One decoded scan of `renderer`'s scene with fresh noise."""
        return quick_scan(renderer, self.patterns, self.model.projector_gamma, self.exposure_s, self.bit_depth, rng)


@dataclass(frozen=True, eq=False)
class MeasuringRig:
    """The geometry a trial reconstructs with and the calibration covariance its U uses."""

    model: RigModel
    calibration: CalibrationUncertainty

    @classmethod
    def true(cls, bench: Bench) -> MeasuringRig:
        return cls(bench.model, CalibrationUncertainty.none("none: the simulator's exact geometry"))

    @classmethod
    def from_calibration(cls, path: str | Path, bench: Bench) -> MeasuringRig:
        """The rig a calibration file (`slscan calibrate`) describes, with its covariance."""
        from scanner.calibration_file import load_rig_model

        model = load_rig_model(path, bench.model.camera.size, bench.model.projector.size)
        return cls(model, CalibrationUncertainty.from_report(json.loads(Path(path).read_text())))

    def windowed(self, window: Pinhole, *, cut_from: Pinhole) -> RigModel:
        """The rig with its camera cut to `window`, a window of the full camera `cut_from`
        (the true one the simulator renders with, `sim.artefact_scenes.cropped_camera`): this
        rig's principal point moved by the window's pixel offset, its lens unchanged. The
        offset is the window's on the sensor, the same for every rig model; taken from this
        rig's own principal point instead it would give every model the true one and drop
        the calibration's principal-point errors from the reconstruction."""
        full = self.model.camera
        K = full.K.copy()
        K[:2, 2] -= cut_from.K[:2, 2] - window.K[:2, 2]
        return replace(self.model, camera=Pinhole(window.width, window.height, K, full.dist))


Measure = Callable[[np.ndarray, Callable[[np.ndarray], Any]], Estimate]
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
            yield from pool.imap(_run_job, range(n))  # type: ignore[misc]  # the pool's results are job's, typed Any
            pool.close()  # let the workers exit on their own: the pool's exit would SIGTERM them, which
            pool.join()  # the command's handler turns into a traceback on stderr
    finally:
        _JOB = None


def run_trials(figures: tuple[str, ...], trial: TrialFunction, n: int, processes: int = 1,
               progress: Callable[[str], None] | None = None) -> tuple[CoverageResult, ...]:
    """Trials 0..n-1 of a study (`map_trials`), with a line to `progress` every tenth of
    the way."""
    done: list[tuple[Trial, ...]] = []
    step = max(1, n // 10)

    def result(i: int, f: str) -> CoverageResult:  # figure i's measured trials, and how many were not
        kept = tuple(t[i] for t in done if t[i].measured)
        return CoverageResult(f, kept, not_measured=len(done) - len(kept))

    def line(i: int, f: str) -> str:
        c = result(i, f)
        return f"{f}: {c.fraction:.1%}" + (f" of {len(c.trials)} measured" if c.not_measured else "")

    for r in map_trials(trial, n, processes):
        done.append(r)
        if progress is not None and (len(done) % step == 0 or len(done) == n):
            progress("; ".join(line(i, f) for i, f in enumerate(figures)) + f" inside ±U after {len(done)} of {n}")
    return tuple(result(i, f) for i, f in enumerate(figures))


def _rig_for(k: int, bench: Bench, rigs: tuple[MeasuringRig, ...]) -> MeasuringRig:
    return rigs[k % len(rigs)] if rigs else MeasuringRig.true(bench)


def _artefact_trial(bench: Bench, position: Position, artefacts: ArtefactSet, *, read: Callable[[Any], Estimate],
                    truth: float, rng: np.random.Generator, rig: MeasuringRig,
                    noise_scales: tuple[float, ...]) -> tuple[Trial, ...]:
    """One scan of an artefact measured as `slscan verify` measures it (`evaluate`), once per
    noise model scale of `noise_scales` (the scan rendered once); `read` takes the figure
    from its PositionResult."""
    t0 = time.perf_counter()
    renderer = window_renderer(bench.model, artefact_objects(position, artefacts), bench.sensor,
                               bench.projector_blur_px)
    decoded = bench.scan(renderer, rng)
    used = rig.windowed(renderer.model.camera, cut_from=bench.model.camera)
    points = triangulate(decoded, Triangulator(used), with_normals=False).points
    measurement = replace(bench.measurement, calibration=rig.calibration)
    at = measurement.of_scan(decoded, used)

    def uncertainties(noise_scale: float) -> Callable[[np.ndarray], Any]:
        def scaled(pixels: np.ndarray) -> Any:
            unc = at(pixels)
            if noise_scale == 1.0:
                return unc
            assert unc.noise is not None, "the bench's measurement model has a noise model"
            return replace(unc, noise=unc.noise.scaled(noise_scale))

        return scaled

    estimates = []
    for noise_scale in noise_scales:
        result = evaluate(position, ScanData(points, uncertainties(noise_scale)), artefacts)
        if result.error:
            raise RuntimeError(f"trial at {position.pose[:3, 3].round(1).tolist()}: {result.error}")
        estimates.append(read(result))
    dt_s = (time.perf_counter() - t0) / len(noise_scales)
    return tuple(Trial(e, truth, dt_s) for e in estimates)


def _scaled_figures(figure: str, noise_scales: tuple[float, ...]) -> tuple[str, ...]:
    """The figure's name for each noise model scale (1: the name itself)."""
    return tuple(figure if s == 1.0 else f"{figure} (noise model x{s:.3g})" for s in noise_scales)


def _inner_estimate(fields: dict[str, Any], name: str) -> Estimate:
    """An Estimate with U from a fit's JSON fields (`name_mm`, `name_u_mm`)."""
    return Estimate(fields[f"{name}_mm"], fields[f"{name}_u_mm"] / 2.0, k=2.0)


def sphere_radius(bench: Bench, artefacts: ArtefactSet, n: int, *, seed: int = 0, rigs: tuple[MeasuringRig, ...] = (),
                  noise_scales: tuple[float, ...] = (1.0,), processes: int = 1,
                  progress: Callable[[str], None] | None = None) -> tuple[CoverageResult, ...]:
    """Coverage of the sphere radius as `slscan verify` measures it (inner variant, with
    its model U): the artefact set's sphere at random places; one result per noise model
    scale of `noise_scales`, from the same scans."""
    s = artefacts.sphere
    assert s is not None
    half = np.array(bench.acceptance.size_mm) / 2 - s.radius_mm - 2.0
    c0 = np.array(bench.acceptance.centre_mm)

    def trial(k: int) -> tuple[Trial, ...]:
        rng = np.random.default_rng((seed, k))
        position = Position("sphere", k, pose_of(np.eye(3), c0 + rng.uniform(-half, half)), "")
        return _artefact_trial(bench, position, artefacts, read=lambda r: _inner_estimate(r.detail["inner"], "radius"),
                               truth=s.radius_mm, rng=rng, rig=_rig_for(k, bench, rigs), noise_scales=noise_scales)

    return run_trials(_scaled_figures("sphere radius", noise_scales), trial, n, processes, progress)


def ball_bar_length(bench: Bench, artefacts: ArtefactSet, n: int, *, seed: int = 0, rigs: tuple[MeasuringRig, ...] = (),
                    noise_scales: tuple[float, ...] = (1.0,), processes: int = 1,
                    progress: Callable[[str], None] | None = None) -> tuple[CoverageResult, ...]:
    """Coverage of the ball bar's centre distance as `slscan verify` measures it (inner
    variant, with its model U): random directions (kept inside the measuring volume)
    through random places near its centre; one result per noise model scale of
    `noise_scales`, from the same scans."""
    b = artefacts.ball_bar
    assert b is not None
    half = np.array(bench.acceptance.size_mm) / 2
    c0 = np.array(bench.acceptance.centre_mm)

    def trial(k: int) -> tuple[Trial, ...]:
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
        position = Position("ball_bar", k, pose_of(R, c0 + rng.uniform(-room, room)), "")
        return _artefact_trial(bench, position, artefacts, read=lambda r: _inner_estimate(r.detail["inner"],
                                                                                          "distance"),
                               truth=b.length_mm, rng=rng, rig=_rig_for(k, bench, rigs), noise_scales=noise_scales)

    return run_trials(_scaled_figures("ball-bar length", noise_scales), trial, n, processes, progress)


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
        x, y = np.meshgrid(np.arange(-w / 2, w / 2 + 1e-9, PLATE_STEP_MM),
                           np.arange(-h / 2, h / 2 + 1e-9, PLATE_STEP_MM))
        p = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
        z = self.bow_mm * (1.0 - (p[:, 0] ** 2 + p[:, 1] ** 2) / ((w / 2) ** 2 + (h / 2) ** 2))
        if self.texture_mm > 0:
            z += Roughness(0, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), self.texture_mm, self.wavelengths_mm,
                           seed=seed).height(p)
        p[:, 2] = z
        rows, cols = x.shape
        k = np.arange(rows * cols).reshape(rows, cols)[:-1, :-1].ravel()
        tris = np.concatenate([np.stack([k, k + 1, k + cols], 1), np.stack([k + 1, k + cols + 1, k + cols], 1)])
        return p, tris.astype(np.int32)


SMOOTH = Plate(bow_mm=0.0, texture_mm=0.0)  # perfectly flat and smooth: every form figure's truth is 0
# smooth, bowed 10 um: its flatness over the region a scan measures (~8.7 um) sits at the bench's
# flatness detection limit (7-9 um), so some scans report a zone and others read "< L"
NEAR_LIMIT = Plate(bow_mm=0.010, texture_mm=0.0)


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
    ~10 µm and ~0.03 mrad), which registration takes out of an inspection too."""
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


def plate_truth(form: Any, true_points: np.ndarray, settings: Any) -> tuple[float, float]:
    """(minimum-zone flatness, Sq) of the true surface over the region a measurement took
    its figures over: the simulator's surface points (N, 3, plate frame) at the pixels
    measured, those the measurement used (`form.region`) averaged on its grid (`grid_mm`,
    `grid_origin_mm`, so the cells are the same), then the figures' definitions: the form
    surface, the second-order Gaussian regression filter of the form cut-off, its minimum
    zone (linear programme); Sq, the RMS of the heights less their Gaussian mean at the
    roughness cut-off."""
    from inspection.form import GaussianFilter, flatness_mz_many

    p = true_points[form.region]
    g = float(form.grid_mm)
    ij = np.floor((p[:, :2] - np.asarray(form.grid_origin_mm)) / g).astype(np.int64)
    ij -= ij.min(axis=0)
    shape = (int(ij[:, 1].max()) + 1, int(ij[:, 0].max()) + 1)
    flat = ij[:, 1] * shape[1] + ij[:, 0]
    count = np.bincount(flat, minlength=shape[0] * shape[1])
    mask = (count > 0).reshape(shape)
    z = np.full(shape, np.nan)
    z[mask] = (np.bincount(flat, p[:, 2], shape[0] * shape[1])[count > 0] / count[count > 0])
    form_surface = GaussianFilter(mask, settings.form_cutoff_mm, g, order=2)(z)
    mean = GaussianFilter(mask, settings.roughness_cutoff_mm, g, order=0)(z)
    rows, cols = np.nonzero(mask)
    centres = (np.stack([cols, rows], axis=1) + 0.5) * g
    flatness = float(flatness_mz_many(centres, form_surface[mask][None])[0])
    return flatness, float(np.sqrt(np.mean((z - mean)[mask] ** 2)))


def plate_figures(bench: Bench, n: int, *, seed: int = 0, rigs: tuple[MeasuringRig, ...] = (), noise_scale: float = 1.0,
                  plate: Plate = Plate(), processes: int = 1,
                  progress: Callable[[str], None] | None = None) -> tuple[CoverageResult, CoverageResult]:
    """Coverage of the minimum-zone flatness and of Sq of a plate (`Plate`) placed at
    random in the measuring volume, tilted up to 20 degrees, measured as `slscan inspect`
    measures a plane face (`measure_face`, its default settings; the camera defocus's bias
    removed, as an inspection does), the plate's points taken into its own frame by an
    ideal registration (`registered`). The truth: `plate_truth`."""
    from inspection.inspect_scan import InspectionSettings, measure_face

    face = _plate_face()
    settings = InspectionSettings()

    def trial(k: int) -> tuple[Trial, Trial]:
        rng = np.random.default_rng((seed, k))
        t0 = time.perf_counter()
        renderer, pose = _plate_renderer(bench, plate, seed, k, rng)
        decoded = bench.scan(renderer, rng)
        rig = _rig_for(k, bench, rigs)
        used = rig.windowed(renderer.model.camera, cut_from=bench.model.camera)
        points = triangulate(decoded, Triangulator(used), with_normals=False).points
        gt = renderer.ground_truth
        ok = np.isfinite(points).all(axis=2) & (gt.object_id == 2)
        rows, cols = np.nonzero(ok)
        camera_points = points[rows, cols].astype(np.float64)
        R, t = registered(camera_points, gt.points[rows, cols].astype(np.float64))
        inv = np.linalg.inv(pose)
        R, t = inv[:3, :3] @ R, inv[:3, :3] @ t + inv[:3, 3]
        measured = camera_points @ R.T + t
        near = np.abs(measured[:, 2]) <= settings.max_distance_mm  # the segmentation's distance gate
        unc = replace(bench.measurement, calibration=rig.calibration).of_scan(decoded, used, defocus=True)(
            np.stack([cols, rows], axis=1)[near])
        if noise_scale != 1.0:
            assert unc.noise is not None, "the bench's measurement model has a noise model"
            unc = replace(unc, noise=unc.noise.scaled(noise_scale))
        m = measured[near]
        got = measure_face(face, camera_points[near], unc, R=R, points=m, deviation=m[:, 2], uv=m[:, :2],
                           normals=np.tile([0.0, 0.0, 1.0], (len(m), 1)), settings=settings.form)
        true_points = gt.points[rows, cols][near].astype(np.float64) @ inv[:3, :3].T + inv[:3, 3]
        flat, sq = plate_truth(got, true_points, settings.form)
        dt_s = time.perf_counter() - t0
        if got.flatness_mz is None or got.sq is None:
            raise RuntimeError(f"plate trial {k}: {got.status} ({got.note})")
        return (Trial(got.flatness_mz, flat, dt_s / 2), Trial(got.sq, sq, dt_s / 2))

    flat, sq = run_trials(("flatness (minimum zone)", "Sq"), trial, n, processes, progress)
    return flat, sq


# ------------------------------------------------------------------------------ pose


def demo_part_pose(bench: Bench, rng: np.random.Generator) -> np.ndarray:
    """The demo part face up (its CAD +z toward the camera, as `config/scenes/demo.toml`
    lays it), turned at random about the camera axis, tilted up to 15 degrees and moved
    up to 15 mm across and 20 mm in depth about the centre of the measuring volume."""
    from sim.calibration_bench import rotation

    R = rotation(*rng.uniform(-15.0, 15.0, 2), rng.uniform(0.0, 360.0)) @ np.diag([1.0, -1.0, -1.0])
    return pose_of(R, np.array(bench.acceptance.centre_mm) + rng.uniform([-15, -15, -20], [15, 15, 20]))


DEMO_PART_FIGURES = ("pose", "face-position")


def demo_part_coverage(bench: Bench, n: int, figures: tuple[str, ...] = ("pose",), *, seed: int = 0,
                       rigs: tuple[MeasuringRig, ...] = (), processes: int = 1,
                       progress: Callable[[str], None] | None = None) -> tuple[CoverageResult, ...]:
    """Coverage of what `slscan inspect` reports of the demo part (`config/parts/demo_part.ply`,
    CAD `demo_part.step`) at random poses (`demo_part_pose`), inspected
    (`inspection.inspect_scan.inspect`), one result per name in `figures`:

    - "pose": the registration's pose U. A trial is inside when both its translation error
      (the displacement of the pose's centre, which its U bounds) and its rotation error are
      within their U; the Estimate recorded is the translation's. A pose the inspection
      gives no U for (not proven) is not measured. Alone, the faces' figures take 2 noise
      draws (the pose does not use them).
    - "face-position": the mean deviation of one plane face drawn at random from those
      measured (the mesh the simulator renders is the CAD's: its truth is 0), its U with the
      noise, the pose's fit and the calibration less the pose's following of it; a scan
      with no plane face measured is not measured."""
    from inspection.cad import load_cad
    from inspection.form import FormSettings
    from inspection.inspect_scan import InspectionSettings, inspect
    from inspection.measured_cloud import from_organised
    from inspection.registration import RegistrationSettings
    from inspection.views.align import pose_error
    from scanner.config import CONFIG_DIR
    from sim.scene import SceneObject, load_mesh

    unknown = set(figures) - set(DEMO_PART_FIGURES)
    if unknown:
        raise ValueError(f"demo part figures {sorted(unknown)}: not among {DEMO_PART_FIGURES}")
    parts = CONFIG_DIR / "parts"
    vertices, triangles = load_mesh(parts / "demo_part.ply", parts, None)
    cad = load_cad(parts / "demo_part.step")
    form = FormSettings(draws=2) if figures == ("pose",) else FormSettings()

    def pose_trial(report: InspectionReport, pose: np.ndarray, seconds: float) -> PoseTrial:
        bounds = None if report.pose_u is None else report.pose_u.bounds()
        if report.pose_u is None or report.pose_u.covariance is None or bounds is None:
            # ambiguous, or a motion the view does not fix: no pose U to cover
            return PoseTrial(Estimate(0.0, 0.0), 0.0, seconds, measured=False)
        U_r, U_t = bounds
        # transform · pose is the identity when exact; U_t bounds the displacement of the pose's centre
        r_err, t_err = pose_error(np.linalg.inv(report.registration.transform), pose, report.pose_u.covariance.centre)
        return PoseTrial(Estimate(t_err, U_t / 2.0, k=2.0), 0.0, seconds, rotation_error_deg=r_err, rotation_u_deg=U_r)

    def face_trial(report: InspectionReport, rng: np.random.Generator, seconds: float) -> Trial:
        measured = [e for e in (row.form.figure("deviation_mean") for row in report.faces if row.type == "plane")
                    if e is not None and e.value is not None]
        if not measured:
            return Trial(Estimate(0.0, 0.0), 0.0, seconds, measured=False)
        return Trial(measured[int(rng.integers(len(measured)))], 0.0, seconds)

    def trial(k: int) -> tuple[Trial, ...]:
        rng = np.random.default_rng((seed, k))
        t0 = time.perf_counter()
        pose = demo_part_pose(bench, rng)
        obj = SceneObject("demo_part", "mesh", pose, 0.7, vertices=vertices, triangles=triangles)
        renderer = window_renderer(bench.model, (obj,), bench.sensor, bench.projector_blur_px)
        decoded = bench.scan(renderer, rng)
        rig = _rig_for(k, bench, rigs)
        used = rig.windowed(renderer.model.camera, cut_from=bench.model.camera)
        cloud = triangulate(decoded, Triangulator(used))
        scan = from_organised(cloud, f"demo part trial {k}")
        unc = replace(bench.measurement, calibration=rig.calibration).of_scan(decoded, used, defocus=True)(scan.pixels)
        settings = InspectionSettings(registration=RegistrationSettings(seed=k), form=form)
        report = inspect(scan, cad, None, settings=settings, uncertainty=unc)
        seconds = (time.perf_counter() - t0) / len(figures)
        made = {"pose": lambda: pose_trial(report, pose, seconds),
                "face-position": lambda: face_trial(report, np.random.default_rng((seed, k, 1)), seconds)}
        return tuple(made[f]() for f in figures)

    return run_trials(figures, trial, n, processes, progress)


@dataclass(frozen=True)
class PoseTrial(Trial):
    """A pose trial: the translation error as `estimate` (truth 0), the rotation error
    and its U (degrees); inside when both are within their U; not `measured` when the
    inspection states no pose U (ambiguous, or a motion the view does not fix at all)."""

    rotation_error_deg: float = 0.0
    rotation_u_deg: float = 0.0

    @property
    def translation_inside(self) -> bool:
        return super().inside

    @property
    def rotation_inside(self) -> bool:
        return self.rotation_error_deg <= self.rotation_u_deg

    @property
    def inside(self) -> bool:
        return self.measured and self.translation_inside and self.rotation_inside


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
        scans = [bench.scan(renderer, rng) for _ in range(2)]
        z = [triangulate(d, Triangulator(renderer.model), with_normals=False).points[..., 2].astype(np.float64)
             for d in scans]
        inside = np.isfinite(z[0]) & np.isfinite(z[1]) & (renderer.ground_truth.object_id == 2)
        inside = ndimage.binary_erosion(inside, np.ones((17, 17)))
        rows, cols = np.nonzero(inside)
        px = np.stack([cols, rows], axis=1)
        measurement = replace(bench.measurement, fringe=None, calibration=CalibrationUncertainty.none("not studied"))
        # as an inspection takes them: the defocus bias removed from each scan, the noise model raised for it
        noises = [measurement.of_scan(d, renderer.model, defocus=True)(px).noise for d in scans]
        assert all(n is not None for n in noises), "the bench's measurement model has a noise model"
        moved = [n.defocus_removed() for n in noises if n is not None]
        diff = (z[0] - z[1])[rows, cols] + moved[0][0] - moved[1][0]
        r = diff / (np.sqrt(2.0) * moved[0][1].sigma_z)
        even = (rows + cols) % 2 == 0
        return float(np.std(r)), float(np.std(r[even])), float(np.std(r[~even])), len(r)

    done = np.array(list(map_trials(placement, n, processes)))
    return NoiseModelCheck(done[:, 0], done[:, 1:3], int(np.median(done[:, 3])))
