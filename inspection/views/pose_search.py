"""Starting poses for a view pair from the directions its surfaces face: what local
descriptors miss when two views share mostly planes and a cylinder (a turntable's views a
quarter turn apart: the shared top faces look alike everywhere, and the sides each sees are
different sides).

1. Rotations. Each view's normals, binned on a Fibonacci sphere of `SPHERE_BINS` directions
   (about 2.3 deg apart) and summed over `SPREAD_DEG`, peak at the directions its faces face
   (`normal_modes`: up to `MAX_MODES` peaks, each at least `MIN_SHARE` of the view's points,
   `APART_DEG` apart). Two modes of the source and two of the target at the same angle
   (within `ANGLE_TOL_DEG`: a mode is the mean of hundreds of normals, good to a degree or
   so) give the rotation taking the one pair onto the other (`rotations`): a plate's top
   and one side, seen in both views, fix the turn.
   Views a half turn apart may share one face direction only (a plate's top): the
   `SWEPT` strongest modes of each are laid onto each other and turned about it every
   `SWEEP_DEG`.
2. Translations. Under a rotation, a source point and a target point whose normals agree
   (within `NORMAL_TOL_DEG`) vote for the translation between them; points on three faces
   of different directions vote for one translation, points on one face for a plane of
   them: the most voted voxel (`VOTE_VOXELS` of the registration voxel) wins
   (`translations`).

Every (rotation, translation) is only a start: `pair_registration` refines and judges it.
Units mm, degrees.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

SPHERE_BINS = 8000
SPREAD_DEG = 4.0
MAX_MODES = 10
MIN_SHARE = 0.005
APART_DEG = 15.0
ANGLE_TOL_DEG = 3.0
NORMAL_TOL_DEG = 10.0
VOTE_VOXELS = 2.0
SWEPT, SWEEP_DEG = 2, 7.5
VOTERS, VOTED = 80, 1000  # source points casting votes, target points voted for (random draws)


def fibonacci_sphere(n: int) -> np.ndarray:
    """n unit vectors spread evenly over the sphere."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5 ** 0.5) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def normal_modes(normals: np.ndarray) -> np.ndarray:
    """The directions (M, 3) the view's faces face, strongest first (module docstring)."""
    dirs = fibonacci_sphere(SPHERE_BINS)
    tree = cKDTree(dirs)
    _, b = tree.query(normals)
    counts = np.bincount(b, minlength=SPHERE_BINS).astype(float)
    chord = 2.0 * np.sin(np.radians(SPREAD_DEG) / 2.0)
    pairs = tree.query_pairs(chord, output_type="ndarray")
    spread = counts.copy()
    np.add.at(spread, pairs[:, 0], counts[pairs[:, 1]])
    np.add.at(spread, pairs[:, 1], counts[pairs[:, 0]])
    modes: list[np.ndarray] = []
    cos_apart = np.cos(np.radians(APART_DEG))
    for i in np.argsort(-spread):
        if spread[i] < MIN_SHARE * len(normals) or len(modes) == MAX_MODES:
            break
        if all(dirs[i] @ m < cos_apart for m in modes):  # a few dozen peaks at most before the shares run out
            m = normals[normals @ dirs[i] > np.cos(np.radians(SPREAD_DEG))].sum(axis=0)
            modes.append(m / np.linalg.norm(m))
    return np.array(modes).reshape(-1, 3)


def rotations(source: np.ndarray, target: np.ndarray) -> list[np.ndarray]:
    """Rotations taking two source modes onto two target modes at the same angle, and each
    of the `SWEPT` strongest source modes onto each of the target's, turned about it every
    `SWEEP_DEG` (module docstring)."""
    out = [_turn(c, np.radians(a)) @ _onto(s, c) for s in source[:SWEPT] for c in target[:SWEPT]
           for a in np.arange(0.0, 360.0, SWEEP_DEG)]
    tol = np.radians(ANGLE_TOL_DEG)
    for a in range(len(source)):
        for b in range(a + 1, len(source)):
            angle = np.arccos(np.clip(source[a] @ source[b], -1.0, 1.0))
            if not np.radians(APART_DEG) < angle < np.pi - np.radians(APART_DEG):
                continue
            for c in range(len(target)):
                for d in range(len(target)):
                    if c != d and abs(np.arccos(np.clip(target[c] @ target[d], -1.0, 1.0)) - angle) < tol:
                        out.append(_frame(target[c], target[d]) @ _frame(source[a], source[b]).T)
    return out


def _onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit a onto unit b."""
    from scipy.spatial.transform import Rotation

    return Rotation.align_vectors([b], [a])[0].as_matrix()


def _turn(axis: np.ndarray, angle: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(angle * axis).as_matrix()


def _frame(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """An orthonormal frame (columns) from u and the part of v across it."""
    w = v - (v @ u) * u
    w /= np.linalg.norm(w)
    return np.column_stack([u, w, np.cross(u, w)])


def translations(R: np.ndarray, source: tuple[np.ndarray, np.ndarray], target: tuple[np.ndarray, np.ndarray],
                 voxel_mm: float, rng: np.random.Generator, best: int = 1) -> list[tuple[float, np.ndarray]]:
    """The `best` most voted translations (3,) under rotation R with their share of the
    votes, weighted and not (module docstring); `source`, `target`: (points, normals) on the registration's voxel grid. A
    voter's vote is shared among the target points its normal agrees with: a point on a big
    face, agreeing with all of that face, votes for a whole plane of translations and
    weighs little at any one of them."""
    sp, sn = source
    pick = rng.choice(len(sp), size=min(VOTERS, len(sp)), replace=False)
    p, n = sp[pick] @ R.T, sn[pick] @ R.T
    pick = rng.choice(len(target[0]), size=min(VOTED, len(target[0])), replace=False)
    tp, tn = target[0][pick], target[1][pick]
    i, j = np.nonzero(n @ tn.T > np.cos(np.radians(NORMAL_TOL_DEG)))
    if len(i) == 0:
        return []
    t = tp[j] - p[i]
    weight = 1.0 / np.bincount(i, minlength=len(p))[i]
    cell = np.floor(t / (VOTE_VOXELS * voxel_mm)).astype(np.int64)
    cell -= cell.min(axis=0)
    key = (cell[:, 0] * (cell[:, 1].max() + 1) + cell[:, 1]) * (cell[:, 2].max() + 1) + cell[:, 2]
    _, inverse = np.unique(key, return_inverse=True)
    out = []
    for votes in (np.bincount(inverse, weights=weight), np.bincount(inverse)):
        out += [(float(votes[k] / votes.sum()), t[inverse == k].mean(axis=0)) for k in np.argsort(-votes)[:best]]
    return out


def face_poses(source: tuple[np.ndarray, np.ndarray], target: tuple[np.ndarray, np.ndarray], voxel_mm: float,
               seed: int = 0) -> np.ndarray:
    """Starting poses (H, 4, 4), source -> target, from the views' face directions (module
    docstring); `source`, `target`: (points, normals) on the registration's voxel grid."""
    rng = np.random.default_rng(seed)
    poses = []
    for R in rotations(normal_modes(source[1]), normal_modes(target[1])):  # some hundreds
        for _, t in translations(R, source, target, voxel_mm, rng):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            poses.append(T)
    return np.array(poses).reshape(-1, 4, 4)
