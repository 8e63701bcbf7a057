"""What a registration's own evidence proves (issue 26): the pose's covariance from its final
fit, the motions the fit leaves free, and whether another pose the search found explains the
scan as well as the best.

**Covariance.** The final fit minimises the Huber loss of the distances r_i from the scan
points to their faces over a small motion x = (omega, t) about the fit points' centroid c (model
frame): J_i = [((q_i - c) x n_i)', n_i']. Its covariance is the M-estimator's sandwich
Cov = A^-1 B A^-1, A = sum_i psi'(r_i) J_i J_i', B = sum_ij E[psi(r_i) psi(r_j)] J_i J_j', psi the
Huber influence (threshold 1.345 robust sigma, the textbook 95 %-efficiency constant).
Neighbouring pixels are not independent: besides the blur of camera and projector, the
fringe error of the projector's quantised patterns is shared over tens of pixels (on the
simulated bench the variance of a block's mean residual is 1.4 times the independent one
over 8 x 8 pixels, 2.8 over 32 x 32, 4.9 over 64 x 64). So B is estimated from the residual
field itself by block sums: the image (a bare cloud: space, in units of its point spacing)
cut into squares of side 4, 8, ... 128, B = g/(g - 1) sum_b s_b s_b', s_b = sum over block b
of psi_i J_i, at each side that leaves at least `MIN_BLOCKS` blocks, and the side giving the
largest covariance kept (the correlation's reach is not known in advance; fewer blocks
estimate B too poorly). A face's measurement may also be off as a whole (a narrow wall
seen near a depth step is all mixed pixels: on the simulated bench a 12 mm step wall of
the demo part read 34 um inside the material, and, the wall being what fixed the part's
turn, turned it 0.025 deg): with the CAD faces given, the residuals are split into each
face's mean and the noise about it; the blocks above estimate the noise's part, and the
faces' offsets are random effects, independent across faces: the blur's, which each point
reads in proportion to its share of light from beyond its surface's outline, and the face's
own, read whole (`_face_offsets`), their two variances estimated from the faces' mean
residuals (each shrunk by the share of its offset the fit absorbs, less its noise's part),
added as A^-1 (sum_fc theta_c m_fc m_fc') A^-1, m_fc the sum of the face's J_i, each times
how much of offset c the point reads.
Both parts are estimated from what one scan shows: the noise's along each of its principal
motions from the blocks that carry it (as few as one: seven points of a grazing strip that
alone fix a turn), the offsets' variances from a handful of faces. Each is taken with its
confidence distribution (`variance_law`): its Student-t equivalent shapes the covariance,
and the covariance is sized so that its 95 % ellipsoid holds the error as often as stated
when the variances are drawn from those distributions (the predictive region; for one
variance on nu degrees of freedom exactly the t, Hotelling's F in k dimensions). (A cluster
sandwich over the faces instead, the few clusters each scaled up for what the fit absorbs,
was noisy and short of rank: on repeat scans of the demo part and a random part through
`slscan register` its covariance was up to 99 times the independent one, refusing right
poses as free, yet flat in some direction, the error's Mahalanobis distance within the 95 %
ellipsoid on 2 of 18 scans.) The faces' mean residuals
come also from faces the pose claims that the fit never saw (a sample of the outline bands
and grazing points on faces with no fit point) and from the faces the fit left out as off
that lie mostly in outline bands, entering tau^2 with nothing of theirs absorbed by the fit
(h_f = 0); not from a face left out as off that is measured mostly away from any outline,
whose offset is the part's own (`fine.with_the_rest`: the scanner's face-level error is the
camera's blur mixing a surface with what lies beyond its outline; the demo part with one
top face lifted 0.1 mm would otherwise be refused as free). A pose trapped a few tenths of
a degree off by the points it rests on shows there (random part seed 407191291: 0.26 deg
off, the walls that fix its turn 37-118 um off as a whole, left out of the fit; its U
became 0.43 deg, the turn free, exit 1, where the fit's own points had said 0.03 deg; a
random part of campaign seed 734203079 whose one x-facing wall in the fit, 33 points, read
58 um off: 0.081 mm off along x, refused as free only with its left-out walls counted). Correlation
reaching further than the blocks (a calibration error, which the simulator has none of)
is not in it.

**Free motions.** A motion (an eigenvector of Cov) whose expanded uncertainty (k = 2) exceeds
the pose tolerance the registration must prove (`RegistrationSettings.pose_tolerance_deg` and
`pose_tolerance_mm`, at the scan's RMS radius) is free; so is the leading one when the 95 %
bounds of the pose's rotation angle or of its centre's displacement (`PoseCovariance.bounds`,
the terms the tolerance is stated in) exceed the tolerance, though no single motion's does. A
free motion that also leaves the whole CAD model in place (its surface moves by less than 1e-3
of the motion, a numerical zero: a ring turned about its axis) is a symmetry of the part: the
pose is reported with it named. Any other free motion means the view does not fix the pose.

**Alternatives.** Each other pose the search found, refined, is compared with the best on the
same scan points by which points each explains (within the inlier distance of the model,
normals agreeing, not hidden behind the posed model from the sensor). Points explained by
one pose and not the other are the evidence: if the two explained the scan equally well,
each such discordant point would favour either with probability 1/2 (McNemar's test). The
count favouring the best is compared with that binomial, the counts divided by the variance
inflation the residual field's correlation gives these points (so dependent points are not
counted as independent evidence). The best is proven over an alternative when the one-sided
p-value is below `RegistrationSettings.false_accept / K` (K alternatives, Bonferroni), so the
probability of accepting a pose when an alternative explains the scan at least as well is at
most `false_accept` (1e-3) per registration. The false-refusal rate is not bounded by the test
(it depends on how much of the part that tells the poses apart is in view): it is measured on
random parts (`sim.random_parts`, README). An alternative within the pose tolerance of the
best is the same pose; one that differs from it only by a symmetry of the part is the same
pose with the free motion. The search's poses are not the only alternatives: the final pose
is also moved along its covariance's principal motions while this test prefers the moved
pose (`alternatives.climb`), and where that ends beyond the pose tolerance it is one more
alternative (a fit left on a motion its faces do not fix, which only the outlines fix).
An unrejected alternative inside the pose's own error ellipsoid at `U_LEVEL` (`covers`) is
not another pose: the stated U already covers it, and it is kept as a free motion of its
size (`driver.judge`), so the pose is "free", not "ambiguous".
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import betainc

from inspection.registration.band_effects import BandEffects
from inspection.registration.rigid import transform_points
from inspection.registration.variance_law import VarianceLaw, law, predictive, sandwich_dof

HUBER_K = 1.345  # Huber's threshold in robust sigmas: 95 % efficiency at normal noise (Huber 1964)
BLOCKS = (4.0, 8.0, 16.0, 32.0, 64.0, 128.0)  # block sides tried for the residuals' correlation (lag units)
MIN_BLOCKS = 30  # fewer blocks than this estimate their covariance too poorly to use
SYMMETRY_ZERO = 1e-3  # a motion moving the whole model's surface by less than this share of itself: a symmetry
U_DRAWS = 20000  # draws from the covariance for the 95 % bounds of the rotation angle and the displacement
U_LEVEL = 0.95  # the coverage probability of every pose U stated (k = 2)
MAX_SHARE = 0.5  # the most of a pixel's light the blur can bring from beyond an outline (`fine.mixing`)


def jacobian(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(N, 6) derivatives of the signed distances of model-frame points with their surface
    normals under a small motion (omega rad, t mm) about `centre`."""
    return np.concatenate([np.cross(points - centre, normals), normals], axis=1)


def robust_sigma(r: np.ndarray) -> float:
    """1.4826 x the median absolute deviation: the standard deviation of normal noise."""
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def residual_scale(r: np.ndarray) -> float:
    """1.4826 x the median |r|: the standard deviation of zero-mean normal residuals."""
    return float(1.4826 * np.median(np.abs(r)))


def huber_weights(r: np.ndarray, sigma: float) -> np.ndarray:
    """IRLS weights of the Huber loss at threshold HUBER_K sigma."""
    k = HUBER_K * max(sigma, 1e-12)
    return np.minimum(1.0, k / np.maximum(np.abs(r), 1e-300))


@dataclass(frozen=True)
class ResidualCorrelation:
    """How the fit's residuals are correlated over the image: `block` the side (lag units,
    `unit`) of the square blocks over which the covariance was estimated, `pair` the mean
    correlation of two residuals in one block (0: independent)."""

    block: float
    pair: float
    unit: str

    def inflation(self, where: np.ndarray) -> float:
        """Variance inflation of a sum of unit-variance terms at positions `where`: 1 + the
        number of pairs sharing a block, both ways, times `pair`, over N."""
        if len(where) == 0 or self.pair <= 0:
            return 1.0
        m = np.bincount(_blocks(where, self.block)).astype(np.float64)
        return float(1.0 + self.pair * np.sum(m * (m - 1.0)) / len(where))


def _blocks(where: np.ndarray, size: float) -> np.ndarray:
    """Block index of each position on a grid of squares (cubes) of side `size`."""
    return _dense_labels(np.floor(where / size).astype(np.int64))


def _dense_labels(keys: np.ndarray) -> np.ndarray:
    """The rank of each row of integer `keys` (N, d) among the distinct rows, in
    lexicographic order: `np.unique(keys, axis=0, return_inverse=True)[1]`, without its
    sort where the keys span a grid of at most 4 N cells (as blocks of a scan do)."""
    if len(keys) == 0:
        return np.zeros(0, np.int64)
    lo = keys.min(axis=0)
    span = keys.max(axis=0) - lo + 1
    if float(np.prod(span.astype(np.float64))) > max(4.0 * len(keys), 65536.0):
        return np.unique(keys, axis=0, return_inverse=True)[1].ravel()
    cell = np.ravel_multi_index(tuple((keys - lo).T), tuple(int(x) for x in span))
    present = np.zeros(int(np.prod(span)), bool)
    present[cell] = True
    return (np.cumsum(present) - 1)[cell]


def _label_sums(values: np.ndarray, label: np.ndarray, count: int | None = None) -> np.ndarray:
    """Each label's sums of the rows of `values` (N, k): (labels, k), at least `count` rows."""
    return np.stack([np.bincount(label, weights=values[:, c], minlength=count or 0)
                     for c in range(values.shape[1])], axis=1)


@dataclass(frozen=True)
class FreeMotion:
    """A motion the fit does not fix: `kind` "rotation" (about `axis` through `point`) or
    "translation" (along `axis`), model frame; `u` its expanded uncertainty (k = 2, degrees
    or mm); `symmetry` whether it leaves the whole CAD model in place; `turn_u` the U (deg)
    of the turn a translation comes with (a screw: what may make it free); `blurred` an
    unbounded motion only blurred pixels (creases, outlines) inform, which the fit does not
    step along."""

    kind: str
    axis: tuple[float, float, float]
    point: tuple[float, float, float] | None
    u: float
    symmetry: bool
    turn_u: float = 0.0
    note: str = ""
    blurred: bool = False

    def describe(self) -> str:
        a = ", ".join(f"{x:.3f}" for x in self.axis)
        unit = "deg" if self.kind == "rotation" else "mm"
        u = (f"U {self.u:.3g} {unit}" if np.isfinite(self.u) else
             "fixed only by blurred pixels, not measured" if self.blurred else "not determined at all")
        if self.kind == "rotation":
            p = ", ".join(f"{x:.2f}" for x in self.point or (0.0, 0.0, 0.0))
            what = f"rotation about the axis ({a}) through ({p}) mm ({u})"
        else:
            turn = f", turning {self.turn_u:.3g} deg" if np.isfinite(self.u) and self.turn_u >= 5e-4 else ""
            what = f"translation along ({a}) ({u}{turn})"
        return what + (", a symmetry of the part" if self.symmetry else "") + (f": {self.note}" if self.note else "")

    def as_dict(self) -> dict[str, object]:
        return {"kind": self.kind, "axis": list(self.axis), "point": None if self.point is None else list(self.point),
                "u": self.u if np.isfinite(self.u) else None, "symmetry": self.symmetry,
                "only_blurred_pixels": self.blurred, "description": self.describe()}


@dataclass(frozen=True)
class FaceOffsets:
    """The faces' part of a pose covariance, per CAD face the covariance knows (`faces` (F,),
    CAD ids), for each of a face's two offsets (`_face_offsets`: the blur's, read by each point
    in proportion to its share of light from beyond, and the face's own, read whole):
    `follow` (F, 2, 6) the pose's correction (omega rad, t mm about the centre) per mm of it,
    S A^-1 m_fc; `reads` (F, 2) how much of it the face's points read on average (a_fc);
    `variance` (2,) its variance theta_c (mm^2). The covariance holds
    sum_fc follow_fc follow_fc' theta_c (`kept_variance`)."""

    faces: np.ndarray
    follow: np.ndarray
    reads: np.ndarray
    variance: np.ndarray

    def kept_variance(self, face: int, j: np.ndarray) -> float:
        """The variance (mm^2) of the part of face `face`'s own offsets that the fit did not
        take from it, sum_c (a_fc - j . follow_fc)^2 theta_c (j the face's points' mean
        Jacobian row), which its mean deviation carries beside the pose's error along j; 0 for
        a face the covariance does not know (neither fitted nor told apart)."""
        at = np.flatnonzero(self.faces == face)
        if len(at) == 0:
            return 0.0
        return float(np.sum((self.reads[at[0]] - self.follow[at[0]] @ j) ** 2 * self.variance))


@dataclass(frozen=True)
class PoseCovariance:
    """The pose's covariance (6, 6: a small rotation (rad) about `centre` and a translation
    (mm) of the scan in the model frame) from the final fit (module docstring): `sigma_mm`
    the residuals' robust sigma, `points` the fit's points, `correlation` the residual
    field's, `inflation` how much it widened the trace of the covariance over independent
    points, `radius_mm` the points' RMS distance from the centre, `unbounded` (k, 6) the
    motions the fit has no information on at all (a ring's turn about its axis), whose
    variance `covariance` leaves at 0, and those only blurred pixels inform, which the fit
    does not step along (`fine.fit_covariance`; `covariance` keeps their variance), the
    last `blurred` rows of `unbounded`; `offsets` the faces' part, per face (None without
    the points' faces)."""

    covariance: np.ndarray
    centre: np.ndarray
    sigma_mm: float
    points: int
    correlation: ResidualCorrelation
    inflation: float
    radius_mm: float
    unbounded: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    blurred: int = 0
    offsets: FaceOffsets | None = None

    def bounds(self) -> tuple[float, float]:
        """(rotation angle deg, displacement of the centre mm) that the pose's error stays
        within with 95 % probability (`bounds_of`)."""
        return self.bounds_of(self.covariance)

    @staticmethod
    def bounds_of(covariance: np.ndarray) -> tuple[float, float]:
        """The 95 % bounds of a pose covariance (6, 6) (`bounds`): quantiles of the norms of
        draws from it (the unbounded motions, zero there, left out)."""
        w, v = np.linalg.eigh(covariance)
        draws = np.random.default_rng(0).standard_normal((U_DRAWS, 6)) * np.sqrt(np.maximum(w, 0.0)) @ v.T
        return (float(np.degrees(np.quantile(np.linalg.norm(draws[:, :3], axis=1), U_LEVEL))),
                float(np.quantile(np.linalg.norm(draws[:, 3:], axis=1), U_LEVEL)))

    def as_dict(self) -> dict[str, object]:
        rot, shift = self.bounds()
        return {"rotation_u_deg": rot, "translation_u_mm": shift, "pose_centre_mm": self.centre.tolist(),
                "pose_covariance": self.covariance.tolist(), "residual_sigma_mm": self.sigma_mm,
                "fit_points": self.points, "correlation_block": f"{self.correlation.block:g} {self.correlation.unit}",
                "correlation_inflation": self.inflation}


def pose_covariance(points: np.ndarray, normals: np.ndarray, r: np.ndarray, where: np.ndarray, unit: str,
                    faces: np.ndarray | None = None, *, in_fit: np.ndarray | None = None,
                    mixing: np.ndarray | None = None, offset_bound_mm: float | None = None,
                    band: BandEffects | None = None) -> PoseCovariance:
    """The covariance of the pose fitted to model-frame `points` with their faces' `normals`
    and residuals `r` (mm); `where` the points' image positions (or scan positions) and `unit`
    their lag unit, for the residuals' correlation; `faces` the CAD face of each point, for
    offsets of a face's measurement as a whole (module docstring); `in_fit` the points the
    pose was fitted to (default all; the others' faces only inform the offsets' variance);
    `mixing` each point's share of light from beyond its surface's outline (`fine.mixing`;
    None: not known), which a face's offset grows with (`_face_offsets`); `offset_bound_mm` the
    largest offset a face's points could have and still be assigned to it (None: no bound);
    `band` the blurred points' offsets and trends the fit estimated with the pose
    (`band_effects`; None: a plain fit): the pose's error is then linear in the residuals
    through its rows c_i, not J_i, and each face's trend across its blurred points moves it
    as a random effect of the face's offset variance, as the offset does."""
    in_fit = np.ones(len(points), bool) if in_fit is None else in_fit
    centre = points[in_fit].mean(axis=0)
    radius = float(np.sqrt(np.mean(np.sum((points[in_fit] - centre) ** 2, axis=1))))
    S = np.diag([1.0 / radius] * 3 + [1.0] * 3)  # rotations as mm at the points' radius: a conditioned system
    J_all = jacobian(points, normals, centre) @ S
    J = J_all * in_fit[:, None]
    sigma = residual_scale(r[in_fit])
    k = HUBER_K * max(sigma, 1e-12)
    inside = (np.abs(r) < k) & in_fit
    weight = inside.astype(np.float64)  # psi': the M-estimator's sensitivity per point
    C = J if band is None else band.rows(J, weight, max(sigma, 1e-12))  # the estimator's rows
    A = C[inside].T @ J[inside]
    w, v = np.linalg.eigh(0.5 * (A + A.T))
    info = w > 1e-9 * w.max()  # below: no information at all, a numerical zero
    Ainv = (v[:, info] / w[info]) @ v[:, info].T
    if faces is not None:  # the noise about each face's mean; the face offsets apart (`_face_offsets`)
        ids, face = np.unique(faces, return_inverse=True)
        face = face.ravel()
        n_f = np.bincount(face).astype(np.float64)
        e = r - (np.bincount(face, weights=r) / n_f)[face]
    else:
        e = r
    psi = np.clip(e, -k, k)
    score = C * psi[:, None]
    indep = Ainv @ (score.T @ score) @ Ainv
    cov, corr, chosen, offsets = indep, ResidualCorrelation(0.0, 0.0, unit), np.arange(len(r)), None
    for size in BLOCKS:
        label = _blocks(where, size)
        blocked = _clustered(score, label, Ainv)
        if blocked is None:
            break
        if np.trace(blocked) > np.trace(cov):
            pair = _pair_correlation(psi[in_fit], label[in_fit])
            cov, corr, chosen = blocked, ResidualCorrelation(float(size), pair, unit), label
    parts: tuple[np.ndarray, ...] = ()
    laws: tuple[VarianceLaw, ...] = ()
    if faces is not None:
        load = np.ones((len(r), 2))  # each point's offset per unit of each face's two offsets (`_face_offsets`)
        load[:, 0] = 0.0 if mixing is None else mixing / MAX_SHARE
        laws, m, kept = _face_offsets(r, e, face, block=chosen, J=J_all, C=C, inside=inside, Ainv=Ainv, load=load,
                                      bound=offset_bound_mm)
        follow = np.einsum("ij,cfj->cif", Ainv, m)  # (2, 6, faces): the fit's correction per unit offset
        trend = np.zeros((2, 6, 6))
        if band is not None and mixing is not None:  # the blur's trend across a band, as its offset (`band_effects`)
            trend[0] = Ainv @ band.trends(C, weight, np.ones(len(r))) @ Ainv
        parts = tuple(follow[c] @ follow[c].T + trend[c] for c in (0, 1))  # the covariance per unit of each variance
    lam, axes = np.linalg.eigh(v[:, info].T @ cov @ v[:, info])  # the noise's part, along its own axes
    axes = v[:, info] @ axes
    sums = _label_sums(score, chosen) @ Ainv
    noise = tuple(max(x, 0.0) * np.outer(a, a) for x, a in zip(lam, axes.T, strict=True))
    told = tuple(VarianceLaw.scaled(d) if d > 0.0 else VarianceLaw.point(1.0)  # 0: no noise along it at all
                 for d in sandwich_dof(axes.T, sums))
    scale = predictive(noise + parts, told + laws, basis=v[:, info], level=U_LEVEL)
    cov = sum((t * part for t, part in zip(scale, noise + parts, strict=True)), np.zeros((6, 6)))
    if faces is not None:
        offsets = FaceOffsets(ids, np.einsum("ij,cjf->fci", S, follow), kept, scale[len(noise):])
    unbounded = (S @ v[:, ~info]).T
    unbounded /= np.maximum(np.linalg.norm(unbounded, axis=1, keepdims=True), 1e-300)
    return PoseCovariance(0.5 * (S @ cov @ S + (S @ cov @ S).T), centre, sigma, int(in_fit.sum()), corr,
                          float(np.trace(cov) / max(np.trace(indep), 1e-300)), radius, unbounded, offsets=offsets)


def _face_offsets(r: np.ndarray, e: np.ndarray, face: np.ndarray, *, block: np.ndarray, J: np.ndarray,
                  C: np.ndarray, inside: np.ndarray, Ainv: np.ndarray, load: np.ndarray,
                  bound: float | None) -> tuple[tuple[VarianceLaw, VarianceLaw], np.ndarray, np.ndarray]:
    """(laws, m (2, faces, 6), a (faces, 2)): the faces' offsets as the pose covariance takes
    them (module docstring). Each face f is off by two offsets, independent across faces and of
    each other: beta_f, of variance theta_0, which point i of it reads as `load`_i0 beta_f
    (`load` (N, 2): l_i0 = s_i / `MAX_SHARE`, s_i the point's share of light from beyond its
    surface's outline, `fine.mixing`), and gamma_f, of variance theta_1, read whole
    (l_i1 = 1). The model: the camera's blur mixes a pixel near an outline with what lies
    beyond, so a point's offset grows with its share (a 12 mm step wall of the demo part read
    34 um off as a whole); over 701 faces of 43 scans of random parts at the true pose
    (campaign 1501789337, bench blur 0.6 px, `python -m studies.face_offsets`) the faces' mean
    residuals spread by 180-320 um per unit mean share in each eighth of the shares from 0.001
    to 0.23 (by likelihood 214 um and a floor of 1 um; the faces' z RMS per eighth 0.85-1.19,
    7.1 % beyond 1.96, 1.4 % beyond 3), while the part's own faces, far from any outline, read
    a few um (gamma). The pose moves by -A^-1 sum_g (m_g0 beta_g + m_g1 gamma_g), m_gc the
    sum of face g's estimator rows `C` times l_ic over the points the fit rests on (`inside`;
    `J`'s rows in a plain fit, `band_effects` rows where it estimated the blurred points'
    offsets too, which then take most of beta out), and face f's mean residual by
    rbar_f = sum_c sum_g R_c,fg x_cg + noise, R_c = diag(a_c) - jbar A^-1 m_c' (a_fc the
    face's mean l_ic over all its points, `a`; jbar_f its mean row of `J`: what the fit moves
    into its mean), so E[rbar_f^2] = sum_c theta_c G_fc + v_f, G_fc = sum_g R_c,fg^2, v_f the
    variance of f's mean noise (from the sums over `block`s of the residuals `e` about the
    face's mean). Each theta's confidence distribution (`variance_law.law`, the other at its
    moment estimate; faces' squares weighted by what each tells of it, the Gaussian
    likelihood's score G_fc / s_f^4: a strip of outline pixels 114 um off says nothing of the
    inner faces' few um), at most the largest variance an offset could have: uniform within
    `bound` (mm, the distance within which points are assigned to a face), bound^2 / 3. The
    moment estimates (weighted by a^2, solved non-negative) alone are often 0 with a handful
    of faces whose offsets are not (the demo part's chamfer reads -1.5 um, its bore wall
    +1.1 um in every scan: translation coverage 88 % on 100 scans). Faces with fewer than
    `MIN_BLOCKS` points are no measure of their offset (a few stray points) and are left out
    of the sums, not of the effect; with fewer than two faces to measure by, both variances
    take the bound; with no `bound`, the moment estimates are taken as known."""
    from scipy.optimize import nnls

    g = int(face.max()) + 1
    n = np.bincount(face, minlength=g).astype(np.float64)
    mean = np.bincount(face, weights=r, minlength=g) / np.maximum(n, 1.0)
    cell = _dense_labels(np.stack([face, block], axis=1).astype(np.int64))
    cell_face = np.zeros(int(cell.max()) + 1, np.int64)
    cell_face[cell.ravel()] = face
    v = np.bincount(cell_face, weights=np.bincount(cell.ravel(), weights=e) ** 2, minlength=g) / np.maximum(n, 1.0) ** 2
    m = np.stack([_label_sums(C * (inside * load[:, c])[:, None], face, g) for c in (0, 1)])
    a = _label_sums(load, face, g) / np.maximum(n, 1.0)[:, None]
    jbar = _label_sums(J, face, g) / np.maximum(n, 1.0)[:, None]
    told = n >= MIN_BLOCKS
    G = np.stack([np.sum((np.diag(a[:, c]) - jbar @ Ainv @ m[c].T)[told] ** 2, axis=1) for c in (0, 1)], axis=1)
    L = a[told] ** 2
    coef = L.T @ G
    tau2 = nnls(coef, np.maximum(L.T @ (mean[told] ** 2 - v[told]), 0.0))[0] if coef.any() else np.zeros(2)
    if bound is None:
        return (VarianceLaw.point(tau2[0]), VarianceLaw.point(tau2[1])), m, a
    cap = bound ** 2 / 3.0
    if told.sum() < 2:
        return (VarianceLaw.point(cap), VarianceLaw.point(cap)), m, a
    s2 = np.maximum(G @ tau2 + v[told], 1e-30)  # each face's mean square expected at the moment estimates
    score = G / s2[:, None] ** 2  # how much each face's square tells of each component (likelihood score)
    laws = tuple(law(mean[told] ** 2, G[:, c], G[:, 1 - c] * tau2[1 - c] + v[told], weight=score[:, c], cap=cap)
                 for c in (0, 1))
    return (laws[0], laws[1]), m, a


def _clustered(score: np.ndarray, label: np.ndarray, Ainv: np.ndarray, scale: np.ndarray | None = None,
               min_groups: int = MIN_BLOCKS) -> np.ndarray | None:
    """The cluster sandwich A^-1 (g/(g-1) sum_c s_c s_c') A^-1 of the scores summed per
    `label` (each sum times `scale[c]`), or None with fewer than `min_groups` clusters."""
    g = int(label.max()) + 1
    if g < min_groups:
        return None
    sums = _label_sums(score, label, g)
    if scale is not None:
        sums = sums * scale[:, None]
    return Ainv @ (sums.T @ sums) @ Ainv * g / (g - 1.0)


def _pair_correlation(psi: np.ndarray, label: np.ndarray) -> float:
    """The mean correlation of two influences in one cluster: (sum of the clusters' sums
    squared - sum of squares) / (pairs x variance), at least 0."""
    n = np.bincount(label).astype(np.float64)
    psum = np.bincount(label, weights=psi)
    pair = (np.sum(psum ** 2) - np.sum(psi ** 2)) / max(np.sum(n * (n - 1.0)) * np.mean(psi ** 2), 1e-300)
    return max(float(pair), 0.0)


def free_motions(cov: PoseCovariance, tolerance_deg: float, tolerance_mm: float,
                 model_points: np.ndarray | None = None, model_normals: np.ndarray | None = None) -> list[FreeMotion]:
    """The motions `cov` leaves free (module docstring), each named, the unbounded first;
    with the whole model's dense samples (`model_points`, `model_normals`, model frame) each
    is checked for being a symmetry of the part."""
    rho = max(cov.radius_mm, 1e-9)
    S = np.diag([rho, rho, rho, 1.0, 1.0, 1.0])  # rotations as mm at the scan's radius
    w, v = np.linalg.eigh(S @ cov.covariance @ S)
    motions = [(x, np.inf, np.inf) for x in cov.unbounded]
    first_blurred = len(cov.unbounded) - cov.blurred
    rot_b, shift_b = cov.bounds()
    beyond = rot_b > tolerance_deg or shift_b > tolerance_mm  # the error's 95 % bounds: the tolerance's terms
    for k, (lam, e) in enumerate(zip(w[::-1], v.T[::-1])):
        x = np.linalg.solve(S, e)  # the motion (omega, t)
        sd = float(np.sqrt(max(lam, 0.0)))
        rot_u = float(np.degrees(2.0 * sd * np.linalg.norm(x[:3])))
        shift_u = float(2.0 * sd * np.linalg.norm(x[3:]))
        if rot_u <= tolerance_deg and shift_u <= tolerance_mm and not (beyond and k == 0):
            break  # eigenvalues descend: the rest are fixed
        motions.append((x, rot_u, shift_u))
    out = []
    for k, (x, rot_u, shift_u) in enumerate(motions):
        symmetry = False
        if model_points is not None and model_normals is not None:
            moves = jacobian(model_points, model_normals, cov.centre) @ x
            size = rho * np.linalg.norm(x[:3]) + np.linalg.norm(x[3:])
            symmetry = bool(np.sqrt(np.mean(moves ** 2)) < SYMMETRY_ZERO * size)
        out.append(replace(_named(x, cov.centre, rot_u, shift_u, rho, symmetry),
                           blurred=first_blurred <= k < len(cov.unbounded)))
    return out


def _named(x: np.ndarray, centre: np.ndarray, rot_u: float, shift_u: float, rho: float, symmetry: bool) -> FreeMotion:
    omega, t = x[:3], x[3:]
    if np.linalg.norm(omega) * rho > np.linalg.norm(t):  # mostly a turn: its axis
        a = omega / np.linalg.norm(omega)
        point = centre + np.cross(omega, t) / float(omega @ omega)
        return FreeMotion("rotation", _triple(a), _triple(point), rot_u, symmetry)
    a = t / np.linalg.norm(t)
    return FreeMotion("translation", _triple(a), None, shift_u, symmetry, rot_u)


def _triple(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def disagreement(a: np.ndarray, b: np.ndarray, centre: np.ndarray, radius_mm: float, why: str) -> FreeMotion:
    """The motion taking pose `a` to pose `b` (scan -> model) about `centre` as a free motion
    whose U is its size (deg, mm), `why` the note saying what the two poses rest on."""
    x = twist(a, b, centre)
    return replace(_named(x, centre, float(np.degrees(np.linalg.norm(x[:3]))), float(np.linalg.norm(x[3:])),
                          max(radius_mm, 1e-9), False), note=why)


def moves(m: FreeMotion, points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> float:
    """RMS move (mm) of model-frame `points` along their `normals` when the pose moves along
    the free motion `m` by its U (a unit motion when U is unbounded: the ratio then only
    says whether it moves them at all)."""
    x = np.concatenate([np.asarray(m.axis), np.cross(np.asarray(m.axis), centre - np.asarray(m.point))]
                       if m.kind == "rotation" else [np.zeros(3), np.asarray(m.axis)])
    if m.kind == "rotation" and np.isfinite(m.u):
        x = x * np.radians(m.u)
    elif np.isfinite(m.u):
        x = x * m.u
    return float(np.sqrt(np.mean((jacobian(points, normals, centre) @ x) ** 2))) if len(points) else 0.0


def twist(a: np.ndarray, b: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The motion (rotation vector rad, displacement of `centre` mm) taking pose `a` to `b`
    (both scan -> model), in the model frame."""
    from scipy.spatial.transform import Rotation

    d = b @ np.linalg.inv(a)
    return np.concatenate([Rotation.from_matrix(d[:3, :3]).as_rotvec(),
                           transform_points(d, centre[None])[0] - centre])


def within(a: np.ndarray, b: np.ndarray, centre: np.ndarray, tolerance_deg: float, tolerance_mm: float,
           free: list[FreeMotion] | None = None) -> bool:
    """Whether poses `a` and `b` (scan -> model) are the same within the tolerances at
    `centre` (model frame), once motions along the free symmetries of the part in `free`
    are taken out: the turn about a symmetry axis that the difference makes (its twist
    angle about that axis, however large), the shift along a free translation."""
    from scipy.spatial.transform import Rotation

    d = b @ np.linalg.inv(a)  # model -> model
    for m in (free or []):
        if not m.symmetry:
            continue
        axis = np.asarray(m.axis)
        if m.kind == "translation":
            d[:3, 3] -= (d[:3, 3] @ axis) * axis
            continue
        q = Rotation.from_matrix(d[:3, :3]).as_quat()  # x, y, z, w
        turn = 2.0 * np.arctan2(q[:3] @ axis, q[3])  # the twist about the axis (swing-twist)
        back = np.eye(4)
        back[:3, :3] = Rotation.from_rotvec(-turn * axis).as_matrix()
        back[:3, 3] = np.asarray(m.point) - back[:3, :3] @ np.asarray(m.point)
        d = back @ d
    x = np.concatenate([Rotation.from_matrix(d[:3, :3]).as_rotvec(), transform_points(d, centre[None])[0] - centre])
    return bool(np.degrees(np.linalg.norm(x[:3])) <= tolerance_deg and np.linalg.norm(x[3:]) <= tolerance_mm)


def local_test(final: np.ndarray, other: np.ndarray, cov: PoseCovariance) -> float:
    """p-value of pose `other` lying as far from `final` as it does (or farther) were `final`'s
    error distributed as `cov` says: the likelihood ratio test of the fit, chi-square with as
    many degrees of freedom as the motions the fit bounds (the unbounded taken out)."""
    from scipy.stats import chi2

    x = twist(final, other, cov.centre)
    if len(cov.unbounded):
        x = x - cov.unbounded.T @ np.linalg.lstsq(cov.unbounded.T, x, rcond=None)[0]
    w, v = np.linalg.eigh(cov.covariance)
    keep = w > 1e-12 * max(w.max(), 1e-300)
    d2 = float(np.sum((v[:, keep].T @ x) ** 2 / w[keep]))
    return float(chi2.sf(d2, int(keep.sum())))


def covers(final: np.ndarray, other: np.ndarray, cov: PoseCovariance) -> bool:
    """Whether pose `other` lies inside the region `final`'s stated U covers: its error
    ellipsoid at `U_LEVEL` (`local_test`)."""
    return local_test(final, other, cov) >= 1.0 - U_LEVEL


@dataclass(frozen=True)
class Comparison:
    """The best pose against one alternative on the same scan points: `for_best` points
    explained by the best and not the alternative, `for_other` the reverse, `inflation` the
    variance inflation the points' correlation gives, `p_value` one-sided (module docstring)."""

    transform: np.ndarray
    for_best: int
    for_other: int
    inflation: float
    p_value: float
    fitness: float
    angle_deg: float = 0.0
    shift_mm: float = 0.0

    def as_dict(self) -> dict[str, object]:
        return {"transform": self.transform.tolist(), "points_for_best": self.for_best,
                "points_for_alternative": self.for_other, "inflation": self.inflation, "p_value": self.p_value,
                "fitness": self.fitness, "angle_deg": self.angle_deg, "shift_mm": self.shift_mm}


def sign_test(for_best: int, for_other: int, inflation: float) -> float:
    """One-sided p-value of `for_best` of the discordant points favouring the best when each
    favours either with probability 1/2, counts divided by `inflation` (a real-valued
    binomial tail: the regularised incomplete beta function)."""
    n = (for_best + for_other) / max(inflation, 1.0)
    k = for_best / max(inflation, 1.0)
    if n <= 0 or k <= 0:
        return 1.0
    return float(betainc(k, max(n - k, 0.0) + 1.0, 0.5))
