"""Context-free region growing of paper 002 (Dimitrov & Golparvar-Fard): segments of an
unordered (or organised) point cloud from one user parameter, the radius of interest r.

Stages:
  1. subsample the cloud P to one point per voxel of side 0.1·r, S ⊆ P (the point nearest
     each voxel's centroid, `downsample`), keeping the map from every point of P to its
     representative in S;
  2. multi-scale features on S (`local_features`): roughness (μ, σ), principal
     curvatures and directions, normal, representative scale;
  3. the representative neighbourhood B'_i of every point: the points of S within its
     representative scale (all within 0.19·r and a uniform sample beyond) that lie within
     μ_i + 2σ_i of the point's osculating torus — at their foot (moved onto their own
     fitted surface by their offset) if their μ is within that tolerance too, else at
     their own position. An edge i -> j is trusted when j's own normal agrees with the
     torus normal there (`MAX_NORMAL_ANGLE`) and j -> i is a trusted edge too;
  4. seeds: τ = 0.01·r, γ = 0; the unsegmented point of least μ with μ ≤ τ and
     representative scale d_γ; none: γ += 1; all scales tried: τ *= 2, γ = 0; stop when
     τ exceeds r;
  5. growth from a seed: candidates C = B'_seed; a candidate reached by a trusted edge
     with μ ≤ μ_seg + 2σ_seg joins and adds its B' to C. The others are unreliable (their
     neighbourhood may straddle several objects, or their own surface disagrees with the
     segment's): once that growth stops, their features are recomputed from the
     segment's points only, and those whose re-fit is as smooth (μ' ≤ μ_seg + 2σ_seg)
     join, adding the B' of the recomputed features — which follows the segment's
     surface only; the rest are rejected for this segment (they may seed or join a
     later one). The segment roughness is the pooled fit error of its members (mean μ,
     and σ from the members' mean square μ² + σ²);
  6. points too sparse for any feature (the thin border of a sparsely seen surface), and
     crumbs (segments too small for any fit), join the one larger segment whose members'
     B' hold them if they lie on the torus of the nearest member.
Candidates are examined front by front (all of C at once), not one at a time.

Where the paper is silent or differs, and why:
  - B' tests a neighbour's foot, not its raw position: μ + 2σ bounds the fit error of a
    typical point, so a point whose own noise exceeds it (about 1 in 20 for Gaussian
    roughness: the mean |residual| is 0.8 s and its spread 0.6 s, so μ + 2σ ≈ 2 s) would
    lie outside every neighbour's B' and, its neighbours all taken, end as a segment of
    its own — 7 % of a rough floor was lost so. The foot removes the point's own noise
    and keeps its surface: a point whose fitted surface is another object's stays out.
    Only a neighbour as smooth as the tolerance is moved so: a rougher one's fit may
    straddle two surfaces (a thin part lying on a tray) and put its foot between them;
  - B' reaches only as far as the representative scale, not r: the torus is fitted on
    that ball, and its curvature extrapolated beyond it (from a small ball, noisy) can
    bend into a neighbouring surface;
  - trusted edges and deferred re-evaluation: around a sharp crease, sparse points fit a
    tight circle as well as a fillet, so two points each side of it can look smooth and
    hold each other in their B'; the paper's test (roughness alone) then carries growth
    across. Requiring agreeing normals both ways, and re-fitting from the segment's own
    points everything else, stops that; re-fitting only when the segment's growth has
    stopped gives it the most segment points around the candidate;
  - re-evaluation uses every scale (restricted to the segment's points, searched among
    `REEVAL_OVERSAMPLE`·q neighbours) and keeps the one of least μ, like the features;
    segments with fewer than 2·`MIN_FIT_POINTS` members re-evaluate nothing (no fit);
  - tolerances never drop below `MIN_TOLERANCE`·r (noise-free synthetic data has μ = 0).
Labels: segments in the order they were grown (smoothest seeds first), -1 for points no
segment took (too rough, too few neighbours, rejected everywhere). Units: mm.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from inspection.downsample import downsample, voxel_cells
from inspection.errors import CloudError, SegmentationError
from inspection.regions.local_features import (
    CHUNK,
    FAR_POINTS,
    MIN_FIT_POINTS,
    NEAR_POINTS,
    SCALE_FACTORS,
    SUBSAMPLE_FACTOR,
    LocalFeatures,
    MultiScale,
    in_parallel,
)

INITIAL_TAU = 0.01          # first roughness threshold, x r
MIN_TOLERANCE = 1e-4        # floor of every roughness tolerance, x r
MIN_RADIUS_SPACINGS = 5.0   # r must span at least this many point spacings
# the default r, in point spacings (`default_radius`): on the simulated rooms
# (`sim.clutter`, nominal spacing 1 mm, measured median nearest-neighbour spacing
# 0.55-0.61 mm) the fixed 12 mm default gave beta 13 %, and beta <= 8 % came at ~20 mm;
# at 35 spacings (r 19.2-21.4 mm) seeds 0-4 give beta 6.3-7.4 %, mean 6.85 % (`slscan bench segment
# --seeds 0 1 2 3 4`)
DEFAULT_RADIUS_SPACINGS = 35.0
MIN_SUBSAMPLED = 20         # fewer voxels than this: r is too large for the cloud
MAX_NORMAL_ANGLE = np.radians(30.0)   # B': a neighbour's normal vs the torus normal there


@dataclass(eq=False)
class Segmentation:
    """Per-point segment labels of a cloud (`labels` (N,) int32, -1 unsegmented) and what
    produced them: the subsample S (`subsample` (M,) rows of the input, `owner` (N,) the
    row of S representing each input point, `subsample_labels` (M,)), S's features,
    `reevaluated` (M,) bool for points that joined after re-evaluation, the radius, and
    the timings (s) of each stage."""

    labels: np.ndarray
    radius_mm: float
    subsample: np.ndarray
    owner: np.ndarray
    subsample_labels: np.ndarray
    features: LocalFeatures
    reevaluated: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def n_segments(self) -> int:
        return int(self.subsample_labels.max(initial=-1) + 1)

    def sizes(self) -> np.ndarray:
        """Points of the input per segment (index = label)."""
        return np.bincount(self.labels[self.labels >= 0], minlength=self.n_segments)


def point_spacing(points: np.ndarray, sample: int = 2000, seed: int = 0) -> float:
    """Median distance (mm) from a random sample of points to their nearest neighbour."""
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(points), size=min(sample, len(points)), replace=False)
    tree = cKDTree(points, balanced_tree=False, compact_nodes=False)   # for one query: the quick build
    d, _ = tree.query(points[pick], k=2)
    return float(np.median(d[:, 1]))


def default_radius(points: np.ndarray) -> float:
    """The default radius of interest (mm) of a cloud (N, 3): `DEFAULT_RADIUS_SPACINGS`
    times its point spacing, rounded to 0.1 mm (non-finite rows ignored)."""
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 2:
        raise CloudError("segment", "the cloud has fewer than two points: no spacing to choose a radius from")
    return round(DEFAULT_RADIUS_SPACINGS * point_spacing(pts), 1)


def check_radius(points: np.ndarray, radius_mm: float) -> float:
    """Refuse a radius of interest no neighbourhood can work with: not a positive length,
    below `MIN_RADIUS_SPACINGS` point spacings (the small scales would hold no
    neighbours), or beyond the cloud's size (fewer than `MIN_SUBSAMPLED` voxels)."""
    if not (np.isfinite(radius_mm) and radius_mm > 0):
        raise SegmentationError(f"radius of interest must be a positive length in mm, got {radius_mm}")
    spacing = point_spacing(points)
    if radius_mm < MIN_RADIUS_SPACINGS * spacing:
        raise SegmentationError(
            f"radius of interest {radius_mm:g} mm is below {MIN_RADIUS_SPACINGS:g} point spacings of this cloud "
            f"(spacing {spacing:.4g} mm): its smallest scales would hold no neighbours; "
            f"use r >= {MIN_RADIUS_SPACINGS * spacing:.3g} mm")
    diag = float(np.linalg.norm(np.ptp(points, axis=0)))
    voxels = len(voxel_cells(points, SUBSAMPLE_FACTOR * radius_mm)[1])
    if voxels < MIN_SUBSAMPLED and not diag / 2 > MIN_RADIUS_SPACINGS * spacing:
        raise SegmentationError(f"this cloud ({len(points)} points, extent {diag:.4g} mm) is too small to segment at "
                                f"any radius of interest: scan more of the surface")
    if voxels < MIN_SUBSAMPLED:
        raise SegmentationError(
            f"radius of interest {radius_mm:g} mm is too large for this cloud (extent {diag:.4g} mm): it leaves "
            f"{voxels} voxels of 0.1 r; use r <= {diag / 2:.3g} mm")
    return spacing


def segment(points: np.ndarray, radius_mm: float, viewpoint: np.ndarray | None = None) -> Segmentation:
    """Segment a cloud (N, 3) mm with radius of interest `radius_mm`. Non-finite rows
    (missing points) are labelled -1. `viewpoint` (mm) only orients the normals."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CloudError("segment", f"expected (N, 3) points, got shape {pts.shape}")
    finite = np.isfinite(pts).all(axis=1)
    if not finite.any():
        raise CloudError("segment", "the cloud has no points: nothing to segment")
    rows = np.flatnonzero(finite)
    good = pts[rows]
    spacing = check_radius(good, radius_mm)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    sub = downsample(good, SUBSAMPLE_FACTOR * radius_mm, "density_centre")
    assert sub.indices is not None
    t1 = time.perf_counter()
    timings["subsample"] = t1 - t0
    ms = MultiScale(good, sub.indices, sub.inverse, radius_mm, spacing, viewpoint)
    feats = ms.features(np.arange(len(ms)))
    t2 = time.perf_counter()
    timings["features"] = t2 - t1
    feet = feats.feet(ms.points)
    edges = mutual(representative_neighbourhoods(ms, np.arange(len(ms)), feats, feats, feet))
    t3 = time.perf_counter()
    timings["neighbourhoods"] = t3 - t2
    grower = _Grower(ms, feats, feet, edges)
    grower.run()
    timings["growth"] = time.perf_counter() - t3
    labels = np.full(len(pts), -1, dtype=np.int32)
    labels[rows] = grower.label[sub.inverse]
    owner = np.full(len(pts), -1, dtype=np.int64)
    owner[rows] = sub.inverse
    return Segmentation(labels, float(radius_mm), rows[sub.indices], owner, grower.label, grower.features,
                        grower.reevaluated, {k: round(v, 4) for k, v in timings.items()})


def representative_neighbourhoods(ms: MultiScale, ids: np.ndarray, f: LocalFeatures,
                                  every: LocalFeatures, feet: np.ndarray) -> np.ndarray:
    """B' of points `ids` of S (features `f`): (n, k) rows of S among their growth
    neighbours that lie within the representative scale and within μ + 2σ of the point's
    torus — a neighbour as smooth as that (its μ, from `every`, the features of all of S)
    by its foot (`feet`, per point of S: where it lies on its own fitted surface), any
    other by its own position (its fit may straddle two surfaces: its foot could sit
    between them). An entry is the row j itself where the neighbour's normal agrees with
    the torus normal there (within `MAX_NORMAL_ANGLE`: a trusted edge), `untrusted(j)`
    where it does not, -1 where there is no edge."""
    tol = np.maximum(f.mu + 2 * f.sigma, MIN_TOLERANCE * ms.radius)
    reach = np.asarray(ms.radii)[np.maximum(f.scale, 0)]
    min_cos = np.cos(MAX_NORMAL_ANGLE)

    def chunk(rows: np.ndarray) -> np.ndarray:
        c = ms.growth_neighbours(ids[rows])
        out = np.full(c.shape, -1, dtype=np.int64)
        rows, c, keep = rows[f.valid[rows]], c[f.valid[rows]], np.flatnonzero(f.valid[rows])
        if not rows.size:
            return out
        j = np.maximum(c, 0)
        smooth = every.mu[j] <= tol[rows, None]
        at = np.where(smooth[..., None], feet[j], ms.points[j])
        d, cos = ms.surface_agreement(ids[rows], f.take(rows), c, at, every.normal[j])
        gap = ms.points[np.maximum(c, 0)] - ms.points[ids[rows]][:, None, :]
        near = np.einsum("nkc,nkc->nk", gap, gap) <= (reach[rows] ** 2)[:, None]
        on = (d <= tol[rows, None]) & near
        out[keep] = np.where(on, np.where(cos >= min_cos, c, untrusted(c)), -1)
        return out

    order = np.arange(len(ids))
    return np.concatenate(in_parallel(chunk, [order[i:i + CHUNK] for i in range(0, len(ids), CHUNK)])
                          or [np.empty((0, NEAR_POINTS + FAR_POINTS), dtype=np.int64)])


def untrusted(j: np.ndarray) -> np.ndarray:
    """The edge code of an untrusted edge to row j (and back: the code's own inverse)."""
    return -2 - j


def mutual(edges: np.ndarray) -> np.ndarray:
    """Demote trusted edge i -> j of the B' lists `edges` (one row per point of S) to
    untrusted unless j -> i is trusted too: both points' surfaces must agree, so a point
    whose fit bends across a crease cannot carry growth onto the other side alone."""
    n, k = edges.shape
    src = np.repeat(np.arange(n, dtype=np.int64), k)
    dst = edges.ravel()
    ok = dst >= 0
    # the reversed trusted edges as sorted keys (j, i); the edges themselves, looked up as
    # (i, j), come in row order: a nearly sorted search, far faster than a random one
    keys = np.sort(dst[ok] * n + src[ok])
    ask = src[ok] * n + dst[ok]
    found = np.zeros(len(dst), dtype=bool)
    if len(keys):
        found[ok] = keys[np.minimum(np.searchsorted(keys, ask), len(keys) - 1)] == ask
    return np.where(ok & ~found, untrusted(dst), dst).reshape(n, k)


class _Grower:
    """Seeds and growth over S (see the module docstring)."""

    def __init__(self, ms: MultiScale, features: LocalFeatures, feet: np.ndarray, edges: np.ndarray) -> None:
        self.ms = ms
        self.features = features
        self.feet = feet                             # points of S on their own fitted surfaces
        self.edges = edges
        n = len(ms)
        self.label = np.full(n, -1, dtype=np.int32)
        self.seen = np.full(n, -1, dtype=np.int32)   # last segment that examined the point
        self.reevaluated = np.zeros(n, dtype=bool)
        self.n_segments = 0

    def run(self) -> None:
        f = self.features
        r = self.ms.radius
        mu = np.where(f.valid, f.mu, np.inf)
        tau = INITIAL_TAU * r
        while tau <= r:
            for gamma in range(len(SCALE_FACTORS)):
                cands = np.flatnonzero((mu <= tau) & (f.scale == gamma) & (self.label < 0))
                cands = cands[np.argsort(mu[cands], kind="stable")]
                self._grow_all(cands)
            tau *= 2
        self._absorb_leftovers()

    def _absorb_leftovers(self) -> None:
        """Points without features of their own (too few neighbours at every scale: the
        sparse border of a surface) never seed and cannot be re-evaluated; points left in
        segments too small for any fit (fewer than 2·`MIN_FIT_POINTS`) are crumbs of a
        border or a crease. Such a point joins a larger segment when members of that
        segment only have it in their B' (it lies on their tori) and it lies on the torus
        of the nearest of them."""
        f = self.features
        size = np.bincount(self.label[self.label >= 0], minlength=self.n_segments)
        big = size >= 2 * MIN_FIT_POINTS
        segmented = self.label >= 0
        crumb = np.zeros(len(self.label), dtype=bool)
        crumb[segmented] = ~big[self.label[segmented]]
        loose = crumb | (~segmented & ~f.valid)
        members = np.flatnonzero(segmented & ~crumb)
        codes = self.edges[members]
        dst = np.where(codes <= -2, untrusted(codes), codes).ravel()
        by = np.repeat(self.label[members], codes.shape[1])
        keep = dst >= 0
        keep[keep] = loose[dst[keep]]
        dst, by = dst[keep], by[keep]
        if not dst.size:
            return
        order = np.lexsort((by, dst))
        dst, by = dst[order], by[order]
        start = np.flatnonzero(np.r_[True, dst[1:] != dst[:-1]])
        lo, hi = np.minimum.reduceat(by, start), np.maximum.reduceat(by, start)
        rows, seg = dst[start][lo == hi], lo[lo == hi]
        near = self.ms.growth_neighbours(rows)
        around = np.where(near >= 0, self.label[np.maximum(near, 0)], -1)
        # it lies on the surface of the nearest member around it (within its tolerance)
        mine = (around == seg[:, None]) & f.valid[np.maximum(near, 0)]
        dist = np.where(mine, np.linalg.norm(self.ms.points[np.maximum(near, 0)] - self.ms.points[rows][:, None],
                                             axis=2), np.inf)
        has = mine.any(axis=1)
        rows, seg = rows[has], seg[has]
        nearest = near[has][np.arange(len(rows)), np.argmin(dist[has], axis=1)]
        g = f.take(nearest)
        d, _ = self.ms.surface_agreement(nearest, g, rows[:, None], self.feet[rows][:, None],
                                         np.zeros((len(rows), 1, 3)))
        on = d[:, 0] <= np.maximum(g.mu + 2 * g.sigma, MIN_TOLERANCE * self.ms.radius)
        self.label[rows[on]] = seg[on]

    def _grow_all(self, cands: np.ndarray) -> None:
        """Grow a segment from every candidate seed still free, in order."""
        pos, block = 0, 256
        while pos < len(cands):
            chunk = cands[pos:pos + block]
            free = np.flatnonzero(self.label[chunk] < 0)
            if not free.size:
                pos += block
                continue
            self._grow(int(chunk[free[0]]))
            pos += int(free[0]) + 1

    def _grow(self, seed: int) -> None:
        """Grow segment s from `seed`: points reached by a trusted edge join while they are
        smooth enough; the others wait until that growth stops (so the segment is as
        complete as it gets around them) and are then re-evaluated against it, all at
        once; joiners continue the growth. Points re-evaluated and refused are done for s."""
        s = self.n_segments
        self.n_segments += 1
        f = self.features
        self.label[seed] = s
        self.seen[seed] = s
        stats = np.array([1.0, f.mu[seed], f.mu[seed] ** 2 + f.sigma[seed] ** 2])
        pending = np.zeros(0, dtype=np.int64)
        codes = self.edges[seed]
        while True:
            front, trusted = self._fresh(codes, s)
            while front.size:
                ok = trusted & (f.mu[front] <= self._threshold(stats))
                acc = front[ok]
                self.seen[acc] = s
                self._join(acc, s, stats)
                pending = np.union1d(pending, front[~ok])
                front, trusted = self._fresh(self.edges[acc].ravel(), s)
            pending = pending[self.label[pending] < 0]
            if not pending.size or stats[0] < 2 * MIN_FIT_POINTS:
                return   # nothing to re-evaluate, or too few members for any fit to them
            self.seen[pending] = s
            codes = self._reevaluate(pending, s, stats)
            pending = pending[:0]
            if not codes.size:
                return

    def _threshold(self, stats: np.ndarray) -> float:
        """μ_seg + 2σ_seg from the pooled sums (count, Σμ, Σ(μ² + σ²)), at least the floor."""
        n, s1, s2 = stats
        mean = s1 / n
        return max(mean + 2 * np.sqrt(max(s2 / n - mean * mean, 0.0)), MIN_TOLERANCE * self.ms.radius)

    def _join(self, rows: np.ndarray, s: int, stats: np.ndarray) -> None:
        f = self.features
        self.label[rows] = s
        stats += (len(rows), f.mu[rows].sum(), (f.mu[rows] ** 2 + f.sigma[rows] ** 2).sum())

    def _reevaluate(self, rows: np.ndarray, s: int, stats: np.ndarray) -> np.ndarray:
        """Re-evaluate points `rows` against segment s only; the ones on its surface join
        (their features replaced by the re-fitted ones). Returns the joiners' B' edge
        codes, flattened, trusted only where the target's own B' trusts the joiner back."""
        thr = self._threshold(stats)
        g = self.ms.features(rows, self.label, s)
        join = g.mu <= thr
        if not join.any():
            return np.empty(0, dtype=np.int64)
        j = rows[join]
        gj = g.take(join)
        self.features.put(j, gj)
        self.feet[j] = gj.feet(self.ms.points[j])
        self.reevaluated[j] = True
        self._join(j, s, stats)
        e = representative_neighbourhoods(self.ms, j, gj, self.features, self.feet)
        back = (self.edges[np.maximum(e, 0)] == j[:, None, None]).any(axis=2)
        return np.where((e >= 0) & ~back, untrusted(e), e).ravel()

    def _fresh(self, codes: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
        """The distinct points reached by edge `codes` that are in no segment and not yet
        examined for segment s, and whether a trusted edge reached each."""
        idx = np.where(codes <= -2, untrusted(codes), codes)
        keep = idx >= 0
        idx, trust = idx[keep], codes[keep] >= 0
        keep = (self.label[idx] < 0) & (self.seen[idx] != s)
        idx, trust = idx[keep], trust[keep]
        front = np.unique(idx)
        return front, np.isin(front, idx[trust])
