"""Correspondences between a scan's spheres and a model's by their descriptors (paper 000
section 3): for each scan sphere and descriptor, the nearest model spheres in descriptor
space, scored by distinctiveness 1 - d1/d2 (d2: the best match elsewhere). Multivariate
combination (Eq. 11): where the descriptors' best matches agree, the correspondence is
their score-weighted mean l = sum w_i c_i; where they disagree, both are kept."""

from __future__ import annotations

import numpy as np

from inspection.registration.settings import DESCRIPTORS


def best_matches(src: np.ndarray, dst: np.ndarray, dst_points: np.ndarray, radius: float,
                 k: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(indices (Ks, k) of the k nearest dst descriptors, scores (Ks, k) = 1 - d_j/d_alt)
    where d_alt is the distance of the best match more than a radius away from match j."""
    d2 = (src ** 2).sum(1)[:, None] + (dst ** 2).sum(1)[None, :] - 2.0 * src @ dst.T
    d = np.sqrt(np.maximum(d2, 0.0))
    kk = min(k + 8, d.shape[1])
    part = np.argpartition(d, kk - 1, axis=1)[:, :kk]
    order = np.take_along_axis(d, part, 1).argsort(axis=1)
    cand = np.take_along_axis(part, order, 1)
    cd = np.take_along_axis(d, cand, 1)
    # the alternative of each of the first k: the nearest candidate far from it in space
    sep = np.linalg.norm(dst_points[cand[:, :k, None]] - dst_points[cand[:, None, :]], axis=-1) > radius
    alt = np.where(sep, cd[:, None, :], np.inf).min(axis=2)
    alt = np.where(np.isfinite(alt), alt, cd[:, -1:])
    score = np.clip(1.0 - cd[:, :k] / np.maximum(alt, 1e-12), 0.0, 1.0)
    return cand[:, :k], score


def correspondences(src_pts: np.ndarray, src_desc: dict[str, np.ndarray], dst_pts: np.ndarray,
                    dst_desc: dict[str, np.ndarray], radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(scan points (C, 3), model points (C, 3), weights (C,)) of one scale: each
    descriptor's k best matches; where two descriptors' best matches agree (within half a
    radius) they merge into their score-weighted mean (Eq. 11)."""
    names = [n for n in DESCRIPTORS if n in src_desc]
    matches = {n: best_matches(src_desc[n], dst_desc[n], dst_pts, radius) for n in names}
    s_out, d_out, w_out = [], [], []
    if len(names) == 2:
        (ia, sa), (ib, sb) = matches[names[0]], matches[names[1]]
        ca, cb = dst_pts[ia[:, 0]], dst_pts[ib[:, 0]]
        agree = np.linalg.norm(ca - cb, axis=1) < radius / 2
        wsum = np.maximum(sa[:, 0] + sb[:, 0], 1e-12)
        merged = (sa[:, 0, None] * ca + sb[:, 0, None] * cb) / wsum[:, None]  # Eq. 11
        s_out.append(src_pts[agree])
        d_out.append(merged[agree])
        w_out.append(sa[agree, 0] + sb[agree, 0])
        for idx, sc in ((ia, sa), (ib, sb)):  # disagreeing best matches, and the runners-up
            keep = np.ones_like(sc, bool)
            keep[agree, 0] = False
            s_out.append(np.broadcast_to(src_pts[:, None], idx.shape + (3,))[keep])
            d_out.append(dst_pts[idx][keep])
            w_out.append(sc[keep])
    else:
        idx, sc = matches[names[0]]
        s_out.append(np.broadcast_to(src_pts[:, None], idx.shape + (3,)).reshape(-1, 3))
        d_out.append(dst_pts[idx].reshape(-1, 3))
        w_out.append(sc.ravel())
    return np.concatenate(s_out), np.concatenate(d_out), np.concatenate(w_out)
