"""The calibration's share of a registration pose's covariance
(`inspection.inspect_scan.calibration_covariance`) against closed forms (rigid moves of
every point are followed exactly) and against Monte Carlo: a part of three planes seen by
the small rig, its true projector coordinates triangulated again with rigs drawn from a
simulated calibration's covariance, and a rigid point-to-plane fit written here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from inspection.pose_uncertainty import calibration_covariance
from inspection.uncertainty import CalibrationUncertainty, ScanUncertainty, perturbed
from scanner.geometry import RigModel
from scanner.reconstruct import Triangulator
from scanner.rig import RigConfig


def _corner(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n points on three faces of a box corner (mm) and their outward normals."""
    normals = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    face = rng.integers(0, 3, n)
    p = rng.uniform(0.0, 40.0, (n, 3))
    p[np.arange(n), face] = 0.0
    return p + [3.0, -2.0, 1.0], normals[face]


def test_rigid_moves_are_followed_exactly() -> None:
    """A translation t of every point is undone by the motion −t; a turn ω about a point a
    by −ω about a, which about the centre c is (−ω, −ω×(c − a)): Σ = Σ_d ξ_d ξ_dᵀ."""
    rng = np.random.default_rng(5)
    points, normals = _corner(rng, 3000)
    c = points.mean(axis=0)
    t, w, a = np.array([0.01, -0.02, 0.005]), np.array([2e-4, -1e-4, 3e-4]), np.array([50.0, 10.0, -30.0])
    moves = np.stack([np.broadcast_to(t, points.shape), np.cross(w, points - a)])
    xi = np.array([np.r_[0.0, 0.0, 0.0, -t], np.r_[-w, -np.cross(w, c - a)]])
    assert np.allclose(calibration_covariance(points, normals, c, moves), xi.T @ xi, rtol=1e-8, atol=1e-16)


def _planes_scene(model: RigModel) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The small rig's camera looking at three planes (one per third of the image, turned
    30-40 degrees apart): (rows, cols, true points, their normals, the planes' offsets d
    (n·X = d), the projector coordinate image)."""
    rays = model.camera.ray_grid.astype(np.float64)
    h, w = rays.shape[:2]
    rows, cols = np.mgrid[8:h - 8:2, 8:w - 8:2].reshape(2, -1)
    n = np.array([[0.0, 0.0, -1.0], [np.sin(0.6), 0.0, -np.cos(0.6)], [0.0, np.sin(0.7), -np.cos(0.7)]])
    anchor = np.array([[0.0, 0.0, 400.0], [20.0, 0.0, 405.0], [0.0, 15.0, 395.0]])
    d = np.einsum("ki,ki->k", n, anchor)
    k = np.where(cols < w // 3, 0, np.where(rows < h // 2, 1, 2))
    r = rays[rows, cols]
    X = r * (d[k] / np.einsum("ni,ni->n", r, n[k]))[:, None]
    Xp = X @ model.proj_from_cam[:3, :3].T + model.proj_from_cam[:3, 3]
    coord = np.full((h, w), np.nan, np.float32)
    coord[rows, cols] = model.projector.project(Xp)[:, 0]
    return rows, cols, X, n[k], d[k], coord


def test_pose_calibration_term_matches_refits_with_drawn_calibrations() -> None:
    """200 rigs drawn from a simulated calibration's covariance; each triangulates the
    true projector coordinates again, and the rigid motion that puts the moved points back
    on their planes (linear least squares of n·(X + ω×(X − c) + t) = d) is one draw of the
    pose's calibration error. Its covariance against the one propagated: 200 draws give a
    standard deviation's own standard error of 5 %."""
    model = RigConfig.load().nominal_model().with_camera_size(160, 128)
    cov = json.loads((Path(__file__).parent / "data" / "sim_calibration_covariance.json").read_text())
    calibration = CalibrationUncertainty.from_report(cov)
    rows, cols, X, normals, d, coord = _planes_scene(model)
    c = X.mean(axis=0)
    unc = ScanUncertainty(None, calibration, model, {"vertical": np.ones(len(X))})
    moves = unc.shifts(X)
    assert moves is not None
    predicted = calibration_covariance(X, normals, c, moves)

    rng = np.random.default_rng(20261206)
    J = np.concatenate([np.cross(X - c, normals), normals], axis=1)
    draws = []
    for _ in range(200):
        m = perturbed(model, calibration.draw(rng))
        z = Triangulator(m).depth_scale(coord, "vertical")
        P = m.camera.ray_grid.astype(np.float64)[rows, cols] * z[rows, cols, None]
        ok = np.isfinite(P).all(axis=1)
        residual = np.einsum("ni,ni->n", P[ok], normals[ok]) - d[ok]
        draws.append(-np.linalg.lstsq(J[ok], residual, rcond=None)[0])
    mc = np.cov(np.array(draws).T)
    sd_mc, sd_pred = np.sqrt(np.diag(mc)), np.sqrt(np.diag(predicted))
    assert np.all(sd_mc > 0) and sd_pred == pytest.approx(sd_mc, rel=0.2)
    # the whole covariance, not only its diagonal: the predicted one whitens the draws
    L = np.linalg.cholesky(predicted)
    white = np.linalg.solve(L, np.array(draws).T)
    assert np.allclose(np.cov(white), np.eye(6), atol=0.3)


def test_reported_pose_u_adds_the_calibration_and_is_withheld_when_a_motion_is_free() -> None:
    """The 95 % bounds reported are those of the fit's covariance plus the calibration's
    (drawn here from the sum), and a pose with a motion the view does not fix at all
    states no U (its covariance says nothing along that motion)."""
    from inspection.pose_uncertainty import PoseUncertainty
    from inspection.registration.evidence import FreeMotion, pose_covariance

    rng = np.random.default_rng(11)
    points, normals = _corner(rng, 4000)
    r = rng.normal(0.0, 0.005, len(points))
    fit = pose_covariance(points, normals, r, points[:, :2], "mm")
    cal = np.diag([1e-8, 2e-8, 1e-8, 4e-4, 1e-4, 9e-4])  # rad², mm²
    d = PoseUncertainty(fit, cal).as_dict()
    draws = rng.multivariate_normal(np.zeros(6), fit.covariance + cal, 200_000)
    assert d["translation_u_mm"] == pytest.approx(np.quantile(np.linalg.norm(draws[:, 3:], axis=1), 0.95), rel=0.02)
    assert d["rotation_u_deg"] == pytest.approx(np.degrees(np.quantile(np.linalg.norm(draws[:, :3], axis=1), 0.95)),
                                                rel=0.02)
    assert np.allclose(d["pose_covariance"], fit.covariance + cal) and d["pose_u_calibration"] == "included"
    turn = FreeMotion("rotation", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), float("inf"), False)
    free = PoseUncertainty(fit, cal, (turn,))
    fields = free.as_dict()
    assert fields["translation_u_mm"] is None and fields["rotation_u_deg"] is None and fields["pose_covariance"] is None
    assert "not bounded: rotation about the axis" in fields["pose_u_note"] and free.bounds() is None
    assert free.text().startswith("pose U not bounded: rotation about the axis")
