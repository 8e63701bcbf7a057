"""Exact CAD surfaces as vectorised numpy evaluators: plane, cylinder, cone, sphere, torus
and (rational) B-spline.

Every surface maps parameters (u, v) to points in the model frame (mm) and projects points
back onto itself. Parameter conventions follow OpenCASCADE, so a face's trimming domain (its
UV box and pcurves) applies unchanged:

    plane     P = O + u X + v Y
    cylinder  P = O + R (cos u X + sin u Y) + v Z                    u in rad, v in mm
    cone      P = O + (R0 + v sin a)(cos u X + sin u Y) + v cos a Z  u in rad, v in mm
    sphere    P = O + R cos v (cos u X + sin u Y) + R sin v Z        u, v in rad
    torus     P = O + (R + r cos v)(cos u X + sin u Y) + r sin v Z   u, v in rad

(O, X, Y, Z) is the surface's placement; Z = X x Y or -(X x Y) (OpenCASCADE's direct or
indirect frames), so normals are always computed as S_u x S_v ("natural" normal), and a
face turns it outward with its orientation sign. Signed distances are along the natural
normal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

TWO_PI = 2.0 * np.pi


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


@dataclass(frozen=True, eq=False)
class Surface:
    """Base: placement (origin, X, Y, Z), all (3,) float64 in mm / unit vectors."""

    origin: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    kind: str = field(init=False, default="surface")
    u_period: float | None = field(init=False, default=None)
    v_period: float | None = field(init=False, default=None)

    def evaluate(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points (N, 3) mm, unit natural normals (N, 3), area Jacobian |S_u x S_v| (N,))."""
        p, su, sv = self._point_and_derivatives(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
        n = np.cross(su, sv)
        jac = np.linalg.norm(n, axis=1)
        return p, n / np.where(jac > 0, jac, 1.0)[:, None], jac

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest points: (uv (N, 2), foot points (N, 3), unit natural normals (N, 3),
        signed distance (N,) mm along the natural normal). u (and v) of periodic surfaces
        come in [0, period)."""
        uv = self._closest_uv(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        foot, normal, _ = self.evaluate(uv)
        return uv, foot, normal, _dot(points - foot, normal)

    def local(self, points: np.ndarray) -> np.ndarray:
        """Points (N, 3) in the placement's (X, Y, Z) coordinates."""
        d = np.asarray(points, dtype=np.float64) - self.origin
        return np.stack([d @ self.x, d @ self.y, d @ self.z], axis=1)

    def metric_scale(self, box: tuple[float, float, float, float]) -> tuple[float, float]:
        """Largest mm per unit of u and of v over the UV box (umin, umax, vmin, vmax)."""
        raise NotImplementedError

    def max_jacobian(self, box: tuple[float, float, float, float]) -> float:
        """An upper bound of |S_u x S_v| over the UV box (mm^2 per unit u·v)."""
        su, sv = self.metric_scale(box)
        return su * sv

    def params(self) -> dict[str, Any]:
        """Nominal parameters as plain JSON-able values (mm, rad)."""
        return {"origin_mm": self.origin.tolist(), "axis": self.z.tolist()}

    def _point_and_derivatives(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _closest_uv(self, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _radial(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(u)[:, None], np.sin(u)[:, None]
        return c * self.x + s * self.y, -s * self.x + c * self.y

    def _angle(self, q: np.ndarray) -> np.ndarray:
        return np.mod(np.arctan2(q[:, 1], q[:, 0]), TWO_PI)


@dataclass(frozen=True, eq=False)
class Plane(Surface):
    kind: str = field(init=False, default="plane")

    def _point_and_derivatives(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = self.origin + uv[:, :1] * self.x + uv[:, 1:] * self.y
        return p, np.broadcast_to(self.x, p.shape), np.broadcast_to(self.y, p.shape)

    def _closest_uv(self, p: np.ndarray) -> np.ndarray:
        return self.local(p)[:, :2]

    def metric_scale(self, box: tuple[float, float, float, float]) -> tuple[float, float]:
        return 1.0, 1.0

    def params(self) -> dict[str, Any]:
        return {"origin_mm": self.origin.tolist(), "normal": np.cross(self.x, self.y).tolist()}


@dataclass(frozen=True, eq=False)
class Cylinder(Surface):
    radius: float = 1.0
    kind: str = field(init=False, default="cylinder")
    u_period: float | None = field(init=False, default=TWO_PI)

    def _point_and_derivatives(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e, t = self._radial(uv[:, 0])
        p = self.origin + self.radius * e + uv[:, 1:] * self.z
        return p, self.radius * t, np.broadcast_to(self.z, p.shape)

    def _closest_uv(self, p: np.ndarray) -> np.ndarray:
        q = self.local(p)
        return np.stack([self._angle(q), q[:, 2]], axis=1)

    def metric_scale(self, box: tuple[float, float, float, float]) -> tuple[float, float]:
        return self.radius, 1.0

    def params(self) -> dict[str, Any]:
        return {**super().params(), "radius_mm": self.radius}


@dataclass(frozen=True, eq=False)
class Cone(Surface):
    ref_radius: float = 1.0
    semi_angle: float = 0.0
    kind: str = field(init=False, default="cone")
    u_period: float | None = field(init=False, default=TWO_PI)

    def _point_and_derivatives(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e, t = self._radial(uv[:, 0])
        s, c = np.sin(self.semi_angle), np.cos(self.semi_angle)
        r = (self.ref_radius + uv[:, 1] * s)[:, None]
        p = self.origin + r * e + (uv[:, 1] * c)[:, None] * self.z
        return p, r * t, s * e + c * self.z

    def _closest_uv(self, p: np.ndarray) -> np.ndarray:
        q = self.local(p)
        rho = np.hypot(q[:, 0], q[:, 1])
        v = (rho - self.ref_radius) * np.sin(self.semi_angle) + q[:, 2] * np.cos(self.semi_angle)
        return np.stack([self._angle(q), v], axis=1)

    def metric_scale(self, box: tuple[float, float, float, float]) -> tuple[float, float]:
        s = np.sin(self.semi_angle)
        return float(max(abs(self.ref_radius + box[2] * s), abs(self.ref_radius + box[3] * s))), 1.0

    def params(self) -> dict[str, Any]:
        return {**super().params(), "ref_radius_mm": self.ref_radius, "semi_angle_rad": self.semi_angle}


@dataclass(frozen=True, eq=False)
class Sphere(Surface):
    radius: float = 1.0
    kind: str = field(init=False, default="sphere")
    u_period: float | None = field(init=False, default=TWO_PI)

    def _point_and_derivatives(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e, t = self._radial(uv[:, 0])
        cv, sv = np.cos(uv[:, 1])[:, None], np.sin(uv[:, 1])[:, None]
        R = self.radius
        p = self.origin + R * cv * e + R * sv * self.z
        return p, R * cv * t, -R * sv * e + R * cv * self.z

    def _closest_uv(self, p: np.ndarray) -> np.ndarray:
        q = self.local(p)
        return np.stack([self._angle(q), np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1]))], axis=1)

    def metric_scale(self, box: tuple[float, float, float, float]) -> tuple[float, float]:
        return self.radius, self.radius

    def params(self) -> dict[str, Any]:
        return {"center_mm": self.origin.tolist(), "radius_mm": self.radius}


@dataclass(frozen=True, eq=False)
class Torus(Surface):
    major_radius: float = 1.0
    minor_radius: float = 1.0
    kind: str = field(init=False, default="torus")
    u_period: float | None = field(init=False, default=TWO_PI)
    v_period: float | None = field(init=False, default=TWO_PI)

    def _point_and_derivatives(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e, t = self._radial(uv[:, 0])
        cv, sv = np.cos(uv[:, 1])[:, None], np.sin(uv[:, 1])[:, None]
        R, r = self.major_radius, self.minor_radius
        p = self.origin + (R + r * cv) * e + r * sv * self.z
        return p, (R + r * cv) * t, -r * sv * e + r * cv * self.z

    def _closest_uv(self, p: np.ndarray) -> np.ndarray:
        q = self.local(p)
        u = self._angle(q)
        rho = np.hypot(q[:, 0], q[:, 1]) - self.major_radius
        return np.stack([u, np.mod(np.arctan2(q[:, 2], rho), TWO_PI)], axis=1)

    def metric_scale(self, box: tuple[float, float, float, float]) -> tuple[float, float]:
        return self.major_radius + self.minor_radius, self.minor_radius

    def params(self) -> dict[str, Any]:
        return {**super().params(), "major_radius_mm": self.major_radius, "minor_radius_mm": self.minor_radius}


@dataclass(frozen=True, eq=False)
class BSpline(Surface):
    """A (rational) tensor-product B-spline: `knots` (tu, tv) full knot vectors, `degrees`
    (du, dv), homogeneous control points `control` (nu, nv, 4) = (w x, w y, w z, w).
    Projection: Newton iterations from the nearest of a dense parameter grid."""

    knots: tuple[np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0))
    degrees: tuple[int, int] = (1, 1)
    control: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 4)))
    kind: str = field(init=False, default="bspline")
    # set by __post_init__: the spline (scipy NdBSpline), and a dense grid of parameters
    # with a KD-tree (scipy cKDTree) of its points, where projection starts
    _spline: Any = field(init=False, repr=False)
    _grid_uv: np.ndarray = field(init=False, repr=False)
    _grid_tree: Any = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from scipy.interpolate import NdBSpline

        object.__setattr__(self, "_spline", NdBSpline(self.knots, self.control, self.degrees))
        tu, tv = self.knots
        du, dv = self.degrees
        box = (tu[du], tu[-du - 1], tv[dv], tv[-dv - 1])
        g = np.stack(np.meshgrid(np.linspace(box[0], box[1], 64), np.linspace(box[2], box[3], 64)), -1).reshape(-1, 2)
        from scipy.spatial import cKDTree

        object.__setattr__(self, "_grid_uv", g)
        object.__setattr__(self, "_grid_tree", cKDTree(self._point_and_derivatives(g)[0]))

    def _rational(self, uv: np.ndarray, order: tuple[int, int]) -> np.ndarray:
        return self._spline(uv, nu=order)

    def _point_and_derivatives(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        h = self._rational(uv, (0, 0))
        hu = self._rational(uv, (1, 0))
        hv = self._rational(uv, (0, 1))
        w = h[:, 3:]
        p = h[:, :3] / w
        return p, (hu[:, :3] - p * hu[:, 3:]) / w, (hv[:, :3] - p * hv[:, 3:]) / w

    def _closest_uv(self, p: np.ndarray) -> np.ndarray:
        _, idx = self._grid_tree.query(p)
        uv = self._grid_uv[idx].copy()
        tu, tv = self.knots
        du, dv = self.degrees
        lo = np.array([tu[du], tv[dv]])
        hi = np.array([tu[-du - 1], tv[-dv - 1]])
        for _ in range(12):  # Gauss-Newton on |S(u, v) - p|^2
            s, su, sv = self._point_and_derivatives(uv)
            r = s - p
            a, b, c = _dot(su, su), _dot(su, sv), _dot(sv, sv)
            gu, gv = _dot(su, r), _dot(sv, r)
            det = a * c - b * b
            det = np.where(np.abs(det) > 1e-30, det, 1e-30)
            step = np.stack([(c * gu - b * gv) / det, (a * gv - b * gu) / det], axis=1)
            uv = np.clip(uv - step, lo, hi)
            if np.abs(step).max() < 1e-12:
                break
        return uv

    def metric_scale(self, box: tuple[float, float, float, float]) -> tuple[float, float]:
        g = np.stack(np.meshgrid(np.linspace(box[0], box[1], 16), np.linspace(box[2], box[3], 16)), -1).reshape(-1, 2)
        _, su, sv = self._point_and_derivatives(g)
        return float(np.linalg.norm(su, axis=1).max()), float(np.linalg.norm(sv, axis=1).max())

    def max_jacobian(self, box: tuple[float, float, float, float]) -> float:
        g = np.stack(np.meshgrid(np.linspace(box[0], box[1], 24), np.linspace(box[2], box[3], 24)), -1).reshape(-1, 2)
        return 1.25 * float(self.evaluate(g)[2].max())

    def params(self) -> dict[str, Any]:
        return {"degrees": list(self.degrees), "poles": [int(self.control.shape[0]), int(self.control.shape[1])]}
