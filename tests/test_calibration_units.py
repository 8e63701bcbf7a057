"""Calibration building blocks against independent ground truth: boards and detection,
Gray-code decoding, local fits of projector corners, gamma, the joint solve, coverage advice, the
phase-to-height fit, the artefact measurement and the calibration file."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.board import Board
from calibration.compare import model_errors
from calibration.correspond import local_projector_points
from calibration.coverage import Coverage, needed_poses, tilt_deg
from calibration.detect import detect
from calibration.errors import BoardError, NotEnoughData
from calibration.gamma import fit_gamma, phase_error_rad
from calibration.graycode import GrayCodeLayout, decode_graycode
from calibration.intrinsics import ViewPoints
from calibration.phase_height import evaluate, fit_phase_to_height
from calibration.solve import CalibrationSettings, solve
from calibration.validate import Artefact, measure_sphere_pair
from calibration.views import Correspondence
from calibration.workflow import OperatorBench, Procedure
from scanner.calibration_file import load_calibration, maps_path, write_calibration
from scanner.config import CONFIG_DIR
from scanner.errors import CalibrationFileError, ConfigError
from scanner.geometry import PhaseToHeight, Pinhole, RigModel
from scanner.rig import DEFAULT_RIG, RigConfig, open_rig
from sim.calibration_bench import Target, plan_target_poses, plate_scene
from sim.render import project_points

BENCH = RigConfig.load(DEFAULT_RIG).nominal_model()
SIM_BOARD = Board.load(CONFIG_DIR / "boards" / "sim_chess_9x7.toml")


# ------------------------------------------------------------------ boards and detection


@pytest.mark.parametrize("text, key, problem", [
    ('type = "chessboard"\ninner_corners = [9, 7]\nsquare_mm = 7.0\ncolour = "red"\n', "colour", "unknown key"),
    ('type = "chessboard"\ninner_corners = [9.5, 7]\nsquare_mm = 7.0\n', "inner_corners", "whole numbers"),
    ('type = "chessboard"\ninner_corners = [9, 7]\n', "square_mm", "required key is missing"),
])
def test_board_file_errors_name_file_and_key(tmp_path: Path, text: str, key: str, problem: str) -> None:
    path = tmp_path / "board.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=problem) as exc:
        Board.load(path)
    assert exc.value.key == key and str(path) in str(exc.value)


def test_board_descriptions_that_cannot_be_printed_are_refused() -> None:
    with pytest.raises(BoardError, match="marker_mm < square_mm"):
        Board("charuco", 5, 4, 10.0, marker_mm=12.0, dictionary="DICT_5X5_100")
    with pytest.raises(BoardError, match="dictionary"):
        Board("charuco", 5, 4, 10.0, marker_mm=7.0, dictionary="DICT_NOPE")
    with pytest.raises(BoardError, match="circle_mm"):
        Board("circles_asymmetric", 4, 5, 10.0)
    with pytest.raises(BoardError, match="whole numbers of texels"):
        Board("chessboard", 9, 7, 7.0, 7.0).image(10.3)


@pytest.mark.parametrize("board", [
    Board("chessboard", 9, 7, 7.0, 7.0),
    Board("charuco", 7, 5, 8.0, 8.0, marker_mm=6.0, dictionary="DICT_5X5_100"),
    Board("circles_asymmetric", 4, 7, 6.0, 8.0, circle_mm=5.0),
], ids=lambda b: b.kind)
def test_printed_board_is_found_where_its_model_points_are(board: Board) -> None:
    """Each kind's image, read by its detector, lands on the model points: the homography
    from model points to detections fits to a few hundredths of a pixel with the print's
    scale (wrong ids or ordering would not fit a homography)."""
    ppm = 10.0
    img = board.image(ppm)
    padded = np.pad(img, 40, constant_values=0.85)
    found = detect(board, (padded * 4095).astype(np.uint16))
    assert found is not None and len(found) >= (board.n_points if board.kind != "charuco" else 0.8 * board.n_points)
    obj = board.object_points()[found.ids][:, :2]
    H, _ = cv2.findHomography(obj, found.image_points, 0)
    mapped = cv2.perspectiveTransform(obj.reshape(-1, 1, 2), H).reshape(-1, 2)
    assert np.sqrt(np.mean(np.sum((mapped - found.image_points) ** 2, axis=1))) < 0.05
    expected = (obj + board.image_origin_mm) * ppm - 0.5 + 40  # texel centres at integers
    same = np.abs(found.image_points - expected).max()
    turned = np.abs(found.image_points[::-1] - expected).max()  # 180-degree symmetric boards may start at either end
    assert min(same, turned) < 0.1


# ------------------------------------------------------------------ Gray code


def test_graycode_decodes_its_own_patterns_and_keeps_blurred_last_bits_as_runs() -> None:
    layout = GrayCodeLayout(64, 48)
    stack = layout.patterns().astype(np.uint16) * 16
    maps = decode_graycode(stack, layout, min_contrast=100, min_bit_difference=100)
    yy, xx = np.mgrid[0:48, 0:64]
    assert maps.valid.all() and np.array_equal(maps.u, xx) and np.array_equal(maps.v, yy)
    assert np.all(maps.weight_u == 1.0)
    # the two finest column bits unreadable (pattern = inverse): a run of 4 columns, weight 1/16
    blurred = stack.copy()
    for k in (layout.column_bits - 2, layout.column_bits - 1):
        blurred[2 * k] = blurred[2 * k + 1] = 2000
    maps = decode_graycode(blurred, layout, min_contrast=100, min_bit_difference=100)
    assert np.array_equal(maps.u, (xx // 4) * 4 + 1.5) and np.all(maps.weight_u == 1 / 16)
    assert np.array_equal(maps.v, yy) and np.all(maps.weight_v == 1.0)
    maps = decode_graycode(blurred, layout, 100, 100, max_dropped_bits=1)
    assert not maps.valid.any()


def test_graycode_layout_matches_the_real_capture_patterns() -> None:
    folder = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam-graycode" / "patterns"
    if not folder.is_dir():
        pytest.skip("../shared/data/procam-graycode not present (real data is only in CI and on the bench)")
    shown = np.stack([cv2.imread(str(folder / f"pattern_{k:02d}.png"), cv2.IMREAD_GRAYSCALE) for k in range(42)])
    assert np.array_equal(GrayCodeLayout(1024, 768).patterns(), shown)


# ------------------------------------------------------------------ projector corners


def test_local_fits_recover_projector_corners_and_reject_decoding_errors() -> None:
    rng = np.random.default_rng(0)
    H = np.array([[0.7, 0.05, 30.0], [-0.03, 1.3, 12.0], [1e-4, -5e-5, 1.0]])
    yy, xx = np.mgrid[0:300, 0:400].astype(np.float64)
    q = np.stack([xx, yy, np.ones_like(xx)], -1) @ H.T
    u, v = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
    u = (u + rng.normal(0, 0.05, u.shape)).astype(np.float32)
    v = (v + rng.normal(0, 0.05, v.shape)).astype(np.float32)
    wrong = rng.random(u.shape) < 0.02  # decoding errors: far off
    u[wrong] += 37.0
    u[:, :60] = np.nan  # not decoded
    corners = np.array([[100.3, 80.7], [250.5, 150.2], [330.0, 260.9], [70.0, 150.0], [50.0, 150.0]])
    pc = local_projector_points(corners, u, v, 25.0)
    truth = cv2.perspectiveTransform(corners.reshape(-1, 1, 2), H).reshape(-1, 2)
    # the last corner lies where nothing was decoded (only a strip to its right): not extrapolated
    assert pc.found.tolist() == [True, True, True, True, False]
    assert np.abs(pc.points[:4] - truth[:4]).max() < 0.01


def test_local_fit_follows_lens_curvature_without_bias_and_gives_its_jacobian() -> None:
    """A camera-to-projector mapping that is a homography bent by radial distortion (not a
    homography): the fit's value at a corner is the mapping's there, with no bias from the
    curvature inside its window (a homography fitted over these 20 px windows misses by up
    to 0.03 px; what is left must stay well below the simulated bench's decoding noise
    averaged over a view's 63 corners, 4e-4 px), and its Jacobian is the mapping's derivative."""
    H = np.array([[0.7, 0.05, 30.0], [-0.03, 1.4, 12.0], [1e-4, -5e-5, 1.0]])

    def mapping(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.stack([x, y, np.ones_like(x)], -1) @ H.T
        u, v = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
        r2 = ((u - 300.0) ** 2 + (v - 250.0) ** 2) / 400.0 ** 2  # radial distortion about (300, 250), k1 = -0.08
        return u + (u - 300.0) * -0.08 * r2, v + (v - 250.0) * -0.08 * r2

    yy, xx = np.mgrid[0:400, 0:500].astype(np.float64)
    u, v = mapping(xx, yy)
    corners = np.array([[60.4, 50.2], [250.5, 150.7], [440.3, 360.1], [100.0, 330.6]])
    pc = local_projector_points(corners, u, v, 20.0)
    truth = np.stack(mapping(corners[:, 0], corners[:, 1]), axis=1)
    assert np.abs(pc.points - truth).max() < 2e-4
    h = 1e-4
    for k, step in enumerate(([h, 0.0], [0.0, h])):
        derivative = (np.stack(mapping(*(corners + step).T), 1) - np.stack(mapping(*(corners - step).T), 1)) / (2 * h)
        assert np.allclose(pc.jacobian[:, :, k], derivative, rtol=1e-3, atol=1e-4)


# ------------------------------------------------------------------ gamma


def test_gamma_fit_and_what_compensation_is_worth() -> None:
    rng = np.random.default_rng(1)
    levels = np.round(np.linspace(0, 255, 18)).astype(np.uint8)
    gain = rng.uniform(1500, 3000, (60, 80))
    images = np.stack([200 + gain * (lv / 255.0) ** 2.3 + rng.normal(0, 3, gain.shape) for lv in levels])
    fit = fit_gamma(levels, np.clip(images, 0, 4095).astype(np.uint16), 4095.0)
    assert fit.gamma == pytest.approx(2.3, abs=0.01) and fit.rms < 0.002
    # the phase error of uncompensated fringes agrees with an independent computation on the
    # continuous response (the 8-bit rounding adds up to ~0.005 rad); compensation leaves the rounding
    for steps in (3, 4):
        phi = np.linspace(0, 2 * np.pi, 720, endpoint=False)
        delta = 2 * np.pi * np.arange(steps) / steps
        shown = (0.5 + 0.5 * np.cos(phi[:, None] + delta)) ** 2.3
        est = np.angle((shown * np.exp(-1j * delta)).sum(axis=1))
        continuous = np.abs(np.angle(np.exp(1j * (est - phi)))).max()
        assert phase_error_rad(2.3, steps, False) == pytest.approx(continuous, abs=0.006)
        assert phase_error_rad(2.3, steps, True) < 0.01
    assert phase_error_rad(2.3, 3, False) > 0.3  # three steps alias the second harmonic: wavy surfaces


# ------------------------------------------------------------------ solve


def exact_views(model: RigModel, n: int, noise_px: float, seed: int = 0) -> list[Correspondence]:
    """Correspondences of the simulated bench board at planned poses, projected with `model`."""
    target = Target(np.ones((4, 4), np.float32), SIM_BOARD.size_mm, SIM_BOARD.image_origin_mm,
                    SIM_BOARD.object_points())
    rng = np.random.default_rng(seed)
    obj = SIM_BOARD.object_points()
    out = []
    for k, P in enumerate(plan_target_poses(model, target, n, 400.0, seed)):
        X = obj @ P[:3, :3].T + P[:3, 3]
        Xp = X @ model.proj_from_cam[:3, :3].T + model.proj_from_cam[:3, 3]
        cam = project_points(model.camera, X) + rng.normal(0, noise_px, (len(X), 2))
        proj = project_points(model.projector, Xp) + rng.normal(0, noise_px, (len(X), 2))
        out.append(Correspondence(f"pose_{k:03d}", None, ViewPoints(obj, cam), ViewPoints(obj, proj), None))  # type: ignore[arg-type]
    return out


def test_joint_solve_recovers_the_rig_and_its_uncertainty_covers_the_error() -> None:
    exact = solve(exact_views(BENCH, 10, 0.0), BENCH.camera.size, BENCH.projector.size)
    s = exact.stereo
    errors = model_errors(RigModel(s.camera, s.projector, s.cam_from_proj), BENCH)
    assert max(abs(v) for v in errors.values()) < 1e-6
    noisy = solve(exact_views(BENCH, 10, 0.02, seed=3), BENCH.camera.size, BENCH.projector.size).stereo
    e = model_errors(RigModel(noisy.camera, noisy.projector, noisy.cam_from_proj), BENCH)
    assert noisy.rms_px == pytest.approx(0.02 * np.sqrt(2), rel=0.15)
    assert abs(e["camera.cx_px"]) < 4 * noisy.std["camera.cx"]
    assert abs(e["projector.cy_px"]) < 4 * noisy.std["projector.cy"]
    assert e["translation_mm"] < 4 * noisy.std["extrinsic.translation_mm"]


def test_camera_keeps_its_own_intrinsics_when_the_joint_refinement_cannot_pin_them() -> None:
    views = exact_views(BENCH, 10, 0.02, seed=3)
    joint = solve(views, BENCH.camera.size, BENCH.projector.size)
    assert joint.camera_choice.source == "joint refinement"  # 10 views, 0.02 px: the joint problem pins it
    strict = solve(views, BENCH.camera.size, BENCH.projector.size, CalibrationSettings(max_joint_camera_std=1e-7))
    choice, s = strict.camera_choice, strict.stereo
    assert choice.source == "camera views" and "above the limit" in choice.reason
    assert choice.joint == pytest.approx(joint.camera_choice.joint)  # what the joint refinement would have saved
    assert np.array_equal(s.camera.K, strict.camera.pinhole.K)
    assert np.array_equal(s.camera.dist, strict.camera.pinhole.dist)
    assert s.std["camera.cx"] == strict.camera.std["cx"] > 0
    # the projector and the extrinsics are still refined against both devices' points
    e = model_errors(RigModel(s.camera, s.projector, s.cam_from_proj), BENCH)
    assert s.rms_px == pytest.approx(0.02 * np.sqrt(2), rel=0.15)
    assert abs(e["projector.cy_px"]) < 4 * s.std["projector.cy"] and abs(e["projector.fx_pct"]) < 0.05
    assert e["translation_mm"] < 4 * s.std["extrinsic.translation_mm"]


def test_too_few_views_is_an_error_not_a_calibration() -> None:
    with pytest.raises(NotEnoughData, match="3 usable board pose.*at least 4"):
        solve(exact_views(BENCH, 3, 0.01), BENCH.camera.size, BENCH.projector.size, CalibrationSettings(min_views=4))


def test_coverage_says_what_is_missing() -> None:
    cam = Coverage((1280, 1024))
    proj = Coverage((912, 1140))
    cam.add(np.array([[640.0, 512.0], [650.0, 520.0]]))
    proj.add(np.array([[456.0, 570.0]]))
    advice = needed_poses(cam, proj, [(0.0, 0.0)], 1, 5)
    assert advice[0] == "4 more pose(s)"
    assert any("top left" in a and "camera" in a for a in advice)
    assert sum("away from the camera" in a for a in advice) == 4
    grid = np.stack(np.meshgrid(np.linspace(5, 1275, 40), np.linspace(5, 1019, 40)), -1).reshape(-1, 2)
    cam.add(grid)
    proj.add(grid * [912 / 1280, 1140 / 1024])
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.0, np.radians(25), 0.0]))[0]
    assert tilt_deg(T)[1] == pytest.approx(25.0)
    tilts = [(20.0, 0.0), (-20.0, 0.0), (0.0, 20.0), (0.0, -20.0)]
    assert needed_poses(cam, proj, tilts, 5, 5) == []


def test_operator_bench_asks_and_stops_on_q() -> None:
    said, answers = [], iter(["", "q"])
    bench = OperatorBench(said.append, lambda prompt: next(answers))
    assert bench.place_board(1, ["points in the top left of the camera image"]) is True
    assert "still needed: points in the top left of the camera image" in said[0]
    assert bench.place_board(2, []) is False


def test_procedure_settings_come_from_the_rig_toml(tmp_path: Path) -> None:
    text = DEFAULT_RIG.read_text().replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
    rig = tmp_path / "rig.toml"
    rig.write_text(text + '\n[calibrate]\nposes = 8\nmax_camera_rms_px = 0.2\nplate_heights_mm = [0, 10, 20]\n'
                          'artefact = { type = "sphere_pair", radius_mm = 12.7, distance_mm = 60.0 }\n')
    procedure = Procedure.for_rig(RigConfig.load(rig), poses=10)
    assert procedure.poses == 10 and procedure.settings.max_camera_rms_px == 0.2
    assert procedure.plate_heights_mm == (0.0, 10.0, 20.0) and procedure.artefact == Artefact(12.7, 60.0)
    assert procedure.patterns.orientations == ("vertical", "horizontal") and procedure.board.name == "sim-chess-9x7"
    rig.write_text(text + '\n[calibrate]\nplate_heights_mm = [5, 10]\n')
    with pytest.raises(ConfigError, match="start at 0") as exc:
        Procedure.for_rig(RigConfig.load(rig))
    assert exc.value.key == "calibrate.plate_heights_mm"


# ------------------------------------------------------------------ phase-to-height


def test_eq17_fit_recovers_the_geometry_where_the_model_is_exact() -> None:
    """Parallel optical axes (the geometry Eq. 17 is derived for): projector beside the
    camera, both looking along z at a plate 450 mm away; phases computed exactly."""
    l_mm, d_mm, fringes = 450.0, 80.0, 64
    cam = Pinhole.from_fov(320, 256, 30.0)
    proj = Pinhole.from_fov(912, 570, 34.0)
    rays = cam.ray_grid.astype(np.float64)

    def phase(height: float) -> np.ndarray:
        z = l_mm - height
        u = proj.K[0, 0] * (rays[..., 0] * z - d_mm) / z + proj.K[0, 2]
        return 2 * np.pi * fringes * (u + 0.5) / proj.width

    heights = [0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0]
    mask = [True, False, True, False, True, False, True]
    phases = [phase(h) for h in heights]
    plane = np.array([0.0, 0.0, -1.0, l_mm])
    model = fit_phase_to_height(heights, phases, plane, cam, mask)
    pitch = proj.width / fringes * l_mm / proj.K[0, 0]  # λ0 on the plate
    assert model.l_mm == pytest.approx(l_mm, rel=1e-6) and model.d_mm == pytest.approx(d_mm, rel=1e-6)
    assert model.pitch_mm == pytest.approx(pitch, rel=1e-6)
    assert model.per_pixel and np.nanmax(np.abs(model.l_map_mm - l_mm)) < 1e-3
    points = [rays * (l_mm - h) for h in heights]
    errors = evaluate(heights, mask, phases, points, model)
    # 0.1 um: the reference phase is stored as float32, like every decoded map (~1e-5 rad at 400 rad)
    assert all(e.eq17_mm < 1e-4 and e.per_pixel_mm < 1e-4 and e.triangulation_mm < 1e-9 for e in errors)
    assert [e.held_out for e in errors] == [not m for m in mask]


# ------------------------------------------------------------------ validation artefact


def test_sphere_pair_is_measured_from_an_organised_cloud() -> None:
    cam = Pinhole.from_fov(400, 320, 30.0)
    rays = cam.ray_grid.astype(np.float64)
    z = np.full(rays.shape[:2], 420.0)
    centres = [np.array([-30.0, 5.0, 390.0]), np.array([25.0, -3.0, 400.0])]
    for c in centres:  # nearest intersection of each ray with each sphere
        b = rays @ c
        a = np.sum(rays ** 2, axis=2)
        disc = b * b - a * (c @ c - 12.0 ** 2)
        t = (b - np.sqrt(np.where(disc > 0, disc, 0))) / a
        z = np.where((disc > 0) & (t < z), t, z)
    points = rays * z[..., None]
    v = measure_sphere_pair(points, Artefact(12.0, 55.0))
    true_distance = float(np.linalg.norm(centres[1] - centres[0]))
    assert v.distance_mm == pytest.approx(true_distance, abs=1e-6)
    assert v.distance_error_mm == pytest.approx(true_distance - 55.0, abs=1e-6)
    assert max(abs(r) for r in v.radius_error_mm) < 1e-6 and v.plate_rms_mm < 1e-9


# ------------------------------------------------------------------ calibration file and rig


def test_calibration_file_round_trip_and_refusals(tmp_path: Path) -> None:
    model = replace(BENCH, projector_gamma=2.15)
    path = write_calibration(tmp_path / "cal.json", model, {"rms_px": {"camera": 0.01}}, "bench")
    data = json.loads(path.read_text())
    assert data["format"] == "slscan-calibration" and data["version"] == 1 and data["created"]
    assert data["image_sizes"] == {"camera": [1280, 1024], "projector": [912, 1140]}
    loaded = load_calibration(path, (1280, 1024), (912, 1140)).model
    assert np.allclose(loaded.camera.K, model.camera.K) and loaded.projector_gamma == 2.15
    with pytest.raises(CalibrationFileError, match="camera of 1280 x 1024 px, the rig's camera is 640 x 512"):
        load_calibration(path, (640, 512), (912, 1140))
    data["version"] = 99
    (tmp_path / "v99.json").write_text(json.dumps(data))
    with pytest.raises(CalibrationFileError, match="version 99"):
        load_calibration(tmp_path / "v99.json")


def test_calibration_file_keeps_the_per_pixel_phase_to_height_model(tmp_path: Path) -> None:
    h, w = BENCH.camera.height, BENCH.camera.width
    ref = np.tile(np.linspace(0.0, 400.0, w, dtype=np.float32), (h, 1))
    l_map = np.full((h, w), 420.0, np.float32)
    l_map[:10] = np.nan  # pixels the plate scans did not calibrate
    k_map = np.tile(np.linspace(5.0, 6.0, h, dtype=np.float32)[:, None], (1, w))
    p2h = PhaseToHeight(210.0, 68.0, 3.1, ref, np.array([0.0, 0.0, -1.0, 420.0]), l_map, k_map)
    path = write_calibration(tmp_path / "cal.json", replace(BENCH, phase_to_height=p2h), {}, "bench")
    loaded = load_calibration(path, (w, h), (912, 1140)).model
    assert loaded.calibration == str(path.resolve())  # scans record which calibration they used
    m = loaded.phase_to_height
    assert m.per_pixel and m.maps_file == str(maps_path(path).resolve())
    assert all(np.array_equal(m.maps()[k], a, equal_nan=True) for k, a in p2h.maps().items())
    dphi = np.float32(2.0)
    height = m.height(ref - dphi)  # Eq. 17 with each pixel's own l and K, none where not calibrated
    assert np.allclose(height[10:], 420.0 * 2.0 / (2.0 + k_map[10:]), atol=1e-3) and np.isnan(height[:10]).all()
    assert np.allclose(m.height(ref - dphi, per_pixel=False), 210.0 * 2.0 / (2.0 + 2 * np.pi * 68.0 / 3.1))
    maps_path(path).unlink()
    with pytest.raises(CalibrationFileError, match=r"cal\.npz: phase-to-height maps missing or unreadable"):
        load_calibration(path)


def test_rig_toml_naming_a_calibration_reconstructs_with_it(tmp_path: Path) -> None:
    calibrated = replace(BENCH, cam_from_proj=BENCH.cam_from_proj @ np.diag([1.0, 1.0, 1.0, 1.0]),
                         camera=Pinhole(1280, 1024, BENCH.camera.K * [[1.001], [1.001], [1]], BENCH.camera.dist))
    write_calibration(tmp_path / "cal.json", calibrated, {}, "bench")
    text = DEFAULT_RIG.read_text().replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
    rig_toml = tmp_path / "rig.toml"
    rig_toml.write_text(text.replace("[rig]\n", '[rig]\ncalibration = "cal.json"\n', 1))
    config = RigConfig.load(rig_toml)
    assert config.model.camera.K[0, 0] == pytest.approx(BENCH.camera.K[0, 0] * 1.001)
    with open_rig(config, scene=plate_scene(420.0)) as rig:
        assert rig.model is config.model  # scans reconstruct with the calibration …
        assert rig.extras["renderer"].model.camera.K[0, 0] == BENCH.camera.K[0, 0]  # … the simulator keeps the truth
    rig_toml.write_text(text.replace("[rig]\n", '[rig]\ncalibration = "cal.json"\n', 1).replace(
        "width = 1280", "width = 640").replace("height = 1024", "height = 512"))
    with pytest.raises(ConfigError, match="rig.calibration.*camera of 1280 x 1024 px, the rig's camera is 640 x 512"):
        RigConfig.load(rig_toml)
