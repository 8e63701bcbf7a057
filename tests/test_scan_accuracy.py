"""End-to-end accuracy on the default simulated rig against the simulator's ground truth.

Scene `config/scenes/sphere_plane.toml`: an analytic sphere (r = 20 mm) in front of a plane.
Camera model (config/rigs/sim_bench.toml): 12-bit, full well 10500 e-, read noise 6 e-,
gain 2.56 e-/DN, camera blur 0.6 px, projector gamma 2.2 and blur 0.8 px.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from scanner.acquisition import AcquisitionSettings, acquire
from scanner.config import CONFIG_DIR
from scanner.decode import decode
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
    d, cloud = scans[name]
    acc = evaluate(d, cloud, Truth.of(rig.extras["ground_truth"]), rig.extras["sensor"], Triangulator(rig.model))
    print(name, acc.summary())
    assert acc.pixels > 800_000
    assert acc.ratio <= 1.3, acc.summary()
    assert abs(acc.mean_mm) < 0.2 * acc.rms_mm, acc.summary()
    assert acc.order_errors == 0, acc.summary()
    assert acc.coverage >= 0.98, acc.summary()


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
    centre, radius = fit_sphere(cloud.points[sel].astype(np.float64))
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
    d = decode(stack, ps, rig.camera.bit_depth, rig.model.projector.size)
    cloud = triangulate(d, Triangulator(rig.model))
    raw, low = plane_waviness(cloud.points[..., 2], cloud.points, plane_selection(rig, cloud), sigma_for_2mm(rig))
    assert (low < 0.2 * raw) == compensated, (raw, low)
