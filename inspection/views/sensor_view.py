"""A view as its sensor saw it: which rays it measured, how far along each, and how noisy:
what another view's points are judged against (`pair_evidence`).

A session's cloud is in its camera's frame with every point on its pixel: its depth image
is those points on the camera's own grid (`Pinhole`, distortion and all). A cloud file in
front of its viewpoint (`ScanCloud.viewpoint`, the origin for a cloud with every z > 0)
gets a virtual camera there: a distortion-free pinhole whose pixel is the cloud's median
angular spacing, so that about one point falls on a pixel. A cloud without a viewpoint has
no sensor to judge by (`SensorView.build` returns None, and the caller says so).

What a pixel's measurement is worth (`smooth`): the pixel and its 8 neighbours all measured
and the neighbours on the centre's tangent plane within the noise (|n . (x_nb - x_c)| <=
`SMOOTH_Z` sqrt(2) sigma: two noisy points; `SMOOTH_Z` = 3.84 is the two-sided 1e-3
quantile over the 8 neighbours). A pixel at a silhouette, an edge or a depth step fails it:
there a point's residual to "the" surface is not defined, so it is no evidence either way.

The noise (`sigma_mm`, along the surface normal) is estimated from the view's own points,
not assumed: the second difference of neighbouring points along rows and columns of the
depth image, projected on the normal, n . (x[u-s] - 2 x[u] + x[u+s]), vanishes on a plane
whatever the spacing and has variance 6 sigma^2 for independent noise; s = `STRIDE` pixels
apart, past the camera blur's correlation of neighbouring pixels. Robust (median absolute
value) over the smooth pixels, so edges and spikes do not count. `max_incidence_deg` is the
incidence the sensor was seen to measure: the 99th percentile of the angles between its
points' normals and their rays; a surface turned further from it is not expected to be seen,
and a pixel measured beyond it is no evidence either (seen edge-on, a surface's points spread
along the rays and its normal is anyone's guess: on simulated turntable views, normals at
88 deg came out turned half a turn from the truth, and a right pose "disagreed" there).
Units mm, degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from inspection.measured_cloud import ScanCloud
from scanner.geometry import Pinhole

SMOOTH_Z = 3.84  # two-sided z of 1e-3 over 8 neighbours (Bonferroni): a smooth pixel's neighbours within it
STRIDE = 2  # pixels between the points of a second difference (the noise estimate)
INCIDENCE_QUANTILE = 0.99  # the share of a view's own points within its incidence limit
MAX_VIRTUAL_PX = 4096  # a virtual camera's largest side (px): its pixel grows rather than exceed it


@dataclass(frozen=True, eq=False)
class SensorView:
    """A view's measurements on its camera's grid (camera frame = the cloud's frame, mm):
    `index[r, c]` the cloud point seen at a pixel (-1: none), `points`/`normals` the cloud's,
    `smooth` (H, W) pixels whose measurement is evidence and `point_smooth` (N,) the points
    measured there, `sigma_mm` the noise along the normal, `max_incidence_deg` the incidence
    limit, `camera` real or `virtual`."""

    camera: Pinhole
    virtual: bool
    index: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    smooth: np.ndarray
    point_smooth: np.ndarray
    sigma_mm: float
    max_incidence_deg: float

    @classmethod
    def build(cls, scan: ScanCloud, camera: Pinhole | None = None) -> SensorView | None:
        """The SensorView of `scan` (`camera`: its session's, every point on its pixel),
        None when the scan says nothing of where its sensor was."""
        if camera is not None and scan.pixels is not None:
            pixels, virtual = scan.pixels, False
        elif scan.viewpoint is not None and np.allclose(scan.viewpoint, 0.0) and np.all(scan.points[:, 2] > 0):
            camera, pixels = virtual_camera(scan.points)
            virtual = True
        else:
            return None
        h, w = camera.height, camera.width
        index = np.full((h, w), -1, np.int64)
        rng = np.linalg.norm(scan.points, axis=1)
        order = np.argsort(-rng)  # the nearest point on a pixel is the one written last: the one seen
        index[pixels[order, 1], pixels[order, 0]] = order
        smooth, sigma = _smooth_and_noise(scan.points, scan.normals, index)
        rays = scan.points / np.maximum(rng, 1e-12)[:, None]
        cos_inc = np.clip(-np.einsum("ij,ij->i", scan.normals, rays), -1.0, 1.0)
        max_inc = float(np.degrees(np.arccos(np.quantile(cos_inc, 1.0 - INCIDENCE_QUANTILE))))
        seen = index >= 0
        smooth &= seen & (cos_inc[np.where(seen, index, 0)] >= np.cos(np.radians(max_inc)))
        point_smooth = np.zeros(len(scan.points), bool)
        point_smooth[index[smooth]] = True
        return cls(camera, virtual, index, scan.points, scan.normals, smooth, point_smooth, sigma, max_inc)

    def pixels_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(pixels (N, 2) int column, row; inside (N,) bool): where `points` (this view's
        frame) fall on its grid; points behind the camera or off the image are not inside."""
        ahead = points[:, 2] > 1e-6
        px = np.full((len(points), 2), -1, np.int64)
        if ahead.any():
            px[ahead] = np.rint(self.camera.project(points[ahead])).astype(np.int64)
        inside = ahead & (px[:, 0] >= 0) & (px[:, 0] < self.camera.width) & (px[:, 1] >= 0) & \
            (px[:, 1] < self.camera.height)
        return np.where(inside[:, None], px, 0), inside


def virtual_camera(points: np.ndarray) -> tuple[Pinhole, np.ndarray]:
    """(camera, pixels (N, 2)) of a cloud seen from the origin (every z > 0): a pinhole
    without distortion whose pixel is the points' median angular spacing (their nearest
    neighbour in x/z, y/z), at most `MAX_VIRTUAL_PX` a side."""
    from scipy.spatial import cKDTree

    xy = points[:, :2] / points[:, 2:3]
    probe = np.linspace(0, len(xy) - 1, min(len(xy), 4000)).astype(np.int64)
    d, _ = cKDTree(xy).query(xy[probe], k=2)
    spacing = float(np.median(d[:, 1]))
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    f = 1.0 / max(spacing, float(np.max(hi - lo)) / (MAX_VIRTUAL_PX - 2), 1e-12)
    size = np.ceil((hi - lo) * f).astype(np.int64) + 2
    K = np.array([[f, 0.0, 0.5 - lo[0] * f], [0.0, f, 0.5 - lo[1] * f], [0.0, 0.0, 1.0]])
    camera = Pinhole(int(size[0]), int(size[1]), K)
    return camera, np.rint(xy * f + K[:2, 2]).astype(np.int64)


def _smooth_and_noise(points: np.ndarray, normals: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, float]:
    """(smooth (H, W), sigma mm): see the module docstring."""
    seen = index >= 0
    at = np.where(seen, index, 0)
    x = np.where(seen[..., None], points[at], np.nan)
    n = np.where(seen[..., None], normals[at], np.nan)
    pad = np.pad(x, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
    h, w = seen.shape
    worst = np.zeros((h, w))
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                off = np.abs(np.einsum("hwk,hwk->hw", pad[1 + dr:1 + dr + h, 1 + dc:1 + dc + w] - x, n))
                worst = np.fmax(worst, np.where(np.isnan(off), np.inf, off))
    s = STRIDE
    d2 = [np.einsum("hwk,hwk->hw", x[:, :-2 * s] - 2 * x[:, s:-s] + x[:, 2 * s:], n[:, s:-s]),
          np.einsum("hwk,hwk->hw", x[:-2 * s] - 2 * x[s:-s] + x[2 * s:], n[s:-s])]
    values = np.concatenate([v[np.isfinite(v)] for v in d2])
    sigma = float(1.4826 * np.median(np.abs(values)) / np.sqrt(6.0)) if len(values) >= 50 else float("nan")
    smooth = seen & (worst <= SMOOTH_Z * np.sqrt(2.0) * sigma)
    smooth = ndimage.binary_erosion(seen, np.ones((3, 3), bool)) & smooth
    return smooth, sigma
