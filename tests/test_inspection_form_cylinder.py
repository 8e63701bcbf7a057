"""The cylinder fits of the form stage against truths computed here: the radii's analytic
derivatives against central differences, the least-squares axis against an exact
cylinder's (closed form) and against this file's own fit (another parametrisation of the
axis, numeric derivatives, tolerances at round-off), and the minimum zone against one LP
over every point (`form_truth.cylinder_min_zone`), on random axes and points."""

from __future__ import annotations

import numpy as np
import pytest
from form_truth import cylinder_min_zone, radii
from scipy.optimize import least_squares

from inspection.form import _AxisRadii, cylinder_ls, cylindricity_mz


def _perpendicular(rng: np.random.Generator, n: np.ndarray) -> np.ndarray:
    """A random unit vector perpendicular to unit n."""
    u = np.cross(n, rng.standard_normal(3))
    return u / np.linalg.norm(u)


def _random_axis(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A random axis (point, unit direction) and two unit vectors completing it to a frame."""
    n = rng.standard_normal(3)
    n /= np.linalg.norm(n)
    u = _perpendicular(rng, n)
    return rng.uniform(-50.0, 50.0, 3), n, u, np.cross(n, u)


def _cylinder(rng: np.random.Generator, count: int, radius: float, length: float,
              wobble_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (count, 3) on a random axis: radius plus three lobes, a taper and noise, all
    within about `wobble_mm`; returns (points, axis point, axis direction)."""
    o, n, u, v = _random_axis(rng)
    t = rng.uniform(0.0, 2.0 * np.pi, count)
    z = rng.uniform(-length / 2, length / 2, count)
    r = radius + wobble_mm * (0.5 * np.cos(3 * t + 1.0) + 0.3 * z / length + 0.2 * rng.standard_normal(count))
    return o + np.outer(z, n) + np.outer(r * np.cos(t), u) + np.outer(r * np.sin(t), v), o, n


def _line_gap(o1: np.ndarray, n1: np.ndarray, o2: np.ndarray, n2: np.ndarray, half_length: float) -> float:
    """The largest distance (mm) between two lines over `half_length` either side of o1."""
    ends = o1 + np.outer([-half_length, half_length], n1)
    return float(radii(ends, o2, n2).max())


def _own_fit(points: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least squares sum (r_i - mean r)^2 over the axis as the point where it crosses the
    plane through `origin` normal to the start `axis` (2 in-plane coordinates) and its
    direction by two angles about `axis`; numeric derivatives, tolerances at round-off."""
    e3 = axis / np.linalg.norm(axis)
    e1 = np.cross(e3, [0.0, 0.0, 1.0] if abs(e3[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e3, e1)

    def line(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a, b = p[2], p[3]
        return origin + p[0] * e1 + p[1] * e2, np.cos(a) * (np.cos(b) * e3 + np.sin(b) * e1) + np.sin(a) * e2

    def residuals(p: np.ndarray) -> np.ndarray:
        r = radii(points, *line(p))
        return r - r.mean()

    res = least_squares(residuals, np.zeros(4), method="trf", jac="3-point", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    o, n = line(res.x)
    return o, n, float(radii(points, o, n).mean())


def test_radii_derivatives_against_central_differences() -> None:
    """`_AxisRadii`: the radii equal the distances to the axis `_axis` puts at x, and their
    Jacobian the central differences (h = 1e-6; error O(h^2)), at random axes, points and x."""
    rng = np.random.default_rng(11)
    for _ in range(5):
        p, o, n = _cylinder(rng, 300, rng.uniform(3.0, 40.0), rng.uniform(5.0, 80.0), 0.5)
        u = _perpendicular(rng, n)
        v = np.cross(n, u)
        o0 = o + rng.normal(0.0, 1.0, 3)
        f = _AxisRadii(p - o0, u, v, n)
        for x in rng.normal(0.0, 0.05, (4, 4)):
            m = n + x[0] * u + x[1] * v
            assert f.radii(x) == pytest.approx(radii(p, o0 + x[2] * u + x[3] * v, m / np.linalg.norm(m)), abs=1e-11)
            h = 1e-6
            numeric = np.stack([(f.radii(x + h * e) - f.radii(x - h * e)) / (2 * h) for e in np.eye(4)])
            assert np.abs(f.jacobian(x) - numeric).max() < 1e-6


def test_least_squares_axis_of_an_exact_cylinder() -> None:
    """Points exactly on a cylinder: the fit is its axis and radius (closed form), from a
    nominal axis 3 degrees and 0.5 mm off."""
    rng = np.random.default_rng(12)
    for _ in range(3):
        p, o, n = _cylinder(rng, 2000, rng.uniform(3.0, 40.0), rng.uniform(5.0, 80.0), 0.0)
        radius = float(radii(p, o, n).mean())
        u = _perpendicular(rng, n)
        got_o, got_n, got_r = cylinder_ls(p, o + 0.5 * np.cross(n, u), n + 0.05 * u)
        assert _line_gap(o, n, got_o, got_n, 50.0) < 1e-9
        assert got_r == pytest.approx(radius, rel=1e-12)


def test_least_squares_axis_against_the_tests_own_fit() -> None:
    """Lobed, tapered, noisy cylinders on random axes: the same axis (within 1e-9 of the
    cylinder's size over its length: the sum of squares is flat to round-off about its
    minimum to about that) and radius (1e-9 relative) as `_own_fit`."""
    rng = np.random.default_rng(13)
    for _ in range(6):
        length, radius = rng.uniform(5.0, 80.0), rng.uniform(3.0, 40.0)
        p, o, n = _cylinder(rng, 3000, radius, length, rng.uniform(0.005, 0.5))
        u = _perpendicular(rng, n)
        start_o, start_n = o + 0.3 * np.cross(n, u), n + 0.03 * u
        got_o, got_n, got_r = cylinder_ls(p, start_o, start_n)
        own_o, own_n, own_r = _own_fit(p, start_o, start_n)
        assert _line_gap(own_o, own_n, got_o, got_n, length / 2) < 1e-9 * (radius + length / 2)
        assert got_r == pytest.approx(own_r, rel=1e-9)


def test_minimum_zone_against_one_lp_over_every_point() -> None:
    """Lobed, tapered, noisy cylinders on random axes: the zone equals the LP over every
    point relinearised about the true axis (`form_truth.cylinder_min_zone`) to 1e-7 mm,
    and is never wider than the least-squares zone."""
    rng = np.random.default_rng(14)
    for _ in range(4):
        length = rng.uniform(5.0, 80.0)
        p, o, n = _cylinder(rng, 5000, rng.uniform(3.0, 40.0), length, rng.uniform(0.005, 0.5))
        u = _perpendicular(rng, n)
        got = cylindricity_mz(p, o + 0.3 * np.cross(n, u), n + 0.03 * u)
        assert got == pytest.approx(cylinder_min_zone(p, o, n, rounds=6), abs=1e-7)
        ls_o, ls_n, _ = cylinder_ls(p, o, n)
        r = radii(p, ls_o, ls_n)
        assert got <= r.max() - r.min()
