"""Projector coordinates of board corners from decoded structured light (after Moreno &
Taubin).

Every camera pixel on the board has decoded projector coordinates (u, v) (phase shift in
both fringe orientations, or Gray code). Around each board corner the mapping from camera
pixels to projector pixels is smooth; it is fitted to the decoded pixels in a window around
the corner and evaluated at the corner's camera position, averaging thousands of decoded
pixels into one sub-pixel projector point.

Moreno & Taubin fit a local homography, exact for a plane seen by two pinhole devices. With
lens distortion the mapping curves within the window, and a homography fitted over a
symmetric window then misses the corner by the curvature's mean: 0.4-1 thousandths of a
projector pixel on the simulated bench, the same in every corner of a view, which the joint
refinement (it weights the decoding by its small noise) reads as signal. The fit here is a
quadratic polynomial in the camera offset, each projector coordinate on its own: on a
symmetric window its value at the centre is unbiased for any smooth mapping up to the third
order (odd terms cancel), and it leaves no bias on the bench (< 1e-5 px) at the cost of a
little more noise (the decoding's 0.0019 x 0.0036 px become 0.0025 x 0.0045 px).

The fit is weighted least squares (weights: the decoded coordinates' precision, e.g.
fringe modulation squared), repeated once without the pixels whose residual is an outlier
(decoding errors at square edges, specularities). A corner needs decoded pixels on every
side of it, so its point is interpolated, not extrapolated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_WINDOW_FILL = 0.15  # a corner needs decoded pixels over this fraction of its window (1/2: one colour of squares)
MIN_SIDE_FILL = 0.05  # … and on each side of it (left, right, above, below): a fit is interpolated, never extrapolated
OUTLIER_SIGMAS = 4.0
MIN_OUTLIER_PX = 0.5


@dataclass(frozen=True, eq=False)
class ProjectorCorners:
    """Per corner: projector pixel (N, 2) (NaN where not found), whether it was found,
    decoded pixels used, the RMS residual of the local fit (projector px), and `jacobian`
    (N, 2, 2): ∂(projector px)/∂(camera px) of the local fit at the corner. The projector
    pixel is the fit evaluated where the camera found the corner, so an error e of the
    camera corner moves it by `jacobian` @ e: the two devices' errors of one corner are
    correlated (`calibration.stereo.CornerErrorModel`)."""

    points: np.ndarray
    found: np.ndarray
    pixels_used: np.ndarray
    fit_rms_px: np.ndarray
    jacobian: np.ndarray


def _quadratic_design(s: np.ndarray) -> np.ndarray:
    """Columns 1, x, y, x², xy, y² of offsets `s` (N, 2)."""
    x, y = s[:, 0], s[:, 1]
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)


def _weighted_fit(M: np.ndarray, values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Coefficients (6,) of the weighted least-squares fit M @ c ≈ values."""
    root = np.sqrt(weights)
    return np.linalg.lstsq(M * root[:, None], values * root, rcond=None)[0]


def local_projector_points(corners: np.ndarray, u: np.ndarray, v: np.ndarray, radius_px: float,
                           weight_u: np.ndarray | None = None, weight_v: np.ndarray | None = None) -> ProjectorCorners:
    """Projector coordinates of camera `corners` (N, 2) from per-pixel projector coordinate
    maps `u`, `v` (H, W, NaN where not decoded), fitting a quadratic over the pixels within
    `radius_px` of each corner (module docstring). Weights (H, W) default to 1."""
    h, w = u.shape
    r = int(np.ceil(radius_px))
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1].reshape(2, -1)
    inside = dx * dx + dy * dy <= radius_px ** 2
    dx, dy = dx[inside], dy[inside]
    wu = np.ones_like(u) if weight_u is None else weight_u
    wv = np.ones_like(v) if weight_v is None else weight_v
    n = len(corners)
    points = np.full((n, 2), np.nan)
    used = np.zeros(n, dtype=np.int64)
    fit_rms = np.full(n, np.nan)
    jacobian = np.full((n, 2, 2), np.nan)
    for i, (cx, cy) in enumerate(corners):  # one small fit per board corner
        ix, iy = round(cx) + dx, round(cy) + dy
        ok = (ix >= 0) & (iy >= 0) & (ix < w) & (iy < h)
        ix, iy = ix[ok], iy[ok]
        pu, pv = u[iy, ix].astype(np.float64), v[iy, ix].astype(np.float64)
        good = np.isfinite(pu) & np.isfinite(pv)
        sx, sy = dx[ok][good], dy[ok][good]
        sides = min((sx < 0).sum(), (sx > 0).sum(), (sy < 0).sum(), (sy > 0).sum())
        if good.sum() < MIN_WINDOW_FILL * len(dx) or sides < MIN_SIDE_FILL * len(dx):
            continue
        M = _quadratic_design(np.stack([(ix[good] - cx) / radius_px, (iy[good] - cy) / radius_px], axis=1))
        dst = np.stack([pu[good], pv[good]], axis=1)
        weights = (wu[iy, ix][good].astype(np.float64), wv[iy, ix][good].astype(np.float64))
        keep = np.ones(len(dst), dtype=bool)
        for _ in range(2):  # fit, drop outliers, fit again
            coef = np.stack([_weighted_fit(M[keep], dst[keep, k], weights[k][keep]) for k in range(2)])  # (2, 6)
            res = np.linalg.norm(M @ coef.T - dst, axis=1)
            spread = 1.4826 * np.median(res[keep])
            keep = res <= max(OUTLIER_SIGMAS * spread, MIN_OUTLIER_PX)
        if keep.sum() < MIN_WINDOW_FILL * len(dx):
            continue
        points[i] = coef[:, 0]
        used[i] = int(keep.sum())
        fit_rms[i] = float(np.sqrt(np.mean(res[keep] ** 2)))
        jacobian[i] = coef[:, 1:3] / radius_px
    return ProjectorCorners(points, np.isfinite(points[:, 0]), used, fit_rms, jacobian)
