"""End-to-end accuracy on the default simulated rig against the simulator's ground truth.

Scene `config/scenes/sphere_plane.toml`: an analytic sphere (r = 20 mm) in front of a plane.
Camera model (config/rigs/sim_bench.toml): 12-bit, full well 10500 e-, read noise 6 e-,
gain 2.56 e-/DN, camera blur 0.6 px, projector gamma 2.2 and blur 0.8 px.

The noise bound is predicted from the simulator's sensor model and known intensities
(`sensor_noise.depth_sigma`), not from the decoder's estimates; the camera and projector
models are checked against OpenCV's `projectPoints` and the distortion written out in the
test (simulator and reconstruction share `Pinhole`, so an error there would cancel in a
scan); and a rig model perturbed in a known way must err as the closed form says.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from sensor_noise import depth_sigma, project

from scanner.acquisition import AcquisitionSettings, acquire
from scanner.config import CONFIG_DIR
from scanner.decode import DecodeSettings, decode
from scanner.geometry import Pinhole
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator, triangulate
from scanner.rig import Rig, RigConfig, open_rig
from sim.evaluate import Truth, evaluate, smooth_region

SCENE = CONFIG_DIR / "scenes" / "sphere_plane.toml"
SPHERE_RADIUS_MM = 20.0
PATTERNS = {name: PatternSet.load(CONFIG_DIR / "patterns" / f"{name}.toml")
            for name in ("heterodyne_3x4", "hierarchical_3x4", "graycode_4")}


@pytest.fixture(scope="module")
def rig() -> Rig:
    with open_rig(RigConfig.load(), scene=SCENE, seed=7) as r:
        yield r


@pytest.fixture(scope="module")
def scans(rig: Rig) -> dict:
    tri = Triangulator(rig.model)
    out = {}
    for name, ps in PATTERNS.items():
        stack = acquire(rig, ps, AcquisitionSettings.for_rig(rig), lambda k, f: None)
        d = decode(stack, ps, rig.camera.bit_depth, rig.model.projector.size)
        out[name] = (d, triangulate(d, tri))
    return out


@pytest.mark.parametrize("name", PATTERNS)
def test_depth_error_within_noise_bound(rig: Rig, scans: dict, name: str) -> None:
    """The depth error's RMS over smooth lit pixels within 1.3x the noise the simulator's
    sensor model and intensities allow (the bound `sim.evaluate` builds from the decoder's
    own modulation agrees with it to 10 %)."""
    d, cloud = scans[name]
    gt = Truth.of(rig.extras["ground_truth"])
    acc = evaluate(d, cloud, gt, rig.extras["sensor"], Triangulator(rig.model))
    sel = smooth_region(gt) & cloud.valid & ~d.maps["vertical"].masks["saturated"]
    err = (cloud.points[..., 2] - gt.depth)[sel].astype(np.float64)
    rms = float(np.sqrt(np.mean(err ** 2)))
    bound = float(np.sqrt(np.mean(depth_sigma(rig, PATTERNS[name])[sel] ** 2)))
    print(f"{name}: depth error RMS {rms * 1e3:.2f} um, predicted from the sensor model {bound * 1e3:.2f} um "
          f"(ratio {rms / bound:.3f}); {acc.summary()}")
    assert sel.sum() > 800_000
    assert rms <= 1.3 * bound
    assert acc.bound_mm == pytest.approx(bound, rel=0.1)
    assert abs(err.mean()) < 0.2 * rms
    assert acc.order_errors == 0, acc.summary()
    assert acc.coverage >= 0.98, acc.summary()


def test_device_models_against_opencv_and_the_written_out_distortion(rig: Rig) -> None:
    """`Pinhole` projects as OpenCV's `projectPoints` and as Brown-Conrady written out in the
    test; its undistortion inverts that; and the simulator's truth obeys it: every true
    point lies on its pixel's ray, and the projector pixel lighting it is where OpenCV
    projects it with the rig's extrinsics."""
    model = rig.model
    rng = np.random.default_rng(0)
    for device in (model.camera, model.projector):
        X = np.c_[rng.uniform(-0.2, 0.2, (500, 2)), np.ones(500)] * rng.uniform(300, 500, (500, 1))
        cv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), device.K, device.dist)
        written = project(device, X)
        assert np.abs(cv.reshape(-1, 2) - written).max() < 1e-8
        assert np.abs(device.project(X) - written).max() < 1e-8
        assert np.abs(device.normalized(written) - X[:, :2] / X[:, 2:]).max() < 1e-9
    gt = rig.extras["ground_truth"]
    hit = np.isfinite(gt.depth)
    v, u = np.nonzero(hit)
    assert np.abs(project(model.camera, gt.points[hit]) - np.c_[u, v]).max() < 1e-6
    lit = np.isfinite(gt.proj_uv[..., 0])
    P = model.proj_from_cam
    uv, _ = cv2.projectPoints(gt.points[lit], cv2.Rodrigues(P[:3, :3])[0], P[:3, 3], model.projector.K,
                              model.projector.dist)
    assert np.abs(uv.reshape(-1, 2) - gt.proj_uv[lit]).max() < 1e-6
    rays = model.camera.ray_grid  # float32 (x/z, y/z, 1)
    assert np.abs(project(model.camera, rays[::64, ::64].reshape(-1, 3).astype(np.float64))
                  - np.stack(np.meshgrid(np.arange(0, model.camera.width, 64), np.arange(0, model.camera.height, 64)),
                             -1).reshape(-1, 2)).max() < 1e-3


def _closed_form_depth(rays: np.ndarray, x_n: np.ndarray, proj_from_cam: np.ndarray) -> np.ndarray:
    """Depth z of the point on each camera ray (N, 3) as (x/z, y/z, 1) that a distortion-free
    projector sees at normalised column x_n (N,): R0.(z r) + t0 = x_n (R2.(z r) + t2)."""
    R, t = proj_from_cam[:3, :3], proj_from_cam[:3, 3]
    return (x_n * t[2] - t[0]) / (rays @ R[0] - x_n * (rays @ R[2]))


@pytest.mark.parametrize("perturbation", ["baseline x 1.002", "projector fx + 2 px", "camera fx + 2 px"])
def test_a_rig_model_perturbed_in_a_known_way_errs_as_the_closed_form_says(rig: Rig, perturbation: str) -> None:
    """The true projector columns of every lit pixel reconstructed with a wrong rig model.
    A baseline scaled by 1 + e scales the whole scene about the camera centre (rays and
    projector angles unchanged), so z' = (1 + e) z exactly, distortion and all. A focal
    length off by 2 px (distortion-free devices, so the closed form is a ray-plane
    intersection): z' from the camera ray and the projector column plane the wrong model
    gives them."""
    gt = rig.extras["ground_truth"]
    lit = np.isfinite(gt.proj_uv[..., 0])
    true = rig.model
    if perturbation.startswith("baseline"):
        e = 0.002
        scaled = true.cam_from_proj.copy()
        scaled[:3, 3] *= 1 + e
        wrong = replace(true, cam_from_proj=scaled)
        coord = gt.proj_uv[..., 0]
        depth = gt.depth[lit]
        expected = (1 + e) * depth
    else:  # the scene's true depths along the distortion-free camera's rays, seen by a distortion-free projector
        bare = replace(true, camera=Pinhole(true.camera.width, true.camera.height, true.camera.K),
                       projector=Pinhole(true.projector.width, true.projector.height, true.projector.K))
        v, u = np.nonzero(lit)

        def rays(K: np.ndarray) -> np.ndarray:
            return np.c_[(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(len(u))]

        depth = gt.depth[lit]
        P = bare.proj_from_cam
        coord = np.full(lit.shape, np.nan)
        coord[lit] = project(bare.projector, (depth[:, None] * rays(bare.camera.K)) @ P[:3, :3].T + P[:3, 3])[:, 0]
        device = "projector" if perturbation.startswith("projector") else "camera"
        pin = getattr(bare, device)
        K = pin.K.copy()
        K[0, 0] += 2.0
        wrong = replace(bare, **{device: Pinhole(pin.width, pin.height, K)})
        Kp = wrong.projector.K
        expected = _closed_form_depth(rays(wrong.camera.K), (coord[lit] - Kp[0, 2]) / Kp[0, 0], P)
    z = Triangulator(wrong).depth_scale(coord.astype(np.float32), "vertical")[lit]
    error = expected - depth
    print(f"{perturbation}: depth error {np.median(error) * 1e3:+.1f} um median, {error.min() * 1e3:+.1f} .. "
          f"{error.max() * 1e3:+.1f} um; reconstruction off the closed form by at most "
          f"{np.nanmax(np.abs(z - expected)) * 1e3:.3f} um")
    assert np.median(np.abs(error)) > 0.05  # the perturbation matters
    assert np.isfinite(z).mean() > 0.999 and np.nanmax(np.abs(z - expected)) < 1e-3


def test_heterodyne_and_graycode_agree(scans: dict, rig: Rig) -> None:
    smooth = smooth_region(Truth.of(rig.extras["ground_truth"]))
    z1 = scans["heterodyne_3x4"][1].points[..., 2]
    z2 = scans["graycode_4"][1].points[..., 2]
    both = smooth & ~np.isnan(z1) & ~np.isnan(z2)
    diff = (z1 - z2)[both]
    assert both.sum() > 800_000
    assert abs(diff.mean()) < 0.002 and np.abs(diff).max() < 0.3


def fit_sphere(p: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere (centre, radius) by the algebraic fit refined with Gauss-Newton."""
    A = np.c_[2 * p, np.ones(len(p))]
    sol = np.linalg.lstsq(A, (p ** 2).sum(1), rcond=None)[0]
    c, r = sol[:3], np.sqrt(sol[3] + sol[:3] @ sol[:3])
    for _ in range(10):
        d = p - c
        dist = np.linalg.norm(d, axis=1)
        J = np.c_[-d / dist[:, None], -np.ones(len(p))]
        step = np.linalg.lstsq(J, -(dist - r), rcond=None)[0]
        c, r = c + step[:3], r + step[3]
    return c, float(r)


def test_sphere_radius(scans: dict, rig: Rig) -> None:
    gt = Truth.of(rig.extras["ground_truth"])
    cloud = scans["heterodyne_3x4"][1]
    sel = smooth_region(gt) & cloud.valid & (gt.object_id == 2)
    _centre, radius = fit_sphere(cloud.points[sel].astype(np.float64))
    assert sel.sum() > 50_000
    assert abs(radius - SPHERE_RADIUS_MM) < 0.02, radius


def plane_waviness(cloud_z: np.ndarray, points: np.ndarray, sel: np.ndarray, sigma_px: float) -> tuple[float, float]:
    """(raw residual RMS, RMS of the residual after a Gaussian low-pass of `sigma_px`) of
    the best-fit plane over `sel`, with masked (normalised) convolution."""
    p = points[sel].astype(np.float64)
    A = np.c_[p[:, 0], p[:, 1], np.ones(len(p))]
    coef = np.linalg.lstsq(A, p[:, 2], rcond=None)[0]
    resid = np.zeros(sel.shape, np.float64)
    resid[sel] = p[:, 2] - A @ coef
    w = sel.astype(np.float64)
    k = int(4 * sigma_px) | 1
    low = cv2.GaussianBlur(resid, (k, k), sigma_px) / np.maximum(cv2.GaussianBlur(w, (k, k), sigma_px), 1e-9)
    inner = cv2.erode(sel.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    return float(np.sqrt(np.mean(resid[sel] ** 2))), float(np.sqrt(np.mean(low[inner] ** 2)))


def plane_selection(rig: Rig, cloud) -> np.ndarray:
    gt = Truth.of(rig.extras["ground_truth"])
    return smooth_region(gt, margin_px=5) & cloud.valid & (gt.object_id == 1)


def sigma_for_2mm(rig: Rig) -> float:
    """A ~2 mm low-pass on the plane at ~440 mm, in camera pixels (Gaussian sigma = 2 mm / 2)."""
    return 1.0 / (440.0 / rig.model.camera.K[0, 0])


def test_plane_has_no_waviness(scans: dict, rig: Rig) -> None:
    cloud = scans["heterodyne_3x4"][1]
    raw, low = plane_waviness(cloud.points[..., 2], cloud.points, plane_selection(rig, cloud), sigma_for_2mm(rig))
    assert low < 0.2 * raw, (raw, low)


@pytest.mark.parametrize("compensated", [True, False])
def test_waviness_check_catches_uncompensated_gamma(rig: Rig, compensated: bool) -> None:
    """Control: with 3 steps and coarse fringes the gamma harmonics alias into a ripple of a
    few mm on the plane. Compensated patterns pass the waviness check; the same scan with
    patterns rendered as if the projector were linear fails it. (With the default 4-step,
    70-fringe set the aliased harmonic is blurred away and the ripple is < 1 mm.)"""
    ps = PatternSet("hierarchical", 3, (1.0, 4.0, 16.0))
    honest = rig.model
    if not compensated:
        rig.model = replace(honest, projector_gamma=1.0)
    try:
        stack = acquire(rig, ps, AcquisitionSettings.for_rig(rig), lambda k, f: None)
    finally:
        rig.model = honest
    d = decode(stack, ps, rig.camera.bit_depth, rig.model.projector.size, DecodeSettings(self_check=False))
    # the harmonics also set the frequencies apart far beyond their noise: the decode refuses itself
    # (the second-path mask takes most pixels then, and is not allowed to hide them from the check)
    assert {c.name: c.passed for c in d.checks}["frequency_agreement"] == compensated
    # the ripple itself, on every pixel the mask of second light paths would have taken
    d = decode(stack, ps, rig.camera.bit_depth, rig.model.projector.size,
               DecodeSettings(self_check=False, interreflection=False))
    cloud = triangulate(d, Triangulator(rig.model))
    assert plane_selection(rig, cloud).sum() > 10_000
    raw, low = plane_waviness(cloud.points[..., 2], cloud.points, plane_selection(rig, cloud), sigma_for_2mm(rig))
    assert (low < 0.2 * raw) == compensated, (raw, low)
