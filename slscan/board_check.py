"""A calibration checked on a board it never saw: leave one pose of a capture out,
calibrate on the others, and measure the left-out board by triangulation — its flatness
and the distances between its corners against the board's nominal geometry (multiples
of its square size) — each with its uncertainty.

Triangulation is the scanner's: a camera pixel and one decoded projector coordinate give a
point, with the calibrated rig — the coordinate across the baseline (`coded_orientation`:
the projector row on the procam capture, whose projector sits above the camera); the board
pose the calibration would solve for the left-out view is never used.

- Corners: detected in the board's white image (sub-pixel), their projector column from
  a local quadratic fit of the decoded coordinates around each (`calibration.correspond`),
  then intersected. Their noise (`CornerNoise`), in terms of its sources: the camera
  corner's error and the decoding's error beyond what the camera's error carries into the
  projector coordinate (the local fit is evaluated at the camera corner), each with its
  covariance as a function of the lag between two corners on the board, estimated
  robustly from the residuals the calibration left on its own views (type A) and mixed
  with the left-out pose's own local-fit Jacobians; through ∂X/∂(pixel, coordinate)
  (`inspection.uncertainty.measurement_jacobian`); plus the calibration's covariance.
  Distances are taken between corners on one row or one column of the board (nominal
  k x square).
- Flatness: the minimum-zone flatness of the triangulated corners (each corner's
  projector coordinate comes from thousands of decoded pixels; a single pixel's Gray code
  is a whole projector row, quantised to several millimetres of depth at this stand-off),
  its noise bias removed, U and detection limit from draws of the corners' correlated
  noise, the calibration's covariance propagated.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import cv2
import numpy as np

from inspection.form import flatness_mz, from_draws
from inspection.uncertainty import CalibrationUncertainty, Estimate, measurement_jacobian
from scanner.geometry import RigModel
from scanner.reconstruct import Triangulator


def triangulate_corners(model: RigModel, pixels: np.ndarray, coded: np.ndarray, orientation: str,
                        iterations: int = 20) -> np.ndarray:
    """Camera-frame points (N, 3) of camera pixels (N, 2) (sub-pixel) and the projector
    coordinate (N,) they see along the coded axis (x for "vertical", y for "horizontal"):
    on each pixel's ray, the point whose projector image has that coordinate. The
    projector's distortion mixes in the other coordinate, so that one is taken from the
    point found so far and the intersection repeated until it settles."""
    axis = 0 if orientation == "vertical" else 1
    rays = np.column_stack([model.camera.normalized(pixels), np.ones(len(pixels))])
    P = model.proj_from_cam
    R, t = P[:3, :3], P[:3, 3]
    a, b = rays @ R[axis], rays @ R[2]  # the ray's projector coordinate along the axis and depth, per unit depth
    rvec = cv2.Rodrigues(R)[0].ravel()
    other = np.full(len(pixels), model.projector.K[1 - axis, 2])
    X = rays
    for _ in range(iterations):
        uv = np.column_stack([coded, other] if axis == 0 else [other, coded])
        n = model.projector.normalized(uv)[:, axis]
        depth = (t[axis] - n * t[2]) / (n * b - a)  # (depth a + t_axis) = n (depth b + t_z)
        X = rays * depth[:, None]
        new = cv2.projectPoints(np.ascontiguousarray(X).reshape(-1, 1, 3), rvec, t, model.projector.K,
                                model.projector.dist)[0].reshape(-1, 2)[:, 1 - axis]
        if np.max(np.abs(new - other)) < 1e-6:
            break
        other = new
    return X


def coded_orientation(model: RigModel, view: Any) -> str:
    """The fringe orientation whose projector coordinate fixes depth best on this rig
    (the smaller median |dz/dc| over the view's decoded pixels): with a baseline mostly
    vertical it is the projector row (horizontal stripes)."""
    tri = Triangulator(model)
    slopes = {o: np.nanmedian(tri.depth_scale(m.astype(np.float32), o, sensitivity=True)[1])
              for o, m in (("vertical", view.u), ("horizontal", view.v))}
    return min(slopes, key=lambda o: slopes[o])


@dataclass(frozen=True)
class PoseCheck:
    """One left-out pose: its flatness, and per corner pair on a row or column the
    nominal distance (mm), the measured minus nominal and its U (k = 2), and the part of U
    the corners' noise makes (`U_noise_mm`; the rest is the calibration's uncertainty)."""

    name: str
    corners: int
    flatness: Estimate
    plane_rms_mm: float
    nominal_mm: np.ndarray
    error_mm: np.ndarray
    U_mm: np.ndarray
    U_noise_mm: np.ndarray
    calibration_rms_px: dict[str, float]
    orientation: str

    @property
    def inside(self) -> float:
        """The fraction of corner distances whose error is within ±U."""
        return float(np.mean(np.abs(self.error_mm) <= self.U_mm))

    def summary(self, square_mm: float) -> dict[str, Any]:
        adj = np.isclose(self.nominal_mm, square_mm)
        longest = self.nominal_mm >= self.nominal_mm.max() - 1e-6
        return {"pose": self.name, "corners": self.corners, **self.flatness.fields("flatness_mz"),
                "plane_rms_mm": self.plane_rms_mm, "pairs": len(self.error_mm),
                "adjacent_error_rms_mm": float(np.sqrt(np.mean(self.error_mm[adj] ** 2))),
                "adjacent_error_max_mm": float(np.abs(self.error_mm[adj]).max()),
                "adjacent_U_median_mm": float(np.median(self.U_mm[adj])),
                # U's sources for adjacent corners: the corners' noise, and the calibration's uncertainty
                "adjacent_U_noise_median_mm": float(np.median(self.U_noise_mm[adj])),
                "adjacent_U_calibration_median_mm": float(np.median(np.sqrt(np.maximum(
                    self.U_mm[adj] ** 2 - self.U_noise_mm[adj] ** 2, 0.0)))),
                # U (k = 2) over the error's RMS: 2 when U is honest for this pose
                "adjacent_U_over_error_rms": float(np.median(self.U_mm[adj])
                                                   / np.sqrt(np.mean(self.error_mm[adj] ** 2))),
                # RMS of error / (U / 2) over every distance: 1 when U is honest
                "normalised_error_rms": float(np.sqrt(np.mean((2.0 * self.error_mm / self.U_mm) ** 2))),
                "longest_nominal_mm": float(self.nominal_mm.max()),
                "longest_error_mm": self.error_mm[longest].tolist(), "longest_U_mm": self.U_mm[longest].tolist(),
                "within_U": self.inside, "calibration_rms_px": self.calibration_rms_px,
                "coded_axis": "projector rows" if self.orientation == "horizontal" else "projector columns"}


def pooled_summary(checks: list[PoseCheck], square_mm: float) -> dict[str, Any]:
    """What the poses say together, counted honestly: each pose is one independent check
    (its own left-out board pose, its own calibration of the others); its distances share
    both, so they are not independent trials. The truth is the board's nominal geometry,
    the scale the calibrations assumed too: an error of the printed square size is not
    seen here."""
    errors = np.concatenate([c.error_mm for c in checks])
    U = np.concatenate([c.U_mm for c in checks])
    adj = np.concatenate([np.isclose(c.nominal_mm, square_mm) for c in checks])
    normalised = [float(np.sqrt(np.mean((2.0 * c.error_mm / c.U_mm) ** 2))) for c in checks]
    return {"independent_poses": len(checks), "distances": len(errors),
            "within_U": float(np.mean(np.abs(errors) <= U)),
            "poses_with_95_percent_within_U": int(sum(c.inside >= 0.95 for c in checks)),
            "adjacent_error_rms_mm": float(np.sqrt(np.mean(errors[adj] ** 2))),
            "adjacent_U_median_mm": float(np.median(U[adj])),
            "adjacent_U_over_error_rms": float(np.median(U[adj]) / np.sqrt(np.mean(errors[adj] ** 2))),
            "normalised_error_rms": float(np.sqrt(np.mean(np.square(normalised)))),
            "normalised_error_rms_per_pose": normalised,
            "truth": f"the board's nominal geometry (multiples of {square_mm:g} mm), the scale the calibrations "
                     f"assumed: a wrong printed square size is not seen by this check"}


OUTLIER_ALPHA = 1e-3  # the chance that a Gaussian residual vector is set aside by `robust_second_moment`


def robust_second_moment(v: np.ndarray, rounds: int = 5) -> np.ndarray:
    """E[v vᵀ] (3, 3) of vectors `v` (n, 3) that are Gaussian about 0 but for a few gross
    errors: start from the components' median absolute values (1.4826 x, the Gaussian's
    sigma), set aside the vectors beyond the chi-square (3 dof) point a Gaussian vector
    exceeds with probability OUTLIER_ALPHA, take the second moment of the rest, corrected
    for that truncation (for a Gaussian, E[v vᵀ | inside] = Σ · P(χ²₅ ≤ q) / P(χ²₃ ≤ q)),
    and repeat."""
    from scipy.stats import chi2

    if len(v) == 0:
        return np.zeros((3, 3))
    q = float(chi2.ppf(1.0 - OUTLIER_ALPHA, 3))
    shrink = float(chi2.cdf(q, 5) / chi2.cdf(q, 3))
    S = np.diag(np.maximum((1.4826 * np.median(np.abs(v), axis=0)) ** 2, 1e-30))
    for _ in range(rounds):
        inside = np.einsum("ni,ij,nj->n", v, np.linalg.pinv(S), v) <= q
        if not inside.any():
            break
        S = v[inside].T @ v[inside] / inside.sum() / shrink
    return 0.5 * (S + S.T)


def _unique_lags(h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`np.unique(h, axis=0, return_inverse=True, return_counts=True)` of integer lags (n, 2),
    by counting them in the box they span (n is pairs x views: millions, which the row sort
    of `np.unique` takes seconds over)."""
    lo = h.min(axis=0)
    rows = int(h[:, 1].max() - lo[1] + 1)
    key = (h[:, 0] - lo[0]) * rows + (h[:, 1] - lo[1])
    counts = np.bincount(key)
    present = np.flatnonzero(counts)
    rank = np.cumsum(counts > 0) - 1
    return np.column_stack([present // rows + lo[0], present % rows + lo[1]]), rank[key], counts[present]


def _grid(obj: np.ndarray, square_mm: float) -> np.ndarray:
    """Board corners' (N, 3) integer grid positions (N, 2), in squares."""
    return np.rint(obj[:, :2] / square_mm).astype(int)


@dataclass(frozen=True)
class CornerNoise:
    """How the errors of two corners covary with their lag on the board, in the terms of
    their sources: the camera corner's error e (x, y) and the decoding's error n of the
    coded projector coordinate beyond what e carries into it (the projector coordinate is
    the local fit evaluated at the camera corner: its error is a·e + n, a the fit's
    Jacobian row of the coded axis, `calibration.stereo.CornerErrorModel`). `lags` (L, 2) in
    squares (canonical: dx > 0, or dx = 0 and dy >= 0) and their covariances (L, 3, 3) of
    (e_x, e_y, n), C(h) = E[s(g) s(g + h)ᵀ]; the lag -h has C(h)ᵀ. Estimated from the
    residuals a calibration left on its own views (each view's own a taken out), pooled
    over views and corner pairs; `pairs` how many pairs each lag pooled.

    Pooling the residuals of (camera, coded coordinate) as they are mixes views whose a
    differ (the board's tilt sets it): the camera error's share of the coded coordinate,
    which moves a triangulated corner along the board and not in depth, then reads as
    depth noise (on the procam capture, at 3.4 m, it set the adjacent distances' U to
    ~0.3 mm of noise where the errors were 0.09-0.12 mm RMS)."""

    lags: np.ndarray
    covariances: np.ndarray
    pairs: np.ndarray

    @classmethod
    def from_residuals(cls, views: list[tuple[np.ndarray, ...]], axis: int, square_mm: float) -> CornerNoise:
        """`views`: per calibration view the camera's object points (N, 3) and residuals
        (N, 2), the projector's (M, 3) and (M, 2) (px), and optionally the projector
        points' local-fit Jacobians (M, 2, 2) (absent: the coded coordinate's error is
        taken as independent of the camera's); `axis` the projector's coded coordinate
        (0 x, 1 y). Only corners seen by both devices count.

        C(0) is the pooled second moment of a corner's residuals; C(h) for h != 0 is C(0)
        minus half the pooled second moment of the differences r(g + h) − r(g) over the
        pairs at that lag (plus the products' antisymmetric part, the cross-covariance's
        direction), so a distance between corners at lag h sees exactly the spread the
        residuals' differences at that lag have: the views' residuals are not stationary
        (a view's smooth misfit across the board, a few corners far off in one view), and
        products pooled over different pairs than C(0) misstate the difference
        (on the procam capture the adjacent camera-x spread came out 0.32 px from the
        products, 0.27 px measured on the differences). Both second moments are robust
        (`robust_second_moment`): a few corners the detector got wrong by pixels (the
        capture's poses seen through a glass pane's edge) would otherwise set the spread of
        every distance (adjacent camera-x differences: 0.27 px RMS, 0.12 px without them);
        a distance to such a corner then falls outside its U, and the share of distances
        outside U says how often that happens."""
        lag_parts, product_parts, vector_parts = [], [], []
        for cam_obj, cam_res, proj_obj, proj_res, *jacobian in views:
            g_cam, g_proj = _grid(cam_obj, square_mm), _grid(proj_obj, square_mm)
            index = {tuple(g): k for k, g in enumerate(g_cam)}
            both = [(index[tuple(g)], k) for k, g in enumerate(g_proj) if tuple(g) in index]
            if not both:
                continue
            ci, pi = np.array(both).T
            e = np.asarray(cam_res).reshape(-1, 2)[ci]
            n = np.asarray(proj_res).reshape(-1, 2)[pi, axis]
            if jacobian:
                n = n - np.einsum("mj,mj->m", np.asarray(jacobian[0])[pi, axis, :], e)
            r = np.column_stack([e, n])
            g = g_cam[ci]
            a, b = (x.ravel() for x in np.meshgrid(np.arange(len(g)), np.arange(len(g)), indexing="ij"))
            h = g[b] - g[a]
            canonical = (h[:, 0] > 0) | ((h[:, 0] == 0) & (h[:, 1] >= 0))
            a, b = a[canonical], b[canonical]
            lag_parts.append(h[canonical])
            product_parts.append((r[a][:, :, None] * r[b][:, None, :]).reshape(-1, 9))
            vector_parts.append(np.where((a == b)[:, None], r[a], r[b] - r[a]))  # lag 0: the residual itself
        lags, inverse, pairs = _unique_lags(np.concatenate(lag_parts))
        values = np.concatenate(product_parts)
        sums = np.stack([np.bincount(inverse, values[:, c], len(lags)) for c in range(9)], axis=1)
        products = (sums / pairs[:, None]).reshape(-1, 3, 3)
        by_lag = np.split(np.concatenate(vector_parts)[np.argsort(inverse, kind="stable")], np.cumsum(pairs)[:-1])
        moments = np.stack([robust_second_moment(v) for v in by_lag])
        zero = np.all(lags == 0, axis=1)
        c0 = moments[zero][0]
        cov = c0 - 0.5 * moments + 0.5 * (products - np.transpose(products, (0, 2, 1)))
        cov[zero] = c0
        return cls(lags, cov, pairs)

    def covariance(self, grid: np.ndarray, coupling: np.ndarray | None = None) -> np.ndarray:
        """The joint covariance (N, 3, N, 3) of the measured (camera x, camera y, coded
        projector coordinate) of corners at `grid` (N, 2) (squares) whose local fits have
        the coded axis' Jacobian rows `coupling` (N, 2) (None: zero): the sources' C of each
        pair's lag (zero for a lag the calibration never saw), made positive semi-definite
        (negative eigenvalues of the pooled estimate set to 0), then mixed,
        measured = (e, a·e + n)."""
        n = len(grid)
        h = (grid[None, :, :] - grid[:, None, :]).reshape(-1, 2)
        flip = ~((h[:, 0] > 0) | ((h[:, 0] == 0) & (h[:, 1] >= 0)))
        key = np.where(flip[:, None], -h, h)
        table = {tuple(k): c for k, c in zip(self.lags, self.covariances)}
        zero = np.zeros((3, 3))
        blocks = np.array([table.get(tuple(k), zero) for k in key])
        blocks[flip] = np.transpose(blocks[flip], (0, 2, 1))
        full = blocks.reshape(n, n, 3, 3).transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
        w, v = np.linalg.eigh(0.5 * (full + full.T))
        sources = ((v * np.clip(w, 0.0, None)) @ v.T).reshape(n, 3, n, 3)
        if coupling is None:
            return sources
        mix = np.tile(np.eye(3), (n, 1, 1))
        mix[:, 2, :2] = coupling
        return np.einsum("iab,ibjc,jdc->iajd", mix, sources, mix)

    @classmethod
    def from_calibration(cls, solution: Any, axis: int, square_mm: float) -> CornerNoise:
        """From a `calibration.solve.Solution`: its joint refinement's residuals per view."""
        s = solution.stereo
        return cls.from_residuals([(c.camera.object_points, rc, c.projector.object_points, rp,
                                    c.projector_corners.jacobian[c.projector_corners.found])
                                   for c, rc, rp in zip(solution.correspondences, s.camera_residuals,
                                                        s.projector_residuals)], axis, square_mm)


def check_pose(view: Any, index: int, board: Any, *, model: RigModel, calibration: CalibrationUncertainty,
               noise: Callable[[int], CornerNoise], rms_px: dict[str, float]) -> PoseCheck:
    """Triangulate the left-out `view` with `model` and measure it (module docstring);
    `noise(axis)`: the corners' noise for the coded projector axis."""
    from calibration.views import correspond

    corr = correspond(board, view, index)
    orientation = coded_orientation(model, view)
    axis = 0 if orientation == "vertical" else 1
    found = corr.projector_corners.found
    pix = corr.detection.image_points[found]
    coded = corr.projector_corners.points[found, axis]
    obj = board.object_points()[corr.detection.ids[found]]
    X = triangulate_corners(model, pix, coded, orientation)
    A = measurement_jacobian(X, model, orientation)
    # corners' joint covariance in mm (N, 3, N, 3): A_i C_ij A_jᵀ
    coupling = corr.projector_corners.jacobian[found][:, axis, :]
    cov = np.einsum("iab,ibjc,jdc->iajd", A, noise(axis).covariance(_grid(obj, board.square_mm), coupling), A)
    shifts = calibration.shifts(X, model, {orientation: np.ones(len(X))})
    i, j = np.triu_indices(len(X), 1)
    same_line = np.isclose(obj[i, 0], obj[j, 0]) | np.isclose(obj[i, 1], obj[j, 1])
    i, j = i[same_line], j[same_line]
    d = X[i] - X[j]
    dist = np.linalg.norm(d, axis=1)
    e = d / dist[:, None]
    pair = cov[i, :, i] + cov[j, :, j] - cov[i, :, j] - cov[j, :, i]
    noise_var = np.einsum("ni,nij,nj->n", e, pair, e)
    var = noise_var.copy()
    if shifts is not None:
        var += np.sum(np.einsum("dni,ni->dn", shifts[:, i] - shifts[:, j], e) ** 2, axis=0)
    nominal = np.linalg.norm(obj[i] - obj[j], axis=1)
    flat, rms = _flatness(X, cov, shifts)
    return PoseCheck(view.name, int(found.sum()), flat, rms, nominal, dist - nominal, 2.0 * np.sqrt(var),
                     2.0 * np.sqrt(noise_var), rms_px, orientation)


def _flatness(X: np.ndarray, cov: np.ndarray, shifts: np.ndarray | None, draws: int = 200,
              seed: int = 0) -> tuple[Estimate, float]:
    """The minimum-zone flatness of the triangulated corners (N, 3) with its U (noise bias
    removed and detection limit from draws of the corners' noise, joint covariance
    (N, 3, N, 3); calibration from `shifts` (D, N, 3)), and their RMS distance from their plane."""
    centre = X.mean(axis=0)
    normal = np.linalg.svd(X - centre, full_matrices=False)[2][2]
    w, v = np.linalg.eigh(cov.reshape(3 * len(X), 3 * len(X)))
    root = v * np.sqrt(np.clip(w, 0.0, None))
    noise = (np.random.default_rng(seed).standard_normal((draws, 3 * len(X))) @ root.T).reshape(draws, len(X), 3)
    value = flatness_mz(X, normal)
    cal = None if shifts is None else np.array([flatness_mz(X + s, normal) - value for s in shifts])
    flat = X - np.outer((X - centre) @ normal, normal)  # the corners on their plane: a perfectly flat board
    est, _ = from_draws(value, np.array([flatness_mz(X + e, normal) for e in noise]),
                        np.array([flatness_mz(flat + e, normal) for e in noise]), cal)
    d = (X - centre) @ normal
    return est, float(np.sqrt(np.mean(d ** 2)))


def leave_one_out(views: list[Any], board: Any, projector_size: tuple[int, int], say: Callable[[str], None]
                  ) -> list[PoseCheck]:
    """Each view left out in turn: calibrate on the others, check it."""
    from calibration.solve import CalibrationSettings
    from calibration.workflow import calibrate_views

    out = []
    for k, view in enumerate(views):
        others = views[:k] + views[k + 1:]
        say(f"{view.name}: calibrating on {', '.join(v.name for v in others)}")
        result = calibrate_views(board, others, projector_size, CalibrationSettings(), "leave-one-out", lambda s: None)
        report = result.report()
        check = check_pose(view, k, board, model=result.model, calibration=CalibrationUncertainty.from_report(report),
                           noise=partial(CornerNoise.from_calibration, result.solution, square_mm=board.square_mm),
                           rms_px={"camera": report["rms_px"]["camera"], "projector": report["rms_px"]["projector"]})
        s = check.summary(board.square_mm)
        say(f"{view.name}: flatness {check.flatness.text()}, adjacent corners error RMS "
            f"{s['adjacent_error_rms_mm']:.3f} mm (U median {s['adjacent_U_median_mm']:.3f} mm), "
            f"{check.inside:.0%} of {s['pairs']} distances within ±U")
        out.append(check)
    return out
