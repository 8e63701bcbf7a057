"""Coarse poses by the normal distributions transform (paper 001 Eq. 23-26): the model as
normal distributions on a voxel grid, the score maximised by Newton steps from the 24
axis-aligned turns of the scan about its centroid, on coarse-to-fine cells."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from inspection.registration.rigid import distinct_poses, transform_points, twist_matrix
from inspection.registration.settings import RegistrationSettings
from inspection.registration.target import ModelTarget

NdtGrid = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # lo, dims, codes, mu, icov


def ndt_grid(points: np.ndarray, cell: float) -> NdtGrid:
    """Paper 001 Eq. 23-24: per voxel of side `cell` holding at least 5 model points, the
    mean and the (regularised) inverse covariance; (lo, dims, codes (sorted), mu, icov)."""
    key = np.floor(points / cell).astype(np.int64)
    lo = key.min(axis=0)
    dims = key.max(axis=0) - lo + 1
    code = ((key[:, 0] - lo[0]) * dims[1] + (key[:, 1] - lo[1])) * dims[2] + (key[:, 2] - lo[2])
    uniq, inv, counts = np.unique(code, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    mu = np.stack([np.bincount(inv, weights=points[:, k]) for k in range(3)], 1) / counts[:, None]
    d = points - mu[inv]
    cov = np.zeros((len(uniq), 3, 3))
    np.add.at(cov, inv, np.einsum("ni,nj->nij", d, d))
    cov /= np.maximum(counts - 1, 1)[:, None, None]
    w, v = np.linalg.eigh(cov)
    w = np.maximum(w, 1e-2 * w[:, 2:3] + (0.05 * cell) ** 2)  # keep flat cells invertible
    icov = np.einsum("kij,kj,klj->kil", v, 1.0 / w, v)
    good = counts >= 5
    return lo, dims, uniq[good], mu[good], icov[good]


def ndt_cells(q: np.ndarray, grid: NdtGrid, cell: float) -> np.ndarray:
    """Index into the grid's cells of each point's voxel, -1 where it has none."""
    lo, dims, codes, _, _ = grid
    if not len(codes):   # no cell holds enough points
        return np.full(len(q), -1)
    key = np.floor(q / cell).astype(np.int64) - lo
    inside = np.all((key >= 0) & (key < dims), axis=1)
    code = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    pos = np.clip(np.searchsorted(codes, code), 0, len(codes) - 1)
    return np.where(inside & (codes[pos] == code), pos, -1)


def ndt_refine(src: np.ndarray, T: np.ndarray, grid: NdtGrid, cell: float, iterations: int) -> tuple[np.ndarray, float]:
    """Newton-like ascent of the NDT score (Eq. 25-26) from pose T; (pose, score)."""
    mu, icov = grid[3], grid[4]
    score = 0.0
    for _ in range(iterations):
        q = transform_points(T, src)
        cid = ndt_cells(q, grid, cell)
        ok = cid >= 0
        if ok.sum() < 10:
            return T, 0.0
        x = q[ok] - mu[cid[ok]]
        A = icov[cid[ok]]
        Ax = np.einsum("nij,nj->ni", A, x)
        e = np.exp(-0.5 * np.einsum("ni,ni->n", x, Ax))
        score = float(e.sum())
        # gradient of sum e wrt (omega, t) with q' = q + omega x q + t
        J = np.zeros((len(x), 3, 6))
        qq = q[ok]
        J[:, :, :3] = np.stack([np.cross(np.eye(3)[k], qq) for k in range(3)], axis=2)
        J[:, :, 3:] = np.eye(3)
        g = -np.einsum("n,ni,nij->j", e, Ax, J)
        H = np.einsum("n,nki,nkl,nlj->ij", e, J, A, J) + 1e-6 * np.eye(6)
        step = np.linalg.solve(H, g)
        T = twist_matrix(step) @ T
        if np.linalg.norm(step) < 1e-6:
            break
    return T, score


def coarse_ndt_poses(src_pts: np.ndarray, target: ModelTarget, settings: RegistrationSettings,
                     rng: np.random.Generator) -> list[np.ndarray]:
    """Distinct coarse poses from NDT started at the 24 axis-aligned rotations of the
    scan about its centroid, placed on the model's centroid (coarse-to-fine cells)."""
    src = src_pts[rng.choice(len(src_pts), size=min(1500, len(src_pts)), replace=False)]
    starts = []
    for R in Rotation.create_group("O").as_matrix():
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = target.coarse.points.mean(axis=0) - R @ src.mean(axis=0)
        starts.append(T)
    cells = [8.0 * target.voxel_mm, 4.0 * target.voxel_mm, 2.0 * target.voxel_mm]
    grids = [ndt_grid(target.coarse.points, c) for c in cells]
    poses, scores = [], []
    for T in starts:
        for c, g in zip(cells, grids):
            T, s = ndt_refine(src, T, g, c, 15)
        poses.append(T)
        scores.append(s)
    P = np.array(poses)
    return distinct_poses(P, np.argsort(-np.array(scores)), settings.verify, 10.0, 0.1 * target.diagonal_mm)
