"""A triangle mesh from an organised cloud: neighbouring valid camera pixels joined into
two triangles per 2 x 2 cell, wound to face the camera, cells spanning a depth jump (an
occluding edge, not a surface) left open."""

from __future__ import annotations

import numpy as np

JUMP_SPACINGS = 8.0
"""Default depth-jump limit in units of the cloud's median neighbour spacing: a cell whose
corners differ in depth by more is an edge between surfaces, not a surface."""


def grid_triangles(index: np.ndarray, depth_mm: np.ndarray, max_jump_mm: float) -> np.ndarray:
    """Triangles (T, 3) of point indices from `index` (H, W): each pixel's point index, -1
    where there is none. Each 2 x 2 cell of pixels a b / c d gives triangles (a, c, b) and
    (b, c, d) when their three corners are valid and their depths (`depth_mm` per point,
    its distance from the camera centre) span at most `max_jump_mm`. Winding: counter-clockwise seen
    from the camera (x right, y down, z forward), so normals face it."""
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, :-1].ravel(), index[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, c, b], axis=1), np.stack([b, c, d], axis=1)])
    tris = tris[(tris >= 0).all(axis=1)]
    z = depth_mm[tris]
    return tris[(z.max(axis=1) - z.min(axis=1)) <= max_jump_mm]


def neighbour_spacing(index: np.ndarray, points: np.ndarray) -> float:
    """The median distance (mm) between horizontally neighbouring valid pixels' points."""
    a, b = index[:, :-1].ravel(), index[:, 1:].ravel()
    both = (a >= 0) & (b >= 0)
    if not both.any():
        return 0.0
    return float(np.median(np.linalg.norm(points[a[both]] - points[b[both]], axis=1)))
