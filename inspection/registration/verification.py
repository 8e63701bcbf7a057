"""Judging and improving poses: the fitness of many poses at once, the fitness and RMSE of
one, and a local search of the fitness about a refined pose (hypothesis verification,
paper 000 section 3)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from inspection.downsample import coherent_order, query_in_order
from inspection.registration.clouds import Samples
from inspection.registration.point_to_plane import icp
from inspection.registration.rigid import transform_points
from inspection.registration.settings import RegistrationSettings
from inspection.registration.target import ModelTarget


def fitness(src: np.ndarray, src_nrm: np.ndarray, target: Samples, *, T: np.ndarray, inlier_mm: float,
            max_normal_deg: float, workers: int = -1) -> np.ndarray:
    """Fitness (H,) of each pose (H, 4, 4): the fraction of points within inlier_mm of the
    target whose normals agree within max_normal_deg (one batched KD-tree query with
    `workers` threads, -1 all)."""
    q = np.einsum("hij,nj->hni", T[:, :3, :3], src) + T[:, None, :3, 3]
    n = np.einsum("hij,nj->hni", T[:, :3, :3], src_nrm)
    order = (len(src) * np.arange(len(T))[:, None] + coherent_order(src)).ravel()  # pose by pose
    d, j = query_in_order(target.tree, q.reshape(-1, 3), order, distance_upper_bound=inlier_mm, workers=workers)
    ok = np.isfinite(d)
    j = np.where(ok, j, 0)
    ok &= np.einsum("ij,ij->i", n.reshape(-1, 3), target.normals[j]) > np.cos(np.radians(max_normal_deg))
    return ok.reshape(len(T), -1).mean(axis=1)


def evaluate_pose(src: np.ndarray, src_nrm: np.ndarray, target: Samples, T: np.ndarray, inlier_mm: float,
                  max_normal_deg: float) -> tuple[float, float]:
    """(fitness, RMSE mm): fraction of points within inlier_mm of the model with normals
    agreeing, and the RMS distance of those."""
    q = transform_points(T, src)
    d, j = query_in_order(target.tree, q, coherent_order(src), distance_upper_bound=inlier_mm,
                          workers=-1 if len(q) > 20000 else 1)
    ok = np.isfinite(d)
    j = np.where(ok, j, 0)
    ok &= np.einsum("ij,ij->i", src_nrm @ T[:3, :3].T, target.normals[j]) > np.cos(np.radians(max_normal_deg))
    # distance to the tangent plane of the nearest sample: free of the sampling spacing
    dp = np.abs(np.einsum("ij,ij->i", q - target.points[j], target.normals[j]))
    return float(ok.mean()), float(np.sqrt(np.mean(dp[ok] ** 2))) if ok.any() else float("nan")


def explained(src: np.ndarray, src_nrm: np.ndarray, target: ModelTarget, *, T: np.ndarray, inlier_mm: float,
              max_normal_deg: float, viewpoint: np.ndarray | None) -> np.ndarray:
    """Which points (scan frame) pose T explains: within `inlier_mm` of the target's dense
    samples with normals agreeing within `max_normal_deg`, and not hidden from `viewpoint`
    behind the posed model (`ModelTarget.hidden`, at twice the inlier distance)."""
    q = transform_points(T, src)
    d, j = query_in_order(target.dense.tree, q, coherent_order(src), distance_upper_bound=inlier_mm, workers=1)
    ok = np.isfinite(d)
    j = np.where(ok, j, 0)
    ok &= np.einsum("ij,ij->i", src_nrm @ T[:3, :3].T, target.dense.normals[j]) > np.cos(np.radians(max_normal_deg))
    if viewpoint is not None:
        ok &= ~target.hidden(T, src, viewpoint, 2.0 * inlier_mm)
    return ok


def explore(src: np.ndarray, src_nrm: np.ndarray, target: Samples, *, T: np.ndarray, inlier_mm: float,
            degrees: tuple[float, ...], icp_mm: float, settings: RegistrationSettings, rounds: int = 4) -> np.ndarray:
    """Local search of the fitness about a refined pose: the scan turned by `degrees`
    either way about each of its principal axes (through its centroid), and shifted along
    them by as many inlier distances; a move that fits more of the scan is refined by ICP
    (from `icp_mm`) and kept. It finds what ICP cannot: along large planes (a part seen
    from above) a turn or a shift moves only a few edge points, which ICP rejects as
    outliers, while the fitness counts them. Moves are pre-scored on every
    `settings.explore_prescore_stride`-th point, the best `explore_top` on all."""
    max_normal_deg = settings.max_normal_deg
    c = src.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((src - c).T))
    moves = []
    for a in axes.T:
        for deg in degrees:
            for sgn in (-1.0, 1.0):
                F = np.eye(4)
                F[:3, :3] = Rotation.from_rotvec(sgn * np.radians(deg) * a).as_matrix()
                F[:3, 3] = c - F[:3, :3] @ c
                moves.append(F)
                F = np.eye(4)
                F[:3, 3] = sgn * deg * inlier_mm * a
                moves.append(F)
    M = np.array(moves)
    best = fitness(src, src_nrm, target, T=T[None], inlier_mm=inlier_mm, max_normal_deg=max_normal_deg)[0]
    pre = slice(None, None, settings.explore_prescore_stride)
    for _ in range(rounds):
        cand = np.einsum("ij,mjk->mik", T, M)
        # pre-score every move on a subsample, then the most promising on all points
        pre_fits = fitness(src[pre], src_nrm[pre], target, T=cand, inlier_mm=inlier_mm, max_normal_deg=max_normal_deg)
        top = np.argsort(-pre_fits)[:settings.explore_top]
        fits = fitness(src, src_nrm, target, T=cand[top], inlier_mm=inlier_mm, max_normal_deg=max_normal_deg)
        k, fit_k = int(top[np.argmax(fits)]), float(fits.max())
        if fit_k <= best + 0.002:
            break
        U = icp(src, src_nrm, target, T=cand[k], max_dist=icp_mm, min_dist=0.5 * inlier_mm,
                max_normal_deg=max_normal_deg, iterations=20,
                tangential=settings.tangential_weight)
        fit = fitness(src, src_nrm, target, T=U[None], inlier_mm=inlier_mm, max_normal_deg=max_normal_deg)[0]
        T, best = (U, fit) if fit > fit_k else (cand[k], fit_k)
    return T
