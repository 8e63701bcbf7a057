"""Point-to-plane ICP with normal-angle rejection (paper 001 Eq. 27-29, with the
point-to-plane metric), and the linearised least-squares step it and the exact-distance
refinement share."""

from __future__ import annotations

import numpy as np

from inspection.downsample import coherent_order, query_in_order
from inspection.registration.clouds import Samples
from inspection.registration.rigid import cross_rows, transform_points, twist_matrix
from inspection.registration.settings import RegistrationSettings


def icp(src: np.ndarray, src_nrm: np.ndarray, target: Samples, *, T: np.ndarray, max_dist: float,
        min_dist: float, max_normal_deg: float, iterations: int = 30,
        tangential: float = RegistrationSettings.tangential_weight) -> np.ndarray:
    """Point-to-plane ICP with normal-angle rejection: pairs farther than a threshold
    (shrinking from max_dist toward min_dist, or 3 robust sigma of the residuals) or whose
    normals differ by more than max_normal_deg are rejected. A tangential term (weight
    `tangential`) keeps points from sliding off a face's edge, which the plane metric
    alone does not see; a large one widens the basin of convergence along large planes."""
    cos_max = np.cos(np.radians(max_normal_deg))
    thr = max_dist
    order = coherent_order(src)
    for _ in range(iterations):
        q = transform_points(T, src)
        n = src_nrm @ T[:3, :3].T
        d, j = query_in_order(target.tree, q, order, distance_upper_bound=thr, workers=-1 if len(q) > 20000 else 1)
        ok = np.isfinite(d)
        j = np.where(ok, j, 0)
        tn = target.normals[j]
        ok &= np.einsum("ij,ij->i", n, tn) > cos_max
        if ok.sum() < 6:
            break
        step, r = point_to_plane_step(q[ok], target.points[j[ok]], tn[ok], tangential)
        T = twist_matrix(step) @ T
        sigma = 1.4826 * np.median(np.abs(r))
        thr = float(np.clip(max(3.0 * sigma, 0.5 * thr), min_dist, max_dist))
        if np.linalg.norm(step) < 1e-8:
            break
    return T


def point_to_plane_step(p: np.ndarray, q: np.ndarray, n: np.ndarray, tangential: float = 0.0,
                        damping: float = 1e-12, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The small motion x = (omega, t) minimising sum w e'We, e = p + omega x p + t - q,
    W = (1 - l^2) n n' + l^2 I: point-to-plane plus a weak (l = `tangential`) point-to-point
    term (unweighted), Levenberg damping `damping` x the largest curvature, `weights` w per
    point (None: 1). Normal equations from sums over the points (O(n)); returns (x, normal
    residuals)."""
    e = p - q
    r = np.einsum("ij,ij->i", e, n)
    a = np.concatenate([cross_rows(p, n), n], axis=1)  # d(e.n)/dx
    wa = a if weights is None else a * weights[:, None]
    H = (1.0 - tangential ** 2) * (wa.T @ a)
    g = (1.0 - tangential ** 2) * (wa.T @ r)
    if tangential > 0:  # point-to-point: J = [-[p]x, I], J'J and J'e from sums
        sp, m = p.sum(axis=0), len(p)
        px = np.array([[0, -sp[2], sp[1]], [sp[2], 0, -sp[0]], [-sp[1], sp[0], 0]])
        block = np.zeros((6, 6))
        block[:3, :3] = np.einsum("ni,ni->", p, p) * np.eye(3) - p.T @ p
        block[:3, 3:] = px
        block[3:, :3] = px.T
        block[3:, 3:] = m * np.eye(3)
        H += tangential ** 2 * block
        g += tangential ** 2 * np.concatenate([cross_rows(p, e).sum(axis=0), e.sum(axis=0)])
    return np.linalg.solve(H + damping * np.abs(np.diag(H)).max() * np.eye(6), -g), r
