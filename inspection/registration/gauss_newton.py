"""Gauss-Newton on the exact distances from points to their CAD faces: each step projects
the points onto their face's surface (`segmentation.project_to_faces`) and solves the
linearised point-to-plane problem there. A sample's tangent plane departs from a small
cylinder by up to s^2/(8R) (s the sample spacing), which the exact faces do not.

The loss is Huber's (iteratively reweighted), not a cut at a few sigma: a face that alone
fixes a motion (the one wall seen along a plate) and starts off by more than the cut would
otherwise be dropped whole and the pose left to slide along it."""

from __future__ import annotations

import numpy as np

from inspection.cad import CadModel
from inspection.registration.evidence import huber_weights, residual_scale
from inspection.registration.point_to_plane import point_to_plane_step
from inspection.registration.rigid import transform_points, twist_matrix
from inspection.segmentation import project_to_faces


def gauss_newton(src: np.ndarray, face: np.ndarray, T: np.ndarray, model: CadModel, iterations: int) -> np.ndarray:
    """The pose T (scan -> model) refined by up to `iterations` Gauss-Newton steps on the
    points `src` (N, 3) assigned to the faces `face` (N,), Huber-weighted (threshold from
    the residuals' robust sigma); a numerical damping (1e-9 of the largest curvature) keeps a
    motion the data do not constrain at all (a ring's turn about its axis) where it is."""
    for _ in range(iterations):
        q = transform_points(T, src)
        _, foot, normal, r = project_to_faces(model, q, face)
        w = huber_weights(r, max(residual_scale(r), 1e-6))
        step, _ = point_to_plane_step(q, foot, normal, damping=1e-9, weights=w)
        T = twist_matrix(step) @ T
        if np.linalg.norm(step) < 1e-9:
            break
    return T
