"""Gauss-Newton on the exact distances from points to their CAD faces: each step projects
the points onto their face's surface (`segmentation.project_to_faces`) and solves the
linearised point-to-plane problem there. A sample's tangent plane departs from a small
cylinder by up to s^2/(8R) (s the sample spacing), which the exact faces do not.

The loss is Huber's (iteratively reweighted), not a cut at a few sigma: a face that alone
fixes a motion (the one wall seen along a plate) and starts off by more than the cut would
otherwise be dropped whole and the pose left to slide along it.

**Mixed pixels** (`MixedPixels`, issue 26). A point within the camera's blur of its
surface's outline (a depth step, or a crease where another CAD face begins) reads a mix of
both surfaces, off its face by up to the assignment bound. Least squares takes such a point
as fully informative (leverage 1 where it alone has a lever arm): on top-down views of the
demo part one to four crease pixels 50-130 um off their face were all that fixed the turn
about the boss axis, and the fit turned the part until they read 0 (stored pose-coverage
scan 635461529/88: 0.19 deg; scan 49: 1.41 deg); an 11-point outline strip 25 um off, and
tilted as much, turned it 0.061 deg (coverage seed 55805, trial 1). So the band points of
each face share one unknown offset and linear trend across the image, which each point reads
in proportion to its share of light from beyond (`MixedPixels`), and the fit estimates them
with the pose under that prior and keeps the pose's part (`band_effects`: the Schur
complement A of the normal matrix, and the gradient reduced alike): a lone band point counts
with variance sigma^2 + l^2 tau^2 (l its share over the most), a strip's tilt is its own,
while many band points on one face still fix what their face's shape fixes beyond a plane's
tilt. A step is taken only along the eigen-directions of A whose standard deviation
sigma / sqrt(eigenvalue) is within the pose tolerance; along the others the pose stays where
the previous stage put it, and `fine.fit_covariance` names those directions free: a pose is
never accepted along a motion only band points fix (false accept), at the price of refusing
as free a pose whose only lever along some motion is band points that happen to read right
(false refusal)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from inspection.cad import CadModel
from inspection.registration.band_effects import BandEffects
from inspection.registration.evidence import MAX_SHARE, huber_weights, jacobian, residual_scale
from inspection.registration.point_to_plane import point_to_plane_step
from inspection.registration.rigid import transform_points, twist_matrix
from inspection.segmentation import project_to_faces


@dataclass(frozen=True)
class MixedPixels:
    """The exact fit's model of blurred points (module docstring): `band` (N,) bool, which
    of the fit's points lie within the blur of an outline (`fine.blurred`);
    `offset_variance_mm2` tau^2 (mm^2), the variance of the common offset (and of each trend
    coefficient, `band_effects`) of one face's band points were half their light from beyond
    the outline (an offset uniform within the assignment bound B has B^2/3; a larger tau^2
    refuses more poses as free, a smaller one lets band points turn the pose again); a point
    whose share of light from beyond is s reads s / `MAX_SHARE` of it, as the faces' offsets
    grow (`evidence._face_offsets`);
    `tolerance_deg` / `tolerance_mm` the pose tolerance a direction's standard deviation
    must be within (rotations at the points' RMS radius) for the fit to step along it;
    `mixing` (N,) the share of each point's light from beyond its surface's outline
    (`fine.mixing`), for the pose covariance's face offsets; `pixels` (N, 2) the points'
    image positions (px), over which a band's trend runs."""

    band: np.ndarray
    offset_variance_mm2: float
    tolerance_deg: float
    tolerance_mm: float
    mixing: np.ndarray
    pixels: np.ndarray

    def subset(self, keep: np.ndarray) -> MixedPixels:
        """The model for the points `keep` (a mask or indices) of these."""
        return replace(self, band=self.band[keep], mixing=self.mixing[keep], pixels=self.pixels[keep])

    def effects(self, face: np.ndarray, *, within: np.ndarray | None = None) -> BandEffects:
        """The band points' offsets and trends per CAD face (`face` (N,)) as random effects
        (`band_effects`), each point's scaled by its own share of light from beyond;
        only the band points `within` flags (default all)."""
        band = self.band if within is None else self.band & within
        return BandEffects.of(face, band, self.pixels, loading=self.mixing / MAX_SHARE,
                              variance_mm2=self.offset_variance_mm2)


@dataclass(frozen=True)
class Information:
    """The exact fit's weighted least-squares system at one pose, in scaled coordinates
    z = S^-1 (omega, t) about `centre` (rotations as mm at `radius_mm`; `scale` = S): `A` the
    normal matrix and `gradient` sum w c r once each face's band points' offset and trend are
    taken out (module docstring; c the rows `band_effects` gives), `sigma` the residuals'
    scale (mm)."""

    centre: np.ndarray
    radius_mm: float
    scale: np.ndarray
    A: np.ndarray
    gradient: np.ndarray
    sigma: float

    def directions(self, tolerance_deg: float, tolerance_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """(bounded, unbounded): the eigenvectors of A (columns, scaled coordinates) whose
        standard deviation sigma / sqrt(eigenvalue) is within the tolerance (the smaller of
        `tolerance_mm` and `tolerance_deg` at the points' RMS radius), and the others."""
        lam, U = np.linalg.eigh(self.A / self.sigma ** 2)
        tol = min(tolerance_mm, self.radius_mm * np.radians(tolerance_deg))
        ok = lam > 1.0 / tol ** 2
        return U[:, ok], U[:, ~ok]

    def motions(self, directions: np.ndarray, centre: np.ndarray) -> np.ndarray:
        """`directions` (columns in this system's scaled coordinates) as rows (omega rad,
        t mm) of small rigid motions about `centre` (mm): the same displacement field, its
        translation moved with the centre, t' = t + omega x (centre - self.centre)."""
        m = (self.scale @ directions).T
        m[:, 3:] += np.cross(m[:, :3], np.asarray(centre, np.float64) - self.centre)
        return m


def information(q: np.ndarray, normal: np.ndarray, r: np.ndarray, effects: BandEffects) -> Information:
    """The exact fit's `Information` at model-frame points `q` (N, 3) with their faces'
    `normal`s and residuals `r` (mm), Huber-weighted as `gauss_newton` weighs them; each
    face's band points sharing one offset and trend (`effects`, `MixedPixels.effects`) of
    variance tau^2, each point's scaled by its share of light from beyond."""
    sigma = max(residual_scale(r), 1e-6)
    w = huber_weights(r, sigma)
    centre = q.mean(axis=0)
    radius = max(float(np.sqrt(np.mean(np.sum((q - centre) ** 2, axis=1)))), 1e-9)
    S = np.diag([1.0 / radius] * 3 + [1.0] * 3)
    J = jacobian(q, normal, centre) @ S
    wC = effects.rows(J, w, sigma) * w[:, None]
    A = wC.T @ J
    return Information(centre, radius, S, 0.5 * (A + A.T), wC.T @ r, sigma)


def gauss_newton(src: np.ndarray, face: np.ndarray, T: np.ndarray, model: CadModel, iterations: int, *,
                 mixed: MixedPixels | None = None) -> np.ndarray:
    """The pose T (scan -> model) refined by up to `iterations` Gauss-Newton steps on the
    points `src` (N, 3) assigned to the faces `face` (N,), Huber-weighted (threshold from
    the residuals' robust sigma); a numerical damping (1e-9 of the largest curvature) keeps a
    motion the data do not constrain at all (a ring's turn about its axis) where it is.
    With `mixed`, each step is the least-squares step within the directions the points
    bound to the pose tolerance once their band points' offsets are allowed for (module
    docstring); along the others the pose stays as T has it."""
    effects = None if mixed is None else mixed.effects(face)  # the points and their faces stay: one model
    for _ in range(iterations):
        q = transform_points(T, src)
        _, foot, normal, r = project_to_faces(model, q, face)
        if mixed is None or effects is None:
            w = huber_weights(r, max(residual_scale(r), 1e-6))
            step, _ = point_to_plane_step(q, foot, normal, damping=1e-9, weights=w)
        else:
            step = _bounded_step(information(q, normal, r, effects), mixed)
        T = twist_matrix(step) @ T
        if np.linalg.norm(step) < 1e-9:
            break
    return T


def _bounded_step(info: Information, mixed: MixedPixels) -> np.ndarray:
    """The Gauss-Newton step (omega, t about the origin) within the directions `info` bounds
    to the pose tolerance (`Information.directions`); zero when it bounds none."""
    U, _ = info.directions(mixed.tolerance_deg, mixed.tolerance_mm)
    if U.shape[1] == 0:
        return np.zeros(6)
    reduced = U.T @ info.A @ U
    z = -U @ np.linalg.solve(reduced + 1e-12 * np.abs(np.diag(reduced)).max() * np.eye(U.shape[1]),
                             U.T @ info.gradient)
    x = info.scale @ z  # (omega, t) about the centre
    return np.concatenate([x[:3], x[3:] - np.cross(x[:3], info.centre)])
