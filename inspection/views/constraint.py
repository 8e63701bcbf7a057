"""How well an overlap fixes a pose: the motions its point-to-plane partners cannot see.

A rigid motion (small rotation w about the partners' centre c, translation t) moves a partner
p along its target normal n by n . (w x (p - c) + t) = [(p - c)/L x n, n] . [L w, t], with L the
RMS distance of the partners from c. The 6x6 information H = sum J^T J, J = [(p - c)/L x n, n],
is then free of units: an eigenvalue divided by the number of partners is the mean squared
shift (mm^2 per mm of motion, a rotation counted by the shift it gives at L) that motion
along its eigenvector gives a partner. Points on one plane leave three motions unseen (both
in-plane shifts, the turn about the normal); on a cylinder two (the turn about and the shift
along its axis); a box corner none. A motion whose eigenvalue is a small share of the
largest is one the overlap barely fixes: ICP may slide along it with the fit as good as at
the truth, so such a pose is not to be trusted however well it fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inspection.views.pairwise import point_to_plane_information


@dataclass(frozen=True, eq=False)
class Constraint:
    """`eigenvalues` of the scaled information (ascending, per partner), `motions` their unit
    eigenvectors as columns ([L w, t]), `centre` c and `length_mm` L (mm)."""

    eigenvalues: np.ndarray
    motions: np.ndarray
    centre: np.ndarray
    length_mm: float

    @property
    def weakest(self) -> float:
        """The smallest eigenvalue over the largest (0: a motion left free; 1: all alike)."""
        return float(self.eigenvalues[0] / max(self.eigenvalues[-1], 1e-300))

    def describe(self, k: int = 0) -> str:
        """The motion along eigenvector `k` in words: a turn about an axis (its direction and
        a point on it, mm) when it moves a point at L more by turning than by shifting, a
        shift along a direction otherwise."""
        a, b = self.motions[:3, k], self.motions[3:, k]
        if np.linalg.norm(a) >= np.linalg.norm(b):
            axis = a / np.linalg.norm(a)
            point = self.centre + self.length_mm * np.cross(a, b) / float(a @ a)  # the screw axis of w = a / L
            return f"rotation about the axis along {_vec(axis, 2)} through {_vec(point, 1)} mm"
        return f"translation along {_vec(b / np.linalg.norm(b), 2)}"


def _vec(v: np.ndarray, digits: int) -> str:
    return "(" + ", ".join(f"{x:.{digits}f}" for x in v) + ")"


def overlap_constraint(points: np.ndarray, normals: np.ndarray) -> Constraint:
    """The Constraint of partners at `points` (mm) on surfaces with unit `normals`."""
    if len(points) < 6:
        return Constraint(np.zeros(6), np.eye(6), np.zeros(3), 1.0)
    centre = points.mean(axis=0)
    length = max(float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1)))), 1e-9)
    H = point_to_plane_information((points - centre) / length, normals, 1.0) / len(points)
    values, vectors = np.linalg.eigh(H)
    return Constraint(np.clip(values, 0.0, None), vectors, centre, length)


def along(constraint: Constraint, k: int, shift_mm: float) -> np.ndarray:
    """The 4x4 rigid motion along eigenvector `k` that moves a point at L from the centre by
    about `shift_mm` (mm): the screw [L w, t] = shift_mm x eigenvector, about the centre."""
    from scanner.stage_model import rotation_about

    a, b = shift_mm * constraint.motions[:3, k], shift_mm * constraint.motions[3:, k]
    angle = float(np.linalg.norm(a)) / constraint.length_mm
    R = rotation_about(a / np.linalg.norm(a), angle) if angle > 1e-12 else np.eye(3)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, constraint.centre - R @ constraint.centre + b
    return M
