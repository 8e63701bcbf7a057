"""Stereo extrinsics and the joint refinement of every parameter of the rig.

The camera and the projector (an inverse camera) see the same board poses. One
least-squares problem holds both devices' intrinsics and distortion, the projector's pose
relative to the camera, and every board pose (board -> camera); it minimises the
reprojection errors (pixels) of both devices together, with OpenCV's analytic derivatives
(`projectPoints`, `composeRT`). Its covariance gives one-sigma uncertainties of every
parameter, the measure of how well the views determine the rig.

The errors' model (`CornerErrorModel`), from how the points are measured: a camera corner is
found in the camera image with an error e (σ per axis); its projector pixel is the local
fit of the decoded coordinates evaluated at that camera corner (`calibration.correspond`),
so it carries A·e (A = the fit's Jacobian there) plus the decoding's own error n (σ per
projector axis; the two axes come from separate fringe sequences). A corner's four
coordinates are therefore correlated: on the simulated bench its camera and projector
errors correlate at 0.93-0.96. The fit weights each device's rows by its own σ (each group's σ estimated
from its residuals over its redundancy: variance component estimation, Förstner 1979); its
covariance is that weighted fit's under the model, B·M·B with B = (JᵀJ)⁻¹ of the weighted
rows and M adding each projector point's correlation with its camera corner and its own
variance A·Σₑ·Aᵀ + Σₙ. Weighting by the model itself (each projector residual minus A times
its camera residual) is the maximum-likelihood fit and held on the simulator, but on the
real procam capture it leaned on the Gray-code decoding's systematic errors: the projector's
focal length moved by 1.05 % between leave-one-pose-out solutions (0.50 % weighted this way).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from calibration.errors import NotEnoughData
from calibration.intrinsics import INTRINSIC_NAMES, ViewPoints, pose_matrix, rms
from scanner.geometry import Pinhole

EXTRINSIC_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")  # Rodrigues vector (rad), translation (mm)
_N_INTR = len(INTRINSIC_NAMES)
RIG_PARAMETERS = tuple(f"{d}.{n}" for d in ("camera", "projector") for n in INTRINSIC_NAMES) + \
    tuple(f"extrinsic.{n}" for n in EXTRINSIC_NAMES)


@dataclass(frozen=True)
class CornerLinks:
    """How one view's projector points were measured from its camera points:
    `camera_index` (M,) the camera point each projector point was evaluated at, and
    `jacobian` (M, 2, 2) ∂(projector px)/∂(camera px) there (the local fit's,
    `calibration.correspond.ProjectorCorners`)."""

    camera_index: np.ndarray
    jacobian: np.ndarray


WEIGHT_GROUPS = ("camera x", "camera y", "projector x", "projector y")


@dataclass(frozen=True)
class CornerErrorModel:
    """The corners' error model the covariance rests on (module docstring): `sigma_px` the
    one-sigma of each group of WEIGHT_GROUPS, which weights the fit, each estimated from
    its residuals over its `redundancy` (degrees of freedom); `decoding_px` the decoding's
    own one-sigma per projector axis, beyond what the camera corner's error carries into
    the projector point (NaN when `coupled` is False: the views gave no links and the two
    devices' errors are taken as independent)."""

    sigma_px: tuple[float, float, float, float]
    decoding_px: tuple[float, float]
    redundancy: tuple[float, float, float, float]
    coupled: bool

    def to_dict(self) -> dict[str, object]:
        return {"model": ("projector corner = local fit of the decoded coordinates at the camera corner: its error "
                          "is A·e_camera + e_decoding, A the fit's Jacobian; camera and decoding errors independent, "
                          "Gaussian, one sigma per axis; the fit weights each device's rows by its sigma and its "
                          "covariance carries the correlation" if self.coupled else
                          "camera and projector corner errors independent, Gaussian, one sigma per axis"),
                "sigma_px": dict(zip(WEIGHT_GROUPS, self.sigma_px)),
                "decoding_px": dict(zip(("x", "y"), self.decoding_px)) if self.coupled else None,
                "redundancy": dict(zip(WEIGHT_GROUPS, self.redundancy)),
                "estimated": "variance components: each group's residual sum of squares over its redundancy",
                "assumed": "the board's printed geometry (square size, flatness) exact; the corners' errors "
                           "independent from corner to corner: errors that are fields over a view (a lens or a "
                           "window the model lacks) are not in the covariance"}

    def summary(self) -> str:
        s = self.sigma_px
        text = (f"corner noise (estimated from the residuals): camera {s[0]:.4f} x {s[1]:.4f} px, projector "
                f"{s[2]:.4f} x {s[3]:.4f} px")
        if self.coupled:
            text += (f", of which the decoding's own {self.decoding_px[0]:.4f} x {self.decoding_px[1]:.4f} px (the "
                     f"rest is the camera corner's error carried through the local fit)")
        return text


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """The jointly refined rig. `proj_from_cam` maps camera-frame points into the projector
    frame; `board_poses` (V, 4, 4) board -> camera. Residuals are observed − projected
    pixels per view. `rms_px` is the RMS over both devices' points (OpenCV's stereo RMS);
    `covariance` (24, 24) is the covariance of the rig's parameters (`RIG_PARAMETERS`: both
    devices' intrinsics and distortion, then proj_from_cam as a Rodrigues vector (rad) and a
    translation (mm)), the board poses marginalised out; zero where a parameter was held fixed.
    `std` holds one-sigma uncertainties ('camera.fx', 'projector.cy', 'extrinsic.tx' (mm),
    'extrinsic.rotation_deg', ...); `decoding_covariance` (24, 24) the part of `covariance`
    the decoding's own error makes (the rest is the camera corners'); `noise` the corners'
    error model they rest on;
    `camera_tests`, `projector_tests` per view each point's outlier statistic under that
    model (`_Weighting.point_tests`: chi-square with 2 degrees of freedom for a point that
    fits it)."""

    camera: Pinhole
    projector: Pinhole
    proj_from_cam: np.ndarray
    board_poses: np.ndarray
    camera_residuals: list[np.ndarray]
    projector_residuals: list[np.ndarray]
    std: dict[str, float]
    covariance: np.ndarray
    decoding_covariance: np.ndarray
    noise: CornerErrorModel
    camera_tests: list[np.ndarray]
    projector_tests: list[np.ndarray]

    @property
    def cam_from_proj(self) -> np.ndarray:
        return np.linalg.inv(self.proj_from_cam)

    def decoding_share(self) -> dict[str, float]:
        """Per parameter of RIG_PARAMETERS with a variance: the fraction of it the decoding's
        own error makes (the rest is the camera corners' error)."""
        total, part = np.diag(self.covariance), np.diag(self.decoding_covariance)
        return {n: float(p / t) for n, t, p in zip(RIG_PARAMETERS, total, part) if t > 0}

    @property
    def camera_rms_px(self) -> float:
        return rms(self.camera_residuals)

    @property
    def projector_rms_px(self) -> float:
        return rms(self.projector_residuals)

    @property
    def rms_px(self) -> float:
        return rms(self.camera_residuals + self.projector_residuals)

    def per_view_rms_px(self, device: str) -> np.ndarray:
        res = self.camera_residuals if device == "camera" else self.projector_residuals
        return np.array([rms(r) for r in res])


def _uncertainties(cov: np.ndarray, e0: int) -> tuple[dict[str, float], np.ndarray]:
    """One-sigma uncertainty of every parameter from the parameters' covariance, and the
    covariance of the rig's parameters (the first e0 + 6)."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    std = {f"camera.{n}": float(sd[i]) for i, n in enumerate(INTRINSIC_NAMES)}
    std |= {f"projector.{n}": float(sd[_N_INTR + i]) for i, n in enumerate(INTRINSIC_NAMES)}
    std |= {f"extrinsic.{n}": float(sd[e0 + i]) for i, n in enumerate(EXTRINSIC_NAMES)}
    std["extrinsic.rotation_deg"] = float(np.degrees(np.sqrt(max(np.trace(cov[e0:e0 + 3, e0:e0 + 3]), 0.0))))
    std["extrinsic.translation_mm"] = float(np.sqrt(max(np.trace(cov[e0 + 3:e0 + 6, e0 + 3:e0 + 6]), 0.0)))
    return std, cov[:e0 + 6, :e0 + 6]


def _with_camera(J: np.ndarray, free: np.ndarray, e0: int, cov: np.ndarray, camera_cov: np.ndarray) -> np.ndarray:
    """The rig's covariance when the camera's intrinsics were held at values of covariance
    `camera_cov` (9, 9): the refined parameters follow the camera's to first order,
    G = -(J_fᵀJ_f)⁻¹J_fᵀJ_c, so Σ = [[Σ_c, Σ_c Gᵀ], [G Σ_c, Σ_f|c + G Σ_c Gᵀ]] over the rig's
    parameters (the first e0 + 6; the board poses marginalised out)."""
    n = e0 + 6
    f = np.flatnonzero(free)
    G = np.zeros((len(free), 9))
    G[f] = -covariance(J[:, f], 1.0) @ (J[:, f].T @ J[:, :9])
    out = cov.copy()
    out[:9, :9] = camera_cov
    Gr = G[9:n]
    out[9:n, :9] = Gr @ camera_cov
    out[:9, 9:n] = out[9:n, :9].T
    out[9:n, 9:n] += Gr @ camera_cov @ Gr.T
    return out


def _intrinsic_vector(p: Pinhole) -> np.ndarray:
    K = p.K
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *p.dist])


def _pinhole(size: tuple[int, int], x: np.ndarray) -> Pinhole:
    K = np.array([[x[0], 0.0, x[2]], [0.0, x[1], x[3]], [0.0, 0.0, 1.0]])
    return Pinhole(size[0], size[1], K, x[4:9])


def initial_extrinsics(camera_poses: np.ndarray, projector_poses: np.ndarray) -> np.ndarray:
    """proj_from_cam from the board poses each device found on its own (V, 4, 4): the mean
    of the per-view estimates T_proj·T_cam⁻¹ (rotations averaged on SO(3))."""
    each = np.stack([Tp @ np.linalg.inv(Tc) for Tc, Tp in zip(camera_poses, projector_poses)])
    u, _, vt = np.linalg.svd(each[:, :3, :3].sum(axis=0))
    T = np.eye(4)
    T[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    T[:3, 3] = np.median(each[:, :3, 3], axis=0)
    return T


def covariance(J: np.ndarray, s2: float) -> np.ndarray:
    """s2·(JᵀJ)⁻¹, with J's columns scaled to unit length first: the parameters span many
    orders of magnitude (focal lengths ~1e3 px, k3 ~1, rotations ~1e-3 rad), and without the
    scaling the weakly determined directions, whose uncertainty matters most, would be lost
    to rounding."""
    scale = 1.0 / np.maximum(np.linalg.norm(J, axis=0), 1e-300)
    Js = J * scale
    w, v = np.linalg.eigh(Js.T @ Js)
    inv = np.where(w > w.max() * 1e-14, 1.0 / np.maximum(w, 1e-300), 0.0)
    return (v * inv) @ v.T * np.outer(scale, scale) * s2


MAX_VARIANCE_ROUNDS = 30
VARIANCE_TOLERANCE = 1e-3  # the groups' variances settle to 0.1 %


class _Weighting:
    """The joint problem's rows over their group's sigma (WEIGHT_GROUPS), the groups'
    variance factors from a fit, and the covariance of that weighted fit under the
    corners' error model (module docstring)."""

    def __init__(self, cam_views: list[ViewPoints], proj_views: list[ViewPoints],
                 links: list[CornerLinks] | None) -> None:
        starts, cam, proj, A, group = 0, [], [], [], []
        for v, (cv, pv) in enumerate(zip(cam_views, proj_views)):
            n, m = len(cv), len(pv)
            group += [(0, 1)] * n + [(2, 3)] * m
            if links is not None and m:
                cam.append(starts + np.asarray(links[v].camera_index, dtype=np.int64))
                proj.append(starts + n + np.arange(m))
                A.append(np.asarray(links[v].jacobian, dtype=np.float64))
            starts += n + m
        self.coupled = bool(cam)
        self.cam = np.concatenate(cam) if cam else np.zeros(0, np.int64)
        self.proj = np.concatenate(proj) if proj else np.zeros(0, np.int64)
        self.A = np.concatenate(A) if A else np.zeros((0, 2, 2))
        if not np.isfinite(self.A).all():
            raise NotEnoughData("joint refinement: a projector point without its local fit's Jacobian")
        self.group = np.array(group, dtype=np.int64).reshape(-1, 2)

    def residuals(self, res: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        return (res.reshape(-1, 2) / sigma[self.group]).ravel()

    def jacobian(self, jac: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        return (jac.reshape(-1, 2, jac.shape[1]) / sigma[self.group][..., None]).reshape(jac.shape)

    def point_tests(self, res: np.ndarray, J: np.ndarray) -> np.ndarray:
        """Per point (camera or projector, in the rows' order): the sum of its two weighted
        residuals squared, each over its redundancy 1 − leverage (Baarda's standardised
        residuals): about chi-square with 2 degrees of freedom when the point follows the
        model."""
        leverage = np.einsum("ij,jk,ik->i", J, covariance(J, 1.0), J)
        return np.sum((res ** 2 / np.maximum(1.0 - leverage, 1e-9)).reshape(-1, 2), axis=1)

    def variance_factors(self, res: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per group: its weighted residuals' sum of squares over its redundancy (the
        rows' share of the degrees of freedom, 1 − leverage summed), and that redundancy."""
        leverage = np.einsum("ij,jk,ik->i", J, covariance(J, 1.0), J)
        g = self.group.ravel()
        redundancy = np.bincount(g, 1.0 - leverage, len(WEIGHT_GROUPS))
        squares = np.bincount(g, res ** 2, len(WEIGHT_GROUPS))
        factor = np.where(redundancy > 0.5, squares / np.maximum(redundancy, 0.5), 1.0)
        return factor, redundancy

    def decoding_sigma(self, raw: np.ndarray, redundancy: np.ndarray) -> np.ndarray:
        """The decoding's own one-sigma per projector axis (px): the projector residuals
        minus A times their camera corner's, over the projector rows' redundancy."""
        if not self.coupled:
            return np.full(2, np.nan)
        r = raw.reshape(-1, 2)
        n = r[self.proj] - np.einsum("mij,mj->mi", self.A, r[self.cam])
        return np.sqrt(np.sum(n ** 2, axis=0) / np.maximum(redundancy[2:4], 1.0))

    def covariance(self, J: np.ndarray, sigma: np.ndarray, decoding: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The fitted parameters' covariance (B M B, B = (JᵀJ)⁻¹ of the weighted rows J):
        M = JᵀJ where the rows' errors are independent with the groups' sigmas, plus, for a
        projector point carrying its camera corner's error (error A·e + n), the
        correlation with that corner's rows and its own variance under the model; and the
        part of it the decoding's own error n makes (B M_n B; the rest is the camera
        corners' error e; without links, the projector points' whole error)."""
        B = covariance(J, 1.0)
        M = J.T @ J
        P = J.shape[1]
        if not self.coupled:
            Jp = J.reshape(-1, 2, P)[self.group[:, 0] == 2].reshape(-1, P)
            return B @ M @ B, B @ (Jp.T @ Jp) @ B
        Jp = J.reshape(-1, 2, P)[self.proj]  # (m, 2, P), rows over the projector sigmas
        Jc = J.reshape(-1, 2, P)[self.cam]
        sc, sp = sigma[:2], sigma[2:4]
        ce = np.diag(sc ** 2)
        pp = np.einsum("mij,jk,mlk->mil", self.A, ce, self.A) + np.diag(decoding ** 2)  # (m, 2, 2) px²
        pp = pp / np.outer(sp, sp) - np.eye(2)  # beyond the weighting's own identity
        pc = np.einsum("mij,jk->mik", self.A, ce) / np.outer(sp, sc)  # Cov(projector, camera rows)
        M = M + np.einsum("mip,mij,mjq->pq", Jp, pp, Jp) + np.einsum("mip,mij,mjq->pq", Jp, pc, Jc)
        M = M + np.einsum("mip,mij,mjq->pq", Jc, np.transpose(pc, (0, 2, 1)), Jp)
        M_n = np.einsum("mip,i,miq->pq", Jp, decoding ** 2 / sp ** 2, Jp)
        return B @ M @ B, B @ M_n @ B


MAX_POLISH_STEPS = 50
POLISH_TOLERANCE = 1e-3  # of each parameter's one-sigma


def converged(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray],
              x: np.ndarray) -> np.ndarray:
    """`x` moved to the least-squares minimum by Gauss-Newton steps until the last step is
    below POLISH_TOLERANCE of every parameter's one-sigma. Levenberg-Marquardt's own tests
    (relative change of x and of the cost) stop early along the joint problem's flat
    valleys: on the simulated bench its answer still lay 1-2 sigma (of projector cy, the
    extrinsic ty and rz) from the minimum, which alone made the true rig lie outside the
    covariance. A step that raises the cost is halved."""
    r = fun(x)
    for _ in range(MAX_POLISH_STEPS):
        J = jac(x)
        C = covariance(J, 1.0)
        step = -C @ (J.T @ r)
        sd = np.sqrt(np.maximum(np.diag(C), 1e-300) * max(float(r @ r) / max(len(r) - len(x), 1), 1e-300))
        for _ in range(30):
            new = fun(x + step)
            if new @ new <= r @ r:
                break
            step = step / 2
        else:
            return x
        x, r = x + step, new
        if np.all(np.abs(step) <= POLISH_TOLERANCE * sd):
            break
    return x


def joint_refine(cam_views: list[ViewPoints], proj_views: list[ViewPoints], camera: Pinhole, projector: Pinhole,
                 proj_from_cam: np.ndarray, board_poses: np.ndarray, *, fix_k3: bool = False,
                 fix_camera: bool = False, camera_covariance: np.ndarray | None = None,
                 links: list[CornerLinks] | None = None) -> StereoCalibration:
    """Refine every parameter from the starting values given; `fix_camera` keeps the
    camera's intrinsics and distortion as given (their uncertainties are then reported as
    0, unless `camera_covariance` (9, 9) gives theirs: it is then carried into the
    covariance, with the refined parameters' response to the camera's, `_with_camera`).
    `links` (one per view): how the projector points were measured from the camera's,
    weighting the fit by the corners' correlated errors (module docstring); None: the two
    devices' points have independent errors."""
    n_views = len(cam_views)
    if len(proj_views) != n_views or len(board_poses) != n_views:
        raise NotEnoughData(f"joint refinement: {n_views} camera views, {len(proj_views)} projector views and "
                            f"{len(board_poses)} board poses must match")
    # each board pose is solved as a small rotation after its starting one (the board's
    # points turned by it beforehand): a Rodrigues vector near 0, never near π, where its
    # inverse (and so the projector's composed pose) is discontinuous and its derivatives lose
    # their precision (a frontal chessboard found turned by a half turn sits exactly there)
    start = np.asarray(board_poses, dtype=np.float64)[:, :3, :3]
    cam_obj = [np.ascontiguousarray(v.object_points @ R.T) for v, R in zip(cam_views, start)]
    proj_obj = [np.ascontiguousarray(v.object_points @ R.T) for v, R in zip(proj_views, start)]
    x0_parts = [_intrinsic_vector(camera), _intrinsic_vector(projector),
               cv2.Rodrigues(proj_from_cam[:3, :3])[0].ravel(), proj_from_cam[:3, 3]]
    for T in board_poses:
        x0_parts += [np.zeros(3), T[:3, 3]]
    x0 = np.concatenate(x0_parts)
    free = np.ones(len(x0), dtype=bool)
    if fix_k3:
        free[[8, _N_INTR + 8]] = False
    if fix_camera:
        free[:_N_INTR] = False
    n_cam = sum(len(v) for v in cam_views)
    rows = 2 * (n_cam + sum(len(v) for v in proj_views))
    if rows <= free.sum():
        raise NotEnoughData(f"joint refinement: {rows // 2} points for {int(free.sum())} parameters")
    e0 = 2 * _N_INTR  # first extrinsic parameter

    def raw_residuals(x: np.ndarray, jac: np.ndarray | None = None) -> np.ndarray:
        """The unweighted residuals at `x`; their Jacobian written into `jac` (rows, len(x),
        zeros) when given."""
        res = np.empty(rows)
        kc, dc = _pinhole((1, 1), x[:_N_INTR]).K, x[4:9]
        kp, dp = _pinhole((1, 1), x[_N_INTR:e0]).K, x[_N_INTR + 4:e0]
        re, te = x[e0:e0 + 3], x[e0 + 3:e0 + 6]
        row = 0
        for v, (cv, pv) in enumerate(zip(cam_views, proj_views)):  # one block of rows per view and device
            o = e0 + 6 + 6 * v
            rv, tv = x[o:o + 3], x[o + 3:o + 6]
            n = len(cv)
            px, J = cv2.projectPoints(cam_obj[v], rv, tv, kc, dc)
            res[row:row + 2 * n] = (cv.image_points - px.reshape(-1, 2)).ravel()
            if jac is not None:
                jac[row:row + 2 * n, o:o + 6] = -J[:, :6]
                jac[row:row + 2 * n, :_N_INTR] = -J[:, 6:6 + _N_INTR]
            row += 2 * n
            n = len(pv)
            if n == 0:
                continue
            r3, t3, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(rv, tv, re, te)
            px, J = cv2.projectPoints(proj_obj[v], r3, t3, kp, dp)
            res[row:row + 2 * n] = (pv.image_points - px.reshape(-1, 2)).ravel()
            if jac is not None:
                d_rt3 = J[:, :6]
                # chain rule through the composed pose: (r3, t3) from (rv, tv) and (re, te)
                d_view = d_rt3[:, :3] @ np.hstack([dr3dr1, dr3dt1]) + d_rt3[:, 3:] @ np.hstack([dt3dr1, dt3dt1])
                d_ext = d_rt3[:, :3] @ np.hstack([dr3dr2, dr3dt2]) + d_rt3[:, 3:] @ np.hstack([dt3dr2, dt3dt2])
                jac[row:row + 2 * n, o:o + 6] = -d_view
                jac[row:row + 2 * n, e0:e0 + 6] = -d_ext
                jac[row:row + 2 * n, _N_INTR:e0] = -J[:, 6:6 + _N_INTR]
            row += 2 * n
        return res

    weigh = _Weighting(cam_views, proj_views, links)
    sigma = np.ones(len(WEIGHT_GROUPS))

    def fun(xf: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[free] = xf
        return weigh.residuals(raw_residuals(x), sigma)

    def jac(xf: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[free] = xf
        J = np.zeros((rows, len(x)))
        raw_residuals(x, J)
        return weigh.jacobian(J, sigma)[:, free]

    xf = x0[free]
    for _ in range(MAX_VARIANCE_ROUNDS):  # fit, re-estimate the groups' sigmas from their residuals, fit again
        xf = least_squares(fun, xf, jac=jac, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12, max_nfev=200).x
        xf = converged(fun, jac, xf)
        factor, redundancy = weigh.variance_factors(fun(xf), jac(xf))
        sigma = np.maximum(sigma * np.sqrt(factor), 1e-12)
        if np.all(np.abs(factor - 1.0) < VARIANCE_TOLERANCE):
            break
    x = x0.copy()
    x[free] = xf
    J_raw = np.zeros((rows, len(x)))
    raw = raw_residuals(x, J_raw)
    res, J = weigh.residuals(raw, sigma), weigh.jacobian(J_raw, sigma)
    decoding = weigh.decoding_sigma(raw, redundancy)
    full, from_decoding = np.zeros((2, len(free), len(free)))
    full[np.ix_(free, free)], from_decoding[np.ix_(free, free)] = weigh.covariance(J[:, free], sigma, decoding)
    std, cov = _uncertainties(full, e0)
    if fix_camera and camera_covariance is not None:
        cov = _with_camera(J, free, e0, cov, camera_covariance)
    proj_from_cam = pose_matrix(x[e0:e0 + 3], x[e0 + 3:e0 + 6])
    poses = np.stack([pose_matrix(x[e0 + 6 + 6 * v:e0 + 9 + 6 * v], x[e0 + 9 + 6 * v:e0 + 12 + 6 * v])
                      for v in range(n_views)])
    poses[:, :3, :3] = poses[:, :3, :3] @ start
    splits = np.cumsum([n for cv, pv in zip(cam_views, proj_views) for n in (len(cv), len(pv))])[:-1]
    blocks = np.split(raw.reshape(-1, 2), splits)
    cam_res, proj_res = blocks[0::2], blocks[1::2]
    tests = np.split(weigh.point_tests(res, J[:, free]), splits)
    s_cx, s_cy, s_px, s_py = (float(v) for v in sigma)
    d_x, d_y = (float(v) for v in decoding)
    r_cx, r_cy, r_px, r_py = (float(v) for v in redundancy)
    corners = CornerErrorModel((s_cx, s_cy, s_px, s_py), (d_x, d_y), (r_cx, r_cy, r_px, r_py), weigh.coupled)
    return StereoCalibration(_pinhole(camera.size, x[:_N_INTR]), _pinhole(projector.size, x[_N_INTR:e0]),
                             proj_from_cam, poses, cam_res, proj_res, std, cov, from_decoding[:e0 + 6, :e0 + 6],
                             corners, tests[0::2], tests[1::2])
