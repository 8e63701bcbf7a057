"""Point samples with normals as registration uses them: a KD-tree beside the points, the
voxel-grid cloud every coarse stage works on, and normal-space sampling for the fine step."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from inspection.downsample import voxel_cells


@dataclass(eq=False)
class Samples:
    """Points (N, 3) with unit normals and their KD-tree."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree = field(init=False)

    def __post_init__(self) -> None:
        self.tree = cKDTree(self.points)


def voxel_grid(points: np.ndarray, normals: np.ndarray, voxel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(centroids, unit mean normals) of the occupied voxels of side `voxel_mm`."""
    cell, counts = voxel_cells(points, voxel_mm)
    p = np.stack([np.bincount(cell, weights=points[:, k], minlength=len(counts)) for k in range(3)], 1)
    n = np.stack([np.bincount(cell, weights=normals[:, k], minlength=len(counts)) for k in range(3)], 1)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    ok = norm[:, 0] > 1e-9
    return (p / counts[:, None])[ok], (n / np.where(norm > 0, norm, 1.0))[ok]


def normal_space_sample(normals: np.ndarray, n: int, rng: np.random.Generator, bins: int = 12) -> np.ndarray:
    """Indices of up to n points drawn without replacement so that their normals spread
    as evenly as the cloud allows over a (bins x 2 bins) grid of directions: the few
    points on walls and in holes, which fix the pose along a large plane, are kept."""
    if len(normals) <= n:
        return np.arange(len(normals))
    theta = np.arccos(np.clip(normals[:, 2], -1.0, 1.0))
    phi = np.arctan2(normals[:, 1], normals[:, 0])
    cell = (np.minimum((theta / np.pi * bins).astype(np.int64), bins - 1) * 2 * bins
            + np.minimum(((phi + np.pi) / (2 * np.pi) * 2 * bins).astype(np.int64), 2 * bins - 1))
    count = np.bincount(cell, minlength=2 * bins * bins)
    key = rng.exponential(size=len(normals)) * count[cell]  # weighted sampling, weight 1/count
    return np.argpartition(key, n - 1)[:n]
