"""The batched zone paths the form stage's noise draws run through, against truths
computed here: the minimum zone of every surface by brute force over the planes that can
bound it (small sets) and by one LP over every point (`form_truth.plane_min_zone`, large
sets, draws whose extreme points differ from the measured surface's), least-squares
flatness by numpy's lstsq, and the Gaussian mean that the form filter hands back beside
its regression by the tests' own FFT convolution (`form_truth.gaussian_mean`)."""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pytest
from form_truth import gaussian_mean, plane_min_zone

from inspection.form import (
    ROW_CHUNK,
    GaussianFilter,
    flatness_ls_many,
    flatness_mz,
    flatness_mz_many,
    gaussian_filter,
    plane_zone_tilt,
)


def _brute_min_width(p: np.ndarray) -> float:
    """The least width of a point set (N, 3) over every orientation: the narrowest slab is
    bounded by a plane through three points (a face of the hull) or by two parallel planes
    through two points each (two hull edges); every candidate normal is tried."""
    normals = [np.cross(p[j] - p[i], p[k] - p[i]) for i, j, k in combinations(range(len(p)), 3)]
    edges = [p[j] - p[i] for i, j in combinations(range(len(p)), 2)]
    normals += [np.cross(e, f) for e, f in combinations(edges, 2)]
    best = np.inf
    for n in normals:
        size = np.linalg.norm(n)
        if size > 1e-12:
            h = p @ (n / size)
            best = min(best, h.max() - h.min())
    return float(best)


def test_min_zone_of_small_sets_equals_the_brute_force_width() -> None:
    """Near-flat sets (60 mm wide, 20 um tall): the LP's zone across its planes is the true
    least width up to its linearisation in the tilt (relative tilt^2, below 1e-6 here)."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-30, 30, (11, 2))
    heights = 0.02 * rng.random((6, 11)) + 1e-3 * xy[:, 0] * rng.standard_normal((6, 1))  # tilted, rough
    got = flatness_mz_many(xy, heights)
    for h, w in zip(heights, got):
        truth = _brute_min_width(np.column_stack([xy, h]))
        assert w == pytest.approx(truth, rel=1e-6)
        assert flatness_mz(np.column_stack([xy, h]), np.array([0.0, 0.0, 1.0])) == pytest.approx(truth, rel=1e-6)


def test_min_zone_of_noise_draws_whose_extremes_move() -> None:
    """A bowed surface plus draws of noise as large as its form (each draw held by other
    points than the measured surface's zone), solved together from a few candidates and
    the measured zone's tilt: every draw's zone equals the LP over all its points, and a
    misleading tilt changes nothing (the violators are found and added)."""
    rng = np.random.default_rng(7)
    xy = rng.uniform(-25, 25, (4000, 2))
    base = 4e-5 * xy[:, 0] ** 2 - 3e-5 * xy[:, 0] * xy[:, 1] + 0.002 * np.sin(xy[:, 1] / 3)
    draws = base + rng.standard_normal((12, len(xy))) * np.array([0.0005, 0.002, 0.01])[:, None].repeat(4, 0)
    tilt = plane_zone_tilt(xy, base)
    truth = np.array([plane_min_zone(np.column_stack([xy, h])) for h in draws])
    base_support = _support(xy, base)
    assert any(not _support(xy, h) <= base_support for h in draws)  # the draws' zones rest on other points
    np.testing.assert_allclose(flatness_mz_many(xy, draws, tilt), truth, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(flatness_mz_many(xy, draws, np.array([0.3, -0.2])), truth, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(flatness_mz_many(xy, draws - base), [plane_min_zone(np.column_stack([xy, h - base]))
                                                                      for h in draws], rtol=1e-9, atol=1e-12)


def _support(xy: np.ndarray, h: np.ndarray) -> set[int]:
    """The points (indices) within 1 nm of the bounds of the zone over all points (the
    LP in the least-squares plane's frame, as `form_truth.plane_min_zone`, its solution
    read back by a least-squares fit of the bounding planes' tilt)."""
    from scipy.optimize import linprog

    p = np.column_stack([xy, h])
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    x, y, z = ((p - c) @ vt.T).T
    one = np.ones_like(x)
    a_ub = np.concatenate([np.stack([-x, -y, -one, -one], 1), np.stack([x, y, one, 0 * one], 1)])
    res = linprog([0, 0, 0, 1], A_ub=a_ub,
                  b_ub=np.concatenate([-z, z]), bounds=[(None, None)] * 3 + [(0, None)], method="highs")
    a, b, lo, w = res.x
    r = z - a * x - b * y
    return set(np.flatnonzero((r < lo + 1e-6) | (r > lo + w - 1e-6)).tolist())


def test_least_squares_flatness_of_many_surfaces() -> None:
    rng = np.random.default_rng(11)
    xy = rng.uniform(-20, 20, (500, 2))
    heights = 1e-3 * xy[:, 0] + rng.standard_normal((5, 500)) * 0.003
    truth = []
    for h in heights:
        A = np.column_stack([xy, np.ones(len(xy))])
        (a, b, _), *_ = np.linalg.lstsq(A, h, rcond=None)
        r = (h - a * xy[:, 0] - b * xy[:, 1]) / np.sqrt(1 + a * a + b * b)  # distances across the LS plane
        truth.append(r.max() - r.min())
    np.testing.assert_allclose(flatness_ls_many(xy, heights), truth, rtol=1e-9)


def test_form_filter_hands_back_the_gaussian_mean() -> None:
    """`with_mean`: the regression as the filter gives it alone, and the Gaussian mean of
    the same cut-off as the tests' own convolution, for a stack of fields on a masked grid
    (more than the filter takes at a time, ROW_CHUNK: each field's results as it alone gets)."""
    g = 0.25
    x = np.arange(0, 30, g)
    X, Y = np.meshgrid(x, x)
    mask = np.hypot(X - 15, Y - 15) < 13
    rng = np.random.default_rng(5)
    fields = 1e-4 * (X - 10) ** 2 + rng.standard_normal((ROW_CHUNK + 2, *X.shape)) * 0.002
    f = GaussianFilter(mask, 8.0, g, order=2)
    reg, mean = f.with_mean(fields)
    np.testing.assert_array_equal(reg, f(fields))
    for k in range(len(fields)):
        alone = f.with_mean(fields[k])
        np.testing.assert_array_equal(reg[k], alone[0])
        np.testing.assert_array_equal(mean[k], alone[1])
        truth = gaussian_mean(np.where(mask, fields[k], 0.0), mask, 8.0, g)
        assert np.abs(mean[k] - truth)[mask].max() < 1e-9  # mm; the two kernels end at 2.6 and 3 alpha lc
        # mm; the two kernels end at 2.6 and 3 alpha lc
        assert np.abs(gaussian_filter(fields[k], mask, 8.0, g) - truth)[mask].max() < 1e-9


def test_noise_draws_filtered_in_single_precision_stay_within_a_nanometre() -> None:
    """The draws go through the filter in float32 (`single=True`): on noise of the
    scanner's size (10 um per cell) over a bowed surface, the regression and the mean stay
    within 1e-6 mm of the tests' own float64 Gaussian mean and of the double path; the
    measured surface's path is float64 (the 1e-9 mm checks above)."""
    g = 0.15
    x = np.arange(0, 40, g)
    X, Y = np.meshgrid(x, x)
    mask = (np.abs(X - 20) < 18) & (np.abs(Y - 20) < 15)
    rng = np.random.default_rng(11)
    fields = 2e-4 * (X - 20) ** 2 + rng.standard_normal((4, *X.shape)) * 0.010
    f = GaussianFilter(mask, 8.0, g, order=2)
    reg, _mean = f.with_mean(fields)
    reg32, mean32 = f.with_mean(fields, single=True)
    assert reg32.dtype == np.float32 and mean32.dtype == np.float32
    ok = np.isfinite(reg)
    assert np.array_equal(ok, np.isfinite(reg32))
    assert np.abs(reg32[ok] - reg[ok]).max() < 1e-6
    for k in range(len(fields)):
        truth = gaussian_mean(np.where(mask, fields[k], 0.0), mask, 8.0, g)
        assert np.abs(mean32[k] - truth)[mask].max() < 1e-6
