"""Least-squares fits of the shapes calibration measures: planes (the reference plate, the
plate behind the artefact) and spheres (the artefact's balls). Points (N, 3) in mm."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares


def fit_plane(points: np.ndarray) -> np.ndarray:
    """(nx, ny, nz, c), n·X + c = 0, fitted to (N, 3) points, n turned toward the origin."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    n = vt[2]
    if n @ centre > 0:
        n = -n
    return np.array([*n, -n @ centre])


def plane_rms(points: np.ndarray) -> float:
    """RMS distance of points from their best-fit plane (flatness)."""
    plane = fit_plane(points)
    return float(np.sqrt(np.mean((points @ plane[:3] + plane[3]) ** 2)))


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(centre, radius, RMS of the radial residuals) of (N, 3) points: algebraic fit, then
    geometric least squares."""
    A = np.column_stack([2 * points, np.ones(len(points))])
    b = np.sum(points ** 2, axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    centre = sol[:3]
    radius = float(np.sqrt(sol[3] + centre @ centre))

    def residual(p: np.ndarray) -> np.ndarray:
        return np.linalg.norm(points - p[:3], axis=1) - p[3]

    fit = least_squares(residual, [*centre, radius], x_scale="jac")
    return fit.x[:3], float(fit.x[3]), float(np.sqrt(np.mean(fit.fun ** 2)))
