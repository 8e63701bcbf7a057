"""Local shape descriptors at keypoints: FPFH (Open3D) and SHOT (vectorised numpy).

SHOT (Signature of Histograms of OrienTations, Tombari, Salti and Di Stefano 2010):
a repeatable local reference frame from the distance-weighted covariance of the support
(eigenvectors x, y, z by decreasing eigenvalue; x and z turned toward the majority of the
support, y = z x x); the spherical support split into 8 azimuth x 2 elevation x 2 radial
volumes, each a histogram of 11 bins of cos(angle between the neighbour's normal and z);
every neighbour spread over the neighbouring bins of all four dimensions (quadrilinear
interpolation); the 352 values normalised to unit length.

Both work on a cloud with unit normals. Neighbourhoods are the `max_nn` nearest points
within `radius` (the voxel grid the clouds are sampled on makes that the whole support).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

SHOT_AZIMUTH, SHOT_ELEVATION, SHOT_RADIAL, SHOT_COS = 8, 2, 2, 11
SHOT_DIM = SHOT_AZIMUTH * SHOT_ELEVATION * SHOT_RADIAL * SHOT_COS  # 352
FPFH_DIM = 33


def neighbourhoods(tree: cKDTree, centres: np.ndarray, radius: float, max_nn: int) -> tuple[np.ndarray, np.ndarray]:
    """(index (K, max_nn), valid (K, max_nn)) of the points within `radius` of each centre."""
    d, idx = tree.query(centres, k=max_nn, distance_upper_bound=radius, workers=-1)
    valid = np.isfinite(d)
    return np.where(valid, idx, 0), valid


def local_frames(points: np.ndarray, centres: np.ndarray, idx: np.ndarray, valid: np.ndarray,
                 radius: float) -> np.ndarray:
    """SHOT's local reference frames (K, 3, 3), rows x, y, z; NaN where the support has
    fewer than 5 points."""
    d = points[idx] - centres[:, None, :]
    dist = np.linalg.norm(d, axis=2)
    w = np.where(valid, np.maximum(radius - dist, 0.0), 0.0)
    cov = np.einsum("kn,kni,knj->kij", w, d, d) / np.maximum(w.sum(axis=1), 1e-12)[:, None, None]
    _, vec = np.linalg.eigh(cov)  # ascending eigenvalues: columns z, y, x
    x, z = vec[:, :, 2], vec[:, :, 0]
    for axis in (x, z):  # disambiguate the sign: toward the majority of the support
        s = np.einsum("kni,ki->kn", d, axis)
        flip = (np.where(valid, s >= 0, False).sum(1) < np.where(valid, s < 0, False).sum(1))
        axis[flip] *= -1.0
    frames = np.stack([x, np.cross(z, x), z], axis=1)
    frames[valid.sum(axis=1) < 5] = np.nan
    return frames


def _linear_bins(c: np.ndarray, n: int, circular: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bin coordinate c (bin b spans [b, b+1)) -> (bin a, weight a, bin b, weight b) of
    linear interpolation between bin centres."""
    t = c - 0.5
    lo = np.floor(t)
    frac = t - lo
    lo = lo.astype(np.int64)
    hi = lo + 1
    if circular:
        return np.mod(lo, n), 1.0 - frac, np.mod(hi, n), frac
    w_lo = np.where(lo < 0, 0.0, np.where(hi > n - 1, 1.0, 1.0 - frac))
    return np.clip(lo, 0, n - 1), w_lo, np.clip(hi, 0, n - 1), 1.0 - w_lo


def shot(points: np.ndarray, normals: np.ndarray, centres: np.ndarray, radius: float,
         tree: cKDTree | None = None, max_nn: int = 128) -> np.ndarray:
    """SHOT descriptors (K, 352) of the support `radius` (mm) around each centre (K, 3),
    computed from `points`/`normals` (N, 3); rows of zeros where the frame is undefined."""
    tree = cKDTree(points) if tree is None else tree
    idx, valid = neighbourhoods(tree, centres, radius, max_nn)
    frames = local_frames(points, centres, idx, valid, radius)
    ok = np.isfinite(frames[:, 0, 0])
    frames = np.nan_to_num(frames)
    local = np.einsum("kab,knb->kna", frames, points[idx] - centres[:, None, :])
    r = np.linalg.norm(local, axis=2)
    valid &= (r > 1e-9) & ok[:, None]
    cosang = np.clip(np.einsum("knb,kb->kn", normals[idx], frames[:, 2]), -1.0, 1.0)
    azim = np.mod(np.arctan2(local[..., 1], local[..., 0]), 2 * np.pi)
    elev = np.arctan2(local[..., 2], np.hypot(local[..., 0], local[..., 1]))
    k, n = np.nonzero(valid)
    dims = [_linear_bins(azim[k, n] / (2 * np.pi / SHOT_AZIMUTH), SHOT_AZIMUTH, True),
            _linear_bins((elev[k, n] + np.pi / 2) / (np.pi / SHOT_ELEVATION), SHOT_ELEVATION, False),
            _linear_bins(r[k, n] / (radius / SHOT_RADIAL), SHOT_RADIAL, False),
            _linear_bins((cosang[k, n] + 1.0) / 2.0 * SHOT_COS, SHOT_COS, False)]
    sizes = (SHOT_AZIMUTH, SHOT_ELEVATION, SHOT_RADIAL, SHOT_COS)
    hist = np.zeros(len(centres) * SHOT_DIM)
    for corner in range(16):  # the 2^4 neighbouring bins of quadrilinear interpolation
        flat = k * SHOT_DIM
        weight = np.ones(len(k))
        stride = SHOT_DIM
        for dim, (size, (b0, w0, b1, w1)) in enumerate(zip(sizes, dims)):
            stride //= size
            upper = (corner >> dim) & 1
            flat = flat + (b1 if upper else b0) * stride
            weight = weight * (w1 if upper else w0)
        hist += np.bincount(flat, weights=weight, minlength=len(hist))
    per_centre = hist.reshape(len(centres), SHOT_DIM)
    norm = np.linalg.norm(per_centre, axis=1, keepdims=True)
    return np.where(norm > 0, per_centre / np.where(norm > 0, norm, 1.0), 0.0)


def fpfh(points: np.ndarray, normals: np.ndarray, keypoints: np.ndarray, radius: float,
         max_nn: int = 128) -> np.ndarray:
    """Open3D's FPFH (K, 33) of the points indexed by `keypoints`, from neighbourhoods of
    `radius` (mm) in `points`/`normals`; each row normalised to unit length."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.normals = o3d.utility.Vector3dVector(normals)
    # only the keypoints' histograms (and their neighbours'), which Open3D returns in
    # ascending index order
    keys, back = np.unique(np.asarray(keypoints, dtype=np.int64), return_inverse=True)
    if not len(keys):
        return np.zeros((0, 33))
    f = o3d.pipelines.registration.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius, max_nn),
                                                        keys.tolist())
    d = np.asarray(f.data).T[back.ravel()]
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return np.where(norm > 0, d / np.where(norm > 0, norm, 1.0), 0.0)
