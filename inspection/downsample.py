"""Voxel-grid downsampling: plain voxel averaging, or the density-centre selection of
paper 001 (Deng et al. 2023, Eq. 9-16) with its voxel size from the point density.

Paper 001, section 3.1:
  - Eq. 11-12: the bounding box of the cloud, each side widened by a margin λ,
    V = Lx·Ly·Lz (Eq. 12 prints y for the z extent: a typo; z is used here);
  - Eq. 13: the voxel side L = α·(s·V/N)^(1/3) — it grows with the mean volume per point
    (Eq. 9-10 write it through a "regulatory factor" g = sqrt(N/V) that does not
    substitute into Eq. 13 as printed; Eq. 13 is the one implemented);
  - Eq. 14-15: each point's grid code from its offset to the box corner divided by L
    (floor here, where the paper writes ceil: the same cells but for points exactly on a
    cell face, which the paper's ceil would put alone in a cell of index 0);
  - Eq. 16: the density centre of each cell, the mean of its points; then points are kept
    or removed by their distance to it — here exactly one point is kept per cell, the one
    nearest the density centre, so the result is a subset of the input (its normals,
    colours and labels stay valid) spread like the voxel centroids.

Voxel averaging returns the centroids themselves (new points, not a subset).
Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from inspection.errors import CloudError, SegmentationError

METHODS = ("average", "density_centre")
QUERY_CELLS = 64  # cells along a cloud's longest side whose order its points are asked in (`coherent_order`)


@dataclass(frozen=True, eq=False)
class Downsampled:
    """`points` (M, 3) mm, one per occupied voxel; `inverse` (N,) the output row of every
    input point (its voxel); `indices` (M,) the input rows kept (density-centre selection
    only, else None); `voxel_mm` the voxel side used."""

    points: np.ndarray
    inverse: np.ndarray
    indices: np.ndarray | None
    voxel_mm: float

    def __len__(self) -> int:
        return len(self.points)


def density_voxel_size(points: np.ndarray, alpha: float = 1.0, scale: float = 1.0,
                       margin_mm: float | None = None) -> float:
    """The voxel side L (mm) of paper 001 Eq. 13, L = α·(s·Lx·Ly·Lz / N)^(1/3), each
    extent widened by the margin λ of Eq. 12 (`margin_mm`; default 1% of the largest
    extent, so a flat cloud still has a volume)."""
    pts = _checked(points)
    if not (alpha > 0 and scale > 0):
        raise SegmentationError(f"alpha and scale must be > 0, got alpha={alpha}, scale={scale}")
    extent = pts.max(axis=0) - pts.min(axis=0)
    lam = 0.01 * float(extent.max()) if margin_mm is None else float(margin_mm)
    if not lam >= 0:
        raise SegmentationError(f"margin_mm must be >= 0, got {margin_mm}")
    volume = float(np.prod(extent + lam))
    if not volume > 0:
        raise CloudError("downsample", "all points coincide: the voxel size cannot be derived from the density; "
                                       "give voxel_mm")
    return float(alpha * np.cbrt(scale * volume / len(pts)))


def voxel_cells(points: np.ndarray, voxel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(cell (N,) int64 dense voxel index of every point, counts (M,) points per voxel):
    the grid codes of Eq. 14-15, numbered 0..M-1 in code order."""
    _, cell, counts = _voxel_sort(_checked(points), voxel_mm)
    return cell, counts


def _voxel_sort(pts: np.ndarray, voxel_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(order (N,): the points sorted by voxel code, stably; cell (N,); counts (M,)), as
    `voxel_cells`, from one sort."""
    if not (np.isfinite(voxel_mm) and voxel_mm > 0):
        raise SegmentationError(f"voxel size must be a positive length in mm, got {voxel_mm}")
    code = np.floor((pts - pts.min(axis=0)) / voxel_mm).astype(np.int64)
    dims = code.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) >= 2.0 ** 62:
        raise SegmentationError(f"voxel size {voxel_mm} mm is too small for a cloud of extent "
                                f"{np.ptp(pts, axis=0).round(3).tolist()} mm")
    key = (code[:, 0] * dims[1] + code[:, 1]) * dims[2] + code[:, 2]
    order = np.argsort(key, kind="stable")
    sk = key[order]
    first = np.r_[True, sk[1:] != sk[:-1]]
    cell = np.empty(len(key), dtype=np.int64)
    cell[order] = np.cumsum(first) - 1
    counts = np.diff(np.r_[np.flatnonzero(first), len(key)])
    return order, cell, counts


def downsample(points: np.ndarray, voxel_mm: float | None = None, method: str = "average", *,
               alpha: float = 1.0, scale: float = 1.0) -> Downsampled:
    """One point per occupied voxel of side `voxel_mm` (default: Eq. 13 with `alpha`,
    `scale`): the voxel centroid (`method="average"`) or the input point nearest it
    (`"density_centre"`, Eq. 16; the first in input order among equally near ones)."""
    if method not in METHODS:
        raise SegmentationError(f"unknown downsampling method {method!r}; use one of {METHODS}")
    pts = _checked(points)
    size = density_voxel_size(pts, alpha, scale) if voxel_mm is None else float(voxel_mm)
    order, cell, counts = _voxel_sort(pts, size)
    # weighted bincounts are float (numpy's stubs say integer)
    centre: np.ndarray = np.stack([np.bincount(cell, weights=pts[:, k], minlength=len(counts)) for k in range(3)],
                                  axis=1)
    centre /= counts[:, None]
    if method == "average":
        return Downsampled(centre, cell, None, size)
    off = pts[order] - centre[cell[order]]
    keep = order[first_minimum_per_run(cell[order], np.einsum("ij,ij->i", off, off))]
    return Downsampled(pts[keep], cell, keep, size)


def coherent_order(points: np.ndarray) -> np.ndarray:
    """Indices putting `points` (N, 3) in the order of the cells (`QUERY_CELLS` along their
    longest side) they lie in, for `query_in_order`: a scan in random order (a subsample, a
    view of CAD samples) asked so is 1.4x (4000 points) to 4x (40 000 points) faster against
    the demo part's 285 k dense samples. A rigid motion of the points keeps it coherent."""
    if not len(points):
        return np.zeros(0, np.int64)
    cell = max(float(np.ptp(points, axis=0).max()) / QUERY_CELLS, 1e-9)
    c = ((points - points.min(axis=0)) / cell).astype(np.int64)
    n = c.max(axis=0) + 1
    return np.argsort((c[:, 0] * n[1] + c[:, 1]) * n[2] + c[:, 2])


def query_in_order(tree: cKDTree, q: np.ndarray, order: np.ndarray, **options: Any) -> tuple[np.ndarray, np.ndarray]:
    """`tree.query(q, **options)` with the points `q` (N, 3) asked in `order`
    (`coherent_order`): each point's answer is its own, so the same as asked in any order,
    but the tree's branches are still in cache from the point before."""
    d, j = tree.query(q[order], **options)
    dist, idx = np.empty_like(d), np.empty_like(j)
    dist[order], idx[order] = d, j
    return dist, idx


def first_minimum_per_run(key: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Positions of the least of `values` in each run of equal `key` (N,) (runs adjacent,
    e.g. sorted by key), the first of equals: a stable sort by (key, value)'s first of
    each run, at a fraction of its time."""
    if not len(key):
        return np.zeros(0, np.int64)
    new = np.r_[True, key[1:] != key[:-1]]
    run = np.cumsum(new) - 1
    hit = np.flatnonzero(values == np.minimum.reduceat(values, np.flatnonzero(new))[run])
    return hit[np.r_[True, run[hit][1:] != run[hit][:-1]]]


def _checked(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CloudError("downsample", f"expected (N, 3) points, got shape {pts.shape}")
    if len(pts) == 0:
        raise CloudError("downsample", "the cloud is empty")
    if not np.isfinite(pts).all():
        raise CloudError("downsample", "the cloud has non-finite coordinates; drop invalid points first")
    return pts
