"""Hypotheses verification looks at beside the coarse poses (paper 000 section 3): each
pose's half turns about the scan's principal axes (what a prismatic or nearly symmetric
part is confused with), and, for scans that are mostly one plane, poses laying that plane
on the model's largest planar faces."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from inspection.registration.point_to_plane import icp
from inspection.registration.target import ModelTarget
from inspection.registration.verification import fitness


def with_flips(poses: list[np.ndarray], points: np.ndarray, n_best: int = 2) -> list[np.ndarray]:
    """The poses, plus, for the best `n_best`, the scan turned half a turn about each of its
    principal axes (through its centroid) first: the poses a prismatic or nearly symmetric
    part is confused with, so that verification sees them side by side."""
    c = points.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((points - c).T))
    flips = []
    for a in axes.T:
        F = np.eye(4)
        F[:3, :3] = 2.0 * np.outer(a, a) - np.eye(3)  # rotation by pi about a
        F[:3, 3] = c - F[:3, :3] @ c
        flips.append(F)
    return poses + [T @ F for T in poses[:n_best] for F in flips]


def plane_poses(src_pts: np.ndarray, src_nrm: np.ndarray, target: ModelTarget, n_best: int = 4,
                n_faces: int = 4, step_deg: float = 10.0) -> list[np.ndarray]:
    """Poses from the scan's dominant plane, for scans that are mostly one plane (a flat
    part seen from above), where local descriptors have little to grip: the plane laid on
    each of the model's largest planar faces, turned about its normal every `step_deg`,
    plane centroids matched; the most promising shortly refined by ICP; the `n_best` by
    fitness."""
    if target.model is None or target.samples is None:
        return []
    rng = np.random.default_rng(0)
    cand = src_nrm[rng.choice(len(src_nrm), size=min(200, len(src_nrm)), replace=False)]
    near = (cand @ src_nrm.T) > np.cos(np.radians(5.0))
    k = int(np.argmax(near.sum(axis=1)))
    on = near[k]
    ns = src_nrm[on].mean(axis=0)
    ns /= np.linalg.norm(ns)
    h = src_pts[on] @ ns  # several parallel planes (steps) share the normal: take the most populated
    bins = np.floor((h - h.min()) / target.voxel_mm).astype(np.int64)
    level = h.min() + (np.argmax(np.bincount(bins)) + 0.5) * target.voxel_mm
    cs = src_pts[on][np.abs(h - level) < target.voxel_mm].mean(axis=0)
    planes = sorted((f for f in target.model.faces if f.type == "plane"), key=lambda f: -f.area_mm2)[:n_faces]
    poses = []
    for f in planes:
        sel = target.samples.face == f.index
        m = target.samples.normals[sel].mean(axis=0)
        m /= np.linalg.norm(m)
        cm = target.samples.points[sel].mean(axis=0)
        R0, _ = Rotation.align_vectors([m], [ns])
        for deg in np.arange(0.0, 360.0, step_deg):
            R = (Rotation.from_rotvec(np.radians(deg) * m) * R0).as_matrix()
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = cm - R @ cs
            poses.append(T)
    if not poses:
        return []
    pick = rng.choice(len(src_pts), size=min(300, len(src_pts)), replace=False)
    v = target.voxel_mm
    P = np.array(poses)
    first = np.argsort(-fitness(src_pts[pick], src_nrm[pick], target.coarse, T=P, inlier_mm=6.0 * v,
                                max_normal_deg=45.0))[:3 * n_best]
    P = np.array([icp(src_pts[pick], src_nrm[pick], target.coarse, T=P[i], max_dist=20.0 * v, min_dist=2.0 * v,
                      max_normal_deg=45.0, iterations=8, tangential=0.5)
                  for i in first])  # a short, nearly point-to-point ICP: the plane centroids are only a guess
    fits = fitness(src_pts[pick], src_nrm[pick], target.coarse, T=P, inlier_mm=3.0 * v, max_normal_deg=45.0)
    return [P[i] for i in np.argsort(-fits)[:n_best]]
