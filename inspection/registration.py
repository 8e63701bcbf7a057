"""Part-in-whole registration of a single-view scan to a whole CAD model (or a cloud).

The method of paper 000 (Kong et al. 2023, section 3), with the coarse and fine steps of
paper 001 (Deng et al. 2023, section 3.2):

1. Both clouds on one voxel grid (`voxel_mm`: the model's diagonal / `VOXEL_FRACTION`),
   normals averaged per voxel.
2. Multi-scale random sphere cover sets (RSCS): per scale, a random uncovered point is
   the next sphere centre until every point is covered. The radii follow Eq. 19,
   r = (3/(4 pi) * 0.7/(2 m) * V)^(1/3) with V the volume of the scan's circumscribed
   sphere, for m = `RegistrationSettings.spheres` (snapped to a half-octave ladder of the
   voxel, so a model's features are computed once per radius). Spheres whose normals are
   all parallel (a patch of one plane: nothing to describe) are screened out. The model
   is covered densely (centres every r/4), so every scan sphere has a model sphere at
   nearly the same place.
3. Descriptors of each sphere: FPFH (Open3D) and SHOT (`features.shot`), support = the
   sphere. For each scan sphere and descriptor, the nearest model spheres in descriptor
   space; the match score is the distinctiveness 1 - d1/d2 (d2: the best match elsewhere).
   Multivariate combination (Eq. 11): where the descriptors' best matches agree, the
   correspondence is their score-weighted mean l = sum w_i c_i; where they disagree, both
   are kept as candidates.
4. Coarse pose: SAC-IA — triplets of correspondences drawn by score (scan points spread
   apart, edge lengths consistent on both sides), the rigid transform of each (Kabsch,
   Eq. 12-15), scored by the Huber penalty of paper 001 Eq. 22 over the distances from a
   sample of scan points to the model. Alternatives: RANSAC (score = correspondences
   within the inlier distance) and NDT (paper 001 Eq. 23-26: the model as normal
   distributions on a voxel grid, the score maximised by Newton steps from 24 axis-aligned
   starts).
5. Hypothesis verification: the best distinct coarse poses, and the best two turned half
   a turn about the scan's principal axes (the usual confusions of a prismatic or nearly
   symmetric part), are each refined by ICP and judged by fitness (scan points within `inlier_mm` of the model with agreeing normals)
   minus the fraction of scan points the posed model would hide from the sensor (a
   surface in front of a measured point means that pose is wrong). A symmetric or
   prismatic part that fits several poses equally well is reported as ambiguous.
6. Fine pose: point-to-plane ICP with normal-angle rejection (paper 001 Eq. 27-29, with
   the point-to-plane metric) on the dense scan (points seen at grazing incidence left
   out, normal-space sampling so walls and holes weigh in) against dense model samples;
   then, for STEP models, Gauss-Newton on the exact point-to-face distances (a sample's
   tangent plane departs from a small cylinder by up to s^2/(8R), s the sample spacing).

A pose is reported only when it explains the scan: otherwise `RegistrationFailed`.
Transforms are 4x4, taking scan coordinates onto the model (SOURCE onto TARGET); mm.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from inspection.cad import CadModel
from inspection.downsample import voxel_cells
from inspection.errors import RegistrationFailed
from inspection.features import fpfh, shot
from inspection.measured_cloud import ScanCloud
from inspection.sampling import LabelledCloud, sample_model
from inspection.segmentation import assign_faces, project_to_faces

VOXEL_FRACTION = 150.0
DENSE_FRACTION = 3.0  # model samples for ICP: spacing = voxel / DENSE_FRACTION
COARSE_METHODS = ("sac-ia", "ransac", "ndt")
DESCRIPTORS = ("fpfh", "shot")
MAX_INCIDENCE_DEG = 75.0  # fine step: points seen more obliquely than this are left out
EXPLORED = 4  # verification: hypotheses explored further
COARSE_TURNS_DEG = (2.5, 5.0, 10.0, 20.0, 30.0)  # verification: turns tried about the scan's principal axes
FINE_TURNS_DEG = (0.1, 0.25, 0.5, 1.0, 2.0)  # and about the best pose, with a tight inlier distance
EXACT_POINTS = 40000  # fine step: points in the exact-distance refinement
FACE_BIAS_SIGMA = 3.0  # fine step: faces off their surface by more, as a group, are left out
OFFSET_NOISE_RATIO = 1.25  # fine step: residuals spreading more than this x the noise: a face may be off
BIG_FACE_FRACTION = 0.05  # fine step: faces holding this share of the points are tried left out
TANGENTIAL_WEIGHT = 0.1  # ICP: weight of an extra point-to-point term along the surface
DESCRIPTOR_FRACTION = 5.0  # descriptors are computed on a grid of radius / this
DESCRIPTOR_NN = 64  # neighbours per descriptor support at most
EXPLORE_PRESCORE_STRIDE = 4  # exploration: moves pre-scored on every 4th point,
EXPLORE_TOP = 6  # and the best 6 of them scored on all points
PRESCORED = 150  # SAC-IA: hypotheses scored on all evaluation points after a pre-score on a fifth


@dataclass(frozen=True)
class RegistrationSettings:
    """`descriptors`: any of "fpfh", "shot" (both: the multivariate combination);
    `coarse`: "sac-ia", "ransac" or "ndt"; `spheres`: m of Eq. 19 per RSCS scale;
    `hypotheses`: coarse poses scored; `verify`: distinct poses refined and verified;
    `min_fitness`: below it the registration fails; `max_normal_deg`: ICP's normal-angle
    rejection; `max_points`: scan points used by the fine step; `seed`: randomness."""

    descriptors: tuple[str, ...] = DESCRIPTORS
    coarse: str = "sac-ia"
    spheres: tuple[int, ...] = (200, 100, 50)
    hypotheses: int = 1500
    verify: int = 6
    min_fitness: float = 0.9
    max_normal_deg: float = 30.0
    max_points: int = 40000
    ambiguity_margin: float = 0.02
    seed: int = 0

    def __post_init__(self) -> None:
        if self.coarse not in COARSE_METHODS:
            raise ValueError(f"unknown coarse method {self.coarse!r}; use one of {COARSE_METHODS}")
        if not self.descriptors or any(d not in DESCRIPTORS for d in self.descriptors):
            raise ValueError(f"descriptors must be a non-empty subset of {DESCRIPTORS}, got {self.descriptors}")


@dataclass(frozen=True)
class Registration:
    """`transform` (4x4) takes scan points onto the model; `fitness`: fraction of scan
    points within `inlier_mm` of the model (normals agreeing); `rmse_mm` their RMS
    distance; `coarse` the pose before the fine step; `ambiguous` when another pose
    (`alternatives`) explains the scan as well; `timings_s` per stage."""

    transform: np.ndarray
    fitness: float
    rmse_mm: float
    inlier_mm: float
    coarse: np.ndarray
    method: str
    ambiguous: bool = False
    alternatives: tuple[np.ndarray, ...] = ()
    hidden_fraction: float = 0.0
    timings_s: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        return {"transform": self.transform.tolist(), "fitness": self.fitness, "rmse_mm": self.rmse_mm,
                "inlier_mm": self.inlier_mm, "method": self.method, "ambiguous": self.ambiguous,
                "hidden_fraction": self.hidden_fraction, "timings_s": self.timings_s}


# ------------------------------------------------------------------------------ helpers


def voxel_grid(points: np.ndarray, normals: np.ndarray, voxel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(centroids, unit mean normals) of the occupied voxels of side `voxel_mm`."""
    cell, counts = voxel_cells(points, voxel_mm)
    p = np.stack([np.bincount(cell, weights=points[:, k], minlength=len(counts)) for k in range(3)], 1)
    n = np.stack([np.bincount(cell, weights=normals[:, k], minlength=len(counts)) for k in range(3)], 1)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    ok = norm[:, 0] > 1e-9
    return (p / counts[:, None])[ok], (n / np.where(norm > 0, norm, 1.0))[ok]


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Rigid transforms (..., 4, 4) taking src (..., n, 3) onto dst in the least-squares
    sense (Eq. 12-15: centroids, cross-covariance, SVD, reflection guarded)."""
    w = np.ones(src.shape[:-1]) if weights is None else weights
    w = w / w.sum(axis=-1, keepdims=True)
    cs = np.einsum("...n,...ni->...i", w, src)
    cd = np.einsum("...n,...ni->...i", w, dst)
    h = np.einsum("...n,...ni,...nj->...ij", w, src - cs[..., None, :], dst - cd[..., None, :])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("...ji,...kj->...ik", vt, u)))
    fix = np.ones(h.shape[:-2] + (3,))
    fix[..., 2] = d
    R = np.einsum("...ji,...j,...kj->...ik", vt, fix, u)
    T = np.zeros(h.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = cd - np.einsum("...ij,...j->...i", R, cs)
    T[..., 3, 3] = 1.0
    return T


def pose_difference(a: np.ndarray, b: np.ndarray, about: np.ndarray | None = None) -> tuple[float, float]:
    """(rotation angle in degrees, translation distance in mm) between two poses; the
    distance is that between the images of the point `about` (default: the origin)."""
    d = np.linalg.inv(a) @ b
    angle = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1.0, 1.0)))
    p = np.zeros(3) if about is None else about
    return float(angle), float(np.linalg.norm(transform_points(a, p[None]) - transform_points(b, p[None])))


def _ladder(radius: float, voxel: float) -> float:
    """`radius` snapped to the half-octave ladder voxel * 2^(k/2)."""
    return voxel * 2.0 ** (np.round(2 * np.log2(radius / voxel)) / 2)


# ------------------------------------------------------------------------------- target


@dataclass(eq=False)
class Samples:
    """Points (N, 3) with unit normals and their KD-tree."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree = field(init=False)

    def __post_init__(self) -> None:
        self.tree = cKDTree(self.points)


@dataclass(eq=False)
class _Features:
    points: np.ndarray
    descriptors: dict[str, np.ndarray]


class ModelTarget:
    """What a scan is registered to, prepared once: dense samples with normals (and CAD
    face labels), the voxel-grid cloud the descriptors are computed on, and the sphere
    descriptors per radius (computed when first needed, then kept)."""

    def __init__(self, points: np.ndarray, normals: np.ndarray, name: str, voxel_mm: float | None = None,
                 model: CadModel | None = None, samples: LabelledCloud | None = None) -> None:
        self.name = name
        self.model = model
        self.samples = samples  # CAD targets: the labelled samples `points`/`normals` come from
        self.dense = Samples(points, normals)
        self.diagonal_mm = float(np.linalg.norm(np.ptp(points, axis=0)))
        self.voxel_mm = voxel_mm or self.diagonal_mm / VOXEL_FRACTION
        self.coarse = Samples(*voxel_grid(points, normals, self.voxel_mm))
        self._features: dict[float, _Features] = {}
        self._mesh_scene = None

    @classmethod
    def from_cad(cls, model: CadModel, voxel_mm: float | None = None, seed: int = 0) -> ModelTarget:
        voxel = voxel_mm or model.diagonal_mm / VOXEL_FRACTION
        s = sample_model(model, voxel / DENSE_FRACTION, seed=seed)
        return cls(s.points, s.normals, str(model.path), voxel, model, s)

    @classmethod
    def from_cloud(cls, scan: ScanCloud, voxel_mm: float | None = None) -> ModelTarget:
        return cls(scan.points, scan.normals, scan.source, voxel_mm)

    def features(self, radius: float, descriptors: tuple[str, ...]) -> _Features:
        """Sphere centres every radius/4 over the whole model and their descriptors."""
        f = self._features.get(radius)
        if f is None or any(d not in f.descriptors for d in descriptors):
            cloud = Samples(*voxel_grid(self.coarse.points, self.coarse.normals, radius / DESCRIPTOR_FRACTION))
            centres, _ = voxel_grid(cloud.points, cloud.normals, radius / 4.0)
            _, idx = cloud.tree.query(centres)
            idx = _screen(cloud, np.unique(idx), radius)
            f = _Features(cloud.points[idx], _describe(cloud, idx, radius, descriptors))
            self._features[radius] = f
        return f

    def prepare(self, scan: ScanCloud, settings: RegistrationSettings = RegistrationSettings()) -> None:
        """Compute, ahead of registration, what `register` would compute for a scan like
        `scan` the first time: the sphere descriptors at its RSCS radii (a once-per-model
        cost, kept for every later scan of that size) and the ray-casting scene."""
        pts, _ = voxel_grid(scan.points, scan.normals, self.voxel_mm)
        if settings.coarse != "ndt" and len(pts) >= 50:
            for r in _sphere_radii(pts, self.voxel_mm, settings.spheres)[1]:
                self.features(r, settings.descriptors)
        if scan.viewpoint is not None:
            self.hidden_fraction(np.eye(4), scan.points[:1], scan.viewpoint, 1.0)

    def hidden_fraction(self, T: np.ndarray, points: np.ndarray, viewpoint: np.ndarray, tol_mm: float) -> float:
        """Fraction of scan `points` (scan frame) that the model, posed by T (scan ->
        model), would hide from `viewpoint`: a model surface crossed more than `tol_mm`
        before the point on the ray from the sensor."""
        import open3d as o3d

        if self.model is None:
            return 0.0
        if self._mesh_scene is None:
            tess = self.model.tessellation
            self._mesh_scene = o3d.t.geometry.RaycastingScene()
            self._mesh_scene.add_triangles(o3d.core.Tensor(tess.vertices.astype(np.float32)),
                                           o3d.core.Tensor(tess.triangles.astype(np.uint32)))
        o = transform_points(T, viewpoint[None])[0]
        q = transform_points(T, points)
        d = q - o
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.broadcast_to(o, q.shape), d / dist[:, None]], axis=1).astype(np.float32)
        t = self._mesh_scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        return float(np.mean(t < dist - tol_mm))


def _screen(cloud: Samples, idx: np.ndarray, radius: float, min_points: int = 12) -> np.ndarray:
    """The sphere centres worth describing: enough points, and not all of one plane."""
    d, nb = cloud.tree.query(cloud.points[idx], k=64, distance_upper_bound=radius)
    valid = np.isfinite(d)
    nb = np.where(valid, nb, 0)
    mean = (cloud.normals[nb] * valid[..., None]).sum(axis=1) / np.maximum(valid.sum(axis=1), 1)[:, None]
    return idx[(valid.sum(axis=1) >= min_points) & (np.linalg.norm(mean, axis=1) < 0.98)]


def _describe(cloud: Samples, idx: np.ndarray, radius: float, descriptors: tuple[str, ...]) -> dict[str, np.ndarray]:
    out = {}
    if "fpfh" in descriptors:
        out["fpfh"] = fpfh(cloud.points, cloud.normals, idx, radius, DESCRIPTOR_NN)
    if "shot" in descriptors:
        out["shot"] = shot(cloud.points, cloud.normals, cloud.points[idx], radius, cloud.tree, DESCRIPTOR_NN)
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
    return _screen(cloud, np.array(centres, np.int64), radius)


# ----------------------------------------------------------------------- correspondences


def _best_matches(src: np.ndarray, dst: np.ndarray, dst_points: np.ndarray, radius: float,
                  k: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(indices (Ks, k) of the k nearest dst descriptors, scores (Ks, k) = 1 - d_j/d_alt)
    where d_alt is the distance of the best match more than a radius away from match j."""
    d2 = (src ** 2).sum(1)[:, None] + (dst ** 2).sum(1)[None, :] - 2.0 * src @ dst.T
    d = np.sqrt(np.maximum(d2, 0.0))
    kk = min(k + 8, d.shape[1])
    part = np.argpartition(d, kk - 1, axis=1)[:, :kk]
    order = np.take_along_axis(d, part, 1).argsort(axis=1)
    cand = np.take_along_axis(part, order, 1)
    cd = np.take_along_axis(d, cand, 1)
    # the alternative of each of the first k: the nearest candidate far from it in space
    sep = np.linalg.norm(dst_points[cand[:, :k, None]] - dst_points[cand[:, None, :]], axis=-1) > radius
    alt = np.where(sep, cd[:, None, :], np.inf).min(axis=2)
    alt = np.where(np.isfinite(alt), alt, cd[:, -1:])
    score = np.clip(1.0 - cd[:, :k] / np.maximum(alt, 1e-12), 0.0, 1.0)
    return cand[:, :k], score


def correspondences(src_pts: np.ndarray, src_desc: dict[str, np.ndarray], dst_pts: np.ndarray,
                    dst_desc: dict[str, np.ndarray], radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(scan points (C, 3), model points (C, 3), weights (C,)) of one scale: each
    descriptor's k best matches; where two descriptors' best matches agree (within half a
    radius) they merge into their score-weighted mean (Eq. 11)."""
    names = [n for n in DESCRIPTORS if n in src_desc]
    matches = {n: _best_matches(src_desc[n], dst_desc[n], dst_pts, radius) for n in names}
    s_out, d_out, w_out = [], [], []
    if len(names) == 2:
        (ia, sa), (ib, sb) = matches[names[0]], matches[names[1]]
        ca, cb = dst_pts[ia[:, 0]], dst_pts[ib[:, 0]]
        agree = np.linalg.norm(ca - cb, axis=1) < radius / 2
        wsum = np.maximum(sa[:, 0] + sb[:, 0], 1e-12)
        merged = (sa[:, 0, None] * ca + sb[:, 0, None] * cb) / wsum[:, None]  # Eq. 11
        s_out.append(src_pts[agree])
        d_out.append(merged[agree])
        w_out.append(sa[agree, 0] + sb[agree, 0])
        for idx, sc in ((ia, sa), (ib, sb)):  # disagreeing best matches, and the runners-up
            keep = np.ones_like(sc, bool)
            keep[agree, 0] = False
            s_out.append(np.broadcast_to(src_pts[:, None], idx.shape + (3,))[keep])
            d_out.append(dst_pts[idx][keep])
            w_out.append(sc[keep])
    else:
        idx, sc = matches[names[0]]
        s_out.append(np.broadcast_to(src_pts[:, None], idx.shape + (3,)).reshape(-1, 3))
        d_out.append(dst_pts[idx].reshape(-1, 3))
        w_out.append(sc.ravel())
    return np.concatenate(s_out), np.concatenate(d_out), np.concatenate(w_out)


# --------------------------------------------------------------------------- coarse pose


def huber(l: np.ndarray, ml: float) -> np.ndarray:
    """Paper 001 Eq. 22: l^2/2 below ml, ml (2 l - ml)/2 above."""
    return np.where(l < ml, 0.5 * l * l, 0.5 * ml * (2.0 * l - ml))


def _triplets(src: np.ndarray, dst: np.ndarray, w: np.ndarray, n: int, min_sep: float, tol: float,
              rng: np.random.Generator, max_corr: int = 1500) -> np.ndarray:
    """Up to n index triplets (n, 3) of mutually consistent correspondences: every pair
    of the three has its scan points at least `min_sep` apart and the same distance on
    both sides within tol (+3 %). Correspondences are weighted by their descriptor score
    times their number of consistent partners (correct ones agree with each other, wrong
    ones only by chance); the first is drawn by weight, the second among those consistent
    with it, the third among those consistent with both."""
    keep = np.argsort(-w)[:max_corr]
    src, dst, w = src[keep], dst[keep], w[keep]
    ds, dd = cdist(src, src), cdist(dst, dst)
    C = (np.abs(ds - dd) < tol + 0.03 * ds) & (ds > min_sep)
    score = w * (C.sum(axis=1) + 1.0)
    if not C.any():
        return np.zeros((0, 3), np.int64)
    i = rng.choice(len(w), size=2 * n, p=score / score.sum())

    def pick(mask: np.ndarray) -> np.ndarray:
        weight = mask * score[None, :]
        cum = np.cumsum(weight, axis=1)
        total = cum[:, -1]
        u = rng.random(len(mask)) * total
        j = np.minimum((cum < u[:, None]).sum(axis=1), len(score) - 1)
        return np.where(total > 0, j, -1)

    j = pick(C[i])
    i, j = i[j >= 0], j[j >= 0]
    k = pick(C[i] & C[j])
    ok = k >= 0
    return keep[np.stack([i[ok], j[ok], k[ok]], axis=1)[:n]]


def _score_poses(T: np.ndarray, eval_pts: np.ndarray, target: ModelTarget, ml: float, cap: float,
                 workers: int = -1) -> np.ndarray:
    """Huber score (Eq. 22, lower is better) of each pose (H, 4, 4) over eval_pts
    (`workers`: KD-tree query threads, -1 all)."""
    q = np.einsum("hij,nj->hni", T[:, :3, :3], eval_pts) + T[:, None, :3, 3]
    d, _ = target.coarse.tree.query(q.reshape(-1, 3), distance_upper_bound=cap, workers=workers)
    d = np.minimum(d, cap).reshape(len(T), -1)
    return huber(d, ml).sum(axis=1)


def _distinct(T: np.ndarray, order: np.ndarray, n: int, angle_deg: float, dist_mm: float) -> list[np.ndarray]:
    picked: list[np.ndarray] = []
    for i in order:  # a few thousand at most, usually stops after a handful
        if all(pose_difference(T[i], p)[0] > angle_deg or pose_difference(T[i], p)[1] > dist_mm for p in picked):
            picked.append(T[i])
            if len(picked) == n:
                break
    return picked


def with_flips(poses: list[np.ndarray], points: np.ndarray, n_best: int = 2) -> list[np.ndarray]:
    """The poses, plus, for the best `n_best`, the scan turned half a turn about each of its
    principal axes (through its centroid) first: the poses a prismatic or nearly symmetric
    part is confused with, so that verification sees them side by side."""
    c = points.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((points - c).T))
    flips = []
    for a in axes.T:
        F = np.eye(4)
        F[:3, :3] = 2.0 * np.outer(a, a) - np.eye(3)  # rotation by pi about a
        F[:3, 3] = c - F[:3, :3] @ c
        flips.append(F)
    return poses + [T @ F for T in poses[:n_best] for F in flips]


def plane_poses(src_pts: np.ndarray, src_nrm: np.ndarray, target: ModelTarget, n_best: int = 4,
                n_faces: int = 4, step_deg: float = 10.0) -> list[np.ndarray]:
    """Poses from the scan's dominant plane, for scans that are mostly one plane (a flat
    part seen from above), where local descriptors have little to grip: the plane laid on
    each of the model's largest planar faces, turned about its normal every `step_deg`,
    plane centroids matched; the most promising shortly refined by ICP; the `n_best` by
    fitness."""
    if target.model is None or target.samples is None:
        return []
    rng = np.random.default_rng(0)
    cand = src_nrm[rng.choice(len(src_nrm), size=min(200, len(src_nrm)), replace=False)]
    near = (cand @ src_nrm.T) > np.cos(np.radians(5.0))
    k = int(np.argmax(near.sum(axis=1)))
    on = near[k]
    ns = src_nrm[on].mean(axis=0)
    ns /= np.linalg.norm(ns)
    h = src_pts[on] @ ns  # several parallel planes (steps) share the normal: take the most populated
    bins = np.floor((h - h.min()) / target.voxel_mm).astype(np.int64)
    level = h.min() + (np.argmax(np.bincount(bins)) + 0.5) * target.voxel_mm
    cs = src_pts[on][np.abs(h - level) < target.voxel_mm].mean(axis=0)
    planes = sorted((f for f in target.model.faces if f.type == "plane"), key=lambda f: -f.area_mm2)[:n_faces]
    poses = []
    for f in planes:
        sel = target.samples.face == f.index
        m = target.samples.normals[sel].mean(axis=0)
        m /= np.linalg.norm(m)
        cm = target.samples.points[sel].mean(axis=0)
        R0, _ = Rotation.align_vectors([m], [ns])
        for deg in np.arange(0.0, 360.0, step_deg):
            R = (Rotation.from_rotvec(np.radians(deg) * m) * R0).as_matrix()
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = cm - R @ cs
            poses.append(T)
    if not poses:
        return []
    pick = rng.choice(len(src_pts), size=min(300, len(src_pts)), replace=False)
    v = target.voxel_mm
    P = np.array(poses)
    first = np.argsort(-fitness(src_pts[pick], src_nrm[pick], target.coarse, P, 6.0 * v, 45.0))[:3 * n_best]
    P = np.array([icp(src_pts[pick], src_nrm[pick], target.coarse, P[i], 20.0 * v, 2.0 * v, 45.0, 8, 0.5)
                  for i in first])  # a short, nearly point-to-point ICP: the plane centroids are only a guess
    fits = fitness(src_pts[pick], src_nrm[pick], target.coarse, P, 3.0 * v, 45.0)
    return [P[i] for i in np.argsort(-fits)[:n_best]]


def _sphere_radii(src_pts: np.ndarray, voxel_mm: float, spheres: tuple[int, ...]) -> tuple[float, list[float]]:
    """(radius of the scan's circumscribed sphere about its centroid, the RSCS radii of
    Eq. 19 snapped to the ladder), mm."""
    rc = float(np.linalg.norm(src_pts - src_pts.mean(axis=0), axis=1).max())
    return rc, sorted({_ladder(rc * (0.7 / (2 * m)) ** (1 / 3), voxel_mm) for m in spheres})


def coarse_feature_poses(src_pts: np.ndarray, src_nrm: np.ndarray, target: ModelTarget,
                         settings: RegistrationSettings, rng: np.random.Generator,
                         workers: int = -1) -> list[np.ndarray]:
    """Distinct coarse poses from RSCS + descriptors + SAC-IA (or RANSAC), best first
    (`workers`: KD-tree query threads of the pose scoring, -1 all; 1 suits small clouds
    on a busy machine, where starting threads costs more than they save)."""
    rc, radii = _sphere_radii(src_pts, target.voxel_mm, settings.spheres)
    S, D, W = [], [], []
    for r in radii:
        cloud = Samples(*voxel_grid(src_pts, src_nrm, r / DESCRIPTOR_FRACTION))
        idx = rscs(cloud, r, rng)
        if len(idx) < 3:
            continue
        desc = _describe(cloud, idx, r, settings.descriptors)
        tf = target.features(r, settings.descriptors)
        if len(tf.points) < 3:
            continue
        s, d, w = correspondences(cloud.points[idx], desc, tf.points, tf.descriptors, r)
        S.append(s)
        D.append(d)
        W.append(w)
    if not S:
        return []
    src, dst, w = np.concatenate(S), np.concatenate(D), np.concatenate(W) + 1e-3
    tol = 2.0 * target.voxel_mm
    trip = _triplets(src, dst, w, settings.hypotheses, 0.1 * rc, tol, rng)
    if not len(trip):
        return []
    T = kabsch(src[trip], dst[trip])
    if settings.coarse == "ransac":
        moved = np.einsum("hij,nj->hni", T[:, :3, :3], src) + T[:, None, :3, 3]
        score = -(np.linalg.norm(moved - dst[None], axis=2) < tol).sum(axis=1).astype(float)
    else:
        ev = src_pts[rng.choice(len(src_pts), size=min(300, len(src_pts)), replace=False)]
        ml, cap = 1.5 * target.voxel_mm, 5.0 * target.voxel_mm
        # many hypotheses: a cheap pre-score on a fifth of the points, the best PRESCORED then on all
        score = np.full(len(T), np.inf)
        top = (np.argsort(_score_poses(T, ev[: len(ev) // 5], target, ml, cap))[:PRESCORED]
               if len(T) > PRESCORED else np.arange(len(T)))
        score[top] = _score_poses(T[top], ev, target, ml, cap, workers=workers)
    return _distinct(T, np.argsort(score), settings.verify, 10.0, 0.1 * target.diagonal_mm)


def _ndt_grid(points: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Paper 001 Eq. 23-24: per voxel of side `cell` holding at least 5 model points, the
    mean and the (regularised) inverse covariance; (lo, dims, codes (sorted), mu, icov)."""
    key = np.floor(points / cell).astype(np.int64)
    lo = key.min(axis=0)
    dims = key.max(axis=0) - lo + 1
    code = ((key[:, 0] - lo[0]) * dims[1] + (key[:, 1] - lo[1])) * dims[2] + (key[:, 2] - lo[2])
    uniq, inv, counts = np.unique(code, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    mu = np.stack([np.bincount(inv, weights=points[:, k]) for k in range(3)], 1) / counts[:, None]
    d = points - mu[inv]
    cov = np.zeros((len(uniq), 3, 3))
    np.add.at(cov, inv, np.einsum("ni,nj->nij", d, d))
    cov /= np.maximum(counts - 1, 1)[:, None, None]
    w, v = np.linalg.eigh(cov)
    w = np.maximum(w, 1e-2 * w[:, 2:3] + (0.05 * cell) ** 2)  # keep flat cells invertible
    icov = np.einsum("kij,kj,klj->kil", v, 1.0 / w, v)
    good = counts >= 5
    return lo, dims, uniq[good], mu[good], icov[good]


def _ndt_cells(q: np.ndarray, grid: tuple, cell: float) -> np.ndarray:
    """Index into the grid's cells of each point's voxel, -1 where it has none."""
    lo, dims, codes, _, _ = grid
    if not len(codes):   # no cell holds enough points
        return np.full(len(q), -1)
    key = np.floor(q / cell).astype(np.int64) - lo
    inside = np.all((key >= 0) & (key < dims), axis=1)
    code = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    pos = np.clip(np.searchsorted(codes, code), 0, len(codes) - 1)
    return np.where(inside & (codes[pos] == code), pos, -1)


def _ndt_refine(src: np.ndarray, T: np.ndarray, grid: tuple, cell: float, iterations: int) -> tuple[np.ndarray, float]:
    """Newton-like ascent of the NDT score (Eq. 25-26) from pose T; (pose, score)."""
    mu, icov = grid[3], grid[4]
    score = 0.0
    for _ in range(iterations):
        q = transform_points(T, src)
        cid = _ndt_cells(q, grid, cell)
        ok = cid >= 0
        if ok.sum() < 10:
            return T, 0.0
        x = q[ok] - mu[cid[ok]]
        A = icov[cid[ok]]
        Ax = np.einsum("nij,nj->ni", A, x)
        e = np.exp(-0.5 * np.einsum("ni,ni->n", x, Ax))
        score = float(e.sum())
        # gradient of sum e wrt (omega, t) with q' = q + omega x q + t
        J = np.zeros((len(x), 3, 6))
        qq = q[ok]
        J[:, :, :3] = np.stack([np.cross(np.eye(3)[k], qq) for k in range(3)], axis=2)
        J[:, :, 3:] = np.eye(3)
        g = -np.einsum("n,ni,nij->j", e, Ax, J)
        H = np.einsum("n,nki,nkl,nlj->ij", e, J, A, J) + 1e-6 * np.eye(6)
        step = np.linalg.solve(H, g)
        dT = np.eye(4)
        dT[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
        dT[:3, 3] = step[3:]
        T = dT @ T
        if np.linalg.norm(step) < 1e-6:
            break
    return T, score


def coarse_ndt_poses(src_pts: np.ndarray, target: ModelTarget, settings: RegistrationSettings,
                     rng: np.random.Generator) -> list[np.ndarray]:
    """Distinct coarse poses from NDT started at the 24 axis-aligned rotations of the
    scan about its centroid, placed on the model's centroid (coarse-to-fine cells)."""
    src = src_pts[rng.choice(len(src_pts), size=min(1500, len(src_pts)), replace=False)]
    starts = []
    for R in Rotation.create_group("O").as_matrix():
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = target.coarse.points.mean(axis=0) - R @ src.mean(axis=0)
        starts.append(T)
    cells = [8.0 * target.voxel_mm, 4.0 * target.voxel_mm, 2.0 * target.voxel_mm]
    grids = [_ndt_grid(target.coarse.points, c) for c in cells]
    poses, scores = [], []
    for T in starts:
        for c, g in zip(cells, grids):
            T, s = _ndt_refine(src, T, g, c, 15)
        poses.append(T)
        scores.append(s)
    P = np.array(poses)
    return _distinct(P, np.argsort(-np.array(scores)), settings.verify, 10.0, 0.1 * target.diagonal_mm)


# ----------------------------------------------------------------------------- fine pose


def icp(src: np.ndarray, src_nrm: np.ndarray, target: Samples, T: np.ndarray, max_dist: float,
        min_dist: float, max_normal_deg: float, iterations: int = 30, tangential: float = TANGENTIAL_WEIGHT) -> np.ndarray:
    """Point-to-plane ICP with normal-angle rejection: pairs farther than a threshold
    (shrinking from max_dist toward min_dist, or 3 robust sigma of the residuals) or whose
    normals differ by more than max_normal_deg are rejected. A tangential term (weight
    `tangential`) keeps points from sliding off a face's edge, which the plane metric
    alone does not see; a large one widens the basin of convergence along large planes."""
    cos_max = np.cos(np.radians(max_normal_deg))
    thr = max_dist
    for _ in range(iterations):
        q = transform_points(T, src)
        n = src_nrm @ T[:3, :3].T
        d, j = target.tree.query(q, distance_upper_bound=thr, workers=-1 if len(q) > 20000 else 1)
        ok = np.isfinite(d)
        j = np.where(ok, j, 0)
        tn = target.normals[j]
        ok &= np.einsum("ij,ij->i", n, tn) > cos_max
        if ok.sum() < 6:
            break
        step, r = _point_to_plane_step(q[ok], target.points[j[ok]], tn[ok], tangential)
        T = _apply(step) @ T
        sigma = 1.4826 * np.median(np.abs(r))
        thr = float(np.clip(max(3.0 * sigma, 0.5 * thr), min_dist, max_dist))
        if np.linalg.norm(step) < 1e-8:
            break
    return T


def _point_to_plane_step(p: np.ndarray, q: np.ndarray, n: np.ndarray, tangential: float = 0.0,
                         damping: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """The small motion x = (omega, t) minimising sum e'We, e = p + omega x p + t - q,
    W = (1 - l^2) n n' + l^2 I: point-to-plane plus a weak (l = `tangential`) point-to-point
    term, Levenberg damping `damping` x the largest curvature. Normal equations from sums
    over the points (O(n)); returns (x, normal residuals)."""
    e = p - q
    r = np.einsum("ij,ij->i", e, n)
    a = np.concatenate([np.cross(p, n), n], axis=1)  # d(e.n)/dx
    H = (1.0 - tangential ** 2) * (a.T @ a)
    g = (1.0 - tangential ** 2) * (a.T @ r)
    if tangential > 0:  # point-to-point: J = [-[p]x, I], J'J and J'e from sums
        sp, m = p.sum(axis=0), len(p)
        px = np.array([[0, -sp[2], sp[1]], [sp[2], 0, -sp[0]], [-sp[1], sp[0], 0]])
        block = np.zeros((6, 6))
        block[:3, :3] = np.einsum("ni,ni->", p, p) * np.eye(3) - p.T @ p
        block[:3, 3:] = px
        block[3:, :3] = px.T
        block[3:, 3:] = m * np.eye(3)
        H += tangential ** 2 * block
        g += tangential ** 2 * np.concatenate([np.cross(p, e).sum(axis=0), e.sum(axis=0)])
    return np.linalg.solve(H + damping * np.abs(np.diag(H)).max() * np.eye(6), -g), r


def _apply(step: np.ndarray) -> np.ndarray:
    dT = np.eye(4)
    dT[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
    dT[:3, 3] = step[3:]
    return dT


def refine_exact(src: np.ndarray, src_nrm: np.ndarray, T: np.ndarray, target: ModelTarget, tol: float,
                 max_normal_deg: float, iterations: int = 6, offset_limit_mm: float | None = None) -> np.ndarray:
    """Gauss-Newton on the distances to the exact CAD faces: the points are assigned to
    faces once (`segmentation.assign_faces`: distance, normal, inside the face), then each
    step projects them onto their face's surface; residuals beyond 3 robust sigma are left
    out, and a little damping keeps directions the data do not constrain where they are.
    Then, once converged, faces whose points sit off their surface as a group (median
    residual beyond `FACE_BIAS_SIGMA` times the spread of the faces' medians) are left out
    and the steps repeated: a face that is off as a whole (a pocket floor measured through
    mixed pixels, or truly out of position on the part) must not pull the others. Last, a
    large face off as a whole, by less than `offset_limit_mm`, is found by leaving faces
    out in turn (`_without_offset_face`)."""
    assert target.model is not None and target.samples is not None
    seg = assign_faces(transform_points(T, src), src_nrm @ T[:3, :3].T, target.model, target.samples,
                       target.dense.tree, tol, max_normal_deg)
    src, face = src[seg.assigned], seg.face[seg.assigned]
    if len(src) < 6:
        return T
    T = _gauss_newton(src, face, T, target.model, iterations)
    _, _, _, r, _ = project_to_faces(target.model, transform_points(T, src), face)
    labels, inv, count = np.unique(face, return_inverse=True, return_counts=True)
    med = np.array([np.median(r[inv == k]) for k in range(len(labels))])  # one per face seen
    spread = _robust_sigma(med)
    off = np.abs(med - np.median(med)) > FACE_BIAS_SIGMA * max(spread, 1e-4)
    if off.any() and count[~off].sum() >= 0.5 * len(src):
        src, face = src[~off[inv]], face[~off[inv]]
        T = _gauss_newton(src, face, T, target.model, iterations)
    if offset_limit_mm is None:
        return T
    return _without_offset_face(src, face, T, target.model, iterations, offset_limit_mm)


def _gauss_newton(src: np.ndarray, face: np.ndarray, T: np.ndarray, model: CadModel, iterations: int) -> np.ndarray:
    """Gauss-Newton steps of `refine_exact` on points with their faces: residuals beyond
    3 robust sigma left out, a little damping."""
    for _ in range(iterations):
        q = transform_points(T, src)
        _, foot, normal, r, _ = project_to_faces(model, q, face)
        sigma = 1.4826 * np.median(np.abs(r))
        ok = np.abs(r) < max(3.0 * sigma, 1e-4)
        step, _ = _point_to_plane_step(q[ok], foot[ok], normal[ok], damping=1e-6)
        T = _apply(step) @ T
        if np.linalg.norm(step) < 1e-9:
            break
    return T


def _robust_sigma(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def _without_offset_face(src: np.ndarray, face: np.ndarray, T: np.ndarray, model: CadModel,
                         iterations: int, limit_mm: float) -> np.ndarray:
    """A large face off its nominal place as a whole (a raised step, a bowed top) pulls the
    best fit of all faces into a compromise (tilted, shifted) that then shows as
    deviations on faces that conform. When the residuals spread more than the noise (their
    robust sigma over `OFFSET_NOISE_RATIO` times that of differences between neighbouring
    points, which the smooth form cancels), each face holding `BIG_FACE_FRACTION` of the
    points is left out in turn and the others refined: a fit that brings the others'
    spread down by a fifth and leaves that face off them as a group (median beyond 3 of
    their sigma, and within `limit_mm`: the fine step's inlier distance, so that the face
    still counts in the fitness) is kept, the best such. The majority of the surface
    decides, as a datum would; a part whose faces conform never gets here. A face off by
    more keeps the compromise: the part then reads off on several faces (a profile
    failure) rather than failing registration."""
    from scipy.spatial import cKDTree

    _, _, _, r, _ = project_to_faces(model, transform_points(T, src), face)
    _, nb = cKDTree(src).query(src, k=2)
    noise = _robust_sigma(r - r[nb[:, 1]]) / np.sqrt(2.0)
    if _robust_sigma(r) <= OFFSET_NOISE_RATIO * noise:
        return T
    _, inv, count = np.unique(face, return_inverse=True, return_counts=True)
    best, best_sigma = T, np.inf
    for k in np.flatnonzero(count >= BIG_FACE_FRACTION * len(face)):
        rest = inv != k
        U = _gauss_newton(src[rest], face[rest], T, model, iterations)
        _, _, _, ru, _ = project_to_faces(model, transform_points(U, src), face)
        sigma = _robust_sigma(ru[rest])
        offset = abs(np.median(ru[~rest]) - np.median(ru[rest]))
        if sigma < min(0.8 * _robust_sigma(r[rest]), best_sigma) and 3.0 * sigma < offset < limit_mm:
            best, best_sigma = U, sigma
    return best


def explore(src: np.ndarray, src_nrm: np.ndarray, target: Samples, T: np.ndarray, inlier_mm: float,
            max_normal_deg: float, degrees: tuple[float, ...], icp_mm: float, rounds: int = 4) -> np.ndarray:
    """Local search of the fitness about a refined pose: the scan turned by `degrees`
    either way about each of its principal axes (through its centroid), and shifted along
    them by as many inlier distances; a move that fits more of the scan is refined by ICP
    (from `icp_mm`) and kept. It finds what ICP cannot: along large planes (a part seen
    from above) a turn or a shift moves only a few edge points, which ICP rejects as
    outliers, while the fitness counts them."""
    c = src.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((src - c).T))
    moves = []
    for a in axes.T:
        for deg in degrees:
            for sgn in (-1.0, 1.0):
                F = np.eye(4)
                F[:3, :3] = Rotation.from_rotvec(sgn * np.radians(deg) * a).as_matrix()
                F[:3, 3] = c - F[:3, :3] @ c
                moves.append(F)
                F = np.eye(4)
                F[:3, 3] = sgn * deg * inlier_mm * a
                moves.append(F)
    M = np.array(moves)
    best = fitness(src, src_nrm, target, T[None], inlier_mm, max_normal_deg)[0]
    pre = slice(None, None, EXPLORE_PRESCORE_STRIDE)
    for _ in range(rounds):
        cand = np.einsum("ij,mjk->mik", T, M)
        # pre-score every move on a subsample, then the most promising on all points
        top = np.argsort(-fitness(src[pre], src_nrm[pre], target, cand, inlier_mm, max_normal_deg))[:EXPLORE_TOP]
        fits = fitness(src, src_nrm, target, cand[top], inlier_mm, max_normal_deg)
        k, fit_k = int(top[np.argmax(fits)]), float(fits.max())
        if fit_k <= best + 0.002:
            break
        U = icp(src, src_nrm, target, cand[k], icp_mm, 0.5 * inlier_mm, max_normal_deg, 20)
        fit = fitness(src, src_nrm, target, U[None], inlier_mm, max_normal_deg)[0]
        T, best = (U, fit) if fit > fit_k else (cand[k], fit_k)
    return T


def fitness(src: np.ndarray, src_nrm: np.ndarray, target: Samples, T: np.ndarray, inlier_mm: float,
            max_normal_deg: float, workers: int = -1) -> np.ndarray:
    """Fitness (H,) of each pose (H, 4, 4): the fraction of points within inlier_mm of the
    target whose normals agree within max_normal_deg (one batched KD-tree query with
    `workers` threads, -1 all)."""
    q = np.einsum("hij,nj->hni", T[:, :3, :3], src) + T[:, None, :3, 3]
    n = np.einsum("hij,nj->hni", T[:, :3, :3], src_nrm)
    d, j = target.tree.query(q.reshape(-1, 3), distance_upper_bound=inlier_mm, workers=workers)
    ok = np.isfinite(d)
    j = np.where(ok, j, 0)
    ok &= np.einsum("ij,ij->i", n.reshape(-1, 3), target.normals[j]) > np.cos(np.radians(max_normal_deg))
    return ok.reshape(len(T), -1).mean(axis=1)


def evaluate_pose(src: np.ndarray, src_nrm: np.ndarray, target: Samples, T: np.ndarray, inlier_mm: float,
                  max_normal_deg: float) -> tuple[float, float]:
    """(fitness, RMSE mm): fraction of points within inlier_mm of the model with normals
    agreeing, and the RMS distance of those."""
    q = transform_points(T, src)
    d, j = target.tree.query(q, distance_upper_bound=inlier_mm, workers=-1 if len(q) > 20000 else 1)
    ok = np.isfinite(d)
    j = np.where(ok, j, 0)
    ok &= np.einsum("ij,ij->i", src_nrm @ T[:3, :3].T, target.normals[j]) > np.cos(np.radians(max_normal_deg))
    # distance to the tangent plane of the nearest sample: free of the sampling spacing
    dp = np.abs(np.einsum("ij,ij->i", q - target.points[j], target.normals[j]))
    return float(ok.mean()), float(np.sqrt(np.mean(dp[ok] ** 2))) if ok.any() else float("nan")


# --------------------------------------------------------------------------------- driver


def register(scan: ScanCloud, target: ModelTarget, settings: RegistrationSettings = RegistrationSettings()) -> Registration:
    """The pose taking `scan` onto `target` (see the module docstring). Raises
    RegistrationFailed when no pose explains the scan."""
    rng = np.random.default_rng(settings.seed)
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    v = target.voxel_mm
    src_pts, src_nrm = voxel_grid(scan.points, scan.normals, v)
    if len(src_pts) < 50:
        raise RegistrationFailed(f"{scan.source}: only {len(src_pts)} voxels of {v:.3g} mm hold scan points; "
                                 f"the scan is too small for this model")
    times["prepare"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if settings.coarse == "ndt":
        poses = coarse_ndt_poses(src_pts, target, settings, rng)
    else:
        poses = coarse_feature_poses(src_pts, src_nrm, target, settings, rng)
    if not poses:
        raise RegistrationFailed(f"{scan.source}: no consistent correspondences between the scan and {target.name}")
    poses = with_flips(poses, src_pts) + plane_poses(src_pts, src_nrm, target)
    times["coarse"] = time.perf_counter() - t0  # the dominant-plane poses included
    t0 = time.perf_counter()
    inlier = 1.5 * v
    sub = rng.choice(len(src_pts), size=min(1500, len(src_pts)), replace=False)
    sp, sn = src_pts[sub], src_nrm[sub]
    # ICP on every third point first (most of the way in), then on all of them
    refined = [icp(sp, sn, target.coarse, icp(sp[::3], sn[::3], target.coarse, T, 8.0 * v, 0.5 * v,
                                              settings.max_normal_deg, 20), 8.0 * v, 0.5 * v,
                   settings.max_normal_deg, 10) for T in poses]
    fits = fitness(sp, sn, target.coarse, np.array(refined), inlier, settings.max_normal_deg)
    order = np.argsort(-fits)
    for k in order[:EXPLORED]:  # the most promising few: explored further
        refined[k] = explore(sp, sn, target.coarse, refined[k], inlier, settings.max_normal_deg, COARSE_TURNS_DEG, 4.0 * v)
    judged = []
    for T in refined:  # a handful of distinct hypotheses
        fit, rmse = evaluate_pose(sp, sn, target.dense, T, inlier, settings.max_normal_deg)
        hidden = target.hidden_fraction(T, sp, scan.viewpoint, 2.0 * v) if scan.viewpoint is not None else 0.0
        judged.append((fit - hidden, fit, rmse, hidden, T))
    judged.sort(key=lambda j: -j[0])
    best = judged[0]
    times["verify"] = time.perf_counter() - t0
    if best[1] < settings.min_fitness - 0.1:  # the coarse fit counts at a looser distance
        raise RegistrationFailed(f"{scan.source}: the best pose fits only {best[1]:.0%} of the scan within "
                                 f"{inlier:.3g} mm of {target.name} (needs {settings.min_fitness - 0.1:.0%}); wrong part, "
                                 f"too little of it in view, or other units", best[1], best[2])
    centre = src_pts.mean(axis=0)

    def apart(T: np.ndarray) -> bool:  # another pose, not the same one found twice
        angle, shift = pose_difference(T, best[4], centre)
        return angle > 10.0 or shift > 0.1 * target.diagonal_mm

    alternatives = tuple(j[4] for j in judged[1:] if j[0] >= best[0] - settings.ambiguity_margin and apart(j[4]))
    t0 = time.perf_counter()
    dense = rng.choice(len(scan), size=min(3000, len(scan)), replace=False)
    T = explore(scan.points[dense], scan.normals[dense], target.dense, best[4], 0.3 * v, settings.max_normal_deg,
                FINE_TURNS_DEG, 1.0 * v)
    T = _fine(scan, target, T, settings, rng)
    times["fine"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dense = rng.choice(len(scan), size=min(settings.max_points, len(scan)), replace=False)
    fine_inlier = 0.5 * v
    fit, rmse = evaluate_pose(scan.points[dense], scan.normals[dense], target.dense, T, fine_inlier,
                              settings.max_normal_deg)
    hidden = (target.hidden_fraction(T, scan.points[dense], scan.viewpoint, 2.0 * v)
              if scan.viewpoint is not None else 0.0)
    if fit < settings.min_fitness:
        raise RegistrationFailed(f"{scan.source}: after the fine step only {fit:.0%} of the scan lies within "
                                 f"{fine_inlier:.3g} mm of {target.name} (needs {settings.min_fitness:.0%}): wrong "
                                 f"part, or a part far from its model", fit, rmse)
    times["evaluate"] = time.perf_counter() - t0
    times["total"] = sum(times.values())
    method = f"rscs+{'+'.join(settings.descriptors)}+{settings.coarse}+icp" if settings.coarse != "ndt" else "ndt+icp"
    return Registration(T, fit, rmse, fine_inlier, best[4], method, bool(alternatives), alternatives, hidden,
                        {k: round(x, 4) for k, x in times.items()})


def normal_space_sample(normals: np.ndarray, n: int, rng: np.random.Generator, bins: int = 12) -> np.ndarray:
    """Indices of up to n points drawn without replacement so that their normals spread
    as evenly as the cloud allows over a (bins x 2 bins) grid of directions: the few
    points on walls and in holes, which fix the pose along a large plane, are kept."""
    if len(normals) <= n:
        return np.arange(len(normals))
    theta = np.arccos(np.clip(normals[:, 2], -1.0, 1.0))
    phi = np.arctan2(normals[:, 1], normals[:, 0])
    cell = (np.minimum((theta / np.pi * bins).astype(np.int64), bins - 1) * 2 * bins
            + np.minimum(((phi + np.pi) / (2 * np.pi) * 2 * bins).astype(np.int64), 2 * bins - 1))
    count = np.bincount(cell, minlength=2 * bins * bins)
    key = rng.exponential(size=len(normals)) * count[cell]  # weighted sampling, weight 1/count
    return np.argpartition(key, n - 1)[:n]


def _fine(scan: ScanCloud, target: ModelTarget, T: np.ndarray, settings: RegistrationSettings,
          rng: np.random.Generator) -> np.ndarray:
    """Point-to-plane ICP on the dense scan (points seen at grazing incidence left out,
    the rest drawn by normal-space sampling): a quarter of the points first, then all;
    then, for a STEP model, Gauss-Newton on the exact distances to its faces."""
    v = target.voxel_mm
    p, n = scan.points, scan.normals
    if scan.viewpoint is not None:  # grazing views of a surface measure it worst: leave them out
        ray = scan.viewpoint - p
        grazing = np.einsum("ij,ij->i", ray, n) < np.cos(np.radians(MAX_INCIDENCE_DEG)) * np.linalg.norm(ray, axis=1)
        if (~grazing).sum() > 100:
            p, n = p[~grazing], n[~grazing]
    sel = normal_space_sample(n, settings.max_points, rng)
    first = sel[: max(len(sel) // 4, 1)]
    T = icp(p[first], n[first], target.dense, T, 1.5 * v, 0.1 * v, settings.max_normal_deg, 15)
    T = icp(p[sel], n[sel], target.dense, T, 0.5 * v, 0.05 * v, settings.max_normal_deg, 10)
    if target.model is not None and target.model.kind == "step":
        sel = rng.choice(len(scan), size=min(EXACT_POINTS, len(scan)), replace=False)  # any point will do
        T = refine_exact(scan.points[sel], scan.normals[sel], T, target, 0.3 * v, settings.max_normal_deg,
                         offset_limit_mm=0.5 * v)
    return T
