"""Projector coordinates of board corners from decoded structured light (Moreno & Taubin).

Every camera pixel on the board has decoded projector coordinates (u, v) (phase shift in
both fringe orientations, or Gray code). Around each board corner the board is flat, so
camera pixels and projector pixels are related by a homography; it is fitted to the decoded
pixels in a window around the corner and evaluated at the corner's camera position. A local
homography follows the lens distortion of both devices where one global mapping could not,
and averages thousands of decoded pixels into one sub-pixel projector point.

The fit is a weighted, normalised direct linear transform (weights: the decoded
coordinates' precision, e.g. fringe modulation squared), repeated once without the pixels
whose residual is an outlier (decoding errors at square edges, specularities). A corner
needs decoded pixels on every side of it, so its point is interpolated, not extrapolated.
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
    decoded pixels used, and the RMS residual of the local fit (projector px)."""

    points: np.ndarray
    found: np.ndarray
    pixels_used: np.ndarray
    fit_rms_px: np.ndarray


def _homography(src: np.ndarray, dst: np.ndarray, w_u: np.ndarray, w_v: np.ndarray) -> np.ndarray:
    """The 3x3 H with dst ~ H·src minimising the weighted algebraic error of normalised points."""
    n = len(src)
    A = np.zeros((2 * n, 9))
    x, y, u, v = src[:, 0], src[:, 1], dst[:, 0], dst[:, 1]
    A[:n, 0], A[:n, 1], A[:n, 2] = x, y, 1.0
    A[:n, 6], A[:n, 7], A[:n, 8] = -u * x, -u * y, -u
    A[n:, 3], A[n:, 4], A[n:, 5] = x, y, 1.0
    A[n:, 6], A[n:, 7], A[n:, 8] = -v * x, -v * y, -v
    w = np.concatenate([w_u, w_v])
    M = A.T @ (A * w[:, None])
    _, vecs = np.linalg.eigh(M)
    return vecs[:, 0].reshape(3, 3)


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = pts @ H[:, :2].T + H[:, 2]
    return q[:, :2] / q[:, 2:3]


def local_homography_points(corners: np.ndarray, u: np.ndarray, v: np.ndarray, radius_px: float,
                            weight_u: np.ndarray | None = None, weight_v: np.ndarray | None = None) -> ProjectorCorners:
    """Projector coordinates of camera `corners` (N, 2) from per-pixel projector coordinate
    maps `u`, `v` (H, W, NaN where not decoded), fitting a homography over the pixels within
    `radius_px` of each corner. Weights (H, W) default to 1."""
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
    for i, (cx, cy) in enumerate(corners):  # one small fit per board corner
        ix, iy = int(round(cx)) + dx, int(round(cy)) + dy
        ok = (ix >= 0) & (iy >= 0) & (ix < w) & (iy < h)
        ix, iy = ix[ok], iy[ok]
        pu, pv = u[iy, ix].astype(np.float64), v[iy, ix].astype(np.float64)
        good = np.isfinite(pu) & np.isfinite(pv)
        sx, sy = dx[ok][good], dy[ok][good]
        sides = min((sx < 0).sum(), (sx > 0).sum(), (sy < 0).sum(), (sy > 0).sum())
        if good.sum() < MIN_WINDOW_FILL * len(dx) or sides < MIN_SIDE_FILL * len(dx):
            continue
        src = np.stack([(ix[good] - cx) / radius_px, (iy[good] - cy) / radius_px], axis=1)
        dst_px = np.stack([pu[good], pv[good]], axis=1)
        centre = np.median(dst_px, axis=0)
        scale = max(float(np.abs(dst_px - centre).max()), 1e-9)
        dst = (dst_px - centre) / scale
        ww_u, ww_v = wu[iy, ix][good].astype(np.float64), wv[iy, ix][good].astype(np.float64)
        keep = np.ones(len(src), dtype=bool)
        for _ in range(2):  # fit, drop outliers, fit again
            H = _homography(src[keep], dst[keep], ww_u[keep], ww_v[keep])
            res = np.linalg.norm(_apply(H, src) - dst, axis=1) * scale
            spread = 1.4826 * np.median(res[keep])
            keep = res <= max(OUTLIER_SIGMAS * spread, MIN_OUTLIER_PX)
        if keep.sum() < MIN_WINDOW_FILL * len(dx):
            continue
        points[i] = _apply(H, np.zeros((1, 2)))[0] * scale + centre
        used[i] = int(keep.sum())
        fit_rms[i] = float(np.sqrt(np.mean(res[keep] ** 2)))
    return ProjectorCorners(points, np.isfinite(points[:, 0]), used, fit_rms)
