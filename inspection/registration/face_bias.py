"""Faces that sit off their nominal surface as a whole (a pocket floor measured through
mixed pixels, a raised step, a bowed top, or a face truly out of position on the part)
must not pull the fit of the faces that conform: the exact-distance refinement leaves
them out, as a datum would rest on the majority of the surface."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from inspection.cad import CadModel
from inspection.registration.evidence import robust_sigma
from inspection.registration.gauss_newton import MixedPixels, gauss_newton
from inspection.registration.rigid import transform_points
from inspection.segmentation import project_to_faces


def without_biased_faces(src: np.ndarray, face: np.ndarray, T: np.ndarray, model: CadModel, iterations: int,
                         sigmas: float, *, mixed: MixedPixels | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(which points are kept, pose) after leaving out the faces whose points sit off their
    surface as a group at the converged pose T (median residual beyond `sigmas` times the
    robust spread of the faces' medians) and refining on the rest, provided the rest hold at
    least half the points; otherwise all points and T. `mixed`: the points' blurred-pixel
    model for the refits (`gauss_newton.MixedPixels`; None: plain steps)."""
    _, _, _, r = project_to_faces(model, transform_points(T, src), face)
    labels, inv, count = np.unique(face, return_inverse=True, return_counts=True)
    med = np.array([np.median(r[inv == k]) for k in range(len(labels))])  # one per face seen
    spread = robust_sigma(med)
    off = np.abs(med - np.median(med)) > sigmas * max(spread, 1e-4)
    keep = np.ones(len(src), bool)
    if off.any() and count[~off].sum() >= 0.5 * len(src):
        keep = ~off[inv]
        part = None if mixed is None else mixed.subset(keep)
        T = gauss_newton(src[keep], face[keep], T, model, iterations, mixed=part)
    return keep, T


def without_offset_face(src: np.ndarray, face: np.ndarray, T: np.ndarray, *, model: CadModel, iterations: int,
                        limit_mm: float, noise_ratio: float, big_fraction: float,
                        mixed: MixedPixels | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A large face off its nominal place as a whole pulls the best fit of all faces into a
    compromise (tilted, shifted) that then shows as deviations on faces that conform.
    When the residuals spread more than the noise (their robust sigma over `noise_ratio`
    times that of differences between neighbouring points, which the smooth form
    cancels), each face holding `big_fraction` of the points is left out in turn and the
    others refined: a fit that brings the others' spread down by a fifth and leaves that
    face off them as a group (median beyond 3 of their sigma, and within `limit_mm`: the
    fine step's inlier distance, so that the face still counts in the fitness) is kept,
    the best such. A part whose faces conform never gets here. A face off by more keeps
    the compromise: the part then reads off on several faces (a profile failure) rather
    than failing registration. `mixed` as for `without_biased_faces`. Returns (which
    points the pose rests on, the pose)."""
    _, _, _, r = project_to_faces(model, transform_points(T, src), face)
    _, nb = cKDTree(src).query(src, k=2)
    noise = robust_sigma(r - r[nb[:, 1]]) / np.sqrt(2.0)
    everything = np.ones(len(src), bool)
    if robust_sigma(r) <= noise_ratio * noise:
        return everything, T
    _, inv, count = np.unique(face, return_inverse=True, return_counts=True)
    best, best_sigma, kept = T, np.inf, everything
    for k in np.flatnonzero(count >= big_fraction * len(face)):
        rest = inv != k
        part = None if mixed is None else mixed.subset(rest)
        U = gauss_newton(src[rest], face[rest], T, model, iterations, mixed=part)
        _, _, _, ru = project_to_faces(model, transform_points(U, src), face)
        sigma = robust_sigma(ru[rest])
        offset = abs(np.median(ru[~rest]) - np.median(ru[rest]))
        if sigma < min(0.8 * robust_sigma(r[rest]), best_sigma) and 3.0 * sigma < offset < limit_mm:
            best, best_sigma, kept = U, sigma, rest
    return kept, best
