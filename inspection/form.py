"""Form and texture of one measured face: least-squares and minimum-zone flatness and
cylindricity, the areal Gaussian filter of ISO 16610-61, and Sq (ISO 25178-2).

Inputs are the face's measured points in the model frame (after registration) and their
signed deviations from the nominal surface (`segmentation`). Heights are laid on the
face's own 2D coordinates (a plane: its in-plane axes; a cylinder: arc length R*theta
and axial position, unrolled), resampled on a square grid of about the point spacing.

Filters (ISO 16610-61 weighting function s(x) = exp(-pi (x/(alpha lc))^2)/(alpha lc)^2,
alpha = sqrt(ln 2 / pi): 50 % transmission at the nesting index lc):
  - the form surface is the heights filtered with cut-off `form_cutoff_mm`, as a local
    second-order Gaussian regression (the same weights, a quadratic fitted about each
    cell): it keeps quadratic form (a bow, a taper) exactly up to the face's edges, where
    the plain Gaussian mean would pull it toward the interior;
  - the roughness (S-L) surface is the heights minus their plain Gaussian filter of
    cut-off `roughness_cutoff_mm` (normalised where the face ends), Sq its RMS.

Scanner noise: white height noise sigma_n adds sigma_n^2 to Sq^2 and widens any zone
evaluated on raw points by several sigma_n. So zones are evaluated on the form surface
(the filter divides the noise by sqrt of the points it averages), sigma_n is estimated
from the heights themselves (fourth differences along the grid, blind to the smooth
form and texture), Sq is reported with the noise removed in quadrature, and each zone
comes with its noise floor: the zone the filtered noise alone would span.

Profile of a surface (ISO 1101, zone centred on nominal): 2 max|d| over the form
surface's signed deviations d, not over raw points, whose extremes are those of the noise
(about sigma_n sqrt(2 ln N), 4-5 sigma_n for 1e4-1e6 points, on both sides); the raw
extremes are kept beside it.

Minimum zone (Chebyshev, the ISO 1101 default): the narrowest pair of parallel planes
(coaxial cylinders) holding the surface, solved as a linear programme (HiGHS) on the
planes' (cylinders') small-displacement parameters about the least-squares fit,
relinearised until it settles. Least squares: Eq. 20 (plane) and Eq. 21-22 (cylinder)
of paper 000. Every length in mm.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares, linprog

ALPHA = float(np.sqrt(np.log(2.0) / np.pi))  # ISO 16610-61
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


def cylinder_ls(points: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Paper 000 Eq. 21-22: the axis (point, direction) minimising sum (r_i - mean r)^2,
    r_i = |o p_i x n|, from the nominal axis; returns (origin, unit axis, mean radius)."""
    axis = axis / np.linalg.norm(axis)
    u, v = _frame(axis)
    o0 = origin + ((points - origin) @ axis).mean() * axis  # centred along the axis

    def radii(x: np.ndarray) -> np.ndarray:
        o, n = _axis(o0, u, v, axis, x)
        d = points - o
        return np.linalg.norm(d - np.outer(d @ n, n), axis=1)

    res = least_squares(lambda x: radii(x) - radii(x).mean(), np.zeros(4), method="lm")
    o, n = _axis(o0, u, v, axis, res.x)
    return o, n, float(radii(res.x).mean())


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
    points (LP on the convex hull's vertices, heights along the LS normal)."""
    from scipy.spatial import ConvexHull, QhullError

    c, n = plane_ls(points, normal)
    u, v = _frame(n)
    d = points - c
    x, y, z = d @ u, d @ v, d @ n
    try:
        hull = ConvexHull(np.stack([x, y, z], axis=1)).vertices
    except QhullError:  # flat or degenerate: every point counts
        hull = np.arange(len(points))
    x, y, z = x[hull], y[hull], z[hull]
    # minimise w: c_lo <= z - a x - b y <= c_lo + w      (variables a, b, c_lo, w)
    ones = np.ones_like(x)
    A_ub = np.concatenate([np.stack([-x, -y, -ones, -ones], 1), np.stack([x, y, ones, 0 * ones], 1)])
    b_ub = np.concatenate([-z, z])
    res = linprog([0, 0, 0, 1], A_ub=A_ub, b_ub=b_ub, bounds=[(None, None)] * 3 + [(0, None)], method="highs")
    a, b = res.x[0], res.x[1]
    return float(res.x[3] / np.sqrt(1.0 + a * a + b * b))


def cylindricity_mz(points: np.ndarray, origin: np.ndarray, axis: np.ndarray, rounds: int = 6) -> float:
    """Minimum-zone cylindricity: the least radial distance between two coaxial cylinders
    holding the points. An LP on the axis's four small-displacement parameters about the
    current axis, relinearised; each LP holds only the points with the most extreme radii
    (plus any point the previous solution left outside its zone), which is exact: the
    zone is fixed by a handful of extreme points."""
    o, n, _ = cylinder_ls(points, origin, axis)
    width = np.inf
    for _ in range(rounds):
        u, v = _frame(n)
        d = points - o
        a = d @ n
        radial = d - np.outer(a, n)
        r = np.linalg.norm(radial, axis=1)
        e = radial / r[:, None]
        # dr/dx for the axis o + x2 u + x3 v, direction n + x0 u + x1 v
        J = np.stack([-a * (e @ u), -a * (e @ v), -(e @ u), -(e @ v)], axis=1)
        k = min(len(r), 400)
        active = np.union1d(np.argpartition(r, k - 1)[:k], np.argpartition(-r, k - 1)[:k])
        for _ in range(20):  # add violators until the zone holds every point
            x, R, w = _cylinder_lp(r[active], J[active])
            rr = r + J @ x
            out = np.flatnonzero((rr < R - 1e-9) | (rr > R + w + 1e-9))
            if not out.size:
                break
            active = np.union1d(active, out[np.argsort(-np.maximum(R - rr[out], rr[out] - R - w))[:200]])
        o, n = _axis(o, u, v, n, x)
        d = points - o
        r_new = np.linalg.norm(d - np.outer(d @ n, n), axis=1)
        new = float(r_new.max() - r_new.min())
        if new >= width - 1e-9:
            break
        width = new
    return float(width)


def _cylinder_lp(r: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, float, float]:
    """min w subject to R <= r + J x <= R + w; returns (x, R, w)."""
    ones = np.ones_like(r)
    A_ub = np.concatenate([np.column_stack([-J, ones, 0 * ones]), np.column_stack([J, -ones, -ones])])
    b_ub = np.concatenate([r, -r])
    res = linprog([0, 0, 0, 0, 0, 1], A_ub=A_ub, b_ub=b_ub, bounds=[(None, None)] * 5 + [(0, None)], method="highs")
    return res.x[:4], float(res.x[4]), float(res.x[5])


# ------------------------------------------------------------------------------- filters


def gaussian_kernel_1d(cutoff_mm: float, spacing_mm: float, moment: int = 0) -> np.ndarray:
    """The ISO 16610-61 weighting function sampled every `spacing_mm` out to where it is
    below 1e-9 of its peak, times x^moment (x in mm)."""
    half = int(np.ceil(ALPHA * cutoff_mm * 2.6 / spacing_mm))
    x = np.arange(-half, half + 1) * spacing_mm
    return np.exp(-np.pi * (x / (ALPHA * cutoff_mm)) ** 2) * x ** moment


def _smooth(image: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    out = ndimage.correlate1d(image, kx, axis=1, mode="constant")
    return ndimage.correlate1d(out, ky, axis=0, mode="constant")


def gaussian_filter(z: np.ndarray, mask: np.ndarray, cutoff_mm: float, spacing_mm: float,
                    order: int = 0) -> np.ndarray:
    """The ISO 16610-61 areal Gaussian filter of a gridded surface z (NaN outside `mask`):
    order 0, the Gaussian mean (normalised where the surface ends); order 2, the local
    second-order regression with the same weights (exact for quadratic surfaces)."""
    w = mask.astype(np.float64)
    zw = np.where(mask, z, 0.0)
    if order == 0:
        k = gaussian_kernel_1d(cutoff_mm, spacing_mm)
        return _smooth(zw, k, k) / np.maximum(_smooth(w, k, k), 1e-300)
    # moments about each cell: S_ab = sum w g (dx^a dy^b), T_ab = sum w z g (dx^a dy^b)
    ks = [gaussian_kernel_1d(cutoff_mm, spacing_mm, m) for m in range(5)]  # correlation: offsets x = +j dx
    mono = [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]
    S = {}
    for i, (a1, b1) in enumerate(mono):
        for a2, b2 in mono[i:]:
            key = (a1 + a2, b1 + b2)
            if key not in S:
                S[key] = _smooth(w, ks[key[0]], ks[key[1]])
    Tz = [_smooth(zw, ks[a], ks[b]) for a, b in mono]
    M = np.empty(z.shape + (6, 6))
    for i, (a1, b1) in enumerate(mono):
        for j, (a2, b2) in enumerate(mono):
            M[..., i, j] = S[(a1 + a2, b1 + b2)]
    rhs = np.stack(Tz, axis=-1)
    scale = np.maximum(M[..., 0, 0], 1e-300)[..., None, None]
    ok = mask & (M[..., 0, 0] > 1e-12 * M[..., 0, 0].max())
    out = np.full(z.shape, np.nan)
    Mo = M[ok] / scale[ok]
    ro = rhs[ok] / scale[ok][..., 0]
    coef = np.linalg.solve(Mo + 1e-12 * np.eye(6), ro[..., None])[..., 0]
    out[ok] = coef[:, 0]
    return out


# ------------------------------------------------------------------------ per-face result


@dataclass(frozen=True)
class FormSettings:
    """`form_cutoff_mm`: nesting index of the form filter; `roughness_cutoff_mm`: of the
    roughness (L) filter; `edge_margin_mm`: a band along the face's measured border left
    out of every figure (mixed pixels and blur live there); `outlier_sigma`: points further
    than this many robust sigma from the median deviation are dropped as spikes."""

    form_cutoff_mm: float = FORM_CUTOFF_MM
    roughness_cutoff_mm: float = ROUGHNESS_CUTOFF_MM
    edge_margin_mm: float = 1.0
    outlier_sigma: float = 6.0


@dataclass(frozen=True)
class FaceForm:
    """Figures of one face (mm; None where they do not apply or could not be measured).
    `*_mz_mm` are minimum-zone widths on the form surface, `*_ls_mm` least-squares widths
    on it; `raw_zone_mm` the minimum zone of the unfiltered points (noise included);
    `noise_floor_mm` the zone the filtered scanner noise alone would span; `noise_mm` the
    estimated height noise per point; `sq_mm` the roughness with that noise removed in
    quadrature (`sq_raw_mm` before). Signed deviations from nominal: `deviation_*` of the
    form surface (`deviation_source` "form surface"; "raw points" for a face without
    surface coordinates to filter on, whose figures then carry the noise), `profile_mm`
    = 2 max|deviation| (the ISO 1101 profile zone centred on nominal), `raw_deviation_*`
    the extremes of the unfiltered points the figures rest on (inside the edge margin,
    spikes dropped)."""

    points: int
    status: str
    note: str = ""
    flatness_ls_mm: float | None = None
    flatness_mz_mm: float | None = None
    cylindricity_ls_mm: float | None = None
    cylindricity_mz_mm: float | None = None
    raw_zone_mm: float | None = None
    noise_floor_mm: float | None = None
    sq_mm: float | None = None
    sq_raw_mm: float | None = None
    noise_mm: float | None = None
    deviation_min_mm: float | None = None
    deviation_max_mm: float | None = None
    deviation_mean_mm: float | None = None
    deviation_rms_mm: float | None = None
    profile_mm: float | None = None
    deviation_source: str | None = None
    raw_deviation_min_mm: float | None = None
    raw_deviation_max_mm: float | None = None
    form_cutoff_mm: float | None = None
    roughness_cutoff_mm: float | None = None
    grid_mm: float | None = None

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def _surface_coordinates(face: object, points: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """2D metric coordinates (N, 2) mm of the points on the face: in-plane axes of a
    plane, (R theta, axial) of a cylinder or cone (theta unwrapped), None otherwise."""
    s = face.surface  # type: ignore[attr-defined]
    if face.type == "plane":  # type: ignore[attr-defined]
        if hasattr(s, "local"):
            return s.local(points)[:, :2]
        c = points.mean(axis=0)  # a planar mesh face: its principal axes
        _, _, vt = np.linalg.svd(points - c, full_matrices=False)
        return (points - c) @ vt[:2].T
    if face.type in ("cylinder", "cone"):  # type: ignore[attr-defined]
        t = np.mod(uv[:, 0], 2 * np.pi)
        ts = np.sort(t)
        k = int(np.argmax(np.diff(np.append(ts, ts[0] + 2 * np.pi))))
        t = np.mod(t - ts[(k + 1) % len(ts)], 2 * np.pi)  # the largest empty arc at the seam
        radius = s.radius if face.type == "cylinder" else s.ref_radius  # type: ignore[attr-defined]
        return np.stack([radius * t, uv[:, 1]], axis=1)
    return None


def _grid(xy: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """(mean heights per cell (H, W), NaN where empty; mask; spacing; cell (column, row)
    of each point; origin). The spacing starts at the points' typical nearest-neighbour
    distance and grows until nine cells in ten inside the measured area hold a point."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(xy).query(xy, k=2)
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
    tot = np.bincount(flat, weights=z, minlength=shape[0] * shape[1])
    zg = np.full(shape, np.nan)
    zg[mask] = tot[cnt > 0] / cnt[cnt > 0]
    return zg, mask, g, ij, lo


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


def evaluate_face(face: object, points: np.ndarray, deviation: np.ndarray, uv: np.ndarray,
                  settings: FormSettings = FormSettings(), seed: int = 0) -> FaceForm:
    """Form, texture and deviation figures of one face from its measured points (model
    frame), their signed deviations and the surface parameters of their feet."""
    n = len(points)
    if n < MIN_POINTS:
        return FaceForm(n, "too few points", f"{n} points; at least {MIN_POINTS} are needed")
    med = np.median(deviation)
    rs = 1.4826 * np.median(np.abs(deviation - med))
    keep = np.abs(deviation - med) <= settings.outlier_sigma * max(rs, 1e-6)
    points, deviation, uv = points[keep], deviation[keep], uv[keep]
    xy = _surface_coordinates(face, points, uv)
    if xy is None:
        return FaceForm(len(points), "ok", f"{face.type}: deviations of raw points only (no form filter)",  # type: ignore[attr-defined]
                        **_stats(deviation, deviation, "raw points"))
    zg, mask, g, ij, lo = _grid(xy, deviation)
    margin = int(np.ceil(settings.edge_margin_mm / g))
    region = ndimage.binary_closing(mask, np.ones((3, 3)), border_value=0) | mask  # sampling gaps closed, holes kept
    inner = mask & (ndimage.binary_erosion(region, np.ones((2 * margin + 1, 2 * margin + 1)), border_value=0)
                    if margin else region)
    if inner.sum() < MIN_POINTS:
        return FaceForm(len(points), "too few points", f"fewer than {MIN_POINTS} grid cells of {g:.3g} mm left "
                        f"inside the {settings.edge_margin_mm} mm edge margin")
    zg = np.where(inner, zg, np.nan)  # the border band's mixed pixels must not leak into the filters
    sigma = noise_sigma(zg, inner)
    form = gaussian_filter(zg, inner, settings.form_cutoff_mm, g, order=2)
    rough = zg - gaussian_filter(zg, inner, settings.roughness_cutoff_mm, g, order=0)
    sq_raw = float(np.sqrt(np.mean(rough[inner] ** 2)))
    sq = float(np.sqrt(max(sq_raw ** 2 - (sigma or 0.0) ** 2, 0.0)))
    rng = np.random.default_rng(seed)
    floor = None
    if sigma:
        noise = gaussian_filter(np.where(inner, rng.normal(0.0, sigma, zg.shape), np.nan), inner,
                                settings.form_cutoff_mm, g, order=2)
        floor = float(np.nanmax(noise[inner]) - np.nanmin(noise[inner]))
    rows, cols = np.nonzero(inner)
    cxy = lo + (np.stack([cols, rows], axis=1) + 0.5) * g
    raw_sel = inner[ij[:, 1], ij[:, 0]]
    common = dict(points=int(raw_sel.sum()), status="ok", noise_floor_mm=floor, sq_mm=sq, sq_raw_mm=sq_raw,
                  noise_mm=sigma, form_cutoff_mm=settings.form_cutoff_mm,
                  roughness_cutoff_mm=settings.roughness_cutoff_mm, grid_mm=g,
                  **_stats(form[inner], deviation[raw_sel], "form surface"))
    if face.type == "plane":  # type: ignore[attr-defined]
        up = np.array([0.0, 0.0, 1.0])
        fp = np.column_stack([cxy, form[inner]])
        raw = np.column_stack([xy[raw_sel], deviation[raw_sel]])
        c, nn = plane_ls(fp, up)
        h = (fp - c) @ nn
        return FaceForm(flatness_ls_mm=float(h.max() - h.min()), flatness_mz_mm=flatness_mz(fp, up),
                        raw_zone_mm=flatness_mz(raw, up), **common)
    if face.type == "cylinder":  # type: ignore[attr-defined]
        s = face.surface  # type: ignore[attr-defined]
        R = s.radius
        sign = face.sense * np.sign(np.dot(s.evaluate(np.zeros((1, 2)))[1][0], s.x))  # dev -> radius change
        fp = _unroll(cxy, R + sign * form[inner], R)
        raw = _unroll(xy[raw_sel], R + sign * deviation[raw_sel], R)
        axis0, o0 = np.array([0.0, 0.0, 1.0]), np.zeros(3)
        o, a, _ = cylinder_ls(fp, o0, axis0)
        d = fp - o
        r = np.linalg.norm(d - np.outer(d @ a, a), axis=1)
        return FaceForm(cylindricity_ls_mm=float(r.max() - r.min()), cylindricity_mz_mm=cylindricity_mz(fp, o0, axis0),
                        raw_zone_mm=cylindricity_mz(raw, o0, axis0), **common)
    return FaceForm(note=f"{face.type}: texture and deviations only", **common)  # type: ignore[attr-defined]


def _stats(surface: np.ndarray, raw: np.ndarray, source: str) -> dict[str, float | str]:
    """Deviation figures of `surface` (the form surface's deviations, or the raw ones),
    its profile zone 2 max|d|, and the extremes of the `raw` point deviations (mm)."""
    lo, hi = float(surface.min()), float(surface.max())
    return dict(deviation_min_mm=lo, deviation_max_mm=hi, deviation_mean_mm=float(surface.mean()),
                deviation_rms_mm=float(np.sqrt(np.mean(surface ** 2))), profile_mm=2.0 * max(abs(lo), abs(hi)),
                deviation_source=source, raw_deviation_min_mm=float(raw.min()), raw_deviation_max_mm=float(raw.max()))


def _unroll(xy: np.ndarray, radius: np.ndarray, R: float) -> np.ndarray:
    """3D points in the cylinder's own frame (axis z) from (R theta, z) and radii."""
    t = xy[:, 0] / R
    return np.stack([radius * np.cos(t), radius * np.sin(t), xy[:, 1]], axis=1)
