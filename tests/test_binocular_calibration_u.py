"""The binocular points' calibration term (scanner/binocular.py, 5.): the stereo calibration's
covariance carried to every point by `calibration_jacobian`, judged against the matcher itself
run again with other calibrations, on the closed-form scene (tests/stereo_scene.py) at 320 x 256
with noise-free coordinates (what moves the points is the calibration alone).

The covariance is a joint refinement's (`calibration.stereo.joint_refine`, as
`calibration.stereo_cameras` solves two cameras) of the simulated chessboard's corners projected
through the scene's two lenses in 15 random poses with Gaussian noise: fast, and the same
parameters and covariance as a rendered calibration. Points are compared away from depth edges in
either camera (there a moved epipolar line can move a match onto the other surface: not linear)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import stereo_scene

from calibration.board import Board
from calibration.intrinsics import ViewPoints
from calibration.stereo import joint_refine
from scanner import schema
from scanner.binocular import CameraPhase, Rectification, StereoModel, calibration_jacobian, match, parameter_names
from scanner.binocular_session import StereoModelSchema
from scanner.config import CONFIG_DIR
from scanner.errors import CalibrationFileError, ConfigError
from scanner.stereo_calibration_file import read_stereo_calibration, write_stereo_calibration

BOARD = Board.load(CONFIG_DIR / "boards" / "sim_chess_9x7.toml").object_points()
CORNER_NOISE_PX = 0.02
SEED = 20261206  # fixed here: the bounds below are for this draw (the slow test draws fresh ones)


def _phase(view: stereo_scene.View) -> CameraPhase:
    """Noise-free coordinates of both orientations, stated noise 0.02 projector px (the gates')."""
    return stereo_scene.camera_phase(view, 0.02)


def _edges(depth: np.ndarray, px: int) -> np.ndarray:
    return stereo_scene.depth_edges(depth, px, step_mm=2.0)


def calibrate(truth: StereoModel, rng: np.random.Generator) -> StereoModel:
    """`truth` calibrated from the board's corners in 15 random poses, projected through both
    lenses with CORNER_NOISE_PX of Gaussian noise: the solved model with its covariance."""
    views, poses = [], []
    for _ in range(15):
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rng.normal(0, 0.3, 3) + [np.pi, 0, 0])[0]
        T[:3, 3] = [rng.uniform(-70, 40), rng.uniform(-50, 30), rng.uniform(360, 460)]
        seen = []
        for lens, E in ((truth.left, np.eye(4)), (truth.right, truth.right_from_left)):
            px = lens.project(BOARD @ (E @ T)[:3, :3].T + (E @ T)[:3, 3])
            px += rng.normal(0, CORNER_NOISE_PX, px.shape)
            inside = (px >= 0).all(axis=1) & (px[:, 0] <= lens.width - 1) & (px[:, 1] <= lens.height - 1)
            seen.append(ViewPoints(BOARD[inside], px[inside]))
        views.append(seen)
        poses.append(T)
    j = joint_refine([a for a, _ in views], [b for _, b in views], truth.left, truth.right, truth.right_from_left,
                     np.stack(poses))
    return StereoModel(j.camera, j.projector, j.proj_from_cam, truth.names, truth.epipolar_sigma_px,
                       covariance=j.covariance)


@pytest.fixture(scope="module")
def scene() -> tuple:
    """The rig (its true model, epipolar allowance 0.5 px for calibrations off by their sigma),
    both cameras' phases, the true model's match and the points compared: every 4th pixel each
    way with a point, 3 px from depth edges in either camera (flat indices)."""
    r = stereo_scene.rig(0.25)
    left = stereo_scene.view(r.left, np.eye(4), r.projector, r.world_from_proj)
    right = stereo_scene.view(r.right, r.world_from_right, r.projector, r.world_from_proj)
    truth = StereoModel(r.left, r.right, r.right_from_left, epipolar_sigma_px=0.5)
    L, R = _phase(left), _phase(right)
    base = match(Rectification.of(truth), L, R)
    grid = np.zeros(left.depth.shape, bool)
    grid[2::4, 2::4] = True
    near = _edges(left.depth, 3).ravel()
    idx, xy = base.right_pixels()
    u = np.clip(np.rint(xy).astype(int), 0, [r.right.width - 1, r.right.height - 1])
    near[idx] |= _edges(right.depth, 3)[u[:, 1], u[:, 0]]
    points = np.flatnonzero(grid.ravel() & base.cloud.valid.ravel() & ~near)
    return truth, L, R, base, points


def _points(model: StereoModel, scene: tuple) -> np.ndarray:
    _, L, R, _, points = scene
    return match(Rectification.of(model), L, R).cloud.points.reshape(-1, 3)[points].astype(np.float64)


def test_the_jacobian_is_the_matchers_response(scene: tuple) -> None:
    """Central differences of the whole matcher (rectified again, matched again) for the
    parameters that move the points along and across the epipolar lines: the Jacobian within 1 %
    (median over the points); without the match's slide along the iso-coordinate line (slope 0)
    the rotation about the baseline would be off by more than a tenth."""
    truth, _, _, base, points = scene
    J = base.calibration_jacobian(points)
    flat = calibration_jacobian(truth, base.cloud.points.reshape(-1, 3)[points], np.zeros(len(points)))
    names = parameter_names(truth.names)
    for name, h in (("left.cy", 0.1), ("right.cx", 0.1), ("right.k1", 1e-3), ("extrinsic.rx", 1e-4),
                    ("extrinsic.ry", 1e-4), ("extrinsic.tz", 0.05)):
        p = names.index(name)
        d = np.zeros(len(names))
        d[p] = h
        fd = (_points(truth.perturbed(d), scene) - _points(truth.perturbed(-d), scene)) / (2 * h)
        ok = np.isfinite(fd).all(axis=1)  # a point at the edge of the right view may lose its match
        assert ok.mean() > 0.99
        size = np.median(np.linalg.norm(J[ok, :, p], axis=1))
        err = np.median(np.linalg.norm(fd[ok] - J[ok, :, p], axis=1)) / size
        err_flat = np.median(np.linalg.norm(fd[ok] - flat[ok, :, p], axis=1)) / size
        print(f"{name}: |dX/dp| median {size:.4g} mm per unit, error {err:.2e}, with slope 0 {err_flat:.2e}")
        assert err < 0.01, name
        if name == "extrinsic.rx":
            assert err_flat > 0.1


def test_the_calibration_sigma_against_rigs_drawn_from_the_covariance(scene: tuple) -> None:
    """Rigs drawn from a calibration's covariance, the same phases matched with each: every
    point's depth moves as predicted (the matcher's moves against J·δ of the same draws within
    2 %), the pooled normalised spread is near 1 and about 95 % of the moves lie within
    1.96 predicted sigmas. Each draw moves all points together (one error per scan), so the
    draws, not the points, are the sample: with one direction of the covariance dominating the
    depth, 24 draws give the RMS as sqrt(chi-square(24)/24), 0.6-1.45 for 99.9 % of draws (the
    matcher's own check against the linear moves is the sharp one)."""
    truth, _, _, base, points = scene
    rng = np.random.default_rng(SEED)
    cov = calibrate(truth, rng).covariance
    assert cov is not None
    model = StereoModel(truth.left, truth.right, truth.right_from_left, epipolar_sigma_px=0.5, covariance=cov)
    result = match(Rectification.of(model), *scene[1:3])
    sigma = result.calibration_depth_sigma_mm(points)
    assert sigma is not None
    Jz = result.calibration_jacobian(points)[:, 2]
    X0 = base.cloud.points.reshape(-1, 3)[points, 2]
    w, v = np.linalg.eigh(cov)
    z, z_linear = [], []
    for _ in range(24):
        delta = v @ (np.sqrt(np.maximum(w, 0)) * rng.standard_normal(len(w)))
        z.append((_points(model.perturbed(delta), scene)[:, 2] - X0) / sigma)
        z_linear.append(Jz @ delta / sigma)
    ok = np.isfinite(z).all(axis=0)  # a point at the edge of the right view may lose its match in a draw
    z, z_linear = np.array(z)[:, ok], np.array(z_linear)[:, ok]
    rms, rms_linear = np.sqrt(np.mean(z ** 2)), np.sqrt(np.mean(z_linear ** 2))
    cover = float(np.mean(np.abs(z) <= 1.96))
    print(f"seed {SEED}: {ok.sum()} of {len(points)} points, calibration depth sigma median "
          f"{np.median(sigma) * 1e3:.1f} um; normalised RMS {rms:.3f} (linear {rms_linear:.3f}), within 1.96 sigma "
          f"{cover:.3f}")
    assert ok.mean() > 0.98
    assert np.sqrt(np.mean((z - z_linear) ** 2)) < 0.02 * rms_linear
    assert 0.6 < rms < 1.45
    assert 0.85 < cover < 0.999


@pytest.mark.slow
def test_the_calibration_sigma_against_independent_calibrations(scene: tuple) -> None:
    """Fresh calibrations (new board poses, new corner noise; seed drawn and printed), each
    matching the same phases: each one's depth error against the true model's points over its
    own predicted sigma. The pooled normalised RMS is near 1 and about 95 % lie within 1.96."""
    truth, L, R, base, points = scene
    seed = int(np.random.SeedSequence().entropy % 2 ** 31)
    rng = np.random.default_rng(seed)
    X0 = base.cloud.points.reshape(-1, 3)[points, 2]
    z = []
    for _ in range(30):
        result = match(Rectification.of(calibrate(truth, rng)), L, R)
        sigma = result.calibration_depth_sigma_mm(points)
        assert sigma is not None
        z.append((result.cloud.points.reshape(-1, 3)[points, 2] - X0) / sigma)
    zz = np.array(z)
    ok = np.isfinite(zz).all(axis=0)
    assert ok.mean() > 0.98
    rms, cover = np.sqrt(np.mean(zz[:, ok] ** 2)), float(np.mean(np.abs(zz[:, ok]) <= 1.96))
    print(f"seed {seed}: {ok.sum()} of {len(points)} points, 30 calibrations: normalised RMS {rms:.3f}, within "
          f"1.96 sigma {cover:.3f}; per calibration {np.round(np.sqrt(np.mean(zz[:, ok] ** 2, axis=1)), 2).tolist()}")
    assert 0.6 < rms < 1.45  # 30 calibrations: as the drawn rigs' test says
    assert 0.85 < cover < 0.999


def test_the_covariance_is_stored_read_and_said_missing(scene: tuple, tmp_path: Path) -> None:
    """Our calibration file keeps the covariance once (the report's) and reads it back; a
    manifest's stereo model holds it; a model without one says the term is not included."""
    truth, L, R, _, points = scene
    model = calibrate(truth, np.random.default_rng(SEED))
    assert model.covariance is not None
    path = write_stereo_calibration(tmp_path / "stereo_calibration.json", model, {"rms_px": 0.1})
    got, fmt = read_stereo_calibration([path], truth.left.size, truth.right.size)
    assert fmt == "slscan" and got.covariance is not None and np.array_equal(got.covariance, model.covariance)
    assert "covariance" not in path.read_text().split('"report"')[0]
    manifest = schema.parse(StereoModelSchema, model.to_dict(), tmp_path / "manifest.json").model_dump()
    assert np.array_equal(StereoModel.from_dict(manifest).covariance, model.covariance)
    renamed = model.to_dict() | {"names": ["a", "b"]}
    with pytest.raises(ConfigError, match="covariance parameters"):
        StereoModel.from_dict(renamed)
    broken = path.read_text().replace('"extrinsic.tz"', '"extrinsic.tt"')
    (tmp_path / "broken.json").write_text(broken)
    with pytest.raises(CalibrationFileError, match="covariance parameters"):
        read_stereo_calibration([tmp_path / "broken.json"], truth.left.size, truth.right.size)

    included = match(Rectification.of(got), L, R).calibration_figures()
    assert included["included"] and included["depth_sigma_median_mm"] > 0
    without = match(Rectification.of(truth), L, R)
    assert without.calibration_depth_sigma_mm(points) is None
    assert without.calibration_figures() == {"included": False, "term": without.calibration_term}
    assert without.calibration_term.startswith("not included")


def test_a_figure_on_the_binocular_points_carries_the_calibration_term(scene: tuple) -> None:
    """`slscan verify`'s binocular U (slscan/commands/verify_binocular.py): a figure linear in the
    points (their mean depth) gets u_cal = sqrt(gᵀ·J·Σ·Jᵀ·g), written out here, for the points
    kept after a subset; it is one error of the whole scan, so it stays near the points' own
    calibration sigma instead of falling as 1/sqrt(N); and the matcher run again with rigs drawn
    from the covariance moves the figure by gᵀ·J·δ, to 2 %."""
    from inspection.uncertainty import PointJacobian, PointNoise, ScanUncertainty
    from slscan.commands.verify_binocular import binocular_calibration

    truth, L, R, _, points = scene
    rng = np.random.default_rng(SEED + 1)
    cov = calibrate(truth, rng).covariance
    assert cov is not None
    model = StereoModel(truth.left, truth.right, truth.right_from_left, epipolar_sigma_px=0.5, covariance=cov)
    result = match(Rectification.of(model), L, R)
    X = result.cloud.points.reshape(-1, 3)[points].astype(np.float64)
    noise = PointNoise(np.full(len(points), 1e-3), X / X[:, 2:3])
    whole = ScanUncertainty(noise, binocular_calibration(model), jacobian=PointJacobian(result.calibration_jacobian,
                                                                                        points))
    keep = rng.random(len(points)) < 0.5
    kept = whole.subset(keep)
    g = np.zeros((int(keep.sum()), 3))
    g[:, 2] = 1.0 / keep.sum()
    u_cal = kept.linear_u(X[keep], g).calibration
    Jz = result.calibration_jacobian(points[keep])[:, 2]
    gJ = g[:, 2] @ Jz
    assert u_cal == pytest.approx(float(np.sqrt(gJ @ cov @ gJ)), rel=1e-9)
    sigma = result.calibration_depth_sigma_mm(points[keep])
    assert sigma is not None
    assert u_cal > 0.3 * np.median(sigma) > 10 * np.sqrt(np.sum((g[:, 2] * sigma) ** 2))
    assert binocular_calibration(replace(model, covariance=None)).is_zero
    w, v = np.linalg.eigh(cov)
    for _ in range(6):
        delta = v @ (np.sqrt(np.maximum(w, 0)) * rng.standard_normal(len(w)))
        moved = _points(model.perturbed(delta), scene)[keep, 2]
        ok = np.isfinite(moved)
        assert ok.mean() > 0.98
        change = np.mean(moved[ok] - X[keep][ok, 2])
        assert change == pytest.approx(float(np.mean(Jz[ok] @ delta)), rel=0.02, abs=0.02 * u_cal)
