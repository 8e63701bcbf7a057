"""A view pair's pose refined on what each sensor measured: projective point-to-plane
Gauss-Newton, both ways at once.

Each view's judged points (`pair_registration`: smooth pixels, one per voxel) are
moved into the other view and paired with the point that view measured on the pixel they
fall on (`SensorView`: smooth pixels only, normals within 60 deg), not with the nearest
point in space: a point on a step's wall finds the wall's measurement even when the pose is
a little off, where a nearest-neighbour ICP whose partner distance shrinks to the noise
drops it and stalls on the motions only such points fix (a turn about a boss's axis when
the views share mostly planes across it). Residuals are along the partner's normal, both
directions expressed in the target's frame; each step minimises their Cauchy loss of scale
s, s shrinking from `start_mm` by `ANNEAL` a step to the pair's noise sigma (graduated:
wide enough at first to see the pose's whole error, then down to the noise). Then plain
least squares over the residuals within `start_mm` (the coarse pose's tolerance): the
Cauchy loss at the noise's scale weighs a point a few tenths of a millimetre off at a
hundredth, so the few points that fix a weak motion (a wall's) would hardly pull, and the
pose would stop short where it is only a little off. Units mm.
"""

from __future__ import annotations

import numpy as np

from inspection.views.sensor_view import SensorView

ANNEAL = 0.75  # the Cauchy scale's shrink per step
STEPS = 20
MIN_COS = 0.5  # partners' normals within 60 deg
CUTOFF = 3.0  # residuals beyond this many scales weigh nothing (a hidden point paired with what hides it)

Judging = tuple[np.ndarray, np.ndarray, SensorView]


def _partners(points: np.ndarray, normals: np.ndarray,
              view: SensorView) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mask, partner points, partner normals) of `points` in `view` (its frame)."""
    px, inside = view.pixels_of(points)
    k = view.index[px[:, 1], px[:, 0]]
    ok = inside & (k >= 0) & view.smooth[px[:, 1], px[:, 0]]
    k = np.where(ok, k, 0)
    nb = view.normals[k]
    ok &= np.einsum("ij,ij->i", normals, nb) > MIN_COS
    return ok, view.points[k], nb


def refine_projective(T: np.ndarray, source: Judging, target: Judging, start_mm: float) -> np.ndarray:
    """Pose T (source -> target, 4x4) refined (module docstring); `source`, `target`:
    (points, normals, SensorView) of each view in its own frame."""
    sigma = float(np.hypot(source[2].sigma_mm, target[2].sigma_mm))
    T = _steps(T, source, target, scale=max(start_mm, sigma), floor=sigma, anneal=ANNEAL, cutoff=CUTOFF)
    return _steps(T, source, target, scale=start_mm, floor=start_mm, anneal=1.0, cutoff=1.0, plain=True)


def _steps(T: np.ndarray, source: Judging, target: Judging, *, scale: float, floor: float, anneal: float,
           cutoff: float, plain: bool = False) -> np.ndarray:
    """Gauss-Newton steps, the Cauchy scale from `scale` down by `anneal` to `floor`,
    residuals beyond `cutoff` scales left out; `plain`: least squares (weights 1) inside."""
    (sp, sn, sv), (tp, tn, tv) = source, target
    for _ in range(STEPS):
        R, t = T[:3, :3], T[:3, 3]
        q, qn = sp @ R.T + t, sn @ R.T
        a, xt, nt = _partners(q, qn, tv)
        b, xs, ns = _partners((tp - t) @ R, tn @ R, sv)
        moved, m = xs[b] @ R.T + t, ns[b] @ R.T
        points = np.vstack([q[a], moved])
        if len(points) < 6:
            break
        c = points.mean(axis=0)
        r = np.concatenate([np.einsum("ij,ij->i", q[a] - xt[a], nt[a]), np.einsum("ij,ij->i", tp[b] - moved, m)])
        J = np.vstack([np.hstack([np.cross(q[a] - c, nt[a]), nt[a]]), -np.hstack([np.cross(moved - c, m), m])])
        inside = np.abs(r) < cutoff * scale
        w = np.where(inside, 1.0 if plain else scale ** 2 / (scale ** 2 + r ** 2), 0.0)
        H = J.T @ (J * w[:, None])
        step = np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), -J.T @ (w * r))
        T = _motion(step, c) @ T
        if scale <= floor and np.linalg.norm(step[3:]) < 1e-4 * floor and np.linalg.norm(step[:3]) < 1e-7:
            break
        scale = max(anneal * scale, floor)
    return T


def _motion(step: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The 4x4 motion turning by step[:3] (rad, rotation vector) about `centre` and shifting
    by step[3:] (mm)."""
    from scipy.spatial.transform import Rotation

    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
    M[:3, 3] = centre - M[:3, :3] @ centre + step[3:]
    return M
