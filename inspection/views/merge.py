"""One cloud of the part from its aligned views, overlapping views fused by precision.

Every view, in the part frame by its aligned pose, contributes its points with their
expected noise sigma (`precision.py`). The part frame is cut into cells of `cell_mm` (about
a view's point spacing, so a view puts about one point in a cell) and each cell's points
are split by the direction their normal faces (six bins: the axis and sign its largest
component has), so the two faces of an edge or of a thin wall that share a cell stay
apart. Each (cell, direction) gives one fused point: the mean of its points weighted by
1 / sigma^2, its normal the same weighted mean (renormalised), and its expected noise
1 / sqrt(sum 1 / sigma^2). Where one view saw the surface a fused point is that view's
point; where views overlap it is their inverse-variance mean, so a surface seen well by one
view and at a grazing angle by another takes the better one's position, and two equally
good views halve the variance.

`platter_plane` finds what the part stands on: the largest plane perpendicular to the
stage's turning axis, below the rest of the cloud (the turntable's top, which turns with the
part and so looks like part of it); points on it or beyond it are not the part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inspection.downsample import voxel_cells
from inspection.errors import CloudError
from inspection.measured_cloud import fit_plane
from inspection.views.view_clouds import ViewCloud


@dataclass(frozen=True, eq=False)
class Merged:
    """The fused cloud: `points`, `normals` (N, 3) part frame, `sigma` (N,) expected noise,
    `views` (N,) how many views each fused point has points from."""

    points: np.ndarray
    normals: np.ndarray
    sigma: np.ndarray
    views: np.ndarray
    cell_mm: float

    def __len__(self) -> int:
        return len(self.points)


def direction_bin(normals: np.ndarray) -> np.ndarray:
    """0..5: the axis of each normal's largest component, times two, plus one if negative."""
    axis = np.argmax(np.abs(normals), axis=1)
    negative = normals[np.arange(len(normals)), axis] < 0
    return 2 * axis + negative


def fuse(views: list[ViewCloud], poses: list[np.ndarray], cell_mm: float) -> Merged:
    """Fuse `views` placed by `poses` (part_from_view) on cells of `cell_mm` (see the module
    docstring)."""
    if not cell_mm > 0:
        raise CloudError("merge", f"cell size must be > 0 mm, got {cell_mm}")
    moved = [v.moved(T) for v, T in zip(views, poses)]
    points = np.concatenate([v.points for v in moved])
    normals = np.concatenate([v.normals for v in moved])
    sigma = np.concatenate([v.sigma for v in moved])
    source = np.concatenate([np.full(len(v), k) for k, v in enumerate(moved)])
    cell, _ = voxel_cells(points, cell_mm)
    _, group = np.unique(cell * 6 + direction_bin(normals), return_inverse=True)
    m = int(group.max()) + 1
    w = 1.0 / np.maximum(sigma, 1e-9) ** 2
    total = np.bincount(group, weights=w, minlength=m)
    # weighted bincounts are float (numpy's stubs say integer)
    fused: np.ndarray = np.stack([np.bincount(group, weights=w * points[:, i], minlength=m) for i in range(3)], axis=1)
    fused /= total[:, None]
    nrm: np.ndarray = np.stack([np.bincount(group, weights=w * normals[:, i], minlength=m) for i in range(3)], axis=1)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    seen = np.zeros((m, len(views)), bool)
    seen[group, source] = True
    return Merged(fused, nrm, 1.0 / np.sqrt(total), seen.sum(axis=1), cell_mm)


def platter_plane(points: np.ndarray, axis_direction: np.ndarray, tolerance_mm: float,
                  seed: int = 0) -> tuple[np.ndarray, float] | None:
    """The plane (n, d), n.x + d = 0 with n along the axis, that the part stands on (see the
    module docstring): RANSAC planes are taken largest first until one is within 10 degrees
    of perpendicular to the turning axis `axis_direction` (part frame) with points standing
    on it and next to none under it (a top face of the part has its sides and the platter
    under it). None when there is none."""
    a = np.asarray(axis_direction, float) / np.linalg.norm(axis_direction)
    rng = np.random.default_rng(seed)
    sample = points[rng.choice(len(points), size=min(len(points), 50000), replace=False)]
    remaining = sample
    for _ in range(4):
        if len(remaining) < 100:
            break
        plane, inliers = fit_plane(remaining, tolerance_mm, seed, 1000)
        n, d = np.asarray(plane[:3]), float(plane[3])
        if abs(n @ a) > np.cos(np.radians(10.0)):
            if n @ a < 0:
                n, d = -n, -d
            height = sample @ n + d
            if (height < -tolerance_mm).mean() < 0.02 and (height > tolerance_mm).mean() > 0.02:
                return n, d  # something stands on it, nothing lies under it
        remaining = remaining[~inliers]
    return None
