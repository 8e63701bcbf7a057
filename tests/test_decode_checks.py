"""The consistency checks of a decode (scanner/decode_checks.py, docs/consistency.md) against
analytic expectations: χ² quantiles simulated in the test, the spread phase noise gives, the
offset a rotation of the steps makes, the geometry of a synthetic rig."""

from __future__ import annotations

import numpy as np
import pytest
from fringe_frames import fringe_stack

from scanner.decode import DecodeSettings, NoiseModel, decode
from scanner.decode_checks import (
    ConsistencyError,
    Volume,
    direction,
    epipolar,
    measurement_volume,
    ordering,
    scale_threshold,
)
from scanner.patterns import PatternSet
from slscan.commands.bench.import_ import plane_coordinates, synthetic_rig

PROJ = (912, 1140)
HET = PatternSet("heterodyne", 4, (70.0, 64.0, 59.0))
GRAY = PatternSet("graycode", 4, (57.0,))
SIGMA = 12.0  # DN: large beside the 8-bit patterns' own error (1200 DN amplitude x 0.0023 = 2.7 DN)


def ramp(h: int = 128, w: int = 640) -> np.ndarray:
    """Projector columns per camera pixel: rising smoothly over most of the projector."""
    x = np.linspace(20.0, 890.0, w)[None, :]
    return x + 4.0 * np.sin(np.arange(h)[:, None] / 15.0) + 0.0 * x


def checks_of(stack: np.ndarray, ps: PatternSet, sensor: bool = True) -> dict[str, object]:
    d = decode(stack, ps, 12, PROJ, DecodeSettings(self_check=False),
               NoiseModel(SIGMA ** 2, 0.0) if sensor else None)
    return {c.name: c for c in d.checks}


@pytest.mark.parametrize("dof", [1, 3, 8])
def test_scale_threshold_is_the_simulated_quantile_of_a_chi2_median(dof: int) -> None:
    """The threshold's sampling model: the 95th percentile of median(χ²)/median over many
    simulated images of n pixels equals scale_threshold(alpha=0.05) with an exact model."""
    rng = np.random.default_rng(1)
    n = 2000
    ratios = np.median(rng.chisquare(dof, (3000, n)), axis=1) / np.median(rng.chisquare(dof, 2_000_000))
    assert scale_threshold(dof, n, 0.0, alpha=0.05) == pytest.approx(np.percentile(ratios, 95), rel=0.01)
    assert scale_threshold(dof, n, 0.1, alpha=0.05) == pytest.approx(1.21 * np.percentile(ratios, 95), rel=0.01)


def test_clean_stack_passes_with_statistics_at_one() -> None:
    """Gaussian noise of the σ the sensor model states: the residual and the frequencies'
    spread are χ² scales of 1 (the patterns' error is 4 % of the variance here)."""
    found = checks_of(fringe_stack(ramp(), HET, PROJ[0], noise=SIGMA, seed=2), HET)
    for name in ("phase_residual", "frequency_agreement"):
        assert found[name].passed and found[name].statistic == pytest.approx(1.0, abs=0.08), found[name].line()
    assert all(c.passed is not False for c in found.values()), [c.line() for c in found.values()]


def test_frequency_offset_is_the_step_a_rotation_makes() -> None:
    """Steps rotated by one in every group: each frequency's coordinate moves by P_i/N, so
    the finest less the coarsest by (P_f − P_c)/N = (912/70 − 912/59)/4 = −0.607 px."""
    stack = fringe_stack(ramp(), HET, PROJ[0], noise=SIGMA, seed=3)
    rotated = stack[[1, 2, 3, 0, 5, 6, 7, 4, 9, 10, 11, 8]]
    c = checks_of(rotated, HET)["frequency_offset"]
    assert c.passed is False and c.figures["offset"] == pytest.approx((912 / 70 - 912 / 59) / 4, abs=0.01)
    assert "rotated by 1 of 4" in c.refusal()
    with pytest.raises(ConsistencyError, match="frequency_offset .*rotated by 1 of 4"):
        decode(rotated, HET, 12, PROJ)


def test_swapped_frames_fail_the_residual_and_reversed_ones_do_not() -> None:
    """Two frames of a group swapped (0 and 1) leave an N-step residual far above the noise;
    a group in reverse order is an exact N-step fit (its residual stays at the noise)."""
    stack = fringe_stack(ramp(), HET, PROJ[0], noise=SIGMA, seed=4)
    swapped = checks_of(stack[[1, 0, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11]], HET)["phase_residual"]
    assert swapped.passed is False and swapped.statistic > 50
    reversed_ = checks_of(stack[[3, 2, 1, 0, 7, 6, 5, 4, 11, 10, 9, 8]], HET)["phase_residual"]
    assert reversed_.passed and reversed_.statistic == pytest.approx(1.0, abs=0.08)


def test_without_a_sensor_model_the_residual_is_judged_by_the_noise_along_the_fringes() -> None:
    """No sensor model (another tool's frames): the noise comes from second differences along
    the fringes, 6 σ² plus the scene's variation (an upper bound), never from the residual it
    judges; with Gaussian noise of σ its estimate is within 30 % of σ² here, a clean stack
    passes and two swapped frames fail."""
    from scanner.decode import spatial_noise

    stack = fringe_stack(ramp(), HET, PROJ[0], noise=SIGMA, seed=5)
    estimate = spatial_noise(stack, [0, 1, 2, 3], "vertical", 4095.0)
    assert estimate.sigma(np.float32(1500.0)) ** 2 == pytest.approx(SIGMA ** 2, rel=0.3)
    found = checks_of(stack, HET, sensor=False)
    assert found["phase_residual"].passed and "along the fringes" in found["phase_residual"].expected
    swapped = checks_of(stack[[1, 0, *range(2, 12)]], HET, sensor=False)["phase_residual"]
    assert swapped.passed is False


def test_gray_offset_is_a_step_and_a_wrong_period_count_fails_the_edges() -> None:
    """Gray code + 4 steps: rotating the steps by one puts the phase 2π/4 off the code's
    period; a capture of 60 periods described as 57 (same 6 + 1 Gray frames) moves the phase
    across the code's edges over most of the image."""
    stack = fringe_stack(ramp(), GRAY, PROJ[0], noise=SIGMA, seed=6)
    found = checks_of(stack, GRAY)
    assert found["gray_offset"].passed and found["gray_edges"].passed, [c.line() for c in found.values()]
    rotated = checks_of(stack[[1, 2, 3, 0, *range(4, len(stack))]], GRAY)["gray_offset"]
    assert rotated.passed is False and rotated.figures["offset"] == pytest.approx(np.pi / 2, abs=0.02)
    sixty = fringe_stack(ramp(), PatternSet("graycode", 4, (60.0,)), PROJ[0], noise=SIGMA, seed=7)
    wrong = checks_of(sixty, GRAY)
    assert wrong["gray_edges"].passed is False or wrong["projector_range"].passed is False


def test_two_gray_frames_swapped_break_the_ordering() -> None:
    """A permutation of Gray bits keeps the code's parity (the half-period bit still agrees
    with the phase) but puts stretches of the map out of order along every row."""
    stack = fringe_stack(ramp(), GRAY, PROJ[0], noise=SIGMA, seed=8)
    swapped = stack.copy()
    swapped[[5, 6]] = stack[[6, 5]]
    found = checks_of(swapped, GRAY)
    assert found["gray_edges"].passed and found["ordering"].passed is False


def test_ordering_tolerates_a_few_overhangs_and_refuses_most_lines() -> None:
    u = ramp(h=64).astype(np.float32)
    valid = np.ones(u.shape, bool)
    sigma = np.full(u.shape, 0.02, np.float32)
    few = u.copy()
    few[:8, 300:] -= 40.0  # a step back in 8 of 64 rows: an overhang
    assert ordering(few, valid, sigma, 13.0, "vertical", every=1).passed
    most = u.copy()
    most[:, 200:260] += 60.0  # a stretch of every row 60 px ahead: out of order
    c = ordering(most, valid, sigma, 13.0, "vertical", every=1)
    assert c.passed is False and c.statistic == 1.0
    assert c.figures["rising_share"] == 1.0


def test_direction_and_volume_from_the_rig_geometry() -> None:
    """On a synthetic rig's plane at 600 mm: the decoded coordinate rises with the camera
    column as the geometry predicts; mirrored, the direction check refuses it. A plane at
    600 mm against a declared volume of 360..440 mm is refused naming its depth."""
    rig = synthetic_rig(camera=(320, 256))
    depth, uv = plane_coordinates(rig)
    u = uv[..., 0].astype(np.float32)
    valid = np.isfinite(u) & (u > 0) & (u < rig.projector.size[0] - 1)
    sigma = np.full(u.shape, 0.05, np.float32)
    ok = ordering(np.where(valid, u, np.nan), valid, sigma, 30.0, "vertical", every=1)
    assert direction(ok, rig, "vertical", calibrated=True).passed
    mirrored = ordering(np.where(valid, 1920 - u, np.nan), valid, sigma, 30.0, "vertical", every=1)
    refused = direction(mirrored, rig, "vertical", calibrated=True)
    assert refused.passed is False and refused.statistic == pytest.approx(0.0)
    assert direction(mirrored, rig, "vertical", calibrated=False).passed is None  # no geometry: assumed
    points = (rig.camera.ray_grid * depth[..., None]).astype(np.float32)
    assert measurement_volume(points, rig, Volume(None, None, "none"), ("vertical",)).passed
    far = measurement_volume(points, rig, Volume(360.0, 440.0, "declared"), ("vertical",))
    assert far.passed is False and far.figures["median_depth_mm"] == pytest.approx(np.median(depth), rel=0.01)
    assert "median depth found" in far.refusal()


def test_epipolar_statistic_is_chi2_of_the_predicted_spread() -> None:
    """v measured with noise σ_v; v predicted from u with noise σ_u through dv/du = 1.7:
    the distance is N(0, σ_v² + 1.7²σ_u²), so its χ²_1 scale is 1; a row offset of 3 σ fails."""
    rng = np.random.default_rng(5)
    n = 20000
    v = rng.uniform(0, 1000, n)
    su, sv = np.full(n, 0.04), np.full(n, 0.03)
    v_from_u = v + 1.7 * rng.normal(0, 0.04, n)
    measured = v + rng.normal(0, 0.03, n)
    ok = epipolar(measured, sv, v_from_u, v_from_u_shifted=v_from_u + 1.7 * 0.5, u_sigma=su, shift_px=0.5,
                  accuracy=0.1, noise_source="test", model_px=0.0)
    assert ok.passed and ok.statistic == pytest.approx(1.0, abs=0.05)
    off = epipolar(measured + 3 * np.hypot(0.03, 1.7 * 0.04), sv, v_from_u, v_from_u_shifted=v_from_u + 0.85,
                   u_sigma=su, shift_px=0.5, accuracy=0.1, noise_source="test", model_px=0.0)
    assert off.passed is False and off.statistic > 5


def test_rig_model_tied_to_its_recorded_hash_and_calibration_file(tmp_path) -> None:
    """The recorded model's SHA-256 refuses an edited one; a calibration file changed since the
    capture is said (the session keeps decoding with the model it recorded)."""
    from scanner.decode_checks import rig_model_tie
    from scanner.session import calibration_sha256, rig_model_sha256

    model = {"camera": {"K": [[1000.0, 0, 640], [0, 1000.0, 512], [0, 0, 1]]}, "cam_from_proj": [[1.0]]}
    cal = tmp_path / "calibration.json"
    cal.write_text('{"rig_model": 1}')
    recorded = (str(cal), calibration_sha256(str(cal))["calibration_sha256"])
    assert rig_model_tie(rig_model_sha256(model), model, None, recorded).passed
    edited = {**model, "camera": {"K": [[1010.0, 0, 640], [0, 1000.0, 512], [0, 0, 1]]}}
    refused = rig_model_tie(rig_model_sha256(model), edited, None, recorded)
    assert refused.passed is False and "--rig-model" in refused.refusal()
    assert rig_model_tie(rig_model_sha256(model), edited, "other.json").passed is None  # on purpose
    cal.write_text('{"rig_model": 2}')
    changed = rig_model_tie(rig_model_sha256(model), model, None, recorded)
    assert changed.passed and "changed since the capture" in changed.line()
