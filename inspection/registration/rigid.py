"""Rigid transforms (4x4, mm): applying them, fitting them to correspondences (Kabsch,
paper 000 Eq. 12-15), comparing them, and keeping the distinct ones of a ranked list."""

from __future__ import annotations

import numpy as np


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points (N, 3) mapped by the 4x4 transform T."""
    return p @ T[:3, :3].T + T[:3, 3]


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Rigid transforms (..., 4, 4) taking src (..., n, 3) onto dst in the least-squares
    sense (Eq. 12-15: centroids, cross-covariance, SVD, reflection guarded)."""
    w = np.ones(src.shape[:-1]) if weights is None else weights
    w = w / w.sum(axis=-1, keepdims=True)
    cs = np.einsum("...n,...ni->...i", w, src)
    cd = np.einsum("...n,...ni->...i", w, dst)
    h = np.einsum("...n,...ni,...nj->...ij", w, src - cs[..., None, :], dst - cd[..., None, :])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("...ji,...kj->...ik", vt, u)))
    fix = np.ones(h.shape[:-2] + (3,))
    fix[..., 2] = d
    R = np.einsum("...ji,...j,...kj->...ik", vt, fix, u)
    T = np.zeros(h.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = cd - np.einsum("...ij,...j->...i", R, cs)
    T[..., 3, 3] = 1.0
    return T


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products (N, 3) of a and b (N, 3) or (3,): what np.cross gives, without
    its per-call overhead (it dominates for the few hundred points of an ICP step)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def twist_matrix(step: np.ndarray) -> np.ndarray:
    """The 4x4 transform of a small motion (omega (rad, rotation vector), t (mm)): the
    rotation by Rodrigues' formula (with its series below 1e-6 rad)."""
    w = np.asarray(step[:3], dtype=np.float64)
    theta = float(np.sqrt(w @ w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-6:
        a, b = 1.0 - theta ** 2 / 6.0, 0.5 - theta ** 2 / 24.0
    else:
        a, b = np.sin(theta) / theta, (1.0 - np.cos(theta)) / theta ** 2
    dT = np.eye(4)
    dT[:3, :3] += a * K + b * (K @ K)
    dT[:3, 3] = step[3:]
    return dT


def pose_difference(a: np.ndarray, b: np.ndarray, about: np.ndarray | None = None) -> tuple[float, float]:
    """(rotation angle in degrees, translation distance in mm) between two poses; the
    distance is that between the images of the point `about` (default: the origin)."""
    d = np.linalg.inv(a) @ b
    angle = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1.0, 1.0)))
    p = np.zeros(3) if about is None else about
    return float(angle), float(np.linalg.norm(transform_points(a, p[None]) - transform_points(b, p[None])))


def distinct_poses(T: np.ndarray, order: np.ndarray, n: int, angle_deg: float, dist_mm: float) -> list[np.ndarray]:
    """Up to n of the poses T (H, 4, 4), taken in `order` (best first), each more than
    `angle_deg` or `dist_mm` (about the origin) from every one taken before."""
    picked: list[np.ndarray] = []
    for i in order:  # a few thousand at most, usually stops after a handful
        if all(pose_difference(T[i], p)[0] > angle_deg or pose_difference(T[i], p)[1] > dist_mm for p in picked):
            picked.append(T[i])
            if len(picked) == n:
                break
    return picked
