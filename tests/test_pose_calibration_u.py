"""How a registration pose follows the calibration's errors
(`inspection.pose_uncertainty.calibration_following`), its share of the pose's covariance
and what is left of each face's calibration moves after it (`PoseUncertainty.followed`),
against closed forms (rigid moves of every point are followed exactly) and against Monte
Carlo: parts of planes seen by the small rig, their true projector coordinates triangulated
again with rigs drawn from a simulated calibration's covariance, and a rigid point-to-plane
fit written here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from inspection.pose_uncertainty import PoseUncertainty, calibration_following
from inspection.registration.evidence import pose_covariance
from inspection.uncertainty import CalibrationUncertainty, ScanUncertainty, perturbed
from scanner.geometry import RigModel
from scanner.reconstruct import Triangulator
from scanner.rig import RigConfig

COVARIANCE = Path(__file__).parent / "data" / "sim_calibration_covariance.json"


def _corner(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n points on three faces of a box corner (mm) and their outward normals."""
    normals = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    face = rng.integers(0, 3, n)
    p = rng.uniform(0.0, 40.0, (n, 3))
    p[np.arange(n), face] = 0.0
    return p + [3.0, -2.0, 1.0], normals[face]


def test_rigid_moves_are_followed_exactly() -> None:
    """A translation t of every point is undone by the motion −t; a turn ω about a point a
    by −ω about a, which about the centre c is (−ω, −ω×(c − a)); and nothing of either is
    left in the points' moves relative to the followed pose."""
    rng = np.random.default_rng(5)
    points, normals = _corner(rng, 3000)
    c = points.mean(axis=0)
    t, w, a = np.array([0.01, -0.02, 0.005]), np.array([2e-4, -1e-4, 3e-4]), np.array([50.0, 10.0, -30.0])
    moves = np.stack([np.broadcast_to(t, points.shape), np.cross(w, points - a)])
    xi = np.array([np.r_[0.0, 0.0, 0.0, -t], np.r_[-w, -np.cross(w, c - a)]])
    following = calibration_following(points, normals, c, moves)
    assert np.allclose(following, xi, rtol=1e-8, atol=1e-14)
    fit = pose_covariance(points, normals, rng.normal(0.0, 0.005, len(points)), points[:, :2], "mm")
    assert np.allclose(fit.centre, c)
    left = PoseUncertainty(fit, following).followed(moves, points)
    assert np.abs(left).max() < 1e-9 * np.abs(moves).max()


THREE_PLANES = (np.array([[0.0, 0.0, -1.0], [np.sin(0.6), 0.0, -np.cos(0.6)], [0.0, np.sin(0.7), -np.cos(0.7)]]),
                np.array([[0.0, 0.0, 400.0], [20.0, 0.0, 405.0], [0.0, 15.0, 395.0]]))
# six planes, one per sixth of the image (three columns by two rows), turned 20-40 degrees apart
SIX_PLANES = (np.array([[0.0, 0.0, -1.0], [np.sin(0.5), 0.0, -np.cos(0.5)], [0.0, np.sin(0.6), -np.cos(0.6)],
                        [-np.sin(0.4), 0.0, -np.cos(0.4)], [0.0, -np.sin(0.5), -np.cos(0.5)],
                        [np.sin(0.4) * np.cos(0.8), np.sin(0.4) * np.sin(0.8), -np.cos(0.4)]]),
              np.array([[0.0, 0.0, 400.0], [20.0, 0.0, 405.0], [0.0, 15.0, 395.0], [-20.0, 5.0, 402.0],
                        [5.0, -15.0, 398.0], [10.0, 10.0, 401.0]]))


def _planes_scene(model: RigModel, planes: tuple[np.ndarray, np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The small rig's camera looking at planes (normals, a point on each): three, one per
    third of the image, or six, one per sixth: (rows, cols, true points, their normals, the
    planes' offsets d (n·X = d), each point's plane, the projector coordinate image)."""
    n, anchor = planes
    rays = model.camera.ray_grid.astype(np.float64)
    h, w = rays.shape[:2]
    rows, cols = np.mgrid[8:h - 8:2, 8:w - 8:2].reshape(2, -1)
    d = np.einsum("ki,ki->k", n, anchor)
    if len(n) == 3:
        k = np.where(cols < w // 3, 0, np.where(rows < h // 2, 1, 2))
    else:
        k = np.minimum(cols * 3 // w, 2) + 3 * (rows >= h // 2)
    r = rays[rows, cols]
    X = r * (d[k] / np.einsum("ni,ni->n", r, n[k]))[:, None]
    Xp = X @ model.proj_from_cam[:3, :3].T + model.proj_from_cam[:3, 3]
    coord = np.full((h, w), np.nan, np.float32)
    coord[rows, cols] = model.projector.project(Xp)[:, 0]
    return rows, cols, X, n[k], d[k], k, coord


def _refits(model: RigModel, calibration: CalibrationUncertainty, scene: tuple[np.ndarray, ...], draws: int,
            seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rigs drawn from `calibration` triangulate the scene's true projector coordinates
    again; the rigid motion that puts the moved points back on their planes (linear least
    squares of n·(X + ω×(X − c) + t) = d) is one draw of the pose's calibration error, and
    the planes' mean residuals after it of their deviations': (draws, 6), (draws, planes)."""
    rows, cols, X, normals, d, k, coord = scene
    c = X.mean(axis=0)
    J = np.concatenate([np.cross(X - c, normals), normals], axis=1)
    rng = np.random.default_rng(seed)
    poses, means = [], []
    for _ in range(draws):
        m = perturbed(model, calibration.draw(rng))
        z = Triangulator(m).depth_scale(coord, "vertical")
        P = m.camera.ray_grid.astype(np.float64)[rows, cols] * z[rows, cols, None]
        ok = np.isfinite(P).all(axis=1)
        residual = np.einsum("ni,ni->n", P[ok], normals[ok]) - d[ok]
        xi = -np.linalg.lstsq(J[ok], residual, rcond=None)[0]
        poses.append(xi)
        after = residual + J[ok] @ xi
        means.append(np.bincount(k[ok], after, minlength=k.max() + 1) / np.bincount(k[ok], minlength=k.max() + 1))
    return np.array(poses), np.array(means)


def test_pose_calibration_term_matches_refits_with_drawn_calibrations() -> None:
    """200 rigs drawn from a simulated calibration's covariance (`_refits`): the pose's
    calibration errors' covariance against the one propagated. 200 draws give a standard
    deviation's own standard error of 5 %."""
    model = RigConfig.load().nominal_model().with_camera_size(160, 128)
    calibration = CalibrationUncertainty.from_report(json.loads(COVARIANCE.read_text()))
    scene = _planes_scene(model, THREE_PLANES)
    X, normals = scene[2], scene[3]
    unc = ScanUncertainty(None, calibration, model, {"vertical": np.ones(len(X))})
    moves = unc.shifts(X)
    assert moves is not None
    following = calibration_following(X, normals, X.mean(axis=0), moves)
    predicted = following.T @ following
    draws, _ = _refits(model, calibration, scene, 200, 20261206)
    mc = np.cov(draws.T)
    sd_mc, sd_pred = np.sqrt(np.diag(mc)), np.sqrt(np.diag(predicted))
    assert np.all(sd_mc > 0) and sd_pred == pytest.approx(sd_mc, rel=0.2)
    # the whole covariance, not only its diagonal: the predicted one whitens the draws
    L = np.linalg.cholesky(predicted)
    white = np.linalg.solve(L, draws.T)
    assert np.allclose(np.cov(white), np.eye(6), atol=0.3)


def test_faces_deviations_carry_the_calibration_less_the_poses_following() -> None:
    """Six planes, the pose refitted to every point after each drawn calibration error
    (`_refits`): each plane's mean deviation from the refitted model varies as the moves
    left after the pose's following predict (`PoseUncertainty.followed`, mean per plane
    along its normal), their covariance across the planes too; the moves before the
    following over-state it (here 0.2-0.3 mm against 1-10 um: the whole scan's move, which
    the pose takes up)."""
    model = RigConfig.load().nominal_model().with_camera_size(160, 128)
    calibration = CalibrationUncertainty.from_report(json.loads(COVARIANCE.read_text()))
    scene = _planes_scene(model, SIX_PLANES)
    X, normals, k = scene[2], scene[3], scene[5]
    unc = ScanUncertainty(None, calibration, model, {"vertical": np.ones(len(X))})
    moves = unc.shifts(X)
    assert moves is not None
    fit = pose_covariance(X, normals, np.random.default_rng(3).normal(0.0, 0.005, len(X)), X[:, :2], "mm")
    pose = PoseUncertainty(fit, calibration_following(X, normals, fit.centre, moves))

    def per_plane(m: np.ndarray) -> np.ndarray:  # (D, planes): each plane's mean move along its normal
        along = np.einsum("dni,ni->dn", m, normals)
        return np.stack([np.bincount(k, a, minlength=6) for a in along]) / np.bincount(k, minlength=6)

    left, before = per_plane(pose.followed(moves, X)), per_plane(moves)
    predicted = left.T @ left
    _, means = _refits(model, calibration, scene, 200, 20261207)
    mc = np.cov(means.T)
    sd_mc, sd_pred = np.sqrt(np.diag(mc)), np.sqrt(np.diag(predicted))
    assert np.all(sd_mc > 0) and sd_pred == pytest.approx(sd_mc, rel=0.2)
    # six planes' means with the six motions taken out: a covariance of low rank; its
    # leading directions (down to 1e-3 of the largest variance) whiten the draws
    w, v = np.linalg.eigh(predicted)
    top = w > w.max() * 1e-3
    white = (v[:, top].T @ (means - means.mean(axis=0)).T) / np.sqrt(w[top])[:, None]
    assert np.allclose(np.cov(white), np.eye(int(top.sum())), atol=0.3)
    assert np.all(np.sqrt(np.sum(before ** 2, axis=0)) > 10.0 * sd_mc)


def test_reported_pose_u_adds_the_calibration_and_is_withheld_when_a_motion_is_free() -> None:
    """The 95 % bounds reported are those of the fit's covariance plus the calibration's
    (drawn here from the sum), and a pose with a motion the view does not fix at all
    states no U (its covariance says nothing along that motion)."""
    from inspection.registration.evidence import FreeMotion

    rng = np.random.default_rng(11)
    points, normals = _corner(rng, 4000)
    r = rng.normal(0.0, 0.005, len(points))
    fit = pose_covariance(points, normals, r, points[:, :2], "mm")
    cal = np.diag([1e-8, 2e-8, 1e-8, 4e-4, 1e-4, 9e-4])  # rad², mm²
    d = PoseUncertainty(fit, np.linalg.cholesky(cal).T).as_dict()  # its following: ξᵀξ = cal
    draws = rng.multivariate_normal(np.zeros(6), fit.covariance + cal, 200_000)
    assert d["translation_u_mm"] == pytest.approx(np.quantile(np.linalg.norm(draws[:, 3:], axis=1), 0.95), rel=0.02)
    assert d["rotation_u_deg"] == pytest.approx(np.degrees(np.quantile(np.linalg.norm(draws[:, :3], axis=1), 0.95)),
                                                rel=0.02)
    assert np.allclose(d["pose_covariance"], fit.covariance + cal) and d["pose_u_calibration"] == "included"
    turn = FreeMotion("rotation", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), float("inf"), False)
    free = PoseUncertainty(fit, np.linalg.cholesky(cal).T, (turn,))
    fields = free.as_dict()
    assert fields["translation_u_mm"] is None and fields["rotation_u_deg"] is None and fields["pose_covariance"] is None
    assert "not bounded: rotation about the axis" in fields["pose_u_note"] and free.bounds() is None
    assert free.text().startswith("pose U not bounded: rotation about the axis")
