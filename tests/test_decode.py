"""Pattern sets and decoding against analytic fringe stacks with known projector coordinates."""

from __future__ import annotations

import numpy as np
import pytest

from scanner.decode import DecodeSettings, decode
from scanner.errors import ConfigError, DecodeError
from scanner.patterns import PatternSet, gray_code, gray_to_binary
from tests.conftest import fringe_stack

PROJ = (912, 1140)
FAMILIES = {
    "heterodyne": PatternSet("heterodyne", 4, (70.0, 64.0, 59.0)),
    "hierarchical": PatternSet("hierarchical", 4, (1.0, 8.0, 64.0)),
    "graycode": PatternSet("graycode", 4, (57.0,)),
}


def ramp(h: int = 96, w: int = 640) -> np.ndarray:
    """Projector columns seen by each pixel: a smooth, slightly curved ramp over most of the width."""
    x = np.linspace(20.0, 890.0, w)[None, :]
    y = np.arange(h)[:, None]
    return x + 4.0 * np.sin(y / 15.0) + 0.0 * x


@pytest.mark.parametrize("family", FAMILIES)
def test_each_family_decodes_to_truth(family: str) -> None:
    ps = FAMILIES[family]
    u = ramp()
    d = decode(fringe_stack(u, ps, PROJ[0]), ps, 12, PROJ, DecodeSettings(spatial_check=False))
    m = d.maps["vertical"]
    assert m.valid.mean() > 0.999
    # noise-free: only rounding to integer DN and the pattern's own 8-bit-free profile remain
    assert np.nanmax(np.abs(m.coordinate - u)) < 0.02


@pytest.mark.parametrize("steps", [3, 5, 8])
def test_n_step_phase_shift(steps: int) -> None:
    ps = PatternSet("hierarchical", steps, (1.0, 8.0, 64.0))
    u = ramp()
    d = decode(fringe_stack(u, ps, PROJ[0]), ps, 12, PROJ)
    assert np.nanmax(np.abs(d.maps["vertical"].coordinate - u)) < 0.02


def test_horizontal_fringes_decode_rows() -> None:
    ps = PatternSet("heterodyne", 4, (70.0, 64.0, 59.0), ("horizontal",))
    v = ramp() * (1100 / 912)
    d = decode(fringe_stack(v, ps, PROJ[1]), ps, 12, PROJ)
    assert np.nanmax(np.abs(d.maps["horizontal"].coordinate - v)) < 0.03


def test_both_orientations() -> None:
    ps = PatternSet("heterodyne", 4, (70.0, 64.0, 59.0), ("vertical", "horizontal"))
    u = ramp()
    v = 500.0 + 0.3 * (u - 450.0)
    frames_v = fringe_stack(u, PatternSet("heterodyne", 4, (70.0, 64.0, 59.0)), PROJ[0])
    frames_h = fringe_stack(v, PatternSet("heterodyne", 4, (70.0, 64.0, 59.0), ("horizontal",)), PROJ[1])
    d = decode(np.concatenate([frames_v, frames_h]), ps, 12, PROJ)
    assert np.nanmax(np.abs(d.maps["vertical"].coordinate - u)) < 0.02
    assert np.nanmax(np.abs(d.maps["horizontal"].coordinate - v)) < 0.02


def test_heterodyne_and_graycode_agree_under_noise() -> None:
    u = ramp()
    results = {}
    for family in ("heterodyne", "graycode"):
        ps = FAMILIES[family]
        d = decode(fringe_stack(u, ps, PROJ[0], noise=15.0, seed=3), ps, 12, PROJ)
        results[family] = d.maps["vertical"].coordinate
    both = ~np.isnan(results["heterodyne"]) & ~np.isnan(results["graycode"])
    assert both.mean() > 0.99
    diff = results["heterodyne"][both] - results["graycode"][both]
    assert np.abs(diff).max() < 0.3  # same fringe order everywhere; only noise differs
    assert abs(diff.mean()) < 0.005


def test_phase_noise_matches_prediction() -> None:
    """σφ = sqrt(2/N)·σI/B per frequency, combined by inverse variance across frequencies."""
    ps = FAMILIES["heterodyne"]
    u = ramp(h=256)
    sigma_i = 20.0
    d = decode(fringe_stack(u, ps, PROJ[0], noise=sigma_i, seed=1), ps, 12, PROJ)
    m = d.maps["vertical"]
    err = (m.coordinate - u)[m.valid]
    predicted = np.sqrt(2 / 4) * sigma_i / np.sqrt(m.phase_weight[m.valid]) * m.period_px / (2 * np.pi)
    ratio = np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(predicted ** 2))
    assert 0.9 < ratio < 1.1


def test_masks_saturation_shadow_low_modulation() -> None:
    ps = FAMILIES["heterodyne"]
    u = ramp()
    stack = fringe_stack(u, ps, PROJ[0])
    stack[:, :10, :] = np.clip(stack[:, :10, :].astype(int) * 3, 0, 4095)  # overexposed rows
    stack[:, 20:30, :] = 300  # shadow: ambient only, no fringe
    # a visible but weak fringe: contrast B/A = 0.15, B = 15 DN, below 0.5 % of full scale
    stack[:, 40:50, :] = np.rint(100 + (stack[:, 40:50, :].astype(float) - 1500) * (15 / 1200)).astype(np.uint16)
    d = decode(stack, ps, 12, PROJ)
    m = d.maps["vertical"]
    assert m.masks["saturated"][:10].mean() > 0.3 and not m.valid[:10][m.masks["saturated"][:10]].any()
    assert m.masks["shadow"][20:30].all() and not m.valid[20:30].any()
    assert m.masks["low_modulation"][40:50].all() and not m.valid[40:50].any()
    assert m.valid[60:].all()


def test_fringe_order_errors_are_masked_not_outliers() -> None:
    ps = FAMILIES["heterodyne"]
    u = ramp(h=128)
    clean = fringe_stack(u, ps, PROJ[0], noise=10.0)
    noisy = fringe_stack(u, ps, PROJ[0], noise=100.0, seed=9)  # ~0.06 rad per frequency, ~0.9 rad in the beat
    stack = clean.copy()
    stack[:, 40:90, 100:400] = noisy[:, 40:90, 100:400]
    d = decode(stack, ps, 12, PROJ)
    m = d.maps["vertical"]
    err = np.abs(m.coordinate - u)
    assert m.masks["order_error"][40:90, 100:400].sum() > 100  # there were order errors to catch
    assert np.nanmax(err) < m.period_px / 2, "a wrongly unwrapped pixel survived as an outlier"
    assert m.valid[40:90, 100:400].mean() > 0.5  # and the good pixels there were kept


def test_wrong_frame_count_and_type() -> None:
    ps = FAMILIES["heterodyne"]
    stack = fringe_stack(ramp(), ps, PROJ[0])
    with pytest.raises(DecodeError, match="needs 12 frames"):
        decode(stack[:11], ps, 12, PROJ)
    with pytest.raises(DecodeError, match="integer"):
        decode(stack.astype(np.float32), ps, 12, PROJ)


def test_gray_code_roundtrip() -> None:
    n = np.arange(1024)
    assert np.array_equal(gray_to_binary(gray_code(n), 10), n)
    assert np.all(np.bitwise_count(gray_code(n[1:]) ^ gray_code(n[:-1])) == 1)


@pytest.mark.parametrize("table, key", [
    ({"family": "wavelet", "steps": 4, "fringes": [1]}, "family"),
    ({"family": "heterodyne", "steps": 2, "fringes": [70, 64, 59]}, "steps"),
    ({"family": "heterodyne", "steps": 4, "fringes": [70, 64, 60]}, "fringes"),
    ({"family": "hierarchical", "steps": 4, "fringes": [1, 64]}, "fringes"),
    ({"family": "graycode", "steps": 4, "fringes": [57], "orientations": ["diagonal"]}, "orientations"),
    ({"family": "graycode", "steps": "four", "fringes": [57]}, "steps"),
])
def test_bad_pattern_config_names_key(table: dict, key: str, tmp_path) -> None:
    with pytest.raises(ConfigError) as e:
        PatternSet.from_dict(table, tmp_path / "p.toml")
    assert e.value.key.split("[")[0] == key and "p.toml" in str(e.value)  # e.g. orientations[0]: the bad item


def test_patterns_are_gamma_compensated() -> None:
    ps = FAMILIES["heterodyne"]
    raw = ps.render(912, 1140, gamma=2.2)
    displayed = (raw[0, 0].astype(float) / 255) ** 2.2
    wanted = ps.profile(ps.frames()[0], 912)
    assert np.abs(displayed - wanted).max() < 0.02
