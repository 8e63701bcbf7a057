"""Truths of form figures computed in the tests, independently of `inspection.form`:
minimum zones as linear programmes over every point, the ISO 16610-61 areal Gaussian mean
and second-order Gaussian regression by FFT convolution, the zone known noise spans after
that regression (simulated), and the edge margin as a distance to the region's border.

ISO 16610-61: weighting function s(r) = exp(-pi (r / (alpha lc))^2), alpha = sqrt(ln 2 / pi)
(50 % transmission at the nesting index lc). Lengths in mm.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.optimize import linprog
from scipy.signal import fftconvolve
from scipy.spatial import cKDTree

ALPHA = np.sqrt(np.log(2.0) / np.pi)


def plane_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centroid, 3x3 rows: two in-plane axes and the normal) of the least-squares plane
    through points (N, 3), by SVD."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt


def plane_min_zone(points: np.ndarray) -> float:
    """Minimum-zone flatness of points (N, 3) near a plane: the least distance between two
    parallel planes holding every point (in the least-squares plane's frame, the LP in
    a, b, c, w: c <= z - a x - b y <= c + w, then w measured across the planes)."""
    c, axes = plane_frame(points)
    x, y, z = ((points - c) @ axes.T).T
    one = np.ones_like(x)
    A = np.concatenate([np.stack([-x, -y, -one, -one], 1), np.stack([x, y, one, 0 * one], 1)])
    res = linprog([0, 0, 0, 1], A_ub=A, b_ub=np.concatenate([-z, z]), bounds=[(None, None)] * 3 + [(0, None)],
                  method="highs")
    assert res.status == 0, res.message
    a, b = res.x[:2]
    return float(res.x[3] / np.hypot(1.0, np.hypot(a, b)))


def radii(points: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Distances (N,) of points to the line through `origin` along unit `axis`."""
    d = points - origin
    return np.linalg.norm(d - np.outer(d @ axis, axis), axis=1)


def cylinder_min_zone(points: np.ndarray, origin: np.ndarray, axis: np.ndarray, rounds: int = 4) -> float:
    """Minimum-zone cylindricity of points (N, 3) near a cylinder whose axis is close to
    (`origin`, `axis`): the least radial distance between two coaxial cylinders holding
    every point. Each round solves the LP of the radii linearised in the axis's four
    small displacements (every point a constraint) and moves the axis; the zone is the
    exact radial spread about the final axis."""
    o, n = np.asarray(origin, float), np.asarray(axis, float) / np.linalg.norm(axis)
    for _ in range(rounds):
        u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        d = points - o
        a = d @ n
        radial = d - np.outer(a, n)
        r = np.linalg.norm(radial, axis=1)
        e = radial / r[:, None]
        # r(x) = r - (e.u) x0 - (e.v) x1 - a (e.u) x2 - a (e.v) x3 for the axis o + x0 u + x1 v, n + x2 u + x3 v
        J = -np.stack([e @ u, e @ v, a * (e @ u), a * (e @ v)], axis=1)
        one = np.ones_like(r)
        A = np.concatenate([np.column_stack([-J, one, 0 * one]), np.column_stack([J, -one, -one])])
        res = linprog([0, 0, 0, 0, 0, 1], A_ub=A, b_ub=np.concatenate([r, -r]), bounds=[(None, None)] * 5 + [(0, None)],
                      method="highs")
        assert res.status == 0, res.message
        x = res.x
        o = o + x[0] * u + x[1] * v
        n = n + x[2] * u + x[3] * v
        n /= np.linalg.norm(n)
    r = radii(points, o, n)
    return float(r.max() - r.min())


def inside_margin(mask: np.ndarray, points: np.ndarray, margin_mm: float) -> np.ndarray:
    """Pixels of the region `mask` (H, W) whose true surface points `points` (H, W, 3) lie at
    least `margin_mm` from every border pixel's point (a pixel of the region with one of its
    four neighbours outside it; pixels without a point count as outside the margin)."""
    pad = np.pad(mask, 1)
    finite = np.isfinite(points[..., 0])
    border = mask & ~(pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:]) & finite
    distance, _ = cKDTree(points[border]).query(points[mask & finite])
    out = np.zeros_like(mask)
    out[mask & finite] = distance >= margin_mm
    return out


def raster(xy: np.ndarray, spacing_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mask (H, W) of the cells of a square grid holding a point of `xy` (N, 2), the cell
    centres' coordinates (H, W, 2), each point's cell (N, 2) as (row, column))."""
    lo = xy.min(axis=0)
    ij = np.floor((xy - lo) / spacing_mm).astype(int)
    mask = np.zeros((ij[:, 1].max() + 1, ij[:, 0].max() + 1), bool)
    mask[ij[:, 1], ij[:, 0]] = True
    rows, cols = np.indices(mask.shape)
    centres = lo + (np.stack([cols, rows], axis=-1) + 0.5) * spacing_mm
    return mask, centres, ij[:, ::-1]


def _kernel(cutoff_mm: float, spacing_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(s, x, y) on the grid out to 3 alpha lc (where s < 1e-12 of its peak)."""
    half = int(np.ceil(3 * ALPHA * cutoff_mm / spacing_mm))
    x, y = np.meshgrid(np.arange(-half, half + 1) * spacing_mm, np.arange(-half, half + 1) * spacing_mm)
    return np.exp(-np.pi * (x ** 2 + y ** 2) / (ALPHA * cutoff_mm) ** 2), x, y


def gaussian_mean(z: np.ndarray, mask: np.ndarray, cutoff_mm: float, spacing_mm: float) -> np.ndarray:
    """The ISO 16610-61 Gaussian mean of gridded heights over `mask`, normalised by the
    weights that fall inside it (the filter where the surface ends), by FFT convolution."""
    s, _, _ = _kernel(cutoff_mm, spacing_mm)
    w = mask.astype(float)
    return fftconvolve(np.where(mask, z, 0.0), s, mode="same") / np.maximum(fftconvolve(w, s, mode="same"), 1e-300)


def roughness_sq(z: np.ndarray, mask: np.ndarray, cutoff_mm: float, spacing_mm: float) -> float:
    """Sq (ISO 25178-2) of the S-L surface: RMS over `mask` of the heights less their
    Gaussian mean of nesting index `cutoff_mm`."""
    r = z - gaussian_mean(z, mask, cutoff_mm, spacing_mm)
    return float(np.sqrt(np.mean(r[mask] ** 2)))


def regression_filter(mask: np.ndarray, cutoff_mm: float, spacing_mm: float) -> Callable[[np.ndarray], np.ndarray]:
    """The second-order Gaussian regression filter on the grid cells `mask` (H, W), as a
    function of the heights (H, W) that returns the filtered heights (NaN outside): about
    each cell, the fit of 1, x, y, x^2, xy, y^2 weighted by s, its constant term
    e1' M^-1 sum_j s_j phi_j z_j. The moments are FFT convolutions; M^-1's first row is
    computed once per mask."""
    s, x, y = _kernel(cutoff_mm, spacing_mm)
    mono = [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]

    def moment(field: np.ndarray, a: int, b: int) -> np.ndarray:
        # convolution flips the kernel: moments of (x_j - x_i) need the kernel of (-x)^a (-y)^b
        return fftconvolve(field, s * (-x) ** a * (-y) ** b, mode="same")

    w = mask.astype(float)
    cache: dict[tuple[int, int], np.ndarray] = {}
    M = np.empty((int(mask.sum()), 6, 6))
    for i, (a1, b1) in enumerate(mono):
        for j, (a2, b2) in enumerate(mono):
            key = (a1 + a2, b1 + b2)
            if key not in cache:
                cache[key] = moment(w, *key)[mask]
            M[:, i, j] = cache[key]
    first = np.linalg.inv(M)[:, 0, :]

    def apply(z: np.ndarray) -> np.ndarray:
        zw = np.where(mask, z, 0.0)
        out = np.full(mask.shape, np.nan)
        out[mask] = sum(first[:, k] * moment(zw, a, b)[mask] for k, (a, b) in enumerate(mono))
        return out

    return apply


def predicted_noise_floor(xy: np.ndarray, variance: np.ndarray, cutoff_mm: float, spacing_mm: float,
                          realisations: int = 8, seed: int = 0) -> float:
    """The zone (mm) the form filter's output spans on a nominal face whose points at
    in-plane coordinates `xy` (N, 2) carry independent deviation noise of `variance` (N,):
    the median, over `realisations`, of the range of that noise averaged per grid cell of
    `spacing_mm` (as a form filter grids points) and filtered by `regression_filter`."""
    mask, _, cell = raster(xy, spacing_mm)
    flat = np.ravel_multi_index((cell[:, 0], cell[:, 1]), mask.shape)
    count = np.bincount(flat, minlength=mask.size)
    total = np.bincount(flat, weights=variance, minlength=mask.size)
    sigma = (np.sqrt(total) / np.maximum(count, 1)).reshape(mask.shape)  # of a cell's mean
    rng = np.random.default_rng(seed)
    form = regression_filter(mask, cutoff_mm, spacing_mm)
    ranges = []
    for _ in range(realisations):
        f = form(rng.normal(0.0, 1.0, mask.shape) * sigma)[mask]
        ranges.append(f.max() - f.min())
    return float(np.median(ranges))
