"""Multi-scale random sphere cover sets (RSCS, paper 000 section 3) and the descriptors of
their spheres.

Per scale, a random uncovered point is the next sphere centre until every point is
covered. The radii follow Eq. 19, r = (3/(4 pi) * 0.7/(2 m) * V)^(1/3) with V the volume
of the scan's circumscribed sphere, for m spheres per scale (snapped to a half-octave
ladder of the voxel, so a model's features are computed once per radius). Spheres whose
normals are all parallel (a patch of one plane: nothing to describe) are screened out.
Descriptors: FPFH (Open3D) and SHOT (`features.shot`), support = the sphere."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inspection.features import fpfh, shot
from inspection.registration.clouds import Samples


@dataclass(eq=False)
class SphereFeatures:
    """Sphere centres (K, 3) and their descriptors (name -> (K, D))."""

    points: np.ndarray
    descriptors: dict[str, np.ndarray]


def ladder(radius: float, voxel: float) -> float:
    """`radius` snapped to the half-octave ladder voxel * 2^(k/2)."""
    return voxel * 2.0 ** (np.round(2 * np.log2(radius / voxel)) / 2)


def sphere_radii(src_pts: np.ndarray, voxel_mm: float, spheres: tuple[int, ...]) -> tuple[float, list[float]]:
    """(radius of the scan's circumscribed sphere about its centroid, the RSCS radii of
    Eq. 19 snapped to the ladder), mm."""
    rc = float(np.linalg.norm(src_pts - src_pts.mean(axis=0), axis=1).max())
    return rc, sorted({ladder(rc * (0.7 / (2 * m)) ** (1 / 3), voxel_mm) for m in spheres})


def screen(cloud: Samples, idx: np.ndarray, radius: float, min_points: int = 12) -> np.ndarray:
    """The sphere centres worth describing: enough points, and not all of one plane."""
    d, nb = cloud.tree.query(cloud.points[idx], k=64, distance_upper_bound=radius)
    valid = np.isfinite(d)
    nb = np.where(valid, nb, 0)
    mean = (cloud.normals[nb] * valid[..., None]).sum(axis=1) / np.maximum(valid.sum(axis=1), 1)[:, None]
    return idx[(valid.sum(axis=1) >= min_points) & (np.linalg.norm(mean, axis=1) < 0.98)]


def describe(cloud: Samples, idx: np.ndarray, radius: float, descriptors: tuple[str, ...],
             max_nn: int) -> dict[str, np.ndarray]:
    """The named descriptors of the spheres of `radius` about the points `idx` of `cloud`
    (at most `max_nn` neighbours each)."""
    out = {}
    if "fpfh" in descriptors:
        out["fpfh"] = fpfh(cloud.points, cloud.normals, idx, radius, max_nn)
    if "shot" in descriptors:
        out["shot"] = shot(cloud.points, cloud.normals, cloud.points[idx], radius, cloud.tree, max_nn)
    return out


def rscs(cloud: Samples, radius: float, rng: np.random.Generator) -> np.ndarray:
    """Indices of the sphere centres of a random sphere cover set of `radius`, screened."""
    points, tree = cloud.points, cloud.tree
    n = len(points)
    covered = np.zeros(n, bool)
    order = rng.permutation(n)
    centres = []
    pos = 0
    while True:  # one iteration per sphere: a few hundred at most
        left = np.flatnonzero(~covered[order[pos:]])
        if not left.size:
            break
        pos += int(left[0])
        c = order[pos]
        centres.append(c)
        covered[tree.query_ball_point(points[c], radius)] = True
    return screen(cloud, np.array(centres, np.int64), radius)
