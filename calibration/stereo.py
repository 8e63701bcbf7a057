"""Stereo extrinsics and the joint refinement of every parameter of the rig.

The camera and the projector (an inverse camera) see the same board poses. One
least-squares problem holds both devices' intrinsics and distortion, the projector's pose
relative to the camera, and every board pose (board -> camera); it minimises the
reprojection errors (pixels) of both devices together, with OpenCV's analytic derivatives
(`projectPoints`, `composeRT`). Its covariance gives one-sigma uncertainties of every
parameter, the measure of how well the views determine the rig.

Both devices' residuals count equally, as in OpenCV's `stereoCalibrate`. Weighting each by
its own RMS would be the maximum-likelihood choice for independent noise, but the
residuals left here are mostly systematic (corner localisation, decoding near square
edges): on the simulated bench such weights moved the principal points 5x further from the
truth at half resolution (0.76 against 0.15 px) and changed nothing at full resolution.
The uncertainties assume independent noise of the residuals' own size, so they are a lower
bound when systematic errors dominate.
"""

from __future__ import annotations

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


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """The jointly refined rig. `proj_from_cam` maps camera-frame points into the projector
    frame; `board_poses` (V, 4, 4) board -> camera. Residuals are observed − projected
    pixels per view. `rms_px` is the RMS over both devices' points (OpenCV's stereo RMS);
    `covariance` (24, 24) is the covariance of the rig's parameters (`RIG_PARAMETERS`: both
    devices' intrinsics and distortion, then proj_from_cam as a Rodrigues vector (rad) and a
    translation (mm)), the board poses marginalised out; zero where a parameter was held fixed.
    `std` holds one-sigma uncertainties ('camera.fx', 'projector.cy', 'extrinsic.tx' (mm),
    'extrinsic.rotation_deg', ...)."""

    camera: Pinhole
    projector: Pinhole
    proj_from_cam: np.ndarray
    board_poses: np.ndarray
    camera_residuals: list[np.ndarray]
    projector_residuals: list[np.ndarray]
    std: dict[str, float]
    covariance: np.ndarray

    @property
    def cam_from_proj(self) -> np.ndarray:
        return np.linalg.inv(self.proj_from_cam)

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


def _uncertainties(res: np.ndarray, J: np.ndarray, free: np.ndarray, e0: int) -> tuple[dict[str, float], np.ndarray]:
    """One-sigma uncertainty of every parameter, and the covariance of the rig's
    parameters (the first e0 + 6), from the residuals and Jacobian at the solution."""
    dof = max(len(res) - int(free.sum()), 1)
    cov = np.zeros((len(free), len(free)))
    cov[np.ix_(free, free)] = covariance(J[:, free], float(res @ res) / dof)
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


def joint_refine(cam_views: list[ViewPoints], proj_views: list[ViewPoints], camera: Pinhole, projector: Pinhole,
                 proj_from_cam: np.ndarray, board_poses: np.ndarray, fix_k3: bool = False,
                 fix_camera: bool = False, camera_covariance: np.ndarray | None = None) -> StereoCalibration:
    """Refine every parameter from the starting values given; `fix_camera` keeps the
    camera's intrinsics and distortion as given (their uncertainties are then reported as
    0, unless `camera_covariance` (9, 9) gives theirs: it is then carried into the
    covariance, with the refined parameters' response to the camera's, `_with_camera`)."""
    n_views = len(cam_views)
    if len(proj_views) != n_views or len(board_poses) != n_views:
        raise NotEnoughData(f"joint refinement: {n_views} camera views, {len(proj_views)} projector views and "
                            f"{len(board_poses)} board poses must match")
    # each board pose is refined as a rotation δ applied after its starting one (the board points
    # pre-rotated by it): a board turned ~180° about its normal, as a detector often labels it, has
    # a Rodrigues vector near |r| = π, where that parametrisation and composeRT's derivatives fail
    # (pose rotation columns of the Jacobian ~100 % wrong, covariances then 8x too small)
    start = [np.asarray(T, dtype=np.float64)[:3, :3] for T in board_poses]
    cam_points = [v.object_points @ R.T for v, R in zip(cam_views, start)]
    proj_points = [v.object_points @ R.T for v, R in zip(proj_views, start)]
    x0 = [_intrinsic_vector(camera), _intrinsic_vector(projector),
          cv2.Rodrigues(proj_from_cam[:3, :3])[0].ravel(), proj_from_cam[:3, 3]]
    for T in board_poses:
        x0 += [np.zeros(3), T[:3, 3]]
    x0 = np.concatenate(x0)
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

    def residuals_and_jacobian(x: np.ndarray, want_jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        res = np.empty(rows)
        jac = np.zeros((rows, len(x))) if want_jac else None
        kc, dc = _pinhole((1, 1), x[:_N_INTR]).K, x[4:9]
        kp, dp = _pinhole((1, 1), x[_N_INTR:e0]).K, x[_N_INTR + 4:e0]
        re, te = x[e0:e0 + 3], x[e0 + 3:e0 + 6]
        row = 0
        for v, (cv, pv) in enumerate(zip(cam_views, proj_views)):  # one block of rows per view and device
            o = e0 + 6 + 6 * v
            rv, tv = x[o:o + 3], x[o + 3:o + 6]
            n = len(cv)
            px, J = cv2.projectPoints(cam_points[v], rv, tv, kc, dc)
            res[row:row + 2 * n] = (cv.image_points - px.reshape(-1, 2)).ravel()
            if jac is not None:
                jac[row:row + 2 * n, o:o + 6] = -J[:, :6]
                jac[row:row + 2 * n, :_N_INTR] = -J[:, 6:6 + _N_INTR]
            row += 2 * n
            n = len(pv)
            if n == 0:
                continue
            r3, t3, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(rv, tv, re, te)
            px, J = cv2.projectPoints(proj_points[v], r3, t3, kp, dp)
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
        return res, jac

    def fun(xf: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[free] = xf
        return residuals_and_jacobian(x, False)[0]

    def jac(xf: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[free] = xf
        return residuals_and_jacobian(x, True)[1][:, free]  # type: ignore[index]

    sol = least_squares(fun, x0[free], jac=jac, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12, max_nfev=200)
    x = x0.copy()
    x[free] = sol.x
    res, J = residuals_and_jacobian(x, True)
    std, cov = _uncertainties(res, J, free, e0)  # type: ignore[arg-type]
    if fix_camera and camera_covariance is not None:
        cov = _with_camera(J, free, e0, cov, camera_covariance)  # type: ignore[arg-type]
    proj_from_cam = pose_matrix(x[e0:e0 + 3], x[e0 + 3:e0 + 6])
    poses = np.stack([pose_matrix(x[e0 + 6 + 6 * v:e0 + 9 + 6 * v], x[e0 + 9 + 6 * v:e0 + 12 + 6 * v])
                      for v in range(n_views)])
    poses[:, :3, :3] = poses[:, :3, :3] @ np.stack(start)
    blocks = np.split(res.reshape(-1, 2), np.cumsum([n for cv, pv in zip(cam_views, proj_views)
                                                     for n in (len(cv), len(pv))])[:-1])
    cam_res, proj_res = blocks[0::2], blocks[1::2]
    return StereoCalibration(_pinhole(camera.size, x[:_N_INTR]), _pinhole(projector.size, x[_N_INTR:e0]),
                             proj_from_cam, poses, cam_res, proj_res, std, cov)
