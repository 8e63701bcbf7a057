"""Coarse poses from sphere descriptors (paper 000 section 3, paper 001 section 3.2):
correspondences at every RSCS scale, then SAC-IA — triplets of correspondences drawn by
score (scan points spread apart, edge lengths consistent on both sides), the rigid
transform of each (Kabsch, Eq. 12-15), scored by the Huber penalty of paper 001 Eq. 22
over the distances from a sample of scan points to the model — or RANSAC (score:
correspondences within the inlier distance)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import cdist

from inspection.registration.matching import correspondences
from inspection.registration.rigid import distinct_poses, kabsch
from inspection.registration.settings import RegistrationSettings
from inspection.registration.spheres import rscs, sphere_radii
from inspection.registration.target import ModelTarget


def huber(d: np.ndarray, ml: float) -> np.ndarray:
    """Paper 001 Eq. 22 of the distances `d` (the paper's l): d^2/2 below ml, ml (2 d - ml)/2 above."""
    return np.where(d < ml, 0.5 * d * d, 0.5 * ml * (2.0 * d - ml))


def triplets(src: np.ndarray, dst: np.ndarray, w: np.ndarray, *, n: int, min_sep: float, tol: float,
             rng: np.random.Generator, max_corr: int = 1500) -> np.ndarray:
    """Up to n index triplets (n, 3) of mutually consistent correspondences: every pair
    of the three has its scan points at least `min_sep` apart and the same distance on
    both sides within tol (+3 %). Correspondences are weighted by their descriptor score
    times their number of consistent partners (correct ones agree with each other, wrong
    ones only by chance); the first is drawn by weight, the second among those consistent
    with it, the third among those consistent with both."""
    keep = np.argsort(-w)[:max_corr]
    src, dst, w = src[keep], dst[keep], w[keep]
    ds, dd = cdist(src, src), cdist(dst, dst)
    C = (np.abs(ds - dd) < tol + 0.03 * ds) & (ds > min_sep)
    score = w * (C.sum(axis=1) + 1.0)
    if not C.any():
        return np.zeros((0, 3), np.int64)
    i = rng.choice(len(w), size=2 * n, p=score / score.sum())

    def pick(mask: np.ndarray) -> np.ndarray:
        weight = mask * score[None, :]
        cum = np.cumsum(weight, axis=1)
        total = cum[:, -1]
        u = rng.random(len(mask)) * total
        j = np.minimum((cum < u[:, None]).sum(axis=1), len(score) - 1)
        return np.where(total > 0, j, -1)

    j = pick(C[i])
    i, j = i[j >= 0], j[j >= 0]
    k = pick(C[i] & C[j])
    ok = k >= 0
    return keep[np.stack([i[ok], j[ok], k[ok]], axis=1)[:n]]


def score_poses(T: np.ndarray, eval_pts: np.ndarray, target: ModelTarget, ml: float, cap: float,
                workers: int = -1) -> np.ndarray:
    """Huber score (Eq. 22, lower is better) of each pose (H, 4, 4) over eval_pts
    (`workers`: KD-tree query threads, -1 all)."""
    q = np.einsum("hij,nj->hni", T[:, :3, :3], eval_pts) + T[:, None, :3, 3]
    d, _ = target.coarse.tree.query(q.reshape(-1, 3), distance_upper_bound=cap, workers=workers)
    d = np.minimum(d, cap).reshape(len(T), -1)
    return huber(d, ml).sum(axis=1)


def coarse_feature_poses(src_pts: np.ndarray, src_nrm: np.ndarray, target: ModelTarget,
                         settings: RegistrationSettings, rng: np.random.Generator,
                         workers: int = -1) -> list[np.ndarray]:
    """Distinct coarse poses from RSCS + descriptors + SAC-IA (or RANSAC), best first
    (`workers`: KD-tree query threads of the pose scoring, -1 all; 1 suits small clouds
    on a busy machine, where starting threads costs more than they save)."""
    rc, radii = sphere_radii(src_pts, target.voxel_mm, settings.spheres)
    S, D, W = [], [], []
    for r in radii:
        cloud = target.descriptor_cloud(src_pts, src_nrm, r)
        idx = rscs(cloud, r, rng)
        if len(idx) < 3:
            continue
        desc = target.describe(cloud, idx, r, settings.descriptors)
        tf = target.features(r, settings.descriptors)
        if len(tf.points) < 3:
            continue
        s, d, w = correspondences(cloud.points[idx], desc, tf.points, tf.descriptors, r)
        S.append(s)
        D.append(d)
        W.append(w)
    if not S:
        return []
    src, dst, w = np.concatenate(S), np.concatenate(D), np.concatenate(W) + 1e-3
    tol = 2.0 * target.voxel_mm
    trip = triplets(src, dst, w, n=settings.hypotheses, min_sep=0.1 * rc, tol=tol, rng=rng)
    if not len(trip):
        return []
    T = kabsch(src[trip], dst[trip])
    if settings.coarse == "ransac":
        moved = np.einsum("hij,nj->hni", T[:, :3, :3], src) + T[:, None, :3, 3]
        score = -(np.linalg.norm(moved - dst[None], axis=2) < tol).sum(axis=1).astype(float)
    else:
        ev = src_pts[rng.choice(len(src_pts), size=min(300, len(src_pts)), replace=False)]
        ml, cap = 1.5 * target.voxel_mm, 5.0 * target.voxel_mm
        # many hypotheses: a cheap pre-score on a fifth of the points, the best `prescored` then on all
        score = np.full(len(T), np.inf)
        top = (np.argsort(score_poses(T, ev[: len(ev) // 5], target, ml, cap, workers=workers))[:settings.prescored]
               if len(T) > settings.prescored else np.arange(len(T)))
        score[top] = score_poses(T[top], ev, target, ml, cap, workers=workers)
    return distinct_poses(T, np.argsort(score), settings.verify, 10.0, 0.1 * target.diagonal_mm)
