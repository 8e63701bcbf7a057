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
2. Translations. Along each face direction a rotation was matched on, the planes facing it
   in both views fix the offset: the most common difference of their heights (steps give
   several; the one most points share wins). Across those directions (a line, or a plane
   for a single direction), the points facing elsewhere vote: a source point and a target
   point whose normals agree (within `NORMAL_TOL_DEG`) vote for the translation between
   them, and the most voted cell (`VOTE_VOXELS` registration voxels) wins (`translations`).

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


def rotations(source: np.ndarray, target: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(rotation, the target's face directions it was matched on (k, 3)): two source modes
    onto two target modes at the same angle, and each of the `SWEPT` strongest source modes
    onto each of the target's, turned about it every `SWEEP_DEG` (module docstring)."""
    out = [(_turn(c, np.radians(a)) @ _onto(s, c), c[None]) for s in source[:SWEPT] for c in target[:SWEPT]
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
                        out.append((_frame(target[c], target[d]) @ _frame(source[a], source[b]).T,
                                    target[[c, d]]))
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


def translations(R: np.ndarray, faces: np.ndarray, source: tuple[np.ndarray, np.ndarray],
                 target: tuple[np.ndarray, np.ndarray], voxel_mm: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Translations (3,) under rotation R that was matched on the target's face directions
    `faces` (k, 3): along each, the most common difference between the heights of the
    target's and the turned source's points facing it (the face planes' offsets); across
    them, the most voted of the other points' votes (module docstring), the best two;
    `source`, `target`: (points, normals) on the registration's voxel grid."""
    sp, sn = source[0] @ R.T, source[1] @ R.T
    tp, tn = target
    cos_face = np.cos(np.radians(NORMAL_TOL_DEG))
    along = [_offset(sp[sn @ c > cos_face] @ c, tp[tn @ c > cos_face] @ c, voxel_mm, rng) for c in faces]
    if any(o is None for o in along):
        return []
    _, _, vt = np.linalg.svd(faces)
    across = vt[len(faces):]  # the directions the faces leave free
    flat = np.all(np.abs(sn @ faces.T) < cos_face, axis=1)
    pick = rng.choice(np.flatnonzero(flat), size=min(VOTERS, int(flat.sum())), replace=False)
    flat_t = np.all(np.abs(tn @ faces.T) < cos_face, axis=1)
    picked = rng.choice(np.flatnonzero(flat_t), size=min(VOTED, int(flat_t.sum())), replace=False)
    i, j = np.nonzero(sn[pick] @ tn[picked].T > cos_face)
    A = np.vstack([faces, across])
    if len(i) == 0:
        return []
    votes = (tp[picked][j] - sp[pick][i]) @ across.T
    cell = np.floor(votes / (VOTE_VOXELS * voxel_mm)).astype(np.int64)
    cell -= cell.min(axis=0)
    key = cell[:, 0] * (cell[:, 1].max() + 1) + cell[:, 1] if cell.shape[1] == 2 else cell[:, 0]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return [np.linalg.solve(A, np.concatenate([along, votes[inverse.ravel() == k].mean(axis=0)]))
            for k in np.argsort(-counts)[:2]]


def _offset(source: np.ndarray, target: np.ndarray, voxel_mm: float, rng: np.random.Generator) -> float | None:
    """The most common difference target - source of two sets of heights (mm), None when
    either is empty."""
    if len(source) == 0 or len(target) == 0:
        return None
    s = rng.choice(source, size=min(300, len(source)), replace=False)
    t = rng.choice(target, size=min(300, len(target)), replace=False)
    d = (t[:, None] - s[None, :]).ravel()
    cell = np.floor((d - d.min()) / (0.5 * voxel_mm)).astype(np.int64)
    k = int(np.argmax(np.bincount(cell)))
    return float(d[cell == k].mean())


def face_poses(source: tuple[np.ndarray, np.ndarray], target: tuple[np.ndarray, np.ndarray], voxel_mm: float,
               seed: int = 0) -> np.ndarray:
    """Starting poses (H, 4, 4), source -> target, from the views' face directions (module
    docstring); `source`, `target`: (points, normals) on the registration's voxel grid."""
    rng = np.random.default_rng(seed)
    poses = []
    for R, faces in rotations(normal_modes(source[1]), normal_modes(target[1])):  # some hundreds
        for t in translations(R, faces, source, target, voxel_mm, rng):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            poses.append(T)
    return np.array(poses).reshape(-1, 4, 4)
