"""Rigid transforms (4x4, mm): applying them, fitting them to correspondences (Kabsch,
paper 000 Eq. 12-15), comparing them, and keeping the distinct ones of a ranked list."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


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


def twist_matrix(step: np.ndarray) -> np.ndarray:
    """The 4x4 transform of a small motion (omega (rad, rotation vector), t (mm))."""
    dT = np.eye(4)
    dT[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
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
