"""Gauss-Newton on the exact distances from points to their CAD faces: each step projects
the points onto their face's surface (`segmentation.project_to_faces`) and solves the
linearised point-to-plane problem there. A sample's tangent plane departs from a small
cylinder by up to s^2/(8R) (s the sample spacing), which the exact faces do not."""

from __future__ import annotations

import numpy as np

from inspection.cad import CadModel
from inspection.registration.point_to_plane import point_to_plane_step
from inspection.registration.rigid import transform_points, twist_matrix
from inspection.segmentation import project_to_faces


def gauss_newton(src: np.ndarray, face: np.ndarray, T: np.ndarray, model: CadModel, iterations: int) -> np.ndarray:
    """The pose T (scan -> model) refined by up to `iterations` Gauss-Newton steps on the
    points `src` (N, 3) assigned to the faces `face` (N,): residuals beyond 3 robust sigma
    left out, a little damping keeping directions the data do not constrain where they are."""
    for _ in range(iterations):
        q = transform_points(T, src)
        _, foot, normal, r = project_to_faces(model, q, face)
        sigma = 1.4826 * np.median(np.abs(r))
        ok = np.abs(r) < max(3.0 * sigma, 1e-4)
        step, _ = point_to_plane_step(q[ok], foot[ok], normal[ok], damping=1e-6)
        T = twist_matrix(step) @ T
        if np.linalg.norm(step) < 1e-9:
            break
    return T
