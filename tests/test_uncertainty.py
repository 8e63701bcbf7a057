"""The uncertainty model's parts against independent truths: ISO 14253-1 decisions in
closed form, the calibration Jacobian against re-triangulation with a moved rig, the
fringe error's spread against brute force over offsets, a sphere fit's propagated noise
against Monte Carlo refits, the predicted depth noise against the simulator's, and Sq and
flatness on synthetic surfaces of known form and texture."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.stereo import RIG_PARAMETERS as CALIBRATION_PARAMETERS
from inspection.artefacts import fit_sphere, measure_sphere
from inspection.form import FormSettings, evaluate_face
from inspection.surfaces import Plane
from inspection.tolerances import CONFORMING, NON_CONFORMING, NOT_MEASURED, PLAIN, UNCERTAIN, decide, overall
from inspection.uncertainty import (
    RIG_PARAMETERS,
    CalibrationUncertainty,
    Estimate,
    FringeError,
    PointNoise,
    ScanUncertainty,
    calibration_jacobian,
    depth_noise,
    perturbed,
)
from scanner.geometry import Pinhole
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator
from scanner.rig import RigConfig


def test_decision_rules_iso_14253_1() -> None:
    assert decide(0.010, 0.004, 0.020) == CONFORMING  # 0.014 <= 0.020
    assert decide(0.018, 0.004, 0.020) == UNCERTAIN  # 0.022 > 0.020 >= 0.014
    assert decide(0.025, 0.004, 0.020) == NON_CONFORMING  # 0.021 > 0.020
    assert decide(0.018, 0.004, 0.020, rule=PLAIN) == CONFORMING  # U not applied
    assert decide(0.021, 0.004, 0.020, rule=PLAIN) == NON_CONFORMING
    assert decide(-0.002, 0.002, 0.005, -0.005) == CONFORMING
    assert decide(-0.006, 0.0005, 0.005, -0.005) == NON_CONFORMING
    assert decide(None, 0.001, 0.02, limit=0.006) == CONFORMING  # below a detection limit: [0, 0.007] inside
    assert decide(None, 0.001, 0.0065, limit=0.006) == UNCERTAIN  # the limit inside, the limit + U not
    assert decide(None, 0.001, 0.005, limit=0.006) == UNCERTAIN  # cannot be shown either way
    assert decide(None, 0.0, 0.02) == NOT_MEASURED
    assert overall([CONFORMING, UNCERTAIN]) == UNCERTAIN and overall([UNCERTAIN, NON_CONFORMING]) == NON_CONFORMING
    with pytest.raises(ValueError, match="unknown decision rule"):
        decide(0.0, 0.0, 1.0, rule="lenient")


def test_estimates_print_value_and_u_or_their_detection_limit() -> None:
    assert Estimate(0.0123, 0.00105).text() == "12.3 ± 2.1 µm"
    below = Estimate(None, 0.001, 0.0061)
    assert below.value is None and below.text() == "< 6.1 µm"
    assert below.fields("flatness_mz") == {"flatness_mz_mm": None, "flatness_mz_u_mm": 0.002,
                                            "flatness_mz_limit_mm": 0.0061}


def test_rig_parameters_are_those_the_calibration_writes() -> None:
    assert RIG_PARAMETERS == CALIBRATION_PARAMETERS


def _small_rig() -> object:
    model = RigConfig.load().nominal_model()
    return model.with_camera_size(160, 128)


def test_calibration_jacobian_matches_retriangulation() -> None:
    """∂X/∂θ from implicit differentiation against points triangulated again with the rig
    moved ±δ along each parameter (central differences, the scanner's own triangulation)."""
    model = _small_rig()
    rng = np.random.default_rng(0)
    rays = model.camera.ray_grid.astype(np.float64)
    rows, cols = rng.integers(10, 118, 300), rng.integers(10, 150, 300)
    X = rays[rows, cols] * rng.uniform(370.0, 430.0, 300)[:, None]
    Xp = X @ model.proj_from_cam[:3, :3].T + model.proj_from_cam[:3, 3]
    coord = np.full((128, 160), np.nan, np.float32)
    coord[rows, cols] = model.projector.project(Xp)[:, 0]
    J = calibration_jacobian(X, model, {"vertical": np.ones(len(X))})
    steps = np.array([0.5, 0.5, 0.5, 0.5, 2e-3, 2e-3, 2e-4, 2e-4, 2e-3] * 2 + [1e-4] * 3 + [0.05] * 3)
    for p in (0, 2, 3, 4, 7, 9, 11, 13, 16, 18, 19, 20, 21, 23):  # every kind of parameter of both devices
        step = steps[p]
        d = np.zeros(len(RIG_PARAMETERS))
        d[p] = step
        moved = []
        for sign in (1.0, -1.0):
            m = perturbed(model, sign * d)
            z = Triangulator(m).depth_scale(coord, "vertical")
            moved.append(m.camera.ray_grid.astype(np.float64)[rows, cols] * z[rows, cols, None])
        numeric = (moved[0] - moved[1]) / 2.0
        scale = max(float(np.abs(numeric).max()), 1e-4)
        assert np.abs(J[:, :, p] * step - numeric).max() < 0.02 * scale + 6e-5, RIG_PARAMETERS[p]  # float32 depths


def test_a_figures_calibration_u_is_the_spread_of_refits_with_drawn_calibrations() -> None:
    """The calibration error is one error common to all points of a scan: a sphere's true
    projector coordinates (ray-sphere intersections, written here) triangulated again
    with rigs drawn from a simulated calibration's covariance (every parameter, both
    devices and the extrinsic) and refitted; the radius's and the centre's spread over the
    draws against the u_cal the fit propagates. Propagated as if independent from point to
    point, the same moves give a u_cal far off (moves the radius does not see, such as a
    shift of the whole sphere, no longer cancel)."""
    import json
    from pathlib import Path

    model = RigConfig.load().nominal_model().with_camera_size(160, 128)
    cov = json.loads((Path(__file__).parent / "data" / "sim_calibration_covariance.json").read_text())
    calibration = CalibrationUncertainty.from_report(cov)
    centre, radius = np.array([8.0, -6.0, 400.0]), 12.7
    rays = model.camera.ray_grid.astype(np.float64)
    b = rays @ centre
    disc = b ** 2 - (rays ** 2).sum(axis=2) * (centre @ centre - radius ** 2)
    t = (b - np.sqrt(np.where(disc > 0, disc, np.nan))) / (rays ** 2).sum(axis=2)
    X = rays * t[..., None]
    rows, cols = np.nonzero(np.isfinite(t) & (disc > 0.2 * np.nanmax(disc)))  # away from the outline
    Xp = X[rows, cols] @ model.proj_from_cam[:3, :3].T + model.proj_from_cam[:3, 3]
    coord = np.full(t.shape, np.nan, np.float32)
    coord[rows, cols] = model.projector.project(Xp)[:, 0]
    points = X[rows, cols]
    unc = ScanUncertainty(None, calibration, model, {"vertical": np.ones(len(points))})
    fit, res = measure_sphere(points, unc, radius, viewpoint=None, inner=False)
    rng = np.random.default_rng(12)
    fits = []
    for _ in range(150):
        m = perturbed(model, calibration.draw(rng))
        z = Triangulator(m).depth_scale(coord, "vertical")
        fits.append(fit_sphere(m.camera.ray_grid.astype(np.float64)[rows, cols] * z[rows, cols, None]))
    assert len(points) > 300
    # 150 draws: the spread's own standard error is 6 %
    mc = np.std([f.radius for f in fits], ddof=1)
    assert res.components["calibration"] == pytest.approx(mc, rel=0.15)
    assert res.centre[2].u == pytest.approx(np.std([f.centre[2] for f in fits], ddof=1), rel=0.15)
    moves = np.einsum("nip,dp->dni", calibration_jacobian(points[fit.used], model,
                                                          {"vertical": np.ones(int(fit.used.sum()))}),
                      calibration.directions())
    per_point = np.sqrt(np.sum(np.einsum("dni,ni->dn", moves, fit.influence[:, 3]) ** 2))
    assert not 1.0 / 3.0 < per_point / mc < 3.0


def test_calibration_directions_span_the_covariance_and_draws_follow_it() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(24, 24)) * np.r_[np.full(18, 0.2), np.full(3, 1e-5), np.full(3, 3e-3)]
    cov = A @ A.T
    cal = CalibrationUncertainty(cov, "test")
    d = cal.directions()
    assert np.allclose(d.T @ d, cov, rtol=1e-9, atol=1e-14 * np.abs(cov).max())
    draws = np.array([cal.draw(rng) for _ in range(4000)])
    assert np.allclose(np.cov(draws.T), cov, atol=0.1 * np.sqrt(np.outer(np.diag(cov), np.diag(cov))).max())
    one_sigma = CalibrationUncertainty.from_report({"uncertainty": {"camera.fx": 0.2, "extrinsic.tz": 0.01}})
    assert np.allclose(np.diag(one_sigma.covariance)[[0, 23]], [0.04, 1e-4]) and "uncorrelated" in one_sigma.source


def test_fringe_error_spread_over_offsets_matches_brute_force() -> None:
    rng = np.random.default_rng(1)
    fe = FringeError(rng.normal(0, 0.002, 800), 0.125)
    col = rng.uniform(0.0, 100.0, 500)
    w = rng.normal(size=500)
    offsets = np.arange(800) * 0.125
    sums = np.array([np.sum(w * fe.at(col, o)) for o in offsets])
    assert fe.spread(col, w) == pytest.approx(np.std(sums), rel=1e-9)


def test_sphere_fit_uncertainty_matches_monte_carlo_refits() -> None:
    """A sphere seen from the origin, white depth noise along the rays: the radius and
    centre spread over 300 refits of fresh noise against the propagated u."""
    rng = np.random.default_rng(2)
    c, R = np.array([10.0, -5.0, 400.0]), 12.7
    v = rng.normal(size=(20000, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    p = c + R * v
    p = p[np.einsum("ij,ij->i", v, -p / np.linalg.norm(p, axis=1)[:, None]) > 0.3][:4000]
    rays = p / p[:, 2:3]
    sigma = rng.uniform(0.01, 0.02, len(p))
    unc = ScanUncertainty(PointNoise(sigma, rays), CalibrationUncertainty.none("test"))
    _, res = measure_sphere(p, unc, R, viewpoint=None)
    fits = [fit_sphere(p + rays * (rng.normal(size=len(p)) * sigma)[:, None]) for _ in range(300)]
    radius_sd = np.std([f.radius for f in fits], ddof=1)
    assert res.radius.u == pytest.approx(radius_sd, rel=0.15)
    assert res.centre[2].u == pytest.approx(np.std([f.centre[2] for f in fits], ddof=1), rel=0.15)


def test_predicted_depth_noise_matches_the_simulator() -> None:
    """σ_z from modulation and the sensor model against the spread of two fresh-noise scans
    of the same plane (the simulator's noise, not the model's)."""
    from dataclasses import replace

    from scanner.patterns import PatternSet
    from scanner.reconstruct import triangulate
    from sim.artefact_scenes import quick_scan
    from sim.render import Renderer, SensorModel
    from sim.scene import Scene, SceneObject

    config = RigConfig.load()
    model = config.nominal_model()
    K = model.camera.K.copy()
    K[0, 2] -= 560
    K[1, 2] -= 450
    small = replace(model, camera=Pinhole(160, 120, K, model.camera.dist))
    sensor = SensorModel.from_config(config)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]])
    pose[2, 3] = 410.0
    renderer = Renderer(small, Scene((SceneObject("plate", "plane", pose, 0.8, size_mm=(300.0, 300.0)),)), sensor, 0.8)
    patterns = PatternSet.load(config.patterns_path)
    rng = np.random.default_rng(4)
    tri = Triangulator(small)
    scans = [quick_scan(renderer, patterns, model.projector_gamma, 0.01, 12, rng) for _ in range(2)]
    z = [triangulate(d, tri, with_normals=False).points[..., 2] for d in scans]
    sigma = depth_noise(scans[0], tri, lambda a: sensor.noise_sigma_dn(a, 12)).sigma_z
    diff = (z[0] - z[1]) / np.sqrt(2.0)
    ok = np.isfinite(diff) & np.isfinite(sigma)
    assert ok.sum() > 15000
    assert np.sqrt(np.mean((diff[ok] / sigma[ok]) ** 2)) == pytest.approx(1.0, abs=0.03)


def _plane_face() -> object:
    class Face:
        type = "plane"
        surface = Plane(np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]))

    return Face()


def _plate(bow_mm: float, texture_mm: float, sigma_mm: float, rng: np.random.Generator,
           spacing: float = 0.15) -> tuple[np.ndarray, np.ndarray, PointNoise, np.ndarray]:
    """Points on a 30 x 20 mm plate (z = heights), a bow of `bow_mm` (quadratic, its span
    over the plate), a texture of RMS `texture_mm` at 0.3-1 mm wavelengths, white noise
    of `sigma_mm` along z; returns (points, true heights, noise model, normals)."""
    x, y = np.meshgrid(np.arange(-15, 15, spacing), np.arange(-10, 10, spacing))
    x, y = x.ravel() + rng.uniform(-0.02, 0.02, x.size), y.ravel() + rng.uniform(-0.02, 0.02, x.size)
    h = bow_mm * (1.0 - (x ** 2 + y ** 2) / (15.0 ** 2 + 10.0 ** 2))
    waves = np.zeros_like(x)
    for _ in range(40):
        k = rng.uniform(2 * np.pi / 1.0, 2 * np.pi / 0.3)
        a = rng.uniform(0, 2 * np.pi)
        waves += np.cos(k * (x * np.cos(a) + y * np.sin(a)) + rng.uniform(0, 2 * np.pi))
    h = h + texture_mm * waves / np.sqrt(20.0)
    pts = np.column_stack([x, y, h])
    noise = PointNoise(np.full(len(x), sigma_mm), np.tile([0.0, 0.0, 1.0], (len(x), 1)))
    return pts, h, noise, np.tile([0.0, 0.0, 1.0], (len(x), 1))


def test_sq_with_the_noise_removed_and_its_detection_limit() -> None:
    """Sq of a textured plate through 14 um noise within its U of the noise-free Sq; a
    smooth plate's Sq is below its detection limit (null), never 0."""
    rng = np.random.default_rng(5)
    face = _plane_face()
    pts, h, noise, normals = _plate(0.0, 0.012, 0.014, rng)
    truth = evaluate_face(face, pts, h, uv=pts[:, :2], noise=noise.scaled(0.0), normals=normals).sq
    noisy = pts.copy()
    noisy[:, 2] += rng.normal(0, 0.014, len(pts))
    got = evaluate_face(face, noisy, noisy[:, 2], uv=noisy[:, :2], noise=noise, normals=normals)
    assert got.sq.value is not None and abs(got.sq.value - truth.value) <= got.sq.U
    assert got.sq_raw_mm > truth.value + 0.003  # before the noise was removed it read high
    smooth, _hs, _, _ = _plate(0.0, 0.0, 0.014, rng)
    smooth[:, 2] += rng.normal(0, 0.014, len(smooth))
    flat = evaluate_face(face, smooth, smooth[:, 2], uv=smooth[:, :2], noise=noise.subset(np.arange(len(smooth))),
                         normals=normals[:len(smooth)])
    assert flat.sq.value is None and 0 < flat.sq.limit < 0.01
    assert flat.flatness_mz.value is None and 0 < flat.flatness_mz.limit < 0.01  # nothing but noise


def test_flatness_noise_bias_removed() -> None:
    """A 30 um bow through 14 um point noise: the minimum zone of the form surface, its
    noise bias removed, within its U of the noise-free zone, and the bias it removed is
    positive (noise widens a zone)."""
    rng = np.random.default_rng(6)
    face = _plane_face()
    pts, h, noise, normals = _plate(0.030, 0.0, 0.014, rng)
    truth = evaluate_face(face, pts, h, uv=pts[:, :2], noise=noise.scaled(0.0), normals=normals).flatness_mz
    noisy = pts.copy()
    noisy[:, 2] += rng.normal(0, 0.014, len(pts))
    got = evaluate_face(face, noisy, noisy[:, 2], uv=noisy[:, :2], settings=FormSettings(draws=48), noise=noise,
                        normals=normals).flatness_mz
    # the bow inside the 1 mm margin
    assert truth.value == pytest.approx(0.030 * (14.0 ** 2 + 9.0 ** 2) / 325.0, abs=0.002)
    assert got.bias > 0 and abs(got.value - truth.value) <= got.U


def test_a_removed_bias_carries_its_own_uncertainty() -> None:
    """from_draws, written out: value less the draws' mean shift b; u² = the draws'
    variance + b²/3 (the correction known to within its own size) + the variance / D
    (the mean shift's Monte Carlo error) + the calibration changes' sum of squares."""
    from inspection.form import from_draws

    drawn = np.array([1.1, 1.3, 1.2, 1.4])
    est, parts = from_draws(1.0, drawn, cal=np.array([0.03, 0.04]))
    b, s = 0.25, float(np.std(drawn, ddof=1))
    assert est.value == pytest.approx(1.0 - b) and est.bias == pytest.approx(b)
    assert parts["noise bias"] == pytest.approx(np.sqrt(b * b / 3 + s * s / 4))
    assert est.u == pytest.approx(np.sqrt(s * s + b * b / 3 + s * s / 4 + 0.05 ** 2))


def test_a_truth_over_the_measured_region() -> None:
    """A plate whose outline carries mixed pixels 100 um off: the measurement drops them as
    spikes and keeps its edge margin from what is left; handed its `region`, the noise-free
    evaluation takes its zone over exactly those points (none dropped, no second margin),
    and evaluating the measured points over their own region gives the measured zone
    (within its u: the grid starts at the region's corner)."""
    rng = np.random.default_rng(12)
    face = _plane_face()
    pts, h, noise, normals = _plate(0.030, 0.0, 0.002, rng)
    edge = (np.abs(pts[:, 0]) > 14.8) | (np.abs(pts[:, 1]) > 9.8)
    noisy = pts.copy()
    noisy[:, 2] += rng.normal(0, 0.002, len(pts)) + np.where(edge, rng.choice([-0.1, 0.1], len(pts)), 0.0)
    got = evaluate_face(face, noisy, noisy[:, 2], uv=noisy[:, :2], noise=noise, normals=normals)
    region = got.region
    assert region is not None and not region[edge].any() and 0.5 * len(pts) < region.sum() < len(pts)
    inside = (np.abs(pts[:, 0]) < 13.0) & (np.abs(pts[:, 1]) < 8.0)  # 2 mm inside the outline: past spikes and margin
    assert region[inside].all()
    truth = evaluate_face(face, pts, h, uv=pts[:, :2], noise=noise.scaled(0.0), normals=normals, region=region)
    assert truth.region is not None and (truth.region == region).all()
    again = evaluate_face(face, noisy, noisy[:, 2], uv=noisy[:, :2], noise=noise, normals=normals, region=region)
    assert again.points == got.points
    # the same points on a grid started at the region's own corner: the same zone within its u
    assert again.flatness_mz.value == pytest.approx(got.flatness_mz.value, abs=got.flatness_mz.u)


def test_coverage_factor_of_a_bounded_systematic() -> None:
    """coverage_factor, against closed forms: nothing but normal -> K; a sinusoid's values
    alone (arcsine distribution, P(|x| <= h) = (2/pi) asin(h/A)) -> K * A sin(0.475 pi) /
    (1.96 A/sqrt(2)); normal values for the other part -> K again (to sampling)."""
    from inspection.uncertainty import NORMAL_95, K, coverage_factor

    assert coverage_factor(1.0, np.zeros(0)) == K
    A = 3.0
    sine = A * np.sin(np.linspace(0.0, 2.0 * np.pi, 200000, endpoint=False))
    assert coverage_factor(0.0, sine) == pytest.approx(K * A * np.sin(0.475 * np.pi) / (NORMAL_95 * A / np.sqrt(2.0)),
                                                       rel=1e-4)
    normal = np.random.default_rng(3).standard_normal(200000)
    assert coverage_factor(0.7, normal - normal.mean()) == pytest.approx(K, rel=0.01)


def test_calibration_moves_reach_the_face_figures() -> None:
    """Two calibration directions on a bowed plate: one tilts the plate (a zone cannot see
    it: no contribution), one adds 5 um more of the same dome (the zone grows by the
    dome's span): u_cal of both zones is that span."""
    rng = np.random.default_rng(8)
    face = _plane_face()
    pts, h, noise, normals = _plate(0.030, 0.0, 0.002, rng, spacing=0.25)
    r2 = (pts[:, 0] ** 2 + pts[:, 1] ** 2) / (15.0 ** 2 + 10.0 ** 2)
    shifts = np.zeros((2, len(pts), 3))
    shifts[0, :, 2] = 1e-3 * pts[:, 0] / 15.0  # a tilt of 1 um over the half-length
    shifts[1, :, 2] = 0.005 * (1.0 - r2)  # the same dome, 5 um higher
    got = evaluate_face(face, pts, h, uv=pts[:, :2], noise=noise, normals=normals, shifts=shifts)
    expected = 0.005 * (14.0 ** 2 + 9.0 ** 2) / 325.0  # the added dome's span inside the 1 mm margin
    assert got.u_components["flatness_mz"]["calibration"] == pytest.approx(expected, rel=0.1)
    assert got.u_components["flatness_ls"]["calibration"] == pytest.approx(expected, rel=0.1)


def test_local_quadratic_recovers_gradient_and_laplacian_of_a_quadratic() -> None:
    """Closed form: on c = 3 + 0.5x - 0.2y + 0.01x² + 0.02xy - 0.03y² the fit gives the
    exact gradient and Laplacian (0.02 - 0.06) wherever enough of its window is valid,
    also next to a hole, and NaN inside the hole."""
    from inspection.uncertainty import local_quadratic

    y, x = np.mgrid[0:40, 0:50].astype(np.float64)
    c = 3 + 0.5 * x - 0.2 * y + 0.01 * x * x + 0.02 * x * y - 0.03 * y * y
    valid = np.ones_like(c, dtype=bool)
    valid[15:25, 20:30] = False
    gx, gy, lap = local_quadratic(np.where(valid, c, np.nan), valid)
    ok = np.isfinite(gx)
    assert ok[valid].mean() > 0.9 and not ok[~valid].any()
    assert np.allclose(gx[ok], (0.5 + 0.02 * x + 0.02 * y)[ok], atol=1e-9)
    assert np.allclose(gy[ok], (-0.2 + 0.02 * x - 0.06 * y)[ok], atol=1e-9)
    assert np.allclose(lap[ok], -0.04, atol=1e-9)


def test_defocus_bias_matches_the_simulators_blur() -> None:
    """The simulator blurs its images with the camera's Gaussian defocus; the decoded
    coordinate of a sphere rendered noise-free with that blur minus the one rendered
    without it is the bias `defocus_bias` predicts from the blurred scan alone, inside
    the silhouette band it leaves out (NaN there)."""

    from scipy import ndimage

    from inspection.acceptance import Position, pose_of
    from inspection.artefact_file import DEFAULT_ARTEFACTS, load_artefacts
    from inspection.uncertainty import defocus_bias
    from scanner.decode import decode
    from sim.artefact_scenes import artefact_objects, window_renderer
    from slscan.measurement_model import rig_measurement
    from studies.repeat_scans import Bench

    config = RigConfig.load()
    bench = Bench.of(config, rig_measurement(config.raw, config.nominal_model(), PatternSet.load(config.patterns_path),
                                             12, config.path))
    sigma = bench.sensor.blur_sigma_px
    assert sigma > 0
    position = Position("sphere", 0, pose_of(np.eye(3), np.array(bench.acceptance.centre_mm) + [5.0, -3.0, 2.0]), "")
    decoded = {}
    for blur in (sigma, 0.0):
        r = window_renderer(bench.model, artefact_objects(position, load_artefacts(DEFAULT_ARTEFACTS)),
                            bench.sensor.model_copy(update={"blur_sigma_px": blur}), bench.projector_blur_px)
        p = r.model.projector
        frames = np.stack([np.rint(r.mean_dn(img, bench.exposure_s, bench.bit_depth)).clip(0, 2 ** bench.bit_depth - 1)
                           .astype(np.uint16) for img in bench.patterns.render(p.width, p.height,
                                                                               bench.model.projector_gamma)])
        decoded[blur] = decode(frames, bench.patterns, bench.bit_depth, p.size)
    predicted = defocus_bias(decoded[sigma], sigma)
    both = decoded[sigma].valid & decoded[0.0].valid
    inside = ndimage.distance_transform_edt(both) > 8
    for orientation, m in decoded[sigma].maps.items():
        actual = (m.coordinate - decoded[0.0].maps[orientation].coordinate).astype(np.float64)
        assert np.isnan(predicted[orientation][both & (ndimage.distance_transform_edt(both) <= 2)]).all()
        sel = inside & np.isfinite(predicted[orientation])
        assert sel.sum() > 10000
        slope = np.polyfit(predicted[orientation][sel], actual[sel], 1)[0]
        assert 0.85 < slope < 1.1, slope
        assert np.corrcoef(predicted[orientation][sel], actual[sel])[0, 1] > 0.9
        assert np.std(actual[sel] - predicted[orientation][sel]) < 0.5 * np.std(actual[sel])
        # the scan less it (as an inspection removes it): nearer the unblurred decode
        fixed = actual - predicted[orientation]
        assert np.sqrt(np.mean(fixed[sel] ** 2)) < 0.5 * np.sqrt(np.mean(actual[sel] ** 2))


def test_defocus_correction_noise_gain_matches_a_monte_carlo() -> None:
    """The factor by which the correction's Laplacian term raises white noise, against
    the spread of white noise corrected the same way (σ²/2 · Laplacian of the window fit)."""
    from inspection.uncertainty import _correction_gain, local_quadratic

    sigma = 0.6
    noise = np.random.default_rng(2).standard_normal((400, 400))
    lc = local_quadratic(noise, np.ones(noise.shape, bool))[2][10:-10, 10:-10]
    corrected = noise[10:-10, 10:-10] - 0.5 * sigma ** 2 * lc
    assert np.std(corrected) / np.std(noise[10:-10, 10:-10]) == pytest.approx(_correction_gain(sigma), abs=5e-4)
    assert _correction_gain(sigma) > 1.003 and _correction_gain(0.0) == 1.0
