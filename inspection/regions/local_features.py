"""Multi-scale local surface features of paper 002 (Dimitrov & Golparvar-Fard): normal,
principal curvatures and directions, and roughness from circle fits in planes rotating
about the normal, at six scales, with the representative scale per point.

For a point p of the subsampled cloud S and each scale d_j = f_j·r (f_j in
`SCALE_FACTORS`):
  - the partial neighbourhood B(d_j, q_j): at most q_j points of the full cloud P within
    d_j, sampled uniformly in space — the nearest points of P thinned to a voxel grid of
    side d_j·sqrt(pi/q_j), so a ball of radius d_j on a surface holds about q_j of them
    (q_j is chosen so each plane neighbourhood below gets ~`SLAB_POINTS` points). The
    small scales need P: S has ~11 points in a ball of 0.19·r, too few to tell a crease
    from a tight circle;
  - a rough normal from PCA of that neighbourhood (per scale, so a pipe thinner than r
    still gets its normal at the scales that fit inside it);
  - `N_PLANES` planes through p containing the normal, rotating uniformly about it; the
    points within 0.1·r of a plane form its plane neighbourhood, expressed in the plane's
    2D coordinates (x along the plane's tangent, h along the normal);
  - a least-squares circle in each plane, as A(x²+h²) + Bx + h + D = 0 (the coefficient
    of h fixed to 1: a circle or, for A = 0, a line, never degenerate for a surface
    patch seen along its normal); signed curvature κ = -2A/sqrt(B²+1-4AD), positive
    when the centre of curvature lies on the normal's side;
  - k1 from the plane of largest |κ|, k2 from the plane perpendicular to it (a scale
    whose circle has |k1|·d_j > `MAX_BEND`, i.e. turns by more than ~30 degrees within
    its own ball, is not a surface patch at that scale: sparse points around a sharp
    crease fit such a circle as well as a fillet, so it is refused); their fit
    errors (mean and standard deviation of the points' geometric distances to the circle)
    averaged give the roughness (μ, σ); the normal is the gradient of the two circles at
    p (for finite circles, the direction from their centres to p, as in the paper);
  - the point's own signed offset from the fitted surface is kept as `offset`.
The representative scale of a point is the one of least μ.

Features are computed in chunks of points, one thread per CPU (`in_parallel`: numpy and
the k-d tree queries release the GIL), every neighbourhood operation batched over the
chunk; the per-scale samples and their trees are built in parallel too. Units: mm, 1/mm
for curvatures.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from inspection.downsample import downsample

SCALE_FACTORS = (1.0, 0.72, 0.52, 0.37, 0.27, 0.19)
N_PLANES = 6                # planes rotating about the normal (perpendicular pairs: N_PLANES even)
SLAB_FACTOR = 0.1           # half-width of a plane neighbourhood, x r
SUBSAMPLE_FACTOR = 0.1      # voxel side of S, x r
SLAB_POINTS = 10  # points wanted per plane neighbourhood: sets q_j
MIN_FIT_POINTS = 5          # a circle (3 parameters) needs at least this many points
REEVAL_OVERSAMPLE = 3       # re-evaluation searches this many times q_j neighbours for segment points
NEAR_POINTS = 16            # growth neighbours within the smallest scale (S holds ~11 there) ...
FAR_POINTS = 24             # ... and a uniform sample of this many out to r
CHUNK = 2048                # points per batch
LEAF_SIZE = 32              # k-d tree leaves of the scale samples (queries of 16-80 neighbours: ~25 % faster than 16)
FLAT_CURVATURE = 1e-6       # |k|·r below this: flat (a cylinder or plane in `surface_distance`)
MAX_BEND = 0.5              # |k1|·d above this: the circle turns too far within its own ball

_ANGLES = np.arange(N_PLANES) * np.pi / N_PLANES
_COS, _SIN = np.cos(_ANGLES).astype(np.float32), np.sin(_ANGLES).astype(np.float32)


@dataclass(eq=False)
class LocalFeatures:
    """Representative features of some points (rows), all NaN / -1 where no scale had
    enough neighbours. `mu`, `sigma`: roughness (mm); `scale`: index into
    `SCALE_FACTORS`; `normal`, `k1_dir` (n, 3) unit; `k1`, `k2` signed principal
    curvatures (1/mm, |k1| >= |k2|, positive toward the normal); `offset`: signed
    distance (mm) of the point from its fitted surface along the normal."""

    mu: np.ndarray
    sigma: np.ndarray
    scale: np.ndarray
    normal: np.ndarray
    k1_dir: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    offset: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.scale >= 0

    def __len__(self) -> int:
        return len(self.mu)

    @classmethod
    def empty(cls, n: int) -> LocalFeatures:
        nan = np.full(n, np.nan)
        return cls(nan.copy(), nan.copy(), np.full(n, -1, np.int8), np.full((n, 3), np.nan),
                   np.full((n, 3), np.nan), nan.copy(), nan.copy(), nan.copy())

    def put(self, rows: np.ndarray, other: LocalFeatures) -> None:
        """Overwrite `rows` with `other`'s features (same order)."""
        for name in ("mu", "sigma", "scale", "normal", "k1_dir", "k1", "k2", "offset"):
            getattr(self, name)[rows] = getattr(other, name)

    def take(self, rows: np.ndarray) -> LocalFeatures:
        return LocalFeatures(*(getattr(self, n)[rows] for n in
                               ("mu", "sigma", "scale", "normal", "k1_dir", "k1", "k2", "offset")))

    def feet(self, points: np.ndarray) -> np.ndarray:
        """Where the points `points` (n, 3) mm (the rows these features describe) lie on
        their own fitted surfaces: each moved by -offset along its normal (unchanged
        where there are no features). Tests of whether a point lies on another point's
        surface use this, so the point's own noise does not count against it."""
        ok = self.valid
        out = np.asarray(points, dtype=np.float64).copy()
        out[ok] -= self.offset[ok, None] * self.normal[ok]
        return out


class MultiScale:
    """The partial neighbourhoods of every scale, sampled in a cloud P, for the points of
    its subsample S ⊆ P; the growth neighbourhoods within S; the feature computation."""

    def __init__(self, cloud: np.ndarray, subsample: np.ndarray, owner: np.ndarray, radius_mm: float,
                 spacing_mm: float, viewpoint: np.ndarray | None = None) -> None:
        """`cloud` P (N, 3) mm; `subsample` (M,) the rows of P forming S; `owner` (N,) the
        row of S representing each point of P; `spacing_mm` P's point spacing."""
        self.radius = float(radius_mm)
        pts = np.asarray(cloud, dtype=np.float64)
        self.centre = pts.mean(axis=0)
        self.cloud = (pts - self.centre).astype(np.float32)
        self.subsample = np.asarray(subsample, dtype=np.int64)
        self.owner = np.asarray(owner, dtype=np.int64)
        self.points = self.cloud[self.subsample]
        self.viewpoint = None if viewpoint is None else (np.asarray(viewpoint, float) - self.centre).astype(np.float32)
        self.radii = tuple(f * self.radius for f in SCALE_FACTORS)
        slab = SLAB_FACTOR * self.radius
        # points expected in a plane neighbourhood: q * (2 slab * 2 d) / (pi d^2)
        self.q = tuple(int(np.ceil(SLAB_POINTS * np.pi * d / (4 * slab))) for d in self.radii)
        # per scale, a voxel side thinning P to about q_j points per ball of d_j; None where
        # P is no denser than that (use it all)
        voxels = [v if v >= 1.5 * spacing_mm else None for v in (d * np.sqrt(np.pi / q)
                                                                 for d, q in zip(self.radii, self.q))]
        distinct = list(dict.fromkeys(voxels))
        built = dict(zip(distinct, in_parallel(self._sample, distinct)))
        self.samples = [built[v][0] for v in voxels]
        self.trees = [built[v][1] for v in voxels]
        # growth: all of S within the smallest scale, and a uniform sample of S out to r
        self.near_tree = cKDTree(self.points)
        far = downsample(self.points, self.radius * np.sqrt(np.pi / FAR_POINTS), "density_centre").indices
        assert far is not None
        self.far_rows = far
        self.far_tree = cKDTree(self.points[far])

    def _sample(self, voxel_mm: float | None) -> tuple[np.ndarray | None, cKDTree]:
        """The rows of P kept by density-centre voxel thinning (None: all) and their tree."""
        if voxel_mm is None:
            return None, cKDTree(self.cloud, leafsize=LEAF_SIZE)
        keep = downsample(self.cloud, voxel_mm, "density_centre").indices
        assert keep is not None
        return keep, cKDTree(self.cloud[keep], leafsize=LEAF_SIZE)

    def __len__(self) -> int:
        return len(self.points)

    def neighbours(self, j: int, ids: np.ndarray, labels: np.ndarray | None = None, segment: int = -1
                   ) -> np.ndarray:
        """(n, q_j) rows of P of the partial neighbourhood B(d_j, q_j) of points `ids` of
        S (the point itself excluded), -1 where there are fewer. With `labels` (per point
        of S), only rows of P whose representative is labelled `segment` count: the
        nearest `REEVAL_OVERSAMPLE`·q_j are searched so a point at a segment's border
        still gets up to q_j of the segment's points."""
        tree, sample = self.trees[j], self.samples[j]
        k = self.q[j] * (1 if labels is None else REEVAL_OVERSAMPLE) + 1
        dist, idx = tree.query(self.points[ids], k=k, distance_upper_bound=self.radii[j])
        idx = idx.astype(np.int64)
        ok = np.isfinite(dist)
        idx[~ok] = 0
        if sample is not None:
            idx = sample[idx]
        ok &= idx != self.subsample[ids][:, None]
        if labels is not None:
            ok &= labels[self.owner[idx]] == segment
        return _first_valid(idx, ok, self.q[j])

    def near_neighbours(self, ids: np.ndarray) -> np.ndarray:
        """(n, `NEAR_POINTS`) rows of S within the smallest scale of points `ids` of S
        (the point itself excluded), -1 where there are fewer."""
        d, near = self.near_tree.query(self.points[ids], k=NEAR_POINTS + 1, distance_upper_bound=self.radii[-1])
        ok = np.isfinite(d) & (near != ids[:, None])
        return _first_valid(np.where(ok, near, 0).astype(np.int64), ok, NEAR_POINTS)

    def growth_neighbours(self, ids: np.ndarray) -> np.ndarray:
        """(n, k) rows of S around points `ids` of S that growth may reach: all within the
        smallest scale (at most `NEAR_POINTS`) and a uniform sample of `FAR_POINTS` out
        to r, -1 where there are fewer (the point itself excluded)."""
        df, far = self.far_tree.query(self.points[ids], k=FAR_POINTS + 1, distance_upper_bound=self.radius)
        ok = np.isfinite(df)
        far = self.far_rows[np.where(ok, far, 0)]
        far = _first_valid(far, ok & (far != ids[:, None]), FAR_POINTS)
        return np.concatenate([self.near_neighbours(ids), far], axis=1)

    def features(self, ids: np.ndarray, labels: np.ndarray | None = None, segment: int = -1) -> LocalFeatures:
        """Representative features of points `ids` of S; with `labels` (per point of S),
        only neighbours whose representative is labelled `segment` count (the
        re-evaluation against a segment)."""
        ids = np.asarray(ids, dtype=np.int64)
        chunks = [ids[i:i + CHUNK] for i in range(0, len(ids), CHUNK)]
        parts = in_parallel(lambda c: self._chunk(c, labels, segment), chunks)
        out = LocalFeatures.empty(len(ids))
        start = 0
        for f in parts:
            out.put(np.arange(start, start + len(f)), f)
            start += len(f)
        return out

    def _chunk(self, ids: np.ndarray, labels: np.ndarray | None, segment: int) -> LocalFeatures:
        n = len(ids)
        per_scale = []
        centre = self.points[ids]
        for j, d in enumerate(self.radii):
            idx = self.neighbours(j, ids, labels, segment)
            v = self.cloud[np.maximum(idx, 0)] - centre[:, None, :]
            per_scale.append(_scale_features(v, idx >= 0, d, SLAB_FACTOR * self.radius))
        mu = np.stack([s[0] for s in per_scale], axis=1)
        best = np.argmin(np.where(np.isnan(mu), np.inf, mu), axis=1)
        has = np.isfinite(mu).any(axis=1)
        rows = np.arange(n)
        f = LocalFeatures.empty(n)
        pick = lambda k: np.stack([s[k] for s in per_scale], axis=1)[rows, best]  # noqa: E731
        f.mu[has] = pick(0)[has]
        f.sigma[has] = pick(1)[has]
        f.scale[has] = best[has]
        f.normal[has] = pick(2)[has]
        f.k1_dir[has] = pick(3)[has]
        f.k1[has] = pick(4)[has]
        f.k2[has] = pick(5)[has]
        f.offset[has] = pick(6)[has]
        if self.viewpoint is not None:  # normals toward the viewpoint: curvature signs follow
            flip = np.einsum("ij,ij->i", f.normal, self.viewpoint - centre) < 0
            f.normal[flip] *= -1
            f.k1[flip] *= -1
            f.k2[flip] *= -1
            f.offset[flip] *= -1
        return f

    def surface_agreement(self, ids: np.ndarray, f: LocalFeatures, targets: np.ndarray, target_at: np.ndarray,
                          target_normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For points `targets` (n, k rows of S, -1 ignored) around points `ids` with
        features `f`: the distances (mm, inf where ignored) of the targets, taken at
        `target_at` (n, k, 3: their own positions or feet, `LocalFeatures.feet`, in this
        object's centred frame), from each point's torus, and |cos| of the angle between
        their normals `target_normals` (n, k, 3) and the torus normal there (NaN where a
        target has no normal)."""
        foot = f.feet(self.points[ids])
        v = target_at - foot[:, None, :]
        d, g = surface_distance(v, f.normal, f.k1_dir, f.k1, f.k2, self.radius)
        d[targets < 0] = np.inf
        return d, np.abs(np.einsum("nkc,nkc->nk", g, target_normals))


def in_parallel(work: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
    """`work` applied to every item, in threads (one per CPU; numpy's array operations and
    scipy's k-d tree queries release the GIL), results in order."""
    if len(items) < 2:
        return [work(x) for x in items]
    with ThreadPoolExecutor(min(len(items), os.cpu_count() or 1)) as ex:
        return list(ex.map(work, items))


def _first_valid(idx: np.ndarray, ok: np.ndarray, k: int) -> np.ndarray:
    """The first `k` valid entries of each row of `idx` (order kept), -1 padded."""
    order = np.argsort(~ok, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(np.where(ok, idx, -1), order, axis=1)


def surface_distance(v: np.ndarray, normal: np.ndarray, k1_dir: np.ndarray, k1: np.ndarray, k2: np.ndarray,
                     radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Distances (n, k) of offsets `v` (n, k, 3) from each row's osculating torus, and the
    torus's unit normal (n, k, 3) at the nearest surface point (sign arbitrary). The
    torus passes through the origin with unit `normal`, curvature k1 along `k1_dir` and
    k2 across it (signed toward the normal, |k1| >= |k2|): a tube of radius 1/|k1| in
    the (k1_dir, normal) plane swept around the axis along k1_dir through the centre of
    k2's curvature; a cylinder when k2 is flat, a plane when k1 is too. Float64: the
    large radii of nearly flat directions cancel exactly enough."""
    n = normal[:, None, :]
    e1 = k1_dir[:, None, :]
    e2 = np.cross(normal, k1_dir)[:, None, :]
    u1 = np.einsum("nkc,nkc->nk", v, np.broadcast_to(e1, v.shape))
    u2 = np.einsum("nkc,nkc->nk", v, np.broadcast_to(e2, v.shape))
    w = np.einsum("nkc,nkc->nk", v, np.broadcast_to(n, v.shape))
    flat = FLAT_CURVATURE / radius_mm
    a1, a2 = np.abs(k1)[:, None], np.abs(k2)[:, None]
    plane, cylinder = a1 <= flat, (a1 > flat) & (a2 <= flat)
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(a1 > flat, 1.0 / k1[:, None], 0.0)
        r2 = np.where(a2 > flat, 1.0 / k2[:, None], 0.0)
        # torus: axis along e1 through (0, 0, r2), centre circle of radius |r2 - r1|;
        # a cylinder: axis along e2 through (0, 0, r1)
        rho = np.hypot(u2, w - r2)
        shrink = np.where(cylinder, 0.0, 1.0 - np.abs(r2 - r1) / rho)
        g1, g2 = u1, np.where(cylinder, 0.0, u2 * shrink)
        g3 = np.where(cylinder, w - r1, (w - r2) * shrink)
        dist = np.abs(np.sqrt(g1 * g1 + g2 * g2 + g3 * g3) - np.abs(r1))
    dist = np.where(plane, np.abs(w), dist)
    g = g1[..., None] * e1 + g2[..., None] * e2 + g3[..., None] * n
    g = np.where(plane[..., None], np.broadcast_to(n, g.shape), g)
    g /= np.linalg.norm(g, axis=-1, keepdims=True)
    return dist, g


def _scale_features(v: np.ndarray, ok: np.ndarray, d: float, slab: float) -> tuple[np.ndarray, ...]:
    """Features at one scale for a batch: `v` (n, q, 3) neighbour offsets (mm), `ok` (n, q)
    which count, `d` the scale radius, `slab` the plane neighbourhood half-width (mm).
    Returns mu, sigma, normal, k1_dir, k1, k2, offset (NaN where the scale fails)."""
    n = len(v)
    cnt = ok.sum(axis=1)
    w = ok.astype(np.float32)
    # rough normal: PCA of the neighbourhood
    mean = np.einsum("nq,nqc->nc", w, v) / np.maximum(cnt, 1)[:, None]
    vc = (v - mean[:, None, :]) * w[..., None]
    cov = np.matmul(vc.transpose(0, 2, 1), vc)
    _, vec = np.linalg.eigh(cov)
    nrm = vec[:, :, 0]
    helper = np.where(np.abs(nrm[:, :1]) < 0.9, np.array([[1, 0, 0]], np.float32), np.array([[0, 1, 0]], np.float32))
    e1 = np.cross(nrm, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(nrm, e1)
    frame = np.stack([e1, e2, nrm], axis=2) * np.float32(1.0 / d)   # (n, 3, 3): columns e1, e2, n over d
    a, b, h = np.moveaxis(np.matmul(v, frame), 2, 0)                  # local coordinates in units of d
    h2 = h * h
    ts = np.float32(slab / d)

    # least-squares circles A(x²+h²) + Bx + h + D = 0 in every plane (normalised units):
    # the plane moments are polynomials in (cos, sin) of sums of monomials in (a, b, h)
    # over the plane neighbourhoods, summed for all planes at once by one batched matmul
    mono = _monomials(a * w, b * w, h * w, w)
    inside = (np.abs(b[:, :, None] * _COS - a[:, :, None] * _SIN) < ts) & ok[:, :, None]
    G = np.matmul(mono, inside.astype(np.float32)).astype(np.float64)  # (n, monomials, planes)
    sw, sx, sh, sz, sxx, sxz, szz, sxh, szh = _plane_moments(G)
    A, B, D, good = _solve_circle(sw, sx, sh, sz=sz, sxx=sxx, sxz=sxz, szz=szz, sxh=sxh, szh=szh)
    Q = B * B + 1.0 - 4.0 * A * D
    good &= Q > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        kappa = np.where(good, -2.0 * A / np.sqrt(np.where(good, Q, 1.0)), np.nan)
    perp = (np.arange(N_PLANES) + N_PLANES // 2) % N_PLANES
    pair = good & good[:, perp]
    score = np.where(pair, np.abs(np.nan_to_num(kappa)), -1.0)
    c1 = np.argmax(score, axis=1)
    c2 = perp[c1]
    valid = pair[np.arange(n), c1] & (cnt >= MIN_FIT_POINTS) & (np.abs(kappa[np.arange(n), c1]) <= MAX_BEND)

    rows = np.arange(n)
    Qs = np.where(good, Q, 1.0)
    fit_mu, fit_sd, offs, slopes = [], [], [], []
    for c in (c1, c2):  # fit errors in the two principal planes
        cs, sn = _COS[c][:, None], _SIN[c][:, None]
        x = a * cs + b * sn
        member = ok & (np.abs(b * cs - a * sn) < ts)
        A0, B0, D0, Q0 = (p[rows, c] for p in (A, B, D, Qs))
        Ac, Bc, Dc, Qc = (p.astype(np.float32)[:, None] for p in (A0, B0, D0, Q0))
        P = Ac * (x * x + h2) + Bc * x + h + Dc
        dist = np.where(member, np.abs(2 * P / (np.sqrt(np.maximum(Qc + 4 * Ac * P, 0)) + np.sqrt(Qc))), 0)
        m = member.sum(axis=1)
        mean = dist.sum(axis=1) / np.maximum(m, 1)
        var = np.maximum(np.einsum("nq,nq->n", dist, dist) / np.maximum(m, 1) - mean * mean, 0)
        # residuals of m points shrink by the 3 fitted parameters: correct, so scales with
        # fewer points are not preferred for that alone
        corr = np.sqrt(m / np.maximum(m - 3, 1))
        fit_mu.append(mean * corr)
        fit_sd.append(np.sqrt(var) * corr)
        offs.append(2.0 * D0 / (np.sqrt(np.maximum(Q0 + 4.0 * A0 * D0, 0.0)) + np.sqrt(Q0)))
        slopes.append(B0.astype(np.float32))
    mu = (fit_mu[0] + fit_mu[1]) / 2 * d
    sigma = (fit_sd[0] + fit_sd[1]) / 2 * d
    offset = (offs[0] + offs[1]) / 2 * d
    t1 = _COS[c1][:, None] * e1 + _SIN[c1][:, None] * e2
    t2 = _COS[c2][:, None] * e1 + _SIN[c2][:, None] * e2
    normal = nrm + slopes[0][:, None] * t1 + slopes[1][:, None] * t2
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    k1_dir = t1 - np.einsum("nc,nc->n", t1, normal)[:, None] * normal
    k1_dir /= np.linalg.norm(k1_dir, axis=1, keepdims=True)
    k1 = kappa[rows, c1] / d
    k2 = kappa[rows, c2] / d
    nan = ~valid
    for arr in (mu, sigma, offset, k1, k2):
        arr[nan] = np.nan
    normal[nan] = np.nan
    k1_dir[nan] = np.nan
    return mu, sigma, normal, k1_dir, k1, k2, offset


# the monomials in (a, b, h) the plane moments need, each as a product of two earlier ones
_PRODUCTS = (("aa", "a", "a"), ("ab", "a", "b"), ("bb", "b", "b"), ("hh", "h", "h"), ("ah", "a", "h"),
             ("bh", "b", "h"), ("aaa", "aa", "a"), ("aab", "aa", "b"), ("abb", "a", "bb"), ("bbb", "bb", "b"),
             ("ahh", "a", "hh"), ("bhh", "b", "hh"), ("aaaa", "aa", "aa"), ("aaab", "aa", "ab"),
             ("aabb", "aa", "bb"), ("abbb", "ab", "bb"), ("bbbb", "bb", "bb"), ("aahh", "aa", "hh"),
             ("abhh", "ab", "hh"), ("bbhh", "bb", "hh"), ("hhhh", "hh", "hh"), ("aah", "aa", "h"),
             ("abh", "ab", "h"), ("bbh", "bb", "h"), ("hhh", "hh", "h"))
_MONOMIALS = ("1", "a", "b", "h") + tuple(p[0] for p in _PRODUCTS)
_M = {name: i for i, name in enumerate(_MONOMIALS)}


def _monomials(a: np.ndarray, b: np.ndarray, h: np.ndarray, one: np.ndarray) -> np.ndarray:
    """(n, 29, q) float32: the monomials of `_MONOMIALS` of every neighbour (zero where
    `one` is zero: the neighbours that do not count, whose a, b, h must be zero too)."""
    out = np.empty((a.shape[0], len(_MONOMIALS), a.shape[1]), dtype=np.float32)
    for name, x in (("1", one), ("a", a), ("b", b), ("h", h)):
        out[:, _M[name]] = x
    for name, left, right in _PRODUCTS:
        np.multiply(out[:, _M[left]], out[:, _M[right]], out=out[:, _M[name]])
    return out


def _plane_moments(G: np.ndarray) -> tuple[np.ndarray, ...]:
    """The nine moments (n, planes) of the circle fit in each plane, from the monomial
    sums G (n, 29, planes): with x = a·cos + b·sin and z = x² + h², (Σ1, Σx, Σh, Σz, Σx²,
    Σxz, Σz², Σxh, Σzh)."""
    c, s = _COS.astype(np.float64), _SIN.astype(np.float64)
    g = {k: G[:, i, :] for k, i in _M.items()}
    sx = c * g["a"] + s * g["b"]
    sxx = c * c * g["aa"] + 2 * c * s * g["ab"] + s * s * g["bb"]
    sx3 = c ** 3 * g["aaa"] + 3 * c * c * s * g["aab"] + 3 * c * s * s * g["abb"] + s ** 3 * g["bbb"]
    sxhh = c * g["ahh"] + s * g["bhh"]
    sx4 = (c ** 4 * g["aaaa"] + 4 * c ** 3 * s * g["aaab"] + 6 * c * c * s * s * g["aabb"]
           + 4 * c * s ** 3 * g["abbb"] + s ** 4 * g["bbbb"])
    sxxhh = c * c * g["aahh"] + 2 * c * s * g["abhh"] + s * s * g["bbhh"]
    sxxh = c * c * g["aah"] + 2 * c * s * g["abh"] + s * s * g["bbh"]
    return (g["1"], sx, g["h"], sxx + g["hh"], sxx, sx3 + sxhh, sx4 + 2 * sxxhh + g["hhhh"],
            c * g["ah"] + s * g["bh"], sxxh + g["hhh"])


def _solve_circle(sw: np.ndarray, sx: np.ndarray, sh: np.ndarray, *, sz: np.ndarray, sxx: np.ndarray,
                  sxz: np.ndarray, szz: np.ndarray, sxh: np.ndarray, szh: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, D, solvable) of the normal equations of min Σ (A z + B x + h + D)² from
    its moments, by Cramer's rule (all batched)."""
    m11, m12, m13 = szz, sxz, sz
    m22, m23, m33 = sxx, sx, sw
    r1, r2, r3 = -szh, -sxh, -sh
    c11 = m22 * m33 - m23 * m23
    c12 = m13 * m23 - m12 * m33
    c13 = m12 * m23 - m13 * m22
    det = m11 * c11 + m12 * c12 + m13 * c13
    scale = np.abs(m11 * m22 * m33)
    good = (sw >= MIN_FIT_POINTS) & (np.abs(det) > 1e-9 * scale) & (scale > 0)
    det = np.where(good, det, 1.0)
    c22 = m11 * m33 - m13 * m13
    c23 = m12 * m13 - m11 * m23
    c33 = m11 * m22 - m12 * m12
    A = (c11 * r1 + c12 * r2 + c13 * r3) / det
    B = (c12 * r1 + c22 * r2 + c23 * r3) / det
    D = (c13 * r1 + c23 * r2 + c33 * r3) / det
    return A, B, D, good
