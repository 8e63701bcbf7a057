"""Fits of calibrated artefacts — a sphere, a ball bar (two spheres), a flat plane — and
the VDI/VDE 2634 Part 2 figures taken from them, each with its uncertainty.

Every fit is least squares on the artefact's points (camera frame, mm):
  - sphere: centre and radius free (Gauss-Newton from the algebraic fit); optionally only
    on the points within `band_mm` of a first fit that face the camera at less than
    `max_view_deg` (silhouette pixels mix the sphere with what lies behind it);
  - plane: the total least-squares plane (optionally only the points within `band_mm`);
  - ball bar: two spheres, the distance between their centres.
Every fit then leaves out the 0.3 % of its points furthest from it and is solved again on
the rest (`OUTLIER_FRACTION`: VDI/VDE 2634-2 allows up to 0.3 % of the points to be left
out); its figures (range of the residuals, radius, centre) are those of that second fit.

Uncertainty (see `inspection.uncertainty`): the fitted parameters are linear in the points
to first order, so each point's influence on a figure comes from the fit's normal
equations and noise, fringe systematics and calibration are propagated through it
(`ScanUncertainty.linear_u`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inspection.uncertainty import Estimate, ScanUncertainty

OUTLIER_FRACTION = 0.003  # VDI/VDE 2634-2: up to 0.3 % of the points may be left out of PF and F
MAX_VIEW_DEG = 75.0
MIN_POINTS = 100


class ArtefactError(ValueError):
    """The artefact was not found in the points, or too little of it."""


# ------------------------------------------------------------------------------ sphere


@dataclass(frozen=True, eq=False)
class SphereFit:
    """A least-squares sphere: `centre` (3,) and `radius` (mm), the points used (a mask
    into the points given), their radial residuals, and the influence of every used point
    on the centre and radius, (n, 4, 3) = ∂(cx, cy, cz, r)/∂X_i."""

    centre: np.ndarray
    radius: float
    used: np.ndarray
    residuals: np.ndarray
    influence: np.ndarray

    @property
    def form_range_mm(self) -> float:
        """PF: the range of the radial residuals of the points used (the 0.3 % furthest
        already left out of the fit)."""
        return float(self.residuals.max() - self.residuals.min())

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2)))


def _without_outliers(used: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """`used` (N,) less the OUTLIER_FRACTION of its points whose |distance| (N,) from a fit
    is largest (rounded down: never more than the guideline allows)."""
    drop = int(np.floor(OUTLIER_FRACTION * used.sum()))
    if drop == 0:
        return used
    idx = np.flatnonzero(used)
    out = used.copy()
    out[idx[np.argpartition(-np.abs(distance[idx]), drop - 1)[:drop]]] = False
    return out


def _algebraic_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    A = np.column_stack([2.0 * points, np.ones(len(points))])
    sol, *_ = np.linalg.lstsq(A, np.sum(points ** 2, axis=1), rcond=None)
    return sol[:3], float(np.sqrt(max(sol[3] + sol[:3] @ sol[:3], 0.0)))


def _gauss_newton_sphere(points: np.ndarray, centre: np.ndarray, radius: float,
                         iterations: int = 20) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """(centre, radius, unit radial directions (N, 3), Jacobian (N, 4)) of the geometric
    least-squares sphere from a starting guess."""
    c, r = centre.astype(np.float64), float(radius)
    for _ in range(iterations):
        d = points - c
        dist = np.linalg.norm(d, axis=1)
        n = d / dist[:, None]
        J = np.column_stack([-n, -np.ones(len(points))])
        step = np.linalg.lstsq(J, -(dist - r), rcond=None)[0]
        c, r = c + step[:3], r + step[3]
        if np.max(np.abs(step)) < 1e-10:
            break
    d = points - c
    n = d / np.linalg.norm(d, axis=1)[:, None]
    return c, r, n, np.column_stack([-n, -np.ones(len(points))])


def fit_sphere(points: np.ndarray, nominal_radius_mm: float | None = None, band_mm: float | None = None,
               viewpoint: np.ndarray | None = None, max_view_deg: float = MAX_VIEW_DEG) -> SphereFit:
    """The least-squares sphere of `points` (N, 3). With a `viewpoint` (the camera
    centre), points whose sphere normal turns more than `max_view_deg` from it are left
    out; with `band_mm`, points further than that from the first fit are left out (both
    then refitted). Last, the OUTLIER_FRACTION furthest from it are left out and it is
    refitted (VDI/VDE 2634-2's 0.3 %)."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < MIN_POINTS:
        raise ArtefactError(f"only {len(points)} points on the sphere; at least {MIN_POINTS} are needed")
    c, r = _algebraic_sphere(points)
    used = np.ones(len(points), dtype=bool)
    for _ in range(3):  # fit, select, refit until the selection settles
        c, r, _, _ = _gauss_newton_sphere(points[used], c, r)
        d = points - c
        dist = np.linalg.norm(d, axis=1)
        keep = np.ones(len(points), dtype=bool)
        if band_mm is not None:
            keep &= np.abs(dist - r) <= band_mm
        if viewpoint is not None:
            to_view = viewpoint - points
            cos = np.einsum("ij,ij->i", d, to_view) / (dist * np.linalg.norm(to_view, axis=1))
            keep &= cos >= np.cos(np.radians(max_view_deg))
        if (keep == used).all():
            break
        used = keep
        if used.sum() < MIN_POINTS:
            raise ArtefactError(f"only {int(used.sum())} points near the sphere of radius {r:.3f} mm "
                                f"(nominal {nominal_radius_mm}); is the sphere in view?")
    c, r, _, _ = _gauss_newton_sphere(points[used], c, r)
    used = _without_outliers(used, np.linalg.norm(points - c, axis=1) - r)
    pts = points[used]
    c, r, n, J = _gauss_newton_sphere(pts, c, r)
    residuals = np.linalg.norm(pts - c, axis=1) - r
    # ∂θ/∂X_i = -(JᵀJ)⁻¹ J_iᵀ n_iᵀ: the parameters' first-order response to a point's move
    G = -np.linalg.solve(J.T @ J, J.T)  # (4, n)
    influence = G.T[:, :, None] * n[:, None, :]
    return SphereFit(c, float(r), used, residuals, influence)


@dataclass(frozen=True)
class SphereResult:
    """A measured sphere: radius and centre with their uncertainties, PF (form range,
    the 0.3 % furthest points left out), the points used and their RMS residual."""

    radius: Estimate
    centre: tuple[Estimate, Estimate, Estimate]
    form_range_mm: float
    rms_mm: float
    points: int
    components: dict[str, float]  # u of the radius by source (mm)

    def as_dict(self) -> dict[str, object]:
        return {**self.radius.fields("radius"), "centre_mm": [e.value for e in self.centre],
                "centre_u_mm": [e.U for e in self.centre], "form_range_mm": self.form_range_mm,
                "rms_mm": self.rms_mm, "points": self.points, "radius_u_components_mm": self.components}


INNER_BAND = 0.1  # the inner fits keep points within this fraction of the nominal radius of a first fit
CAMERA_ORIGIN = np.zeros(3)  # the default viewpoint: the camera frame's origin (mm); shared, so read-only
CAMERA_ORIGIN.flags.writeable = False


def measure_sphere(points: np.ndarray, unc: ScanUncertainty, nominal_radius_mm: float,
                   viewpoint: np.ndarray | None = CAMERA_ORIGIN, *,
                   inner: bool = True) -> tuple[SphereFit, SphereResult]:
    """Fit a sphere and propagate the uncertainties to its radius and centre. `inner`:
    only the points within INNER_BAND of the nominal radius of a first fit, facing the
    `viewpoint` at less than MAX_VIEW_DEG (`fit_sphere`); else every point given (the
    guideline's fit). Both leave out the 0.3 % furthest."""
    fit = (fit_sphere(points, nominal_radius_mm, INNER_BAND * nominal_radius_mm, viewpoint) if inner
           else fit_sphere(points, nominal_radius_mm))
    pts, sub = points[fit.used], unc.subset(fit.used)
    radius = sub.linear_u(pts, fit.influence[:, 3], fit.rms_mm)
    cx, cy, cz = (sub.linear_u(pts, fit.influence[:, k], fit.rms_mm).estimate(float(fit.centre[k])) for k in range(3))
    return fit, SphereResult(radius.estimate(fit.radius), (cx, cy, cz), fit.form_range_mm, fit.rms_mm,
                             int(fit.used.sum()), radius.components)


# ---------------------------------------------------------------------------- ball bar


@dataclass(frozen=True)
class BallBarResult:
    """Two measured spheres and the distance between their centres (with U), and the
    outer length: distance plus both radii (bidirectional, as a caliper would take it)."""

    spheres: tuple[SphereResult, SphereResult]
    distance: Estimate
    outer_length: Estimate
    components: dict[str, float]

    def as_dict(self) -> dict[str, object]:
        return {**self.distance.fields("distance"), **self.outer_length.fields("outer_length"),
                "distance_u_components_mm": self.components, "spheres": [s.as_dict() for s in self.spheres]}


def measure_ball_bar(points: tuple[np.ndarray, np.ndarray], unc: tuple[ScanUncertainty, ScanUncertainty],
                     nominal_radius_mm: float, viewpoint: np.ndarray | None = CAMERA_ORIGIN, *,
                     inner: bool = True) -> BallBarResult:
    """Both spheres of a ball bar from their points (`measure_sphere`, `inner` as there),
    and the distance between the centres with the uncertainty of the pair (the two
    spheres share projector columns and the calibration, so their errors are propagated
    together)."""
    fits, results = zip(*(measure_sphere(p, u, nominal_radius_mm, viewpoint, inner=inner) for p, u in zip(points, unc)))
    e = fits[0].centre - fits[1].centre
    length = float(np.linalg.norm(e))
    e /= length
    pts = np.concatenate([p[f.used] for p, f in zip(points, fits)])
    d_infl = np.concatenate([fits[0].influence[:, :3].transpose(0, 2, 1) @ e,
                             -(fits[1].influence[:, :3].transpose(0, 2, 1) @ e)])
    r_infl = np.concatenate([fits[0].influence[:, 3], fits[1].influence[:, 3]])
    joined = ScanUncertainty.join([u.subset(f.used) for u, f in zip(unc, fits)])
    rms = float(np.hypot(fits[0].rms_mm, fits[1].rms_mm) / np.sqrt(2.0))
    distance = joined.linear_u(pts, d_infl, rms)
    outer = joined.linear_u(pts, d_infl + r_infl, rms)
    return BallBarResult(tuple(results), distance.estimate(length),
                         outer.estimate(length + fits[0].radius + fits[1].radius), distance.components)


# ------------------------------------------------------------------------------- plane


@dataclass(frozen=True)
class PlaneResult:
    """A measured flat: the least-squares plane (unit normal toward the camera, a point),
    F (range of signed distances of the points used, the 0.3 % furthest left out), RMS,
    points used."""

    normal: np.ndarray
    point: np.ndarray
    flatness_range_mm: float
    rms_mm: float
    points: int

    def as_dict(self) -> dict[str, object]:
        return {"normal": self.normal.tolist(), "point_mm": self.point.tolist(),
                "flatness_range_mm": self.flatness_range_mm, "rms_mm": self.rms_mm, "points": self.points}


def measure_plane(points: np.ndarray, band_mm: float | None = None) -> PlaneResult:
    """The least-squares plane of `points` (N, 3) and their spread about it; with
    `band_mm`, points further than that from a first fit are left out and it is refitted;
    then the 0.3 % furthest are left out and it is fitted again."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < MIN_POINTS:
        raise ArtefactError(f"only {len(points)} points on the plane; at least {MIN_POINTS} are needed")

    def fit(used: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c = points[used].mean(axis=0)
        n = np.linalg.svd(points[used] - c, full_matrices=False)[2][2]
        return c, n, (points - c) @ n

    used = np.ones(len(points), dtype=bool)
    c, n, d = fit(used)
    if band_mm is not None:
        used = np.abs(d - np.median(d)) <= band_mm
        c, n, d = fit(used)
    used = _without_outliers(used, d)
    c, n, d = fit(used)
    if n @ c > 0:
        n, d = -n, -d
    d = d[used]
    return PlaneResult(n, c, float(d.max() - d.min()), float(np.sqrt(np.mean(d ** 2))), int(used.sum()))
