"""Form and texture of one measured face: least-squares and minimum-zone flatness and
cylindricity of the form surface (a second-order Gaussian regression filter), Sq after
noise removal beside ISO 25178-2's Sq of the measured surface, and the deviations from
nominal, each with its uncertainty (`inspection.uncertainty`).

Inputs are the face's measured points in the model frame (after registration), their
signed deviations from the nominal surface (`segmentation`), and optionally their noise
model (`PointNoise`, rays turned into the model frame) with the face's normals there, and
the points' displacements for each calibration direction. Heights are laid on the face's
own 2D coordinates (a plane: its in-plane axes; a cylinder: arc length R*theta and axial
position, unrolled), resampled on a square grid of about the point spacing.

Filters (the Gaussian weighting function of ISO 16610-61, s(x) = exp(-pi (x/(alpha
lc))^2)/(alpha lc)^2, alpha = sqrt(ln 2 / pi): 50 % transmission at the nesting index lc):
  - the form surface is the heights through a second-order Gaussian regression filter of
    cut-off `form_cutoff_mm` (those weights, a quadratic fitted about each cell; not ISO
    16610-61's Gaussian filter, which is the weighted mean): it keeps quadratic form (a
    bow, a taper) exactly up to the face's edges, where the plain Gaussian mean would pull
    it toward the interior;
  - the roughness (S-L) surface is the heights minus their Gaussian filter (ISO 16610-61,
    the weighted mean, normalised where the face ends) of cut-off `roughness_cutoff_mm`.
    ISO 25178-2's Sq is its RMS (`sq_raw_mm`, the scanner's noise included); the figure
    `sq` is Sq after noise removal: the noise's mean square subtracted (an estimate of
    the true surface's ISO Sq, `_sq`).

Camera defocus. Where the noise model carries the depth bias the camera's blur put on each
point (`PointNoise.defocus_dz`, `inspection.uncertainty.defocus_bias`: first order, away
from edges), it is removed from the points before anything else, and their noise raised
by what the removal adds (Sq of a 1.5-4 mm texture read ~3 % low without it).

Scanner noise. A point moves along its camera ray; its deviation moves by (n·ray)·δz. The
noise model's draws (white noise per point and the fringe systematic per projector
column) are binned into the grid cells like the heights, and every figure is evaluated
again on the measured surface plus each draw (`FormSettings.draws`): the spread gives the
figure's noise uncertainty, the mean shift its noise bias, which is removed and, being
itself uncertain, enters u (`from_draws`) (zones of the form surface, the profile, the
deviation extremes and RMS); the same figure of the drawn
noise alone gives the detection limit of the zones (95th percentile). Sq has the noise's
mean square removed (Sq² - <e²>), and is null below its detection limit. Without a noise
model the noise is estimated from the heights themselves (fourth differences along the
grid, blind to the smooth form and texture, `noise_sigma`) and drawn white per cell.

Profile of a surface (ISO 1101, zone centred on nominal): 2 max|d| over the form
surface's signed deviations d: what the surface does at wavelengths above the form
cut-off (stated in the report). The raw points' extremes, which are those of the noise
(about sigma_n sqrt(2 ln N), 4-5 sigma_n for 1e4-1e6 points, on both sides), are kept
beside it with their own uncertainty.

Minimum zone (Chebyshev, the ISO 1101 default): the narrowest pair of parallel planes
(coaxial cylinders) holding the surface, solved as a linear programme (HiGHS) on the
planes' (cylinders') small-displacement parameters about the least-squares fit,
relinearised until it settles. Least squares: Eq. 20 (plane) and Eq. 21-22 (cylinder)
of paper 000. Every length in mm.

Speed (the draws are most of the work): a plane's zones of the measured surface, of it
plus each draw and of each draw alone are solved a batch at a time, in one LP over a few
candidate points per surface, every point then checked and the violators added (exact);
the draws are filtered as one stack, the L-filter's mean taken from the form filter's
transform. A cylinder's surfaces are each fitted once for both zones, by Levenberg-Marquardt
with the radii's analytic derivatives, and its zone's LP solved by a dual simplex on its
six-row bases (HiGHS only where that fails), each relinearisation from the last one's basis.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable, Iterator
from contextvars import ContextVar
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, TypedDict, TypeVar

import numpy as np
from scipy import fft, ndimage
from scipy.optimize import leastsq, linprog

from inspection import figures
from inspection.surfaces import Cone, Cylinder, Surface
from inspection.uncertainty import DETECTION_QUANTILE, DETECTION_Z, Estimate, PointNoise

if TYPE_CHECKING:
    from inspection.cad import Face

ALPHA = float(np.sqrt(np.log(2.0) / np.pi))  # ISO 16610-61
# threads of the filters' FFTs and the grid's tree query (-1: every core); a thread evaluating a face beside
# others sets 1 (two faces on two cores, each with its own threads, only contend)
FORM_WORKERS: ContextVar[int] = ContextVar("form_workers", default=-1)
FORM_CUTOFF_MM = 8.0
ROUGHNESS_CUTOFF_MM = 8.0
MIN_POINTS = 50


# ------------------------------------------------------------------------- least squares


def plane_ls(points: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Paper 000 Eq. 20: z = a x + b y + c in a frame whose z is the nominal `normal`;
    returns (a point on the plane, its unit normal)."""
    u, v = _frame(normal)
    c0 = points.mean(axis=0)
    d = points - c0
    x, y, z = d @ u, d @ v, d @ normal
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    (a, b, c), *_ = np.linalg.lstsq(A, z, rcond=None)
    n = normal - a * u - b * v
    return c0 + c * normal, n / np.linalg.norm(n)


LS_TOL = 1e-12  # the cylinder fit's tolerances (LM's, relative): its minimum to round-off (the default 1e-8
# stopped up to 1e-7 mm short on a noisy cylinder)


def cylinder_ls(points: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Paper 000 Eq. 21-22: the axis (point, direction) minimising sum (r_i - mean r)^2,
    r_i = |o p_i x n|, from the nominal axis; returns (origin, unit axis, mean radius).
    Levenberg-Marquardt on the axis's four parameters (`_AxisRadii`), derivatives analytic."""
    axis = axis / np.linalg.norm(axis)
    u, v = _frame(axis)
    o0 = origin + (points - origin).mean(axis=0) @ axis * axis  # centred along the axis
    radii = _AxisRadii(points - o0, u, v, axis)
    # MINPACK's lmder (as least_squares' "lm"), the Jacobian handed over a row per parameter as it is made
    x, *_ = leastsq(radii.spread, np.zeros(4), Dfun=radii.spread_jacobian, col_deriv=True,
                    xtol=LS_TOL, ftol=LS_TOL, gtol=LS_TOL)
    o, n = _axis(o0, u, v, axis, x)
    return o, n, float(radii.radii(x).mean())


class _AxisRadii:
    """The radii of points about the axis through o0 + x2 u + x3 v along n0 + x0 u + x1 v
    (`_axis`; (u, v, n0) orthonormal) as functions of x (4,), and their derivatives. With
    the points' coordinates (A, B, C) = (q.u - x2, q.v - x3, q.n0) about that axis point
    (q: relative to o0) and m = (x0, x1, 1) the unnormalised direction, s = |m|:
        r = |(A, B, C) x m| / s   (no cancellation, however long the cylinder),
        dr/dx2 = -e.u, dr/dx3 = -e.v, dr/dx0 = -a e.u / s, dr/dx1 = -a e.v / s,
    a = (A, B, C).m / s the axial coordinate and e the unit radial direction
    ((A, B, C) - a m / s) / r, from r^2 = |d|^2 - (d.n)^2 (d: point less axis point)."""

    def __init__(self, q: np.ndarray, u: np.ndarray, v: np.ndarray, n0: np.ndarray) -> None:
        # einsum: no BLAS threads on thin products (a pool contending with other work costs more than it saves)
        self.qu, self.qv, self.qn = np.einsum("ij,kj->ki", q, np.stack([u, v, n0]))
        self._x = np.full(4, np.nan)
        self._at: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float] | None = None

    def _terms(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """(r, A, B, a, s) at x; the last x's are kept (LM asks for the Jacobian where it has
        just evaluated the residuals)."""
        if not np.array_equal(x, self._x):
            x0, x1, x2, x3 = x
            A, B, C = self.qu - x2, self.qv - x3, self.qn
            s = float(np.sqrt(1.0 + x0 * x0 + x1 * x1))
            r = np.sqrt((B - C * x1) ** 2 + (C * x0 - A) ** 2 + (A * x1 - B * x0) ** 2) / s
            self._x, self._at = x.copy(), (r, A, B, (A * x0 + B * x1 + C) / s, s)
        assert self._at is not None
        return self._at

    def radii(self, x: np.ndarray) -> np.ndarray:
        """The radii (N,) about the axis x."""
        return self._terms(x)[0]

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """dr/dx (4, N) at x, a row per parameter."""
        r, A, B, a, s = self._terms(x)
        eu, ev = (A - a * x[0] / s) / r, (B - a * x[1] / s) / r
        return np.stack([-a * eu / s, -a * ev / s, -eu, -ev])

    def spread(self, x: np.ndarray) -> np.ndarray:
        """r - mean r (N,): the residuals of Eq. 21."""
        r = self.radii(x)
        return r - r.mean()

    def spread_jacobian(self, x: np.ndarray) -> np.ndarray:
        """d(r - mean r)/dx (4, N)."""
        J = self.jacobian(x)
        return J - J.mean(axis=1, keepdims=True)


def _axis(o0: np.ndarray, u: np.ndarray, v: np.ndarray, n0: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = n0 + x[0] * u + x[1] * v
    return o0 + x[2] * u + x[3] * v, n / np.linalg.norm(n)


def _frame(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = normal / np.linalg.norm(normal)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


# ---------------------------------------------------------------------------- min zone


def flatness_mz(points: np.ndarray, normal: np.ndarray) -> float:
    """Minimum-zone flatness: the least distance between two parallel planes holding the
    points (N, 3), heights taken along their least-squares normal (from the nominal
    `normal`); `flatness_mz_many` in the nominal normal's frame."""
    n = normal / np.linalg.norm(normal)
    u, v = _frame(n)
    d = points - points.mean(axis=0)
    return float(flatness_mz_many(np.stack([d @ u, d @ v], axis=1), (d @ n)[None])[0])


def flatness_mz_many(xy: np.ndarray, heights: np.ndarray, tilt: np.ndarray | None = None) -> np.ndarray:
    """Minimum-zone flatness (B,) of B surfaces sampled at the same places: in-plane
    coordinates `xy` (N, 2) and heights (B, N) along the nominal normal, each surface's zone
    measured along its own least-squares normal. An LP on the plane's tilt and the zone's
    bounds over a few candidate points per surface (the most extreme heights, or the most
    extreme about the `tilt` (2,) of a related zone, `plane_zone_tilt`: where the zone of the
    measured surface plus a noise draw is held), then every point checked and the
    violators added until none is left:
    exact, as the zone of a subset is never wider, and one holding every point is the zone
    of them all. All surfaces share one LP (`_plane_lps`)."""
    return _mz_widths(_LsFrames.of(xy, heights), tilt)


def _mz_widths(frames: _LsFrames, tilt: np.ndarray | None = None) -> np.ndarray:
    """`flatness_mz_many` of surfaces already in their LS frames."""
    a, b, _, w = _plane_zones(frames, tilt)
    return w / np.sqrt(1.0 + a * a + b * b)


def flatness_ls_many(xy: np.ndarray, heights: np.ndarray) -> np.ndarray:
    """Least-squares flatness (B,) of B surfaces (as `flatness_mz_many`): the spread of the
    heights about each surface's least-squares plane."""
    return _ls_widths(_LsFrames.of(xy, heights))


def _ls_widths(frames: _LsFrames) -> np.ndarray:
    """`flatness_ls_many` of surfaces already in their LS frames."""
    def widths(rows: slice) -> np.ndarray:
        z = frames.along(frames.n[rows], rows)
        return z.max(axis=1) - z.min(axis=1)

    return np.concatenate([widths(c) for c in _row_chunks(len(frames.n))])


def plane_zone_tilt(xy: np.ndarray, height: np.ndarray) -> np.ndarray:
    """The minimum zone's tilt (2,) relative to the least-squares plane of one surface
    (heights (N,) at `xy` (N, 2))."""
    a, b, _, _ = _plane_zones(_LsFrames.of(xy, height[None]), None)
    return np.array([a[0], b[0]])


@dataclass(frozen=True, eq=False)
class _LsFrames:
    """B surfaces sampled at the same places, each in the frame of its least-squares plane
    (paper 000 Eq. 20, `plane_ls`; in-plane axes `u`, `v` as `_frame` picks them, normal `n`,
    each (B, 3) in the nominal frame), kept as the shared centred in-plane coordinates `X`,
    `Y` (N,) and the heights `Z` (B, N) above each plane's centre: a coordinate along any
    per-surface direction is then one pass (`along`) instead of three stored arrays."""

    X: np.ndarray
    Y: np.ndarray
    Z: np.ndarray
    u: np.ndarray
    v: np.ndarray
    n: np.ndarray

    @classmethod
    def of(cls, xy: np.ndarray, heights: np.ndarray) -> _LsFrames:
        """The frames of surfaces with heights (B, N) along the nominal normal at `xy` (N, 2)."""
        X, Y = (xy - xy.mean(axis=0)).T
        A = np.stack([X, Y, np.ones_like(X)])
        H = heights - heights.mean(axis=1, keepdims=True)
        # (B, 3): z = a x + b y + c fitted to every surface at once (einsum: no BLAS threads on thin products)
        coef = np.linalg.solve(np.einsum("in,jn->ij", A, A), np.einsum("in,bn->ib", A, H)).T
        n = np.column_stack([-coef[:, 0], -coef[:, 1], np.ones(len(H))])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        pick = np.where(np.abs(n[:, :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        u = np.cross(n, pick)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return cls(X, Y, H - coef[:, 2:3], u, np.cross(n, u), n)

    def along(self, e: np.ndarray, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """Coordinates (R, N) of every point of the surfaces `rows` along each one's
        direction e (R, 3)."""
        out = self.Z[rows] * e[:, 2:3]
        out += np.multiply.outer(e[:, 0], self.X)
        out += np.multiply.outer(e[:, 1], self.Y)
        return out

    def at(self, e: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """`along` only at the points (rows, cols) (M,)."""
        return self.X[cols] * e[rows, 0] + self.Y[cols] * e[rows, 1] + self.Z[rows, cols] * e[rows, 2]


ZONE_CANDIDATES = 32  # extreme points per side a zone's LP starts from; violators join this many at a time
ZONE_SLACK_MM = 1e-10  # a point this far outside a zone counts as inside (HiGHS's round-off)
ZONE_SUBSET_STRIDE = 8  # the zone is first found over every 8th point, then checked and completed over all
ROW_CHUNK = 4  # draws worked on at a time where a stack of them would be a fresh mapping (`_row_chunks`)


def _plane_zones(f: _LsFrames, tilt: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """min w subject to lo <= z - a x - b y <= lo + w for every surface (x, y, z its
    coordinates in `f`); returns (a, b, lo, w), each (B,). Active set: each surface's
    extreme heights (about `tilt`, when given), then the violators of each solution, until
    every point is held: first over every ZONE_SUBSET_STRIDE-th point (a smooth surface's
    zone there is all but the whole one's), then over all of them from that active set."""
    B, N = f.Z.shape
    if B == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)
    sub = slice(None, None, ZONE_SUBSET_STRIDE)
    part = _LsFrames(f.X[sub], f.Y[sub], np.ascontiguousarray(f.Z[:, sub]), f.u, f.v, f.n)
    k = min(len(part.X), ZONE_CANDIDATES)
    active = np.zeros((B, len(part.X)), bool)
    rows = np.arange(B)[:, None]
    h = part.along(f.n if tilt is None else f.n - tilt[0] * f.u - tilt[1] * f.v)
    active[rows, np.argpartition(h, k - 1, axis=1)[:, :k]] = True
    active[rows, np.argpartition(-h, k - 1, axis=1)[:, :k]] = True
    sol = np.zeros((B, 4))
    _zone_rounds(part, active, sol, ZONE_CANDIDATES, solved=False)
    held = np.zeros((B, N), bool)
    held[:, sub] = active
    _zone_rounds(f, held, sol, ZONE_SUBSET_STRIDE * ZONE_CANDIDATES, solved=True)
    return sol[:, 0], sol[:, 1], sol[:, 2], sol[:, 3]


def _zone_rounds(f: _LsFrames, active: np.ndarray, sol: np.ndarray, per_round: int, solved: bool) -> None:
    """Solve every surface's zone over its `active` points (B, N), check all points and add
    up to `per_round` of the worst violators per surface, until none is left; `active` and
    `sol` (B, 4: a, b, lo, w) are updated in place; `solved`: `sol` already holds the
    solutions over `active` (the check comes first)."""
    k = min(f.Z.shape[1], per_round)
    todo = np.arange(len(sol))
    for _ in range(50):  # a few rounds at most
        if not solved:
            s, j = np.nonzero(active[todo])
            rs = todo[s]
            sol[todo] = _plane_lps(len(todo), s, f.at(f.u, rs, j), f.at(f.v, rs, j), f.at(f.n, rs, j))
        solved = False
        todo = np.concatenate([_add_violators(f, todo[c], active, sol, k) for c in _row_chunks(len(todo))])
        if not len(todo):
            return


def _add_violators(f: _LsFrames, rows: np.ndarray, active: np.ndarray, sol: np.ndarray, k: int) -> np.ndarray:
    """Mark up to k of the worst points outside each zone `rows` as active; returns the
    rows that had any."""
    a, b, lo, w = (sol[rows, i:i + 1] for i in range(4))
    excess = f.along(f.n[rows] - a * f.u[rows] - b * f.v[rows], rows)  # r, then how far outside the zone
    below = lo - excess
    excess -= lo
    excess -= w
    np.maximum(below, excess, out=excess)
    excess[active[rows]] = -np.inf
    more = (excess > ZONE_SLACK_MM).any(axis=1)
    rows, excess = rows[more], excess[more]
    worst = np.argpartition(-excess, k - 1, axis=1)[:, :k]
    add = np.take_along_axis(excess, worst, axis=1) > ZONE_SLACK_MM
    active[np.broadcast_to(rows[:, None], worst.shape)[add], worst[add]] = True
    return rows


def mz_zone_sensitivity(xy: np.ndarray, height: np.ndarray) -> np.ndarray:
    """The minimum-zone flatness's first-order change per unit height at each of the
    points (N,) of one surface (heights (N,) at `xy` (N, 2)): the zone's LP dual prices on
    the points that hold it (the others 0), over the cos of its tilt."""
    frames = _LsFrames.of(xy, height[None])
    a, b, lo, w = (v[0] for v in _plane_zones(frames, None))
    xs, ys, zs = (frames.along(e)[0] for e in (frames.u, frames.v, frames.n))
    r = zs - a * xs - b * ys
    tol = max(1e-6 * w, 10.0 * ZONE_SLACK_MM)
    support = np.flatnonzero((r <= lo + tol) | (r >= lo + w - tol))
    out = np.zeros(len(height))
    duals = _plane_lp_duals(xs[support], ys[support], zs[support])
    m = len(support)
    upper, lower = duals[:m], duals[m:]
    out[support] = (lower - upper) / np.sqrt(1.0 + a * a + b * b)  # d(w)/d(z): the RHS moves -dz above, +dz below
    return out


def ls_zone_sensitivity(xy: np.ndarray, height: np.ndarray) -> np.ndarray:
    """The least-squares flatness's (range about the LS plane) first-order change per unit
    height at each point (N,): +1 at the highest residual, -1 at the lowest, less what
    moving them does to the plane."""
    A = np.column_stack([xy - xy.mean(axis=0), np.ones(len(xy))])
    coef = np.linalg.lstsq(A, height, rcond=None)[0]
    r = height - A @ coef
    d = np.zeros(len(height))
    d[int(np.argmax(r))] += 1.0
    d[int(np.argmin(r))] -= 1.0
    return d - A @ np.linalg.solve(A.T @ A, A.T @ d)


def _plane_lp_duals(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """HiGHS's dual prices (2m,) of one zone's LP over points (xs, ys, zs) (`_plane_lps`'s
    constraints: the upper side's m rows, then the lower side's)."""
    m = len(xs)
    one = np.ones(m)
    A_ub = np.concatenate([np.stack([-xs, -ys, -one, -one], 1), np.stack([xs, ys, one, 0 * one], 1)])
    res = linprog([0.0, 0.0, 0.0, 1.0], A_ub=A_ub, b_ub=np.concatenate([-zs, zs]),
                  bounds=[(None, None)] * 3 + [(0.0, None)], method="highs")
    if res.status != 0:
        raise ArithmeticError(f"minimum-zone LP of {m} points: {res.message}")
    return np.asarray(res.ineqlin.marginals)


def _plane_lps(count: int, s: np.ndarray, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """One HiGHS LP for `count` independent zones, point m (coordinates xs, ys, zs) held by
    zone s[m]: variables (a, b, lo, w) per zone, minimising the sum of the widths, which,
    the zones sharing no variable, minimises each. Returns (count, 4)."""
    from scipy.sparse import coo_array

    m = len(s)
    one = np.ones(m)
    row = np.concatenate([np.repeat(np.arange(m), 4), np.repeat(np.arange(m, 2 * m), 3)])
    col = np.concatenate([(4 * s[:, None] + np.arange(4)).ravel(), (4 * s[:, None] + np.arange(3)).ravel()])
    val = np.concatenate([np.stack([-xs, -ys, -one, -one], 1).ravel(), np.stack([xs, ys, one], 1).ravel()])
    A_ub = coo_array((val, (row, col)), shape=(2 * m, 4 * count)).tocsr()
    c = np.tile([0.0, 0.0, 0.0, 1.0], count)
    bounds = np.tile([[-np.inf, np.inf]] * 3 + [[0.0, np.inf]], (count, 1))
    res = linprog(c, A_ub=A_ub, b_ub=np.concatenate([-zs, zs]), bounds=bounds, method="highs")
    if res.status != 0:
        raise ArithmeticError(f"minimum-zone LP of {count} zones: {res.message}")
    return res.x.reshape(-1, 4)


def cylindricity_mz(points: np.ndarray, origin: np.ndarray, axis: np.ndarray, rounds: int = 6) -> float:
    """Minimum-zone cylindricity: the least radial distance between two coaxial cylinders
    holding the points, from their least-squares axis (`cylinder_ls`, from the nominal
    axis (`origin`, `axis`)); `cylinder_mz_from`."""
    o, n, _ = cylinder_ls(points, origin, axis)
    return cylinder_mz_from(points, o, n, rounds=rounds)


def cylinder_mz_from(points: np.ndarray, origin: np.ndarray, axis: np.ndarray, *, rounds: int = 6) -> float:
    """`cylindricity_mz` from the axis (`origin`, unit `axis`) of the points' least-squares
    fit: an LP on the axis's four small-displacement parameters about the current axis
    (`_cylinder_zone`), relinearised until the zone stops narrowing (at most `rounds`), each
    round's LP started from the last one's optimal basis (the axis moves little, so it
    mostly still is one)."""
    o, n = origin, axis
    width = np.inf
    at_axis = np.zeros(4)
    basis = None
    for _ in range(rounds):
        u, v = _frame(n)
        radii = _AxisRadii(points - o, u, v, n)
        x, basis = _cylinder_zone(radii.radii(at_axis), radii.jacobian(at_axis), basis)
        r = radii.radii(x)
        new = float(r.max() - r.min())
        if new >= width - 1e-9:
            break
        o, n = _axis(o, u, v, n, x)
        width = new
    return float(width)


CYLINDER_CANDIDATES = 50  # extreme radii per side a cylinder zone starts from
CYLINDER_VIOLATORS = 50  # the worst points outside its zone added to it at a time
CYLINDER_SLACK_MM = 1e-9  # a point this far outside the zone counts as inside
CYLINDER_PIVOTS = 200  # dual simplex steps on a set of points before HiGHS takes over
CYLINDER_BOX = 1e3  # |x_j| <= this: the bounds a zone's dual simplex starts from (`_box_basis`)
DUAL_TOL = 1e-12  # a basis's dual prices (each side's sum to 1) this far below 0 still count as feasible


def _cylinder_zone(r: np.ndarray, dr: np.ndarray, basis: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The axis displacement x (4,) of the narrowest zone R <= r + x.dr <= R + w holding
    every point (radii r (N,), their derivatives dr (4, N), a row per parameter), and the
    zone's optimal basis (`_zone_rows`; None where HiGHS found the zone): the dual simplex
    over every point from `basis` (a previous round's: mostly still optimal, or a few steps
    from it), else the zone of the points with the most extreme radii, then the worst
    violators added and solved again (`_held_zone`, from the last basis) until none is left
    (each round adds one at least), which is exact (the zone of a subset is never wider,
    and one holding every point is the zone of them all). A point already held is never a
    violator: one HiGHS leaves outside by its feasibility tolerance (1e-7) would only
    repeat the LP. Small sets: a step's cost grows with its points, and a zone rests on six."""
    if basis is not None and (found := _dual_simplex(r, dr, basis)) is not None:
        return found[0][:4], found[1]
    k = min(len(r), CYLINDER_CANDIDATES)
    active = np.zeros(len(r), bool)
    active[np.argpartition(r, k - 1)[:k]] = True
    active[np.argpartition(-r, k - 1)[:k]] = True
    basis = None
    while True:
        x, R, w, basis = _held_zone(r, dr, np.flatnonzero(active), basis)
        rr = r + np.einsum("j,ji->i", x, dr)
        excess = np.maximum(R - rr, rr - R - w)
        excess[active] = -np.inf
        out = np.flatnonzero(excess > CYLINDER_SLACK_MM)
        if not out.size:
            return x, basis
        if out.size > CYLINDER_VIOLATORS:
            out = out[np.argpartition(-excess[out], CYLINDER_VIOLATORS - 1)[:CYLINDER_VIOLATORS]]
        active[out] = True


def _held_zone(r: np.ndarray, dr: np.ndarray, held: np.ndarray,
               basis: np.ndarray | None) -> tuple[np.ndarray, float, float, np.ndarray | None]:
    """(x, R, w) of the zone of the points `held` (sorted indices) and its optimal basis:
    the dual simplex (`_dual_simplex`) from `basis` (the zone's of fewer of them, rows
    numbered over all the N points: still dual feasible, its rows being the same), else
    from the bounds on x (`_box_basis`); HiGHS should both fail (basis None)."""
    m, n = len(held), len(r)
    r_held, dr_held = r[held], dr[:, held]
    found = None
    if basis is not None:
        found = _dual_simplex(r_held, dr_held, np.searchsorted(held, basis % n) + m * (basis >= n))
    if found is None:
        found = _dual_simplex(r_held, dr_held, _box_basis(r_held, dr_held))
    if found is None:
        return *_cylinder_lp(r_held, dr_held.T), None
    y, rows = found
    return y[:4], float(y[4]), float(y[5]), held[rows % m] + n * (rows >= m)


def _zone_rows(r: np.ndarray, dr: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows (A (M, 6), b (M,)) of the zone's LP A (x, R, w) <= b over the N points: row
    i < N is point i's inner side R <= r + x.dr, row N + i its outer side r + x.dr <= R + w;
    row 2N + 2j bounds x_j <= CYLINDER_BOX, row 2N + 2j + 1 -x_j <= CYLINDER_BOX."""
    n = len(r)
    bound = rows >= 2 * n
    i, outer = rows % n, ((rows >= n) & ~bound).astype(float)
    s = 2.0 * outer - 1.0
    A = np.column_stack([s[:, None] * dr[:, i].T, -s, -outer])
    b = -s * r[i]
    j = rows[bound] - 2 * n
    A[bound] = 0.0
    A[np.flatnonzero(bound), j // 2] = 1.0 - 2.0 * (j % 2)
    b[bound] = CYLINDER_BOX
    return A, b


def _box_basis(r: np.ndarray, dr: np.ndarray) -> np.ndarray:
    """A dual feasible basis (`_zone_rows`) to start from without any LP: the inner side of
    the lowest radius, the outer side of the highest, and the bound on each x_j pricing its
    derivatives' difference away (dual prices 1, 1 and |dr_j(high) - dr_j(low)|)."""
    low, high = int(np.argmin(r)), int(np.argmax(r))
    return np.concatenate([[low, len(r) + high], 2 * len(r) + 2 * np.arange(4) + (dr[:, high] > dr[:, low])])


def _dual_simplex(r: np.ndarray, dr: np.ndarray, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The zone's LP (`_zone_rows`, min w) by the dual simplex from `basis` (6 rows): while
    the basis's vertex leaves a point outside its zone (beyond CYLINDER_SLACK_MM), the worst
    such row enters and the one whose dual price first falls to 0 leaves (the dual's
    objective only grows). A basis of points' rows with dual prices >= 0 whose vertex holds
    every point is optimal (the KKT conditions; the bounds, never entering, are only a
    start): returns y = (x, R, w) (6,) and the basis there; None where `basis` is not dual
    feasible, is singular, ends holding a bound, or CYLINDER_PIVOTS steps did not end."""
    A, b = _zone_rows(r, dr, basis)
    basis = basis.copy()
    for _ in range(CYLINDER_PIVOTS):
        try:
            inverse = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            return None
        y, dual = inverse @ b, -inverse[5]  # the vertex; the prices of A^T dual = -(0, 0, 0, 0, 0, 1)
        if dual.min() < -DUAL_TOL:
            return None
        rr = r + np.einsum("j,ji->i", y[:4], dr)
        low, high = int(np.argmin(rr)), int(np.argmax(rr))
        below, above = y[4] - rr[low], rr[high] - y[4] - y[5]
        if max(below, above) <= CYLINDER_SLACK_MM:
            return (y, basis) if basis.max() < 2 * len(r) else None
        enter = low if below >= above else len(r) + high
        row, bound = _zone_rows(r, dr, np.array([enter]))
        step = inverse.T @ row[0]
        if step.max() <= 0.0:
            return None
        leave = np.argmin(np.where(step > 0.0, dual / np.where(step > 0.0, step, 1.0), np.inf))
        basis[leave], A[leave], b[leave] = enter, row[0], bound[0]
    return None


def _cylinder_lp(r: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, float, float]:
    """min w subject to R <= r + J x <= R + w; returns (x, R, w)."""
    ones = np.ones_like(r)
    A_ub = np.concatenate([np.column_stack([-J, ones, 0 * ones]), np.column_stack([J, -ones, -ones])])
    b_ub = np.concatenate([r, -r])
    res = linprog([0, 0, 0, 0, 0, 1], A_ub=A_ub, b_ub=b_ub, bounds=[(None, None)] * 5 + [(0, None)], method="highs")
    if res.status != 0:
        raise ArithmeticError(f"minimum-zone LP of {len(r)} points: {res.message}")
    return res.x[:4], float(res.x[4]), float(res.x[5])


# ------------------------------------------------------------------------------- filters


def gaussian_kernel_1d(cutoff_mm: float, spacing_mm: float, moment: int = 0) -> np.ndarray:
    """The ISO 16610-61 weighting function sampled every `spacing_mm` out to where it is
    below 1e-9 of its peak, times x^moment (x in mm)."""
    half = int(np.ceil(ALPHA * cutoff_mm * 2.6 / spacing_mm))
    x = np.arange(-half, half + 1) * spacing_mm
    return np.exp(-np.pi * (x / (ALPHA * cutoff_mm)) ** 2) * x ** moment


class _Correlator:
    """Separable correlations of (..., H, W) fields with outer products of 1-D kernels,
    zero outside the grid (correlation: the kernel's offset +j reads the cell j further
    on), by FFT: one transform per field; the columns' inverse once per column kernel (the
    row kernel is constant along a column), then the rows' inverse per kernel pair, each
    only where the grid is."""

    def __init__(self, shape: tuple[int, int], half: int) -> None:
        self.shape = shape
        self.half = half
        self.size = (fft.next_fast_len(shape[0] + 2 * half), fft.next_fast_len(shape[1] + 2 * half, real=True))
        self._cols: dict[int, np.ndarray] = {}  # column kernels' spectra (S0, 1)
        self._rows: dict[int, np.ndarray] = {}  # row kernels' half spectra (S1 // 2 + 1,)

    def kernel(self, key: int, k: np.ndarray) -> None:
        flipped = k[::-1]  # correlation = convolution with the flip
        self._cols[key] = fft.fft(flipped, n=self.size[0])[:, None]
        self._rows[key] = fft.rfft(flipped, n=self.size[1])

    def transform(self, fields: np.ndarray) -> np.ndarray:
        """The padded 2-D spectrum of fields (..., H, W): rows first, only the H that hold data
        (complex64 for float32 fields: the FFTs are memory-bound, single precision halves them)."""
        rows = fft.rfft(fields, n=self.size[1], axis=-1, workers=FORM_WORKERS.get())
        return fft.fft(rows, n=self.size[0], axis=-2, workers=FORM_WORKERS.get())

    def apply(self, spectrum: np.ndarray, pairs: Iterable[tuple[int, int]]) -> Iterator[np.ndarray]:
        """The correlations (..., H, W) with the kernel pairs (ky, kx), in their order; pairs
        that share ky in a row share the columns' inverse."""
        h, w = self.shape
        ky_done, cols = None, None
        for ky, kx in pairs:
            if ky != ky_done:
                k = self._cols[ky].astype(spectrum.dtype, copy=False)  # single-precision fields stay single
                cols = fft.ifft(spectrum * k, axis=-2, workers=FORM_WORKERS.get())[..., self.half:self.half + h, :]
                ky_done = ky
            k = self._rows[kx].astype(spectrum.dtype, copy=False)
            yield fft.irfft(cols * k, n=self.size[1], axis=-1, workers=FORM_WORKERS.get())[..., self.half:self.half + w]


_MONOMIALS = ((0, 0), (1, 0), (2, 0), (0, 1), (1, 1), (0, 2))  # (power of x, power of y), by y's


class GaussianFilter:
    """Areal Gaussian filters on a grid of `spacing_mm` cells where `mask` holds data:
    order 0, ISO 16610-61's Gaussian (the weighted mean, normalised where the surface
    ends); order 2, the second-order Gaussian regression filter (the same weights, a local
    quadratic: exact for quadratic surfaces). The weights depend on the mask only, so they
    are set up once and the
    filter then applies to any number of fields (`__call__` takes (..., H, W))."""

    def __init__(self, mask: np.ndarray, cutoff_mm: float, spacing_mm: float, order: int = 0) -> None:
        self.mask = mask
        self.order = order
        moments = range(5 if order == 2 else 1)
        ks = [gaussian_kernel_1d(cutoff_mm, spacing_mm, m) for m in moments]
        self._c = _Correlator(mask.shape, len(ks[0]) // 2)
        for m, k in enumerate(ks):
            self._c.kernel(m, k)
        wspec = self._c.transform(mask.astype(np.float64))
        self._norm = np.maximum(next(self._c.apply(wspec, [(0, 0)])), 1e-300)  # the Gaussian mean's weights
        self._norm32 = np.maximum(self._norm, np.finfo(np.float32).tiny).astype(np.float32)
        if order == 0:
            return
        # moments about each cell: S_ab = sum w g (dx^a dy^b); the filtered value is the first
        # row of M^-1 (M_ij = S of the product of monomials i and j) applied to T_j = sum w z g m_j
        ab = [(a, b) for b in range(5) for a in range(5 - b)]
        S = dict(zip(ab, self._c.apply(wspec, [(b, a) for a, b in ab])))
        ok = mask & (S[(0, 0)] > 1e-12 * S[(0, 0)].max())
        scale = np.maximum(S[(0, 0)][ok], 1e-300)
        Mo = np.empty((len(scale), 6, 6))  # only where the filter is defined (symmetric: M_ij = M_ji)
        for i, (a1, b1) in enumerate(_MONOMIALS):
            for j, (a2, b2) in enumerate(_MONOMIALS):
                Mo[:, i, j] = S[(a1 + a2, b1 + b2)][ok] / scale
        e0 = np.zeros((len(Mo), 6, 1))
        e0[:, 0] = 1.0
        row = np.zeros(mask.shape + (6,))
        row[ok] = np.linalg.solve(Mo + 1e-12 * np.eye(6), e0)[..., 0] / scale[:, None]
        self._row = row
        self._row32 = row.astype(np.float32)
        self._ok = ok

    def __call__(self, z: np.ndarray, single: bool = False) -> np.ndarray:
        if (flat := _large_stack(z)) is not None:
            return np.concatenate([self(flat[c], single) for c in _row_chunks(len(flat))]).reshape(z.shape)
        if self.order == 0:
            return next(self._c.apply(self._spectrum(z, single), [(0, 0)])) / (self._norm32 if single else self._norm)
        return self.with_mean(z, single)[0]

    def with_mean(self, z: np.ndarray, single: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Order 2: the regression and the Gaussian mean (order 0, the same cut-off) of z
        from one transform, the mean's correlation being the regression's first term.
        `single`: in float32 (relative error ~1e-6 of the fields' size), for the noise
        draws, whose figures' spread is all that is used of them."""
        if (flat := _large_stack(z)) is not None:
            done = [self.with_mean(flat[c], single) for c in _row_chunks(len(flat))]
            regression, mean = (np.concatenate(each).reshape(z.shape) for each in zip(*done))
            return regression, mean
        spec = self._spectrum(z, single)
        row = self._row32 if single else self._row
        terms = self._c.apply(spec, [(b, a) for a, b in _MONOMIALS])
        mean = next(terms)
        out = mean * row[..., 0]
        for i, term in enumerate(terms, 1):
            out += term * row[..., i]
        return np.where(self._ok, out, np.nan), mean / (self._norm32 if single else self._norm)

    def _spectrum(self, z: np.ndarray, single: bool) -> np.ndarray:
        held = np.zeros(z.shape, np.float32 if single else np.float64)  # one copy, in the transform's precision
        np.copyto(held, z, where=self.mask & np.isfinite(z), casting="same_kind")
        return self._c.transform(held)


def _row_chunks(rows: int) -> Iterator[slice]:
    """Stacks of noise draws (32 fields or surfaces) are worked on ROW_CHUNK rows at a time:
    a piece's temporaries (a few MB) are reused from the allocator's free memory, where a
    whole stack's (40-100 MB each) are fresh mappings the kernel zeroes page by page every
    time (in `slscan bench demo`, 0.8-1.1 s of each face thread's 1.7-2.2 s CPU was the
    kernel zeroing pages). The results are the same bit for bit."""
    return (slice(i, i + ROW_CHUNK) for i in range(0, rows, ROW_CHUNK))


def _large_stack(z: np.ndarray) -> np.ndarray | None:
    """Fields z (..., H, W) as one stack (F, H, W) when there are more than ROW_CHUNK, else None."""
    flat = z.reshape(-1, *z.shape[-2:])
    return flat if len(flat) > ROW_CHUNK else None


def gaussian_filter(z: np.ndarray, mask: np.ndarray, cutoff_mm: float, spacing_mm: float,
                    order: int = 0) -> np.ndarray:
    """`GaussianFilter` applied once to a gridded surface z (NaN outside `mask`)."""
    return GaussianFilter(mask, cutoff_mm, spacing_mm, order)(z)


# ------------------------------------------------------------------------ per-face result


@dataclass(frozen=True)
class FormSettings:
    """`form_cutoff_mm`: nesting index of the form filter; `roughness_cutoff_mm`: of the
    roughness (L) filter; `edge_margin_mm`: a band along the face's measured border left
    out of every figure (mixed pixels and blur live there); `outlier_sigma`: points further
    than this many robust sigma from the median deviation are dropped as spikes; `draws`:
    noise draws behind every figure's uncertainty, bias and detection limit."""

    form_cutoff_mm: float = FORM_CUTOFF_MM
    roughness_cutoff_mm: float = ROUGHNESS_CUTOFF_MM
    edge_margin_mm: float = 1.0
    outlier_sigma: float = 6.0
    draws: int = 32


@dataclass(frozen=True)
class FaceForm:
    """Figures of one face (`inspection.figures`), each an `Estimate` (mm; None where they do
    not apply or could not be measured; the extremes' detection limits are magnitudes).
    `*_mz` are minimum-zone widths of the form surface, `*_ls` its least-squares widths;
    `sq` the roughness with the noise removed; `deviation_*` the signed deviations from
    nominal of the form surface (`deviation_source` "form surface"; "raw points" for a face
    without surface coordinates to filter on, whose figures then carry the noise),
    `profile` = 2 max|deviation| (the ISO 1101 profile zone centred on nominal);
    `raw_deviation_*` the extremes of the unfiltered points (inside the edge margin, spikes
    dropped), noise included. `noise_mm`: the typical noise of one point
    along the face normal and `noise_source` where it came from; `sq_raw_mm`: ISO
    25178-2's Sq of the measured surface (the noise included; `sq` is Sq after noise
    removal) and `sq_noise_mm` the noise's RMS."""

    points: int
    status: str
    note: str = ""
    flatness_ls: Estimate | None = None
    flatness_mz: Estimate | None = None
    cylindricity_ls: Estimate | None = None
    cylindricity_mz: Estimate | None = None
    sq: Estimate | None = None
    profile: Estimate | None = None
    deviation_min: Estimate | None = None
    deviation_max: Estimate | None = None
    deviation_mean: Estimate | None = None
    deviation_rms: Estimate | None = None
    raw_deviation_min: Estimate | None = None
    raw_deviation_max: Estimate | None = None
    noise_mm: float | None = None
    noise_source: str | None = None
    sq_raw_mm: float | None = None
    sq_noise_mm: float | None = None
    deviation_source: str | None = None
    form_cutoff_mm: float | None = None
    roughness_cutoff_mm: float | None = None
    grid_mm: float | None = None
    grid_origin_mm: tuple[float, float] | None = None  # the grid's corner in the face's 2D coordinates
    u_components: dict[str, dict[str, float]] = field(default_factory=dict)
    region: np.ndarray | None = field(default=None, repr=False, compare=False)  # (N,) bool: the input points used
    surface_mm: np.ndarray | None = field(default=None, repr=False, compare=False)  # (N,): the deviation the figures
    # see at each input point (the form surface's at its grid cell; a raw-points face's own), NaN where not used

    def figure(self, name: str) -> Estimate | None:
        """The figure called `name` (`inspection.figures`; an unknown name is refused)."""
        return getattr(self, figures.figure(name).name)

    def as_dict(self) -> dict[str, object]:
        """Flat JSON: every figure's report columns (`inspection.figures.Figure.fields`:
        value, U (k = 2) and, below its detection limit, the limit), the rest as they are."""
        out: dict[str, object] = {}
        names = {g.name for g in figures.FIGURES}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in names:
                out.update(figures.figure(f.name).fields(v))
            elif f.name not in ("u_components", "region", "surface_mm"):
                out[f.name] = v
        out["u_components_mm"] = self.u_components
        return out


def _plane_coordinates(face: Face, points: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """A plane's in-plane axes; a planar mesh face's principal axes."""
    if isinstance(face.surface, Surface):
        return face.surface.local(points)[:, :2]
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return (points - c) @ vt[:2].T


def _unrolled(uv: np.ndarray, radius: float) -> np.ndarray:
    """(R theta, axial) of points on a surface of revolution of radius R, theta unwrapped
    from the largest empty arc (the seam)."""
    t = np.mod(uv[:, 0], 2 * np.pi)
    ts = np.sort(t)
    k = int(np.argmax(np.diff(np.append(ts, ts[0] + 2 * np.pi))))
    t = np.mod(t - ts[(k + 1) % len(ts)], 2 * np.pi)
    return np.stack([radius * t, uv[:, 1]], axis=1)


def _cylinder_coordinates(face: Face, points: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return _unrolled(uv, _surface(face, Cylinder).radius)


def _cone_coordinates(face: Face, points: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return _unrolled(uv, _surface(face, Cone).ref_radius)


_S = TypeVar("_S", bound=Surface)


def _surface(face: Face, kind: type[_S]) -> _S:
    """The face's surface, which its type says is a `kind`."""
    if not isinstance(face.surface, kind):
        raise TypeError(f"a {face.type} face with a {type(face.surface).__name__} surface")
    return face.surface


@dataclass(frozen=True, eq=False)
class _Grid:
    """Points binned on a square grid: `cell` (N,) flat index of each point's cell,
    `counts` per cell, `shape`, `spacing`, `origin` (2,) mm."""

    cell: np.ndarray
    counts: np.ndarray
    shape: tuple[int, int]
    spacing: float
    origin: np.ndarray

    def mean(self, values: np.ndarray) -> np.ndarray:
        """Per-cell means (..., H, W) of per-point values (..., N), NaN in empty cells; a row
        (e.g. a noise draw) at a time, so the only full-size array is the result."""
        flat = values.reshape(-1, values.shape[-1])
        out = np.full((len(flat), len(self.counts)), np.nan)
        filled = self.counts > 0
        for row, v in zip(out, flat):
            np.divide(np.bincount(self.cell, v, len(self.counts)), self.counts, out=row, where=filled)
        return out.reshape(*values.shape[:-1], *self.shape)

    def centres(self, mask: np.ndarray) -> np.ndarray:
        rows, cols = np.nonzero(mask)
        return self.origin + (np.stack([cols, rows], axis=1) + 0.5) * self.spacing


def _grid(xy: np.ndarray) -> _Grid:
    """The grid: its spacing starts at the points' typical nearest-neighbour distance and
    grows until nine cells in ten inside the measured area hold a point."""
    from scipy.spatial import cKDTree

    tree = cKDTree(xy, balanced_tree=False, compact_nodes=False)  # the quick build
    d, _ = tree.query(xy, k=2, workers=FORM_WORKERS.get())
    g = float(np.median(d[:, 1])) * 1.2
    lo = xy.min(axis=0)
    while True:  # a few rounds at most
        ij = np.floor((xy - lo) / g).astype(np.int64)
        shape = (int(ij[:, 1].max()) + 1, int(ij[:, 0].max()) + 1)
        flat = ij[:, 1] * shape[1] + ij[:, 0]
        cnt = np.bincount(flat, minlength=shape[0] * shape[1])
        mask = (cnt > 0).reshape(shape)
        closed = ndimage.binary_closing(mask, np.ones((3, 3)), border_value=0) | mask
        if mask.sum() >= 0.9 * closed.sum():
            break
        g *= np.sqrt(2.0)
    return _Grid(flat, cnt.astype(np.float64), shape, g, lo)


def noise_sigma(z: np.ndarray, mask: np.ndarray) -> float | None:
    """White height noise per grid cell from fourth differences along rows and columns
    (a smooth surface contributes nothing to them): var(D4) = 70 sigma^2."""
    vals = []
    for a in (z, z.T):
        m = np.isfinite(a)
        d = a[:, :-4] - 4 * a[:, 1:-3] + 6 * a[:, 2:-2] - 4 * a[:, 3:-1] + a[:, 4:]
        ok = m[:, :-4] & m[:, 1:-3] & m[:, 2:-2] & m[:, 3:-1] & m[:, 4:]
        vals.append(d[ok])
    v = np.concatenate(vals)
    if len(v) < 20:
        return None
    return float(1.4826 * np.median(np.abs(v)) / np.sqrt(70.0))  # robust: edges and spikes do not count


def from_draws(value: float, drawn: np.ndarray, noise_only: np.ndarray | None = None,
                cal: np.ndarray | None = None, linear: np.ndarray | None = None) -> tuple[Estimate, dict[str, float]]:
    """A figure from its value on the measured surface, its values on the surface plus
    each noise draw (spread: u; mean shift: the noise bias, removed, with its own
    uncertainty), optionally the same figure of the noise alone (its 95th percentile: the
    detection limit), its changes for each calibration direction (root sum of squares:
    u_cal) and, for an extreme-value figure, its first-order changes with each draw
    (`linear`: the draw at the cells that hold the extreme, weighted as they hold it).

    The bootstrap of an extreme understates its spread where the measured surface's
    extreme is itself partly noise: among competing extremes (a bow's four corners) the
    noise has already picked the deepest, and a draw added to it moves the figure less
    than the noise moved it from the truth (on the simulator's bowed plate the zone's
    draws spread 1.2 µm where the corner cells' noise, which sets the error, spread 2.4-3
    µm). The first-order spread is the figure's when the true extremes are unique; u_noise
    is the larger of the two.

    The removed bias is known only to within its own size: it is the shift that noise
    adds to the already noisy measured surface, not to the true one, and for a zone (an
    extreme-value figure) the two differ by a fraction of it, either way (on the
    simulator's bowed plate, 0.71 µm removed on average where 0.52 µm was added). So the
    correction's standard uncertainty is that of a rectangular distribution between no
    bias and twice the estimate, |bias|/sqrt(3), plus the draws' Monte Carlo error of
    the mean shift, u_noise/sqrt(D)."""
    bias = float(np.mean(drawn) - value)
    u_noise = float(np.std(drawn, ddof=1)) if len(drawn) > 1 else 0.0
    if linear is not None and len(linear) > 1:
        u_noise = max(u_noise, float(np.std(linear, ddof=1)))
    u_bias = float(np.hypot(bias / np.sqrt(3.0), u_noise / np.sqrt(len(drawn)))) if len(drawn) > 1 else abs(bias)
    u_cal = float(np.sqrt(np.sum(np.square(cal)))) if cal is not None and len(cal) else 0.0
    u = float(np.sqrt(u_noise ** 2 + u_bias ** 2 + u_cal ** 2))
    parts = {"noise": u_noise, "noise bias": u_bias, "calibration": u_cal}
    if noise_only is None:
        return Estimate(value - bias, u, None, bias), parts
    limit = float(np.quantile(noise_only, DETECTION_QUANTILE))
    corrected = value - bias  # detected only when what is reported exceeds what noise alone reads in 95 % of scans
    return Estimate(corrected if corrected > limit else None, u, limit, bias), parts


def _sq(rough: np.ndarray, drawn_rough: np.ndarray, inner: np.ndarray, model_rel_u: float
        ) -> tuple[Estimate, float, float, dict[str, float]]:
    """Sq with the noise's mean square removed, its uncertainty and detection limit
    (module docstring of `inspection.uncertainty`, "Detection"); also the ISO 25178-2 Sq
    of the measured surface (noise included) and the noise's RMS."""
    r = rough[inner]
    e = _columns(drawn_rough, inner)
    raw2 = float(np.mean(r ** 2))
    noise2 = float(np.mean(e ** 2))
    d = raw2 - noise2
    u_model = 2.0 * model_rel_u * noise2

    def u_at(sq: float) -> tuple[float, float]:
        """(u of the estimate of Sq² for a surface of roughness `sq`: mean(2 s e + e²) over
        fresh noise, s the noise-free roughness (the measured one shrunk to `sq`), with the
        noise model's own uncertainty; its noise part alone)."""
        shrink = sq / np.sqrt(raw2) if raw2 > 0 else 0.0
        stat = _by_rows(lambda x: np.mean(2.0 * shrink * r * x + x ** 2, axis=1), e)
        spread = float(np.std(stat, ddof=1))
        return float(np.hypot(spread, u_model)), spread

    _, spread0 = u_at(0.0)
    # the estimate of a smooth surface's Sq² exceeds this in at most 5 % of scans while the noise model's error
    # is within its bound (model_rel_u: its mean square is off by up to 2 model_rel_u, added, not in quadrature)
    threshold = DETECTION_Z * spread0 + u_model
    limit = float(np.sqrt(threshold))
    if d <= threshold:
        u_d, spread = u_at(limit)
        return Estimate(None, u_d / (2.0 * limit), limit), float(np.sqrt(raw2)), float(np.sqrt(noise2)), \
            {"noise": spread / (2.0 * limit), "noise model": u_model / (2.0 * limit)}
    sq = float(np.sqrt(d))
    u_d, spread = u_at(sq)
    return Estimate(sq, u_d / (2.0 * sq), limit), float(np.sqrt(raw2)), float(np.sqrt(noise2)), \
        {"noise": spread / (2.0 * sq), "noise model": u_model / (2.0 * sq)}


def evaluate_face(face: Face, points: np.ndarray, deviation: np.ndarray, *, uv: np.ndarray,
                  settings: FormSettings = FormSettings(), seed: int = 0, noise: PointNoise | None = None,
                  normals: np.ndarray | None = None, shifts: np.ndarray | None = None,
                  region: np.ndarray | None = None) -> FaceForm:
    """Form, texture and deviation figures of one face from its measured points (model
    frame), their signed deviations and the surface parameters of their feet, each with
    its uncertainty. `noise`: the points' noise model with rays in the model frame, and
    `normals` (N, 3) the face's outward normals at the points (for the deviation a ray
    move makes); `shifts` (D, N, 3): the points' moves for each principal calibration
    direction (model frame). Without `noise` it is estimated from the heights.
    `region` (N,) bool: take the figures over exactly these points (another evaluation's
    `FaceForm.region`, e.g. the noise-free truth over the region a measurement evaluated),
    without the spike test and the edge margin; the result's `region` says which points
    the figures were taken over (spikes dropped, inside the edge margin). A face of a type
    with surface coordinates (`_SURFACE_FORMS`) is evaluated on its form surface, any
    other on its raw points."""
    n = len(points)
    if normals is None and (noise is not None or shifts is not None):
        raise ValueError("a noise model or calibration moves need the points' normals")
    if n < MIN_POINTS:
        return FaceForm(n, "too few points", f"{n} points; at least {MIN_POINTS} are needed")
    if region is None:
        med = np.median(deviation)
        rs = 1.4826 * np.median(np.abs(deviation - med))
        keep = np.abs(deviation - med) <= settings.outlier_sigma * max(rs, 1e-6)
    else:
        keep = region.copy()
        settings = replace(settings, edge_margin_mm=0.0)
    kept = _Kept(keep, points[keep], deviation[keep], uv[keep], None if noise is None else noise.subset(keep),
                 None if normals is None else normals[keep], None if shifts is None else shifts[:, keep])
    if kept.noise is not None and kept.normals is not None:  # the camera defocus's modelled bias removed
        dz, kept.noise = kept.noise.defocus_removed()  # (module docstring)
        kept.points = kept.points + dz[:, None] * kept.noise.ray
        kept.deviation = kept.deviation + dz * np.einsum("ij,ij->i", kept.normals, kept.noise.ray)
    rng = np.random.default_rng(seed)
    kind = _SURFACE_FORMS.get(face.type)
    if kind is None:  # no surface coordinates: deviations of the raw points, their noise included
        return _raw_points_form(face, kept, rng, settings)
    return _surface_form(face, kind, kept, rng, settings)


@dataclass(eq=False)
class _Kept:
    """The points `evaluate_face` takes the figures over (`keep` (N,) bool of the input
    points: spikes dropped, or the given region), with their deviations, surface
    parameters, noise model, normals and calibration moves (the camera defocus's bias
    removed from the points and deviations)."""

    keep: np.ndarray
    points: np.ndarray
    deviation: np.ndarray
    uv: np.ndarray
    noise: PointNoise | None
    normals: np.ndarray | None
    shifts: np.ndarray | None


def _raw_points_form(face: Face, kept: _Kept, rng: np.random.Generator, settings: FormSettings) -> FaceForm:
    """The deviation figures of the raw points, their noise included (no form filter)."""
    deviation, normals, shifts = kept.deviation, kept.normals, kept.shifts
    draws = _point_draws(kept.noise, normals, rng, settings.draws, len(kept.points), float(np.std(deviation)))
    dev_shift = None if shifts is None or normals is None else np.einsum("dij,ij->di", shifts, normals)
    stats, parts = _deviation_stats(deviation, deviation[None] + draws, draws, deviation, draws, dev_shift)
    seen = np.full(len(kept.keep), np.nan)
    seen[kept.keep] = deviation
    return FaceForm(len(kept.points), "ok", f"{face.type}: deviations of raw points only (no form filter)",
                    deviation_source="raw points", u_components=parts, region=kept.keep, surface_mm=seen, **stats)


def _surface_form(face: Face, kind: _SurfaceForm, kept: _Kept, rng: np.random.Generator,
                  settings: FormSettings) -> FaceForm:
    """The figures of the form surface: the heights laid on the face's 2D coordinates
    (`kind.coordinates`), gridded, filtered; the zones of its surface type (`kind.zones`)."""
    points, deviation, noise, normals, shifts = kept.points, kept.deviation, kept.noise, kept.normals, kept.shifts
    xy = kind.coordinates(face, points, kept.uv)
    grid = _grid(xy)
    zg = grid.mean(deviation)
    mask = np.isfinite(zg)
    margin = int(np.ceil(settings.edge_margin_mm / grid.spacing))
    region = ndimage.binary_closing(mask, np.ones((3, 3)), border_value=0) | mask  # sampling gaps closed, holes kept
    inner = mask & (ndimage.binary_erosion(region, np.ones((2 * margin + 1, 2 * margin + 1)), border_value=0)
                    if margin else region)
    if inner.sum() < MIN_POINTS:
        return FaceForm(len(points), "too few points", f"fewer than {MIN_POINTS} grid cells of {grid.spacing:.3g} mm "
                        f"left inside the {settings.edge_margin_mm} mm edge margin")
    zg = np.where(inner, zg, np.nan)  # the border band's mixed pixels must not leak into the filters
    raw_sel = inner.ravel()[grid.cell]
    used = np.zeros(len(kept.keep), bool)
    used[np.flatnonzero(kept.keep)[raw_sel]] = True
    seen = np.full(len(kept.keep), np.nan)
    if noise is not None and normals is not None:
        point_draws = noise.draw(rng, settings.draws)
        point_draws *= np.einsum("ij,ij->i", normals, noise.ray)
        cell_draws = grid.mean(point_draws)
        typical = float(np.median(noise.sigma_z * np.abs(np.einsum("ij,ij->i", normals, noise.ray))))
        source, model_rel_u = noise.source, noise.rel_u
    else:  # estimated from the heights: white per cell
        sigma = noise_sigma(zg, inner) or 0.0
        cell_draws = rng.standard_normal((settings.draws, *zg.shape)) * sigma
        point_draws = None
        typical = sigma * float(np.sqrt(np.median(grid.counts[grid.counts > 0])))
        source, model_rel_u = "estimated from the data (fourth differences)", 1.0 / np.sqrt(max(inner.sum(), 1))
    cell_draws[:, ~inner] = np.nan
    cal_cells = None
    if shifts is not None and normals is not None:
        cal_cells = np.where(inner, grid.mean(np.einsum("dij,ij->di", shifts, normals)), 0.0)
    form_filter = GaussianFilter(inner, settings.form_cutoff_mm, grid.spacing, order=2)
    if settings.roughness_cutoff_mm == settings.form_cutoff_mm:  # the L-filter's mean comes with the form filter
        filters = form_filter.with_mean
    else:
        rough_filter = GaussianFilter(inner, settings.roughness_cutoff_mm, grid.spacing, order=0)

        def filters(z: np.ndarray, single: bool = False) -> tuple[np.ndarray, np.ndarray]:
            return form_filter.with_mean(z, single)[0], rough_filter(z, single)
    form, mean = filters(zg)
    seen[used] = form.ravel()[grid.cell[raw_sel]]  # `used` is in the input order, as raw_sel is
    noise_form, noise_mean = filters(cell_draws, single=True)
    rough = zg - mean
    drawn_rough = np.subtract(cell_draws, noise_mean, out=cell_draws)  # in place: the draws' last use
    sq, sq_raw, sq_noise, sq_parts = _sq(rough, drawn_rough, inner, model_rel_u)
    raw_dev = deviation[raw_sel]
    raw_draws = (_columns(point_draws, raw_sel) if point_draws is not None
                 else rng.standard_normal((settings.draws, int(raw_sel.sum()))) * typical)
    cal = None if cal_cells is None else _columns(cal_cells, inner)
    f, e = form[inner], _columns(noise_form, inner).astype(np.float64)  # the figures in double precision
    fe = f + e  # the form surface plus each draw's
    stats, parts = _deviation_stats(f, fe, e, raw_dev, raw_draws, cal)
    parts["sq"] = sq_parts
    zones, note = _ZoneFigures(), f"{face.type}: texture and deviations only"
    if kind.zones is not None:
        zones, zone_parts = kind.zones(face, _Cells(grid.centres(inner), f, fe, e, cal))
        parts.update(zone_parts)
        note = ""
    return FaceForm(int(raw_sel.sum()), "ok", note, sq=sq, sq_raw_mm=sq_raw, sq_noise_mm=sq_noise, noise_mm=typical,
                    noise_source=source, form_cutoff_mm=settings.form_cutoff_mm,
                    roughness_cutoff_mm=settings.roughness_cutoff_mm, grid_mm=grid.spacing,
                    grid_origin_mm=(float(grid.origin[0]), float(grid.origin[1])), deviation_source="form surface",
                    u_components=parts, region=used, surface_mm=seen, **stats, **zones)


@dataclass(frozen=True, eq=False)
class _Cells:
    """A face's form surface on its grid's inner cells, which its zones are figures of:
    the cells' centres `cxy` (cells, 2) mm in the face's 2D coordinates, the form surface
    `f` (cells,) mm, it plus each noise draw `fe` (D, cells), the draws alone `e` and the
    calibration moves `cal` (D_cal, cells; None: not known)."""

    cxy: np.ndarray
    f: np.ndarray
    fe: np.ndarray
    e: np.ndarray
    cal: np.ndarray | None


class _ZoneFigures(TypedDict, total=False):
    """The zone figures of a face's surface type (`inspection.figures`)."""

    flatness_ls: Estimate
    flatness_mz: Estimate
    cylindricity_ls: Estimate
    cylindricity_mz: Estimate


_Parts = dict[str, dict[str, float]]  # uncertainty components per figure (`FaceForm.u_components`)


def _flatness(face: Face, c: _Cells) -> tuple[_ZoneFigures, _Parts]:
    """Least-squares and minimum-zone flatness of a plane's form surface."""
    cxy, f, fe = c.cxy, c.f, c.fe
    tilt = plane_zone_tilt(cxy, f)  # the draws' zones are held near the measured zone's
    drawn_frames = _LsFrames.of(cxy, fe)  # shared by the draws' LS and MZ zones

    def frames(h: np.ndarray) -> _LsFrames:
        return drawn_frames if h is fe else _LsFrames.of(cxy, h)

    def flat_ls(h: np.ndarray) -> np.ndarray:
        return _ls_widths(frames(h))

    def flat_mz(h: np.ndarray) -> np.ndarray:
        return _mz_widths(frames(h), tilt)

    def noise_mz(h: np.ndarray) -> np.ndarray:  # the noise alone: its zone about its own LS plane
        return flatness_mz_many(cxy, h)

    ls, ls_parts = _zone(flat_ls, f, fe, noise=c.e, cal=c.cal, sensitivity=ls_zone_sensitivity(cxy, f))
    mz, mz_parts = _zone(flat_mz, f, fe, noise=c.e, cal=c.cal, noise_figure=noise_mz,
                         sensitivity=mz_zone_sensitivity(cxy, f))
    return _ZoneFigures(flatness_ls=ls, flatness_mz=mz), {"flatness_ls": ls_parts, "flatness_mz": mz_parts}


def _cylindricity(face: Face, c: _Cells) -> tuple[_ZoneFigures, _Parts]:
    """Least-squares and minimum-zone cylindricity of a cylinder's form surface (its heights
    along the outward normal rolled back onto the cylinder)."""
    s = _surface(face, Cylinder)
    R = s.radius
    sign = face.sense * np.sign(np.dot(s.evaluate(np.zeros((1, 2)))[1][0], s.x))
    axis0, o0 = np.array([0.0, 0.0, 1.0]), np.zeros(3)

    fitted: dict[bytes, tuple[float, float]] = {}  # (LS, MZ) zone of each surface, by its heights' digest

    def zones(h: np.ndarray) -> tuple[float, float]:  # both zones about one least-squares fit
        key = hashlib.blake2b(h.tobytes(), digest_size=16).digest()
        if key not in fitted:
            p = _unroll(c.cxy, R + sign * h, R)
            o, a, _ = cylinder_ls(p, o0, axis0)
            r = _AxisRadii(p - o, *_frame(a), a).radii(np.zeros(4))
            fitted[key] = float(r.max() - r.min()), cylinder_mz_from(p, o, a)
        return fitted[key]

    def cyl_ls(hs: np.ndarray) -> np.ndarray:
        return np.array([zones(h)[0] for h in hs])

    def cyl_mz(hs: np.ndarray) -> np.ndarray:
        return np.array([zones(h)[1] for h in hs])

    ls, ls_parts = _zone(cyl_ls, c.f, c.fe, noise=c.e, cal=c.cal)
    mz, mz_parts = _zone(cyl_mz, c.f, c.fe, noise=c.e, cal=c.cal)
    return (_ZoneFigures(cylindricity_ls=ls, cylindricity_mz=mz),
            {"cylindricity_ls": ls_parts, "cylindricity_mz": mz_parts})


@dataclass(frozen=True)
class _SurfaceForm:
    """How the faces of one surface type are evaluated: `coordinates` lays their points on
    2D metric coordinates (N, 2) mm, where the heights are gridded and filtered; `zones`,
    for a type with zone figures, gives those (None: texture and deviations only)."""

    coordinates: Callable[[Face, np.ndarray, np.ndarray], np.ndarray]
    zones: Callable[[Face, _Cells], tuple[_ZoneFigures, _Parts]] | None = None


_SURFACE_FORMS = {"plane": _SurfaceForm(_plane_coordinates, _flatness),
                  "cylinder": _SurfaceForm(_cylinder_coordinates, _cylindricity),
                  "cone": _SurfaceForm(_cone_coordinates)}
"""The surface types with surface coordinates (`inspection.figures.TEXTURED`); a face of
another type is evaluated on its raw points."""


def _zone(figure: Callable[[np.ndarray], np.ndarray], form: np.ndarray, drawn: np.ndarray, *, noise: np.ndarray,
          cal: np.ndarray | None, noise_figure: Callable[[np.ndarray], np.ndarray] | None = None,
          sensitivity: np.ndarray | None = None) -> tuple[Estimate, dict[str, float]]:
    """A zone of the form surface `form` (cells,) with it plus each noise draw `drawn`
    (D, cells), the draws alone `noise`, and calibration moves (D_cal, cells): bias
    removed, u, detection limit. `figure` takes surfaces (B, cells) and gives their zones
    (B,); `noise_figure`, the same zone computed with hints for the noise alone (default:
    `figure`); `sensitivity` (cells,): the zone's first-order change per unit height at
    each cell (`from_draws`, `linear`)."""
    value = float(figure(form[None])[0])
    changes = None if cal is None else figure(form + cal) - value
    return from_draws(value, figure(drawn), (noise_figure or figure)(noise), changes,
                      None if sensitivity is None else noise @ sensitivity)


def _point_draws(noise: PointNoise | None, normals: np.ndarray | None, rng: np.random.Generator, n: int,
                 count: int, fallback_sigma: float) -> np.ndarray:
    """Deviation draws (n, count) of raw points: the noise model along the normals, or
    white noise of `fallback_sigma`."""
    if noise is not None and normals is not None:
        return noise.draw(rng, n) * np.einsum("ij,ij->i", normals, noise.ray)
    return rng.standard_normal((n, count)) * fallback_sigma


def _deviation_stats(surface: np.ndarray, drawn: np.ndarray, noise: np.ndarray, raw: np.ndarray,
                     raw_draws: np.ndarray, cal: np.ndarray | None) -> tuple[_Deviations, _Parts]:
    """Deviation figures of `surface` (the form surface's deviations, or the raw ones) with
    it plus each draw (`drawn`) and the draws alone (`noise`), its profile zone 2 max|d|,
    and the extremes of the `raw` point deviations
    with theirs; `cal` (D_cal, cells): calibration moves. The extremes and the profile are
    tested against zero (an extreme the noise alone reaches is not a deviation: null, with
    that reach, in magnitude, as its limit); the mean and RMS are not (`Figure.zero_tested`)."""
    def each(fn: Callable[[np.ndarray], np.ndarray], base: np.ndarray, draws: np.ndarray, noise: np.ndarray | None,
             moves: np.ndarray | None, sign: float = 1.0) -> tuple[Estimate, dict[str, float]]:
        value = sign * float(fn(base[None])[0])
        changes = None if moves is None else sign * fn(base + moves) - value
        held = _EXTREME_CELL.get(fn)
        linear = None
        if held is not None:  # the first-order change: the draw at the cell holding the extreme
            k, factor = held(base)
            linear = sign * factor * (draws[:, k] - base[k])
        est, parts = from_draws(value, sign * _by_rows(fn, draws),
                                None if noise is None else sign * _by_rows(fn, noise), changes, linear)
        if sign < 0:
            est = Estimate(None if est.value is None else -est.value, est.u, est.limit, -est.bias)
        return est, parts

    parts: _Parts = {}
    raw_drawn = raw[None] + raw_draws

    def of_surface(name: str, fn: Callable[[np.ndarray], np.ndarray], sign: float) -> Estimate:
        tested = figures.figure(name).zero_tested
        est, parts[name] = each(fn, surface, drawn, noise if tested else None, cal, sign)
        return est

    def of_raw(name: str, fn: Callable[[np.ndarray], np.ndarray], sign: float) -> Estimate:
        tested = figures.figure(name).zero_tested
        est, parts[name] = each(fn, raw, raw_drawn, raw_draws if tested else None, None, sign)
        return est

    out = _Deviations(deviation_min=of_surface("deviation_min", _row_min, -1.0),
                      deviation_max=of_surface("deviation_max", _row_max, 1.0),
                      deviation_mean=of_surface("deviation_mean", _row_mean, 1.0),
                      deviation_rms=of_surface("deviation_rms", _row_rms, 1.0),
                      profile=of_surface("profile", _row_profile, 1.0),
                      raw_deviation_min=of_raw("raw_deviation_min", _row_min, -1.0),
                      raw_deviation_max=of_raw("raw_deviation_max", _row_max, 1.0))
    return out, parts


class _Deviations(TypedDict):
    """The deviation figures of a face (`_deviation_stats`)."""

    deviation_min: Estimate
    deviation_max: Estimate
    deviation_mean: Estimate
    deviation_rms: Estimate
    profile: Estimate
    raw_deviation_min: Estimate
    raw_deviation_max: Estimate


def _columns(a: np.ndarray, where: np.ndarray) -> np.ndarray:
    """a[:, where] (rows, n) stored row after row: numpy's boolean index there lays the
    result out column after column, and every per-draw pass over it then strides."""
    return np.compress(where.ravel(), a.reshape(len(a), -1), axis=1)


def _by_rows(fn: Callable[[np.ndarray], np.ndarray], d: np.ndarray) -> np.ndarray:
    """fn of the rows (draws) of d, ROW_CHUNK rows at a time (`_row_chunks`)."""
    return np.concatenate([fn(d[c]) for c in _row_chunks(len(d))])


def _row_min(d: np.ndarray) -> np.ndarray:
    return d.min(axis=1)


def _row_max(d: np.ndarray) -> np.ndarray:
    return d.max(axis=1)


def _row_mean(d: np.ndarray) -> np.ndarray:
    return d.mean(axis=1)


def _row_rms(d: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(d ** 2, axis=1))


def _row_profile(d: np.ndarray) -> np.ndarray:
    """The profile zone 2 max|d| of each row."""
    return 2.0 * np.abs(d).max(axis=1)


_EXTREME_CELL: dict[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], tuple[int, float]]] = {
    _row_min: lambda d: (int(np.argmin(d)), 1.0),
    _row_max: lambda d: (int(np.argmax(d)), 1.0),
    _row_profile: lambda d: (int(np.argmax(np.abs(d))), 2.0 * float(np.sign(d[int(np.argmax(np.abs(d)))]))),
}  # extreme-value figures of a row (`_deviation_stats`): which cell holds each, and how its height moves it


def _unroll(xy: np.ndarray, radius: np.ndarray, R: float) -> np.ndarray:
    """3D points in the cylinder's own frame (axis z) from (R theta, z) and radii."""
    t = xy[:, 0] / R
    return np.stack([radius * np.cos(t), radius * np.sin(t), xy[:, 1]], axis=1)
