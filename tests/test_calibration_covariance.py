"""The calibration's covariance against the truth it claims to bound.

Correspondences are generated here the way the bench measures them (`calibration.correspond`):
a camera corner with an error e, and its projector pixel where the camera-to-projector
mapping of the board plane takes the erroneous camera corner, plus the decoding's own error
n. The mapping's Jacobian A is computed here from the rig and the board pose (ray, plane,
projection), independently of the solver's fit. A true covariance gives the true rig a
Mahalanobis distance d² whose mean over independent draws is its degrees of freedom.

The rendered check (camera images, decoding, detection: `slscan calibrate
--covariance-check`) takes minutes per calibration; it is the slow test at the end.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.board import Board
from calibration.consistency import mahalanobis, model_parameters, parameters_model, rig_parameters
from calibration.correspond import ProjectorCorners
from calibration.intrinsics import ViewPoints
from calibration.solve import solve
from calibration.views import Correspondence
from scanner.config import CONFIG_DIR
from scanner.geometry import RigModel
from scanner.rig import DEFAULT_RIG, RigConfig
from sim.calibration_bench import Target, plan_target_poses
from sim.render import project_points

BENCH = RigConfig.load(DEFAULT_RIG).nominal_model()
BOARD = Board.load(CONFIG_DIR / "boards" / "sim_chess_9x7.toml")
CAMERA_PX, DECODING_PX = 0.0054, (0.0025, 0.0045)  # the simulated bench's, measured against its truth


def camera_to_projector(model: RigModel, pose: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Projector pixels (N, 2) of the board-plane points seen at camera `pixels` (N, 2)."""
    rays = np.column_stack([cv2.undistortPoints(pixels.reshape(-1, 1, 2), model.camera.K, model.camera.dist,
                                                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100,
                                                          1e-14)).reshape(-1, 2), np.ones(len(pixels))])
    normal, origin = pose[:3, 2], pose[:3, 3]
    X = rays * ((normal @ origin) / (rays @ normal))[:, None]
    P = model.proj_from_cam
    return project_points(model.projector, X @ P[:3, :3].T + P[:3, 3])


def measured_views(model: RigModel, n: int, rng: np.random.Generator, half_turn_first: bool = False,
                   decoding_rng: np.random.Generator | None = None) -> list[Correspondence]:
    """Board views as the bench measures them (module docstring); `half_turn_first`: the
    first (frontal) view's corners numbered from the other end, as the chessboard detector
    may report an odd x odd board: its pose is then a half turn from the others';
    `decoding_rng`: the decoding's errors drawn from it (the poses and camera errors from
    `rng`)."""
    target = Target(np.ones((4, 4), np.float32), BOARD.size_mm, BOARD.image_origin_mm, BOARD.object_points())
    obj = BOARD.object_points()
    out = []
    for k, pose in enumerate(plan_target_poses(model, target, n, 400.0, int(rng.integers(1 << 30)))):
        X = obj @ pose[:3, :3].T + pose[:3, 3]
        true_cam = project_points(model.camera, X)
        camera = true_cam + rng.normal(0.0, CAMERA_PX, true_cam.shape)
        h = 1e-3
        A = np.stack([(camera_to_projector(model, pose, true_cam + d) - camera_to_projector(model, pose, true_cam - d))
                      / (2 * h) for d in ([h, 0.0], [0.0, h])], axis=2)
        projector = camera_to_projector(model, pose, camera) + (decoding_rng or rng).normal(0.0, DECODING_PX,
                                                                                             true_cam.shape)
        board = obj
        if half_turn_first and k == 0:
            order = np.arange(len(obj))[::-1]
            board, camera, projector, A = obj, camera[order], projector[order], A[order]
        found = np.ones(len(obj), dtype=bool)
        corners = ProjectorCorners(projector, found, np.full(len(obj), 400), np.full(len(obj), 0.03), A)
        out.append(Correspondence(f"pose_{k:03d}", None, ViewPoints(board, camera),  # type: ignore[arg-type]
                                  ViewPoints(board, projector), corners))
    return out


def distance_of(views: list[Correspondence]) -> tuple[float, int, object]:
    s = solve(views, BENCH.camera.size, BENCH.projector.size).stereo
    d = mahalanobis(rig_parameters(s.camera, s.projector, s.proj_from_cam), model_parameters(BENCH), s.covariance)
    return d.d2, d.dof, s


def test_the_refinement_estimates_the_noise_it_is_given() -> None:
    d2, dof, s = distance_of(measured_views(BENCH, 10, np.random.default_rng(7)))
    sigma, decoding = s.noise.sigma_px, s.noise.decoding_px
    assert s.noise.coupled
    assert sigma[0] == pytest.approx(CAMERA_PX, rel=0.1) and sigma[1] == pytest.approx(CAMERA_PX, rel=0.1)
    assert decoding[0] == pytest.approx(DECODING_PX[0], rel=0.1)
    assert decoding[1] == pytest.approx(DECODING_PX[1], rel=0.1)
    assert sum(s.noise.redundancy) == pytest.approx(4 * 63 * 10 - (24 + 6 * 10), abs=0.5)  # rows minus parameters
    assert dof == 24 and d2 < 51.2  # chi-square 99.9 % point on 24 dof


def test_a_board_found_turned_by_a_half_turn_solves_to_the_same_rig() -> None:
    """The frontal view's corners numbered from the other end put its pose at a half turn,
    where a Rodrigues vector's inverse is discontinuous: the solve must reach the same
    minimum as with the view numbered the usual way (same measurements)."""
    plain = measured_views(BENCH, 8, np.random.default_rng(11))
    turned = measured_views(BENCH, 8, np.random.default_rng(11), half_turn_first=True)
    a = solve(plain, BENCH.camera.size, BENCH.projector.size).stereo
    b = solve(turned, BENCH.camera.size, BENCH.projector.size).stereo
    sd = np.sqrt(np.diag(a.covariance))
    difference = rig_parameters(a.camera, a.projector, a.proj_from_cam) - rig_parameters(b.camera, b.projector,
                                                                                           b.proj_from_cam)
    assert np.all(np.abs(difference) <= 0.01 * sd)


def test_a_corner_the_detector_got_wrong_is_named() -> None:
    """A camera corner 0.07 px off (13 sigma), its projector point moved with it through the
    local fit: the outlier test names that corner; good points fail it with probability
    1e-4 each (1008 points here: 0.1 expected)."""
    from dataclasses import replace

    views = measured_views(BENCH, 8, np.random.default_rng(5))
    c = views[3]
    error = np.array([0.05, -0.05])
    camera = c.camera.image_points.copy()
    camera[20] += error
    projector = c.projector.image_points.copy()
    projector[20] += c.projector_corners.jacobian[20] @ error
    views[3] = replace(c, camera=ViewPoints(c.camera.object_points, camera),
                       projector=ViewPoints(c.projector.object_points, projector))
    solution = solve(views, BENCH.camera.size, BENCH.projector.size)
    assert 20 in solution.outlier_corners.get("pose_003", {})
    assert sum(len(v) for v in solution.outlier_corners.values()) <= 2


def test_rig_parameters_and_the_model_built_from_them_agree() -> None:
    p = model_parameters(BENCH)
    again = parameters_model(p, BENCH)
    assert np.allclose(again.cam_from_proj, BENCH.cam_from_proj, atol=1e-9)
    assert np.allclose(again.camera.K, BENCH.camera.K) and np.allclose(again.projector.dist, BENCH.projector.dist)
    assert again.camera.size == BENCH.camera.size and np.allclose(model_parameters(again), p)


def test_a_calibration_scaled_in_its_baseline_reads_depth_scaled_by_the_same_factor() -> None:
    """Closed form: a rig whose projector translation is (1 + ε) times the true one
    triangulates every point at (1 + ε) times its depth (similar triangles), so its mean
    depth error over the scene is ε times the mean true depth; a covariance that only lets
    the translation's length vary with a relative sigma s gives that mean a sigma of s
    times the mean depth."""
    from sim.evaluate import Truth, smooth_region
    from sim.render import compute_ground_truth
    from sim.scene import load_scene
    from slscan.calibration_depth import calibration_depth_bias
    from slscan.simulated_calibration_bench import SCAN_CHECK_SCENE

    truth = BENCH.with_camera_size(320, 256)
    p = model_parameters(truth)
    eps, s = 2e-4, 5e-5
    estimate = p.copy()
    estimate[21:24] *= 1 + eps
    covariance = np.zeros((24, 24))
    covariance[21:24, 21:24] = s ** 2 * np.outer(p[21:24], p[21:24])
    gt = Truth.of(compute_ground_truth(truth, load_scene(SCAN_CHECK_SCENE)))
    mean_depth_um = float(np.mean(gt.depth[smooth_region(gt)])) * 1e3
    bias = calibration_depth_bias(truth, estimate, covariance, SCAN_CHECK_SCENE)
    assert bias.error_um == pytest.approx(eps * mean_depth_um, rel=0.01)
    assert bias.sigma_um == pytest.approx(s * mean_depth_um, rel=0.01)
    assert bias.z == pytest.approx(eps / s, rel=0.02)


@pytest.mark.parametrize("rig, count, says", [("hdmi_genicam.toml", "3", "needs a simulated rig"),
                                              ("sim_bench.toml", "0", "give the number of calibrations")])
def test_the_covariance_check_refuses_what_it_cannot_check(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                           rig: str, count: str, says: str) -> None:
    """Only a simulated rig has a true rig to check against; a check of no calibration is
    a usage error. Both before any calibration runs."""
    from slscan import cli

    code = cli.main(["calibrate", "--rig", str(CONFIG_DIR / "rigs" / rig), "--covariance-check", count, "--seed", "1",
                     "--out", str(tmp_path / "check")])
    assert code == 2 and says in capsys.readouterr().err


@pytest.mark.slow  # 40 solves, ~2 min
def test_mahalanobis_distance_of_the_truth_follows_its_chi_square() -> None:
    rng = np.random.default_rng(20261204)
    d2 = np.array([distance_of(measured_views(BENCH, 10, rng))[0] for _ in range(40)])
    ratio = d2.mean() / 24
    print(f"40 draws: mean d²/dof {ratio:.3f}, {np.mean(d2 <= 36.415):.0%} under the chi-square 95 % point")
    assert abs(ratio - 1.0) < 3 * np.sqrt(2 / 24 / 40)
    assert np.mean(d2 <= 36.415) >= 0.85  # 95 % expected; 40 draws put the binomial's 1st percentile at 0.85


@pytest.mark.slow  # 30 solves, ~2 min
def test_the_decodings_share_of_the_covariance_is_the_spread_its_errors_alone_make() -> None:
    """Board poses and camera corners' errors held, the decoding's errors drawn afresh: the
    estimates then scatter by the decoding's part of the covariance alone (to first order),
    B·M_n·B. Each parameter's sample variance over 30 draws over that part has mean 1 and a
    standard deviation of sqrt(2/29) = 0.26; averaged over the 24 (correlated) parameters it
    must lie within 0.7..1.4."""
    draws = 30
    estimates, parts = [], []
    for k in range(draws):
        views = measured_views(BENCH, 10, np.random.default_rng(20261205), decoding_rng=np.random.default_rng(k))
        s = solve(views, BENCH.camera.size, BENCH.projector.size).stereo
        estimates.append(rig_parameters(s.camera, s.projector, s.proj_from_cam))
        parts.append(np.diag(s.decoding_covariance))
    ratio = np.var(np.array(estimates), axis=0, ddof=1) / np.mean(parts, axis=0)
    total = np.diag(s.covariance)
    print(f"sample variance over the decoding's part, per parameter: {np.round(ratio, 2)}; mean {ratio.mean():.2f}; "
          f"decoding's share of the variance {np.round(np.mean(parts, axis=0) / total, 2)}")
    assert 0.7 <= ratio.mean() <= 1.4
    assert np.all(np.mean(parts, axis=0) <= total)


@pytest.mark.slow
@pytest.mark.acceptance  # 30 rendered calibrations at half size: hours on 2 cores; run on purpose
def test_rendered_calibrations_cover_the_true_rig(tmp_path: Path) -> None:
    from slscan import cli

    text = DEFAULT_RIG.read_text().replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
    text = text.replace("width = 1280", "width = 640").replace("height = 1024", "height = 512")
    text = text.replace("timeout_s = 2.0", "timeout_s = 120.0")  # hours of rendering beside other work
    rig = tmp_path / "rig.toml"
    rig.write_text(text + f'\n[calibrate]\nboard = "{CONFIG_DIR / "boards" / "sim_chess_9x7.toml"}"\nposes = 12\n')
    seed = int(np.random.default_rng().integers(1 << 20))
    print(f"seeds {seed}..{seed + 29}")
    assert cli.main(["calibrate", "--rig", str(rig), "--covariance-check", "30", "--seed", str(seed), "--out",
                     str(tmp_path / "check")]) == 0
    s = json.loads((tmp_path / "check" / "covariance_check.json").read_text())
    assert abs(s["mean_d2_over_dof"] - 1.0) < 3 * s["mean_d2_over_dof_expected_sd"]
    assert s["under_chi2_95_interval"][0] <= 0.95 <= s["under_chi2_95_interval"][1]
    # the calibration's mean depth error on the scan check's scene in its own sigmas: standard
    # normal over the draws, so its mean within 3.3 / sqrt(n) of 0 and its spread inside the
    # chi distribution's 99.9 % interval
    from scipy.stats import chi2

    n = s["calibrations"]
    assert abs(s["depth_z_mean"]) < 3.3 / np.sqrt(n)
    assert np.sqrt(chi2.ppf(0.0005, n - 1) / (n - 1)) <= s["depth_z_sd"] * np.sqrt(n / (n - 1)) <= np.sqrt(
        chi2.ppf(0.9995, n - 1) / (n - 1))
