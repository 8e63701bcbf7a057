"""A calibration checked on a board it never saw: leave one pose of a capture out,
calibrate on the others, and measure the left-out board by triangulation — its flatness
and the distances between its corners against the board's nominal geometry (multiples
of its square size) — each with its uncertainty.

Triangulation is the scanner's: a camera pixel and one decoded projector coordinate give a
point, with the calibrated rig — the coordinate across the baseline (`coded_orientation`:
the projector row on the procam capture, whose projector sits above the camera); the board
pose the calibration would solve for the left-out view is never used.

- Corners: detected in the board's white image (sub-pixel), their projector column from
  a local homography of the decoded coordinates around each (`calibration.correspond`),
  then intersected. Their noise: the camera corners with the calibration's camera
  reprojection RMS per coordinate, the projector coordinate with its projector RMS (the
  residuals the calibration itself left, as type A estimates), through ∂X/∂(pixel,
  coordinate) (`inspection.uncertainty.measurement_jacobian`); plus the calibration's
  covariance. Distances are taken between corners on one row or one column of the board
  (nominal k x square).
- Flatness: the minimum-zone flatness of the triangulated corners (each corner's
  projector coordinate comes from thousands of decoded pixels; a single pixel's Gray code
  is a whole projector row, quantised to several millimetres of depth at this stand-off),
  its noise bias removed, U and detection limit from draws of the corners' noise, the
  calibration's covariance propagated.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

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
    return min(slopes, key=slopes.get)


@dataclass(frozen=True)
class PoseCheck:
    """One left-out pose: its flatness, and per corner pair on a row or column the
    nominal distance (mm), the measured minus nominal and its U (k = 2)."""

    name: str
    corners: int
    flatness: Estimate
    plane_rms_mm: float
    nominal_mm: np.ndarray
    error_mm: np.ndarray
    U_mm: np.ndarray
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
                "plane_rms_mm": self.plane_rms_mm, "pairs": int(len(self.error_mm)),
                "adjacent_error_rms_mm": float(np.sqrt(np.mean(self.error_mm[adj] ** 2))),
                "adjacent_error_max_mm": float(np.abs(self.error_mm[adj]).max()),
                "adjacent_U_median_mm": float(np.median(self.U_mm[adj])),
                "longest_nominal_mm": float(self.nominal_mm.max()),
                "longest_error_mm": self.error_mm[longest].tolist(), "longest_U_mm": self.U_mm[longest].tolist(),
                "within_U": self.inside, "calibration_rms_px": self.calibration_rms_px,
                "coded_axis": "projector rows" if self.orientation == "horizontal" else "projector columns"}


def check_pose(view: Any, index: int, board: Any, model: RigModel, calibration: CalibrationUncertainty,
               rms_px: dict[str, float]) -> PoseCheck:
    """Triangulate the left-out `view` with `model` and measure it (module docstring)."""
    from calibration.views import correspond

    corr = correspond(board, view, index)
    orientation = coded_orientation(model, view)
    axis = 0 if orientation == "vertical" else 1
    found = corr.projector_corners.found
    pix = corr.detection.image_points[found]
    coded = corr.projector_corners.points[found, axis]
    obj = board.object_points()[corr.detection.ids[found]]
    X = triangulate_corners(model, pix, coded, orientation)
    A_inv = measurement_jacobian(X, model, orientation)
    s_cam, s_proj = rms_px["camera"] / np.sqrt(2.0), rms_px["projector"] / np.sqrt(2.0)
    cov = A_inv @ np.diag([s_cam ** 2, s_cam ** 2, s_proj ** 2]) @ np.transpose(A_inv, (0, 2, 1))
    shifts = calibration.shifts(X, model, {orientation: np.ones(len(X))})
    i, j = np.triu_indices(len(X), 1)
    same_line = np.isclose(obj[i, 0], obj[j, 0]) | np.isclose(obj[i, 1], obj[j, 1])
    i, j = i[same_line], j[same_line]
    d = X[i] - X[j]
    dist = np.linalg.norm(d, axis=1)
    e = d / dist[:, None]
    var = np.einsum("ni,nij,nj->n", e, cov[i] + cov[j], e)
    if shifts is not None:
        var += np.sum(np.einsum("dni,ni->dn", shifts[:, i] - shifts[:, j], e) ** 2, axis=0)
    nominal = np.linalg.norm(obj[i] - obj[j], axis=1)
    flat, rms = _flatness(X, cov, shifts)
    return PoseCheck(view.name, int(found.sum()), flat, rms, nominal, dist - nominal, 2.0 * np.sqrt(var), rms_px,
                     orientation)


def _flatness(X: np.ndarray, cov: np.ndarray, shifts: np.ndarray | None, draws: int = 200,
              seed: int = 0) -> tuple[Estimate, float]:
    """The minimum-zone flatness of the triangulated corners (N, 3) with its U (noise bias
    removed and detection limit from draws of the corners' noise, covariance (N, 3, 3);
    calibration from `shifts` (D, N, 3)), and their RMS distance from their plane."""
    centre = X.mean(axis=0)
    normal = np.linalg.svd(X - centre, full_matrices=False)[2][2]
    L = np.linalg.cholesky(cov + 1e-18 * np.eye(3))
    noise = np.einsum("nij,dnj->dni", L, np.random.default_rng(seed).standard_normal((draws, len(X), 3)))
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
        check = check_pose(view, k, board, result.model, CalibrationUncertainty.from_report(report),
                           {"camera": report["rms_px"]["camera"], "projector": report["rms_px"]["projector"]})
        s = check.summary(board.square_mm)
        say(f"{view.name}: flatness {check.flatness.text()}, adjacent corners error RMS "
            f"{s['adjacent_error_rms_mm']:.3f} mm (U median {s['adjacent_U_median_mm']:.3f} mm), "
            f"{check.inside:.0%} of {s['pairs']} distances within ±U")
        out.append(check)
    return out
