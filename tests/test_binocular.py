"""Binocular reconstruction (scanner/binocular.py) against a closed-form scene (tests/stereo_scene.py:
ray-plane and ray-sphere intersections written in the test) and OpenCV's own projections.

Seeds are drawn fresh each run and printed; the bounds hold for any draw."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import stereo_scene
from scipy.stats import binom

from scanner.binocular import (
    GRADIENT_FALSE_ACCEPT,
    CameraPhase,
    Rectification,
    StereoModel,
    _Runs,
    bilinear,
    match,
    reconstructor_for,
)
from scanner.errors import DecodeError


def _seed() -> int:
    seed = int(np.random.SeedSequence().entropy % 2 ** 32)
    print(f"seed {seed}")
    return seed


@pytest.fixture(scope="module")
def scene() -> tuple:
    r = stereo_scene.rig(0.5)
    left = stereo_scene.view(r.left, np.eye(4), r.projector, r.world_from_proj)
    right = stereo_scene.view(r.right, r.world_from_right, r.projector, r.world_from_proj)
    model = StereoModel(r.left, r.right, r.right_from_left)
    return r, left, right, Rectification.of(model)


def _phase(view: stereo_scene.View, sigma: float, rng: np.random.Generator,
           orientations: tuple[str, ...] = ("vertical", "horizontal")) -> CameraPhase:
    return stereo_scene.camera_phase(view, sigma, rng=rng, orientations=orientations)


def _edges(depth: np.ndarray, px: int) -> np.ndarray:
    return stereo_scene.depth_edges(depth, px, step_mm=0.5)


def test_rectification_puts_both_projections_of_a_point_on_one_row(scene: tuple) -> None:
    """Points in front of both cameras, projected by OpenCV through each lens: their rectified
    rows agree to 1e-6 px, and the right grid samples the right pixel whose rectified position
    is the grid's (OpenCV's undistortPoints with the rectifying rotation)."""
    r, _, _, rect = scene
    rng = np.random.default_rng(_seed())
    X = np.column_stack([rng.uniform(-60, 60, 500), rng.uniform(-50, 50, 500), rng.uniform(300, 500, 500)])
    T = r.right_from_left
    pl, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), r.left.K, r.left.dist)
    pr, _ = cv2.projectPoints(X, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], r.right.K, r.right.dist)
    P = np.array([[rect.f, 0, 0], [0, rect.f, 0], [0, 0, 1.0]])
    yl = cv2.undistortPoints(pl, r.left.K, r.left.dist, R=rect.R_left, P=P).reshape(-1, 2)
    yr = cv2.undistortPoints(pr, r.right.K, r.right.dist, R=rect.R_right, P=P).reshape(-1, 2)
    assert np.abs(yl[:, 1] - yr[:, 1]).max() < 1e-6
    # the disparity gives the depth in the rectified frame: Z = -f·tx/d
    Z = (X @ rect.R_left.T)[:, 2]
    assert np.allclose(-rect.f * rect.tx_mm / (yl[:, 0] - yr[:, 0]), Z, rtol=1e-9)
    g = rect.right
    i, j = rng.integers(0, g.shape[1], 300), rng.integers(0, g.shape[0], 300)
    src = g.source[j, i].astype(np.float64)
    back = cv2.undistortPoints(src.reshape(-1, 1, 2), r.right.K, r.right.dist, R=rect.R_right, P=P).reshape(-1, 2)
    assert np.abs(back - np.column_stack([i + g.x0, j + g.y0])).max() < 2e-3


def test_bilinear_is_exact_on_linear_functions_and_propagates_nan() -> None:
    rng = np.random.default_rng(_seed())
    yy, xx = np.mgrid[0:40, 0:50].astype(np.float32)
    img = 3.0 * xx - 2.0 * yy + 7.0
    x, y = rng.uniform(0, 49, 1000), rng.uniform(0, 39, 1000)
    assert np.allclose(bilinear(img, x, y), 3.0 * x - 2.0 * y + 7.0, atol=1e-3)
    img[10, 10] = np.nan
    assert np.isnan(bilinear(img, np.array([9.5, 10.0]), np.array([9.5, 10.0]))).all()
    assert np.isnan(bilinear(img, np.array([-0.1, 50.0]), np.array([5.0, 5.0]))).all()


def test_depth_against_the_closed_form_scene_within_the_predicted_noise(scene: tuple) -> None:
    """Both orientations, Gaussian coordinate noise: the depth error over points away from depth
    edges is unbiased and no larger than the predicted noise (the prediction takes a resampled
    right sample's noise as an original pixel's: high by up to ~25 % for white noise); points
    beyond 5 sigma are below 0.1 %, and below 0.01 % away from the left's depth edges (those are
    at the right's, where its resampled map mixes two surfaces)."""
    r, left, right, rect = scene
    rng = np.random.default_rng(_seed())
    sigma = 0.02
    res = match(rect, _phase(left, sigma, rng), _phase(right, sigma, rng))
    z = res.cloud.points[..., 2]
    err = z - left.depth
    ok = np.isfinite(err)
    both = np.isfinite(left.depth) & np.isfinite(left.proj_uv[..., 0])
    print(res.checks)
    assert res.orientation == "vertical"
    assert ok.sum() > 0.85 * both.sum()
    away = ok & ~_edges(left.depth, 2)
    normed = err[away] / res.depth_sigma_mm[away]
    rms, pred = np.sqrt(np.mean(err[away] ** 2)), np.sqrt(np.mean(res.depth_sigma_mm[away] ** 2))
    print(f"depth error RMS {rms * 1e3:.2f} um, predicted {pred * 1e3:.2f} um, normalised std {normed.std():.3f}")
    assert 0.7 * pred < rms <= pred
    assert abs(np.mean(err[away])) < 0.05 * rms
    beyond = ok & (np.abs(err) > 5 * res.depth_sigma_mm)
    print(f"beyond 5 sigma: {beyond.sum()} of {ok.sum()} points, {(np.abs(normed) > 5).sum()} away from the left's "
          f"depth edges (at the right's)")
    assert beyond.sum() < 1e-3 * ok.sum()
    assert (np.abs(normed) > 5).sum() < 1e-4 * ok.sum()
    # the right pixels the points came from are where the right camera sees them
    idx, xy = res.right_pixels()
    T = np.linalg.inv(r.right_from_left)
    truth = stereo_scene.view(r.right, T, r.projector, r.world_from_proj)
    u = np.rint(xy).astype(int)
    inside = (u[:, 0] >= 0) & (u[:, 1] >= 0) & (u[:, 0] < r.right.width) & (u[:, 1] < r.right.height)
    seen = truth.points[u[inside, 1], u[inside, 0]]
    dist = np.linalg.norm(seen - left.points.reshape(-1, 3)[idx[inside]], axis=1)
    assert np.nanmedian(dist) < 0.2  # within a pixel footprint (~0.15 mm at 400 mm)


def test_one_orientation_errs_only_where_the_right_camera_cannot_see_the_point(scene: tuple) -> None:
    """Vertical fringes alone: every point beyond 5 sigma (away from depth edges) is one the
    right camera cannot see (hidden behind the sphere: the documented limit of matching one
    coordinate without the projector's calibration), and the rest are as precise as with two."""
    r, left, right, rect = scene
    rng = np.random.default_rng(_seed())
    res = match(rect, _phase(left, 0.02, rng, ("vertical",)), _phase(right, 0.02, rng, ("vertical",)))
    err = res.cloud.points[..., 2] - left.depth
    ok = np.isfinite(err) & ~_edges(left.depth, 2)
    # visible to the right: the right camera's own first hit along its ray to the point is the point
    P = left.points.reshape(-1, 3)
    T = r.right_from_left
    Xr = P @ T[:3, :3].T + T[:3, 3]
    uv = np.full((len(P), 2), -1.0)
    ahead = np.isfinite(Xr[:, 2]) & (Xr[:, 2] > 0)
    uv[ahead] = r.right.project(Xr[ahead])
    truth = stereo_scene.view(r.right, np.linalg.inv(T), r.projector, r.world_from_proj)
    u = np.rint(uv).astype(int)
    inside = ahead & (u[:, 0] >= 0) & (u[:, 1] >= 0) & (u[:, 0] < r.right.width) & (u[:, 1] < r.right.height)
    visible = np.zeros(len(P), bool)
    d = truth.depth[u[inside, 1], u[inside, 0]]
    visible[inside] = np.abs(d - Xr[inside, 2]) < 1.0
    visible = visible.reshape(left.depth.shape) & ~_edges(truth.depth, 2)[np.clip(u[:, 1], 0, r.right.height - 1),
                                                                         np.clip(u[:, 0], 0, r.right.width - 1)
                                                                         ].reshape(left.depth.shape)
    bad = ok & (np.abs(err) > 5 * res.depth_sigma_mm)
    print(f"{bad.sum()} points beyond 5 sigma, {(bad & visible).sum()} of them visible to the right camera")
    assert (bad & visible).sum() <= 1e-4 * ok.sum()
    normed = (err / res.depth_sigma_mm)[ok & visible]
    assert normed.std() < 1.0


def test_the_gradient_gate_passes_flat_steps_at_its_stated_rate() -> None:
    """Rows whose coordinate does not change along the line (fringes parallel to the epipolar
    lines), with Gaussian noise of the stated sigma: the fraction of sample pairs passing the
    gate matches GRADIENT_FALSE_ACCEPT (binomial 99.9 % bounds)."""
    rng = np.random.default_rng(_seed())
    sigma = 0.03
    c = (np.repeat(np.arange(400, dtype=np.float32)[:, None], 1001, 1) + rng.normal(0, sigma, (400, 1001))
         ).astype(np.float32)
    rows = _Runs.of(c, np.full(c.shape, sigma, np.float32), 3.2905267314919255)  # z for α = 1e-3
    n = rows.gate.size
    lo, hi = binom.ppf([0.0005, 0.9995], n, GRADIENT_FALSE_ACCEPT)
    print(f"{rows.gate.sum()} of {n} pass (expected {n * GRADIENT_FALSE_ACCEPT:.0f})")
    assert lo <= rows.gate.sum() <= hi


def _holding(row: np.ndarray, c: float) -> np.ndarray:
    """The intervals between neighbours of `row` holding c (min <= c < max), one at a time: the count's definition."""
    return np.array([k for k in range(len(row) - 1) if min(row[k], row[k + 1]) <= c < max(row[k], row[k + 1])], int)


def test_runs_count_and_find_as_the_intervals_do_one_by_one() -> None:
    """On random rows (rising, falling and turning, NaN holes, zero steps, and runs nested in
    wider ones: a short run inside the range of a long one), for coordinates inside and beyond
    the rows' range: the count and the holding interval agree with the intervals taken one by
    one, and the match's x interpolates the row there."""
    rng = np.random.default_rng(_seed())
    h, w = 12, 60
    c = np.cumsum(rng.normal(0.2, 1.0, (h, w)), axis=1) + 10
    c[rng.random(c.shape) < 0.08] = np.nan
    c[:, 20] = c[:, 19]  # a zero step in every row
    c[0] = np.nan
    c[0, :5] = [0.0, 50.0, np.nan, 20.0, 25.0]  # a run nested in a wider, earlier one
    c = c.astype(np.float32)
    runs = _Runs.of(c, np.full(c.shape, 0.02, np.float32), 3.0)
    n = 3000
    rows = rng.integers(0, h, n)
    q = rng.uniform(np.nanmin(c) - 5, np.nanmax(c) + 5, n).astype(np.float32)
    q[:200] = c[rows[:200], rng.integers(0, w, 200)]  # exactly on samples: the half-open ends
    q[:200] = np.where(np.isfinite(q[:200]), q[:200], 15.0)
    rows[-1], q[-1] = 0, 30.0  # held once, by the wide interval (0, 50) only: (20, 25) is below, past a hole
    count, k, x, step, _ = runs.find(q, rows)
    assert np.array_equal(count, runs.count(q, rows))
    for i in range(n):
        held = _holding(c[rows[i]], q[i])
        assert count[i] == len(held), (i, rows[i], q[i], held)
        if len(held) == 1:
            a, b = c[rows[i], held[0]], c[rows[i], held[0] + 1]
            assert k[i] == rows[i] * (w - 1) + held[0]
            assert x[i] == pytest.approx(held[0] + (q[i] - a) / (b - a), abs=1e-4) and step[i] == b - a
        else:
            assert k[i] == -1
    assert count[-1] == 1 and k[-1] == 0
    for empty in (np.full((3, 5), np.nan, np.float32), np.full((3, 5), 2.0, np.float32)):  # nothing seen; flat
        count, k, *_ = _Runs.of(empty, np.full(empty.shape, 0.02, np.float32), 3.0).find(
            np.array([1.0, 2.0], np.float32), np.array([0, 2]))
        assert count.tolist() == [0, 0] and k.tolist() == [-1, -1]


def test_reconstructors_are_kept_by_the_models_content(scene: tuple) -> None:
    r = scene[0]
    first = reconstructor_for(StereoModel(r.left, r.right, r.right_from_left))
    assert reconstructor_for(StereoModel(r.left, r.right, r.right_from_left.copy())) is first
    assert reconstructor_for(StereoModel(r.left, r.right, r.right_from_left, epipolar_sigma_px=0.1)) is not first


def test_mismatched_inputs_are_refused(scene: tuple) -> None:
    r, left, right, rect = scene
    rng = np.random.default_rng(0)
    L = _phase(left, 0.02, rng)
    with pytest.raises(DecodeError, match="different fringe orientations"):
        match(rect, L, _phase(right, 0.02, rng, ("vertical",)))
    small = CameraPhase({o: c[::2, ::2] for o, c in L.coordinate.items()},
                        {o: s[::2, ::2] for o, s in L.sigma.items()}, L.texture[::2, ::2], 12)
    with pytest.raises(DecodeError, match="maps are 320 x 256 px, its calibration 640 x 512 px"):
        match(rect, small, _phase(right, 0.02, rng))
    with pytest.raises(ValueError, match="no baseline"):
        StereoModel(r.left, r.right, np.eye(4))
