"""Pattern sets and decoding against analytic fringe stacks with known projector coordinates."""

from __future__ import annotations

import numpy as np
import pytest
from fringe_frames import fringe_stack

from scanner.decode import CHUNK_ROWS, DecodeSettings, decode, interreflection_slivers, small_regions
from scanner.errors import ConfigError, DecodeError
from scanner.patterns import PatternSet, gray_code, gray_to_binary

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


def rows_ramp(h: int = 640, w: int = 96) -> np.ndarray:
    """Projector rows seen by each pixel: rising down the image over most of the projector's
    height (as on a rig with a vertical baseline), slightly curved along each row."""
    return ramp(h=w, w=h).T * (1100 / 912)


def test_horizontal_fringes_decode_rows() -> None:
    ps = PatternSet("heterodyne", 4, (70.0, 64.0, 59.0), ("horizontal",))
    v = rows_ramp()
    d = decode(fringe_stack(v, ps, PROJ[1]), ps, 12, PROJ)
    assert np.nanmax(np.abs(d.maps["horizontal"].coordinate - v)) < 0.03


def test_both_orientations() -> None:
    ps = PatternSet("heterodyne", 4, (70.0, 64.0, 59.0), ("vertical", "horizontal"))
    u = ramp()
    v = 500.0 + 0.3 * (u - 450.0) + 2.0 * np.arange(u.shape[0])[:, None]  # rising down every column
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


@pytest.mark.parametrize("shape,fill", [((3 * CHUNK_ROWS + 17, 300), 0.55), ((CHUNK_ROWS, 90), 0.6),
                                        ((8 * CHUNK_ROWS, 400), 0.5)])
def test_small_regions_match_whole_image_labelling(shape: tuple[int, int], fill: float) -> None:
    """The spatial check's small regions, labelled band by band and joined across band edges,
    are those scipy's whole-image 4-connected labelling finds (regions snaking through many
    bands included)."""
    from scipy import ndimage

    rng = np.random.default_rng(shape[0])
    foreground = rng.random(shape) < fill
    foreground[:, ::9] = True  # long regions crossing every band edge
    labels, _ = ndimage.label(foreground)
    area = np.bincount(labels.ravel())
    for min_px in (2, 12, 400, foreground.size):
        assert np.array_equal(small_regions(foreground, min_px), foreground & (area[labels] < min_px))


def test_second_path_mask_matches_the_whole_image_rule(monkeypatch) -> None:
    """The banded interreflection tests mask exactly the pixels the rule, stated here on the
    whole image, masks: a frequency pair disagreeing beyond its image-wide median offset by
    more than min_rad and 5 sigma of the pair's noise, or a finest/coarsest modulation ratio
    departing from its image-wide median by more than 15 % and 5 sigma; medians over every
    k-th judged pixel in raster order (thinned here as on a full-size image). The stack has
    a patch lit also by a second path (20 %, 37 projector px away) across band edges."""
    from scanner.decode import _SecondPaths

    monkeypatch.setattr(_SecondPaths, "MEDIAN_SAMPLE", 5000)
    ps = FAMILIES["heterodyne"]
    u = ramp(3 * CHUNK_ROWS + 40, 640)
    stack = fringe_stack(u, ps, PROJ[0], amplitude=900.0, offset=1100.0, noise=6.0).astype(np.float64)
    second = fringe_stack(u + 37.0, ps, PROJ[0], amplitude=900.0, offset=1100.0, noise=6.0, seed=1)
    rows, cols = slice(100, 300), slice(200, 420)
    stack[:, rows, cols] += 0.2 * second[:, rows, cols]
    stack = np.rint(stack).astype(np.uint16)
    got = decode(stack, ps, 12, PROJ, DecodeSettings(spatial_check=False)).maps["vertical"].masks["interreflection"]
    m = decode(stack, ps, 12, PROJ, DecodeSettings(spatial_check=False, interreflection=False)).maps["vertical"]
    usable = ~(m.masks["saturated"] | m.masks["shadow"] | m.masks["low_modulation"])
    candidates = usable & ~m.masks["order_error"]
    s, f_max = DecodeSettings(), max(ps.fringes)
    sigma_b = m.noise.sigma(m.background) * np.float32(np.sqrt(2.0 / ps.steps))
    absolute, _ = ps.kind.unwrap(ps.fringes, m.wrapped)
    scaled = [a * np.float32(f_max / f) for a, f in zip(absolute, ps.fringes)]
    noise = [sigma_b / np.maximum(b, np.float32(1e-6)) * np.float32(f_max / f)
             for b, f in zip(m.modulation, ps.fringes)]

    def sample(judged: np.ndarray) -> np.ndarray:
        idx = np.flatnonzero(judged)
        return idx[:: max(1, idx.size // 5000)]

    want = np.zeros_like(candidates)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        dev = scaled[i] - scaled[j]
        dev = np.abs(dev - np.float32(np.median(dev.flat[sample(candidates)])))
        bound = np.maximum(np.hypot(noise[i], noise[j]) * np.float32(s.interreflection_sigmas),
                           np.float32(s.interreflection_min_rad))
        want |= candidates & (dev > bound)
    bf, bc = (np.maximum(m.modulation[k], np.float32(1e-6)) for k in (0, 2))  # finest 70, coarsest 59 fringes
    departure = np.log(bf / bc)
    departure = np.abs(departure - np.float32(np.median(departure.flat[sample(usable)])))
    sigma = sigma_b * np.sqrt(1.0 / bf ** 2 + 1.0 / bc ** 2)
    want |= usable & (departure > np.float32(np.log1p(s.interreflection_ratio))) & \
        (departure > np.float32(s.interreflection_sigmas) * sigma)
    outside = np.ones_like(want)
    outside[rows, cols] = False
    assert want[rows, cols].mean() > 0.5 and want[outside].mean() < 0.01  # the setup: the patch is judged
    assert np.array_equal(got, want)


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


def test_slivers_left_inside_an_interreflection_region_are_masked_and_nothing_else() -> None:
    """A second path that outshines the direct light leaves 1-2 px strips valid among the
    pixels it corrupts: those are masked; a strip as narrow but more than 2 px from any
    interreflection pixel, and a wide region touching one, keep every pixel."""
    valid = np.zeros((40, 60), bool)
    second = np.zeros_like(valid)
    second[:, 10:14] = second[:, 16:20] = True  # the masked region, a 2-px strip left valid in it
    valid[:, 14:16] = True                      # the sliver: columns 14, 15
    valid[:, 20:30] = True                      # a wide region beside the mask
    valid[:, 40:42] = True                      # a strip 20 px from any interreflection pixel
    expected = np.zeros_like(valid)
    expected[:, 14:16] = True
    assert np.array_equal(interreflection_slivers(valid, second, 2), expected)
    # a strip 3 px wide survives the opening: only narrower ones are slivers
    valid3 = valid.copy()
    valid3[:, 13] = True
    second3 = second.copy()
    second3[:, 13] = False
    assert not interreflection_slivers(valid3, second3, 2)[:, 13:16].any()
