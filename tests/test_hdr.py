"""Automatic exposure and multi-exposure (HDR) capture: the exposure request, the choice from a
pre-capture, per-pixel fusion, and HDR sessions on the simulated rig (manifest, every frame kept,
bit-identical re-decode).

Truths used: coverage recomputed here from the linear camera model, synthetic fringe stacks of
known coordinate at known exposures, and the session's own raw frames decoded again.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from scanner.config import CONFIG_DIR
from scanner.decode import decode
from scanner.errors import ConfigError, DecodeError, SessionError
from scanner.exposure import (
    GOOD_MODULATION,
    SATURATION_LEVEL,
    ExposureRequest,
    Probe,
    candidate_exposures,
    choose_exposures,
    fuse,
    plan_exposures,
)
from scanner.patterns import PatternSet
from scanner.pipeline import check_frames_fit, decode_session, exposure_stacks, reprocess, scan
from scanner.rig import RigConfig, open_rig
from scanner.session import Session
from slscan.measurement_model import session_uncertainty

HETERODYNE = CONFIG_DIR / "patterns" / "heterodyne_3x4.toml"
FULL = 4095.0


# --- the request -------------------------------------------------------------------------------

def test_request_parsing():
    assert ExposureRequest.parse("auto").mode == "auto"
    r = ExposureRequest.parse("0.064,0.004,0.016", "10,20,300,200")
    assert (r.mode, r.exposures_s, r.roi) == ("given", (0.004, 0.016, 0.064), (10, 20, 300, 200))
    for bad in ("fast", "0.01,-1", "0.01,0.01", "nan", ""):
        with pytest.raises(ConfigError, match="--exposure"):
            ExposureRequest.parse(bad)
    with pytest.raises(ConfigError, match="--exposure-roi"):
        ExposureRequest.parse("hdr", "1,2,3")


# --- the choice from a pre-capture ---------------------------------------------------------------

def synthetic_probe(exposure_s: float = 0.01, seed: int = 0) -> tuple[Probe, np.ndarray]:
    """A probe of a scene whose projector light spans 3 decades (DN/s per pixel), fringe
    contrast 0.8, clipped at full scale like a camera."""
    rng = np.random.default_rng(seed)
    rate = 10 ** rng.uniform(3.5, 6.5, size=(60, 80))  # DN/s of projector light
    black = np.full_like(rate, 20.0)
    white = np.minimum(black + rate * exposure_s, FULL)
    phase = rng.uniform(0, 2 * np.pi, rate.shape)
    fringe = np.minimum(black + rate * exposure_s * (0.5 + 0.4 * np.cos(phase)), FULL)
    return Probe(white.astype(np.float32), black.astype(np.float32), fringe.astype(np.float32), exposure_s, FULL), rate


def covered_at(rate: np.ndarray, t: float, contrast: float = 0.8) -> np.ndarray:
    """Independent statement of coverage: peak below saturation, modulation at least GOOD."""
    return (20.0 + rate * t < SATURATION_LEVEL * FULL) & (contrast * rate * t / 2 >= GOOD_MODULATION * FULL)


def test_auto_picks_the_exposure_covering_most_pixels():
    probe, rate = synthetic_probe(exposure_s=1e-3)  # nothing saturates; the ROI spans ~2 decades
    roi = probe.roi(None)
    rate = rate[roi]
    plan = choose_exposures(probe, "auto", (1e-4, 0.1))
    grid = candidate_exposures(1e-4, 0.1)
    best = max(covered_at(rate, t).mean() for t in grid)
    assert len(plan.exposures_s) == 1
    assert covered_at(rate, plan.exposures_s[0]).mean() >= best - 0.01
    assert "auto" in plan.reason and "projector brightness" in plan.reason


def test_hdr_covers_the_dynamic_range_a_single_exposure_cannot():
    probe, rate = synthetic_probe(exposure_s=1e-3)
    rate = rate[probe.roi(None)]
    plan = choose_exposures(probe, "hdr", (1e-4, 0.1))
    assert 2 <= len(plan.exposures_s) <= 4 and list(plan.exposures_s) == sorted(plan.exposures_s)
    union = np.logical_or.reduce([covered_at(rate, t) for t in plan.exposures_s])
    single = max(covered_at(rate, t).mean() for t in candidate_exposures(1e-4, 0.1))
    assert union.mean() > 0.9 and union.mean() > single + 0.4  # four exposures at most (HDR_MAX_EXPOSURES)
    assert plan.predicted_coverage == pytest.approx(union.mean(), abs=0.02)


def test_saturated_probe_is_repeated_shorter():
    _, rate = synthetic_probe()
    taken: list[float] = []

    def capture_probe(t: float) -> np.ndarray:
        taken.append(t)
        white = np.minimum(20.0 + rate * t, FULL)
        return np.stack([white, np.full_like(rate, 20.0), np.minimum(20.0 + rate * t * 0.5, FULL)])

    plan = plan_exposures(ExposureRequest("hdr"), capture_probe, 0.05, (1e-5, 0.2), FULL)
    assert taken[0] == 0.05 and len(taken) >= 2 and taken[1] == pytest.approx(0.05 / 8)
    assert plan.probe_captures == len(taken)
    given = plan_exposures(ExposureRequest.parse("0.004,0.016"), capture_probe, 0.05, (1e-5, 0.2), FULL)
    assert given.exposures_s == [0.004, 0.016] and len(taken) == plan.probe_captures
    with pytest.raises(ConfigError, match="outside the camera's range"):
        plan_exposures(ExposureRequest.parse("0.5"), capture_probe, 0.05, (1e-5, 0.2), FULL)


# --- fusion --------------------------------------------------------------------------------------

def fringe_stack(ps: PatternSet, u: np.ndarray, rate: np.ndarray, t: float, seed: int) -> np.ndarray:
    """Frames of coordinate `u` (H, W) at light `rate` (DN/s) and exposure t, shot noise
    (gain 2.5 e/DN) and clipping like the simulated camera."""
    rng = np.random.default_rng(seed)
    extent = 912
    out = []
    for spec in ps.frames():
        prof = np.interp(u, np.arange(extent), ps.profile(spec, extent))
        mean_e = (40.0 + rate * t * prof) * 2.5
        out.append(np.clip(np.rint(rng.poisson(mean_e) / 2.5), 0, FULL))
    return np.stack(out).astype(np.uint16)


def test_fusion_takes_each_pixel_from_its_best_exposure():
    ps = PatternSet.load(HETERODYNE)
    u = np.broadcast_to(np.linspace(20, 890, 240), (64, 240))
    rate = np.where(np.arange(64)[:, None] < 32, 4.0e5, 1.0e4) * np.ones((1, 240))  # bright top, dark bottom
    exposures = (0.004, 0.064)
    results = [decode(fringe_stack(ps, u, rate, t, i), ps, 12, (912, 1140)) for i, t in enumerate(exposures)]
    short, long_ = (r.maps["vertical"] for r in results)
    top, bottom = np.zeros((64, 240), bool), np.zeros((64, 240), bool)
    top[:32], bottom[32:] = True, True
    assert short.masks["saturated"].sum() == 0 and long_.masks["saturated"][top].all()  # the setup
    assert long_.valid[bottom].mean() > 0.99
    fused = fuse(results, exposures)
    m = fused.maps["vertical"]
    assert np.all(m.exposure_index[top] == 0) and np.mean(m.exposure_index[bottom] == 1) > 0.99
    assert m.valid.mean() >= max(short.valid.mean(), long_.valid.mean())
    err = np.abs(m.coordinate - u)[m.valid]
    assert np.max(err) < 0.5
    chosen_sigma = np.where(m.exposure_index == 0, short.phase_sigma, long_.phase_sigma)
    assert np.array_equal(m.phase_sigma, chosen_sigma, equal_nan=True)
    assert np.nanmedian(m.phase_sigma[bottom]) < np.nanmedian(np.where(short.valid, short.phase_sigma, np.nan)[bottom])


def test_fusion_keeps_a_second_path_seen_by_any_exposure_masked():
    """A patch lit also by a second path (15 % of the direct light, 37 projector px away): the
    long exposure resolves it and masks it as interreflection; the short one is too noisy to and
    passes half of it as valid. The fused maps must not take those pixels from the short one."""
    ps = PatternSet.load(HETERODYNE)
    u = np.broadcast_to(np.linspace(20, 850, 240), (64, 240))
    patch = np.zeros((64, 240), bool)
    patch[16:48, 60:180] = True
    exposures = (0.004, 0.064)
    results = []
    for i, t in enumerate(exposures):
        rng = np.random.default_rng(i)
        frames = []
        for spec in ps.frames():
            profile = ps.profile(spec, 912)
            light = np.interp(u, np.arange(912), profile) + np.where(patch, 0.15 * np.interp(u + 37, np.arange(912),
                                                                                             profile), 0.0)
            frames.append(np.clip(np.rint(rng.poisson((40.0 + 3e4 * t * light) * 2.5) / 2.5), 0, FULL))
        results.append(decode(np.stack(frames).astype(np.uint16), ps, 12, (912, 1140)))
    short, long_ = (r.maps["vertical"] for r in results)
    assert long_.masks["saturated"].sum() == 0 and long_.masks["interreflection"][patch].mean() > 0.95  # the setup
    assert short.masks["interreflection"][patch].mean() < 0.05 and short.valid[patch].mean() > 0.3
    m = fuse(results, exposures).maps["vertical"]
    seen = short.masks["interreflection"] | long_.masks["interreflection"]
    assert not (m.valid & seen).any()
    assert m.masks["interreflection"][seen].all() and np.all(m.exposure_index[long_.masks["interreflection"]] == 1)
    assert np.array_equal(m.valid & ~seen, (short.valid | long_.valid) & ~seen)  # elsewhere the best valid exposure
    assert np.max(np.abs(m.coordinate - u)[m.valid & ~patch]) < 0.5


# --- sessions on the simulated rig ------------------------------------------------------------------

def loaded_rig(tmp_path: Path, small: bool = False) -> Path:
    """The bench rig with a frame timeout generous enough for a heavily loaded machine
    (`small`: a 320 x 256 camera, same field of view)."""
    text = (CONFIG_DIR / "rigs" / "sim_bench.toml").read_text()
    text = text.replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
    text = text.replace("timeout_s = 2.0", "timeout_s = 30.0")
    if small:
        text = text.replace("width = 1280", "width = 320").replace("height = 1024", "height = 256")
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.acceptance  # issue 18's figure: an HDR session re-decodes bit-identically
def test_hdr_session_keeps_every_exposure_and_redecodes_bit_identically(tmp_path):
    config = RigConfig.load(loaded_rig(tmp_path))
    patterns = PatternSet.load(config.patterns_path)
    with open_rig(config, scene=CONFIG_DIR / "scenes" / "sphere_plane.toml", seed=1) as rig:
        result = scan(rig, patterns, tmp_path / "s", exposure=ExposureRequest.parse("0.004,0.016"))
    session = Session.open(tmp_path / "s")
    n = patterns.n_frames
    assert session.exposures_s == (0.004, 0.016)
    frames = session.manifest.frames
    assert len(frames) == 2 * n and {f.exposure_s for f in frames[:n]} == {0.004}
    assert {f.exposure_s for f in frames[n:]} == {0.016}
    outputs = session.outputs
    with np.load(outputs / "maps.npz") as z:
        index = z["vertical/exposure_index"]
        assert set(np.unique(index)) == {0, 1}  # the bright plane from 4 ms (16 ms clips it), the rest from 16 ms
        assert np.isfinite(z["vertical/phase_sigma"][z["valid"]]).all()
    before = {name: digest(outputs / name) for name in ("maps.npz", "cloud.ply")}
    assert result.decoded.valid.mean() > 0.5
    reprocess(Session.open(tmp_path / "s"))
    assert {name: digest(outputs / name) for name in before} == before
    # a manifest whose frame list lost an exposure is refused, naming the count
    manifest = json.loads((tmp_path / "s" / "manifest.json").read_text())
    manifest["frames"] = manifest["frames"][:n]
    (tmp_path / "s" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(SessionError, match="x 2 exposures"):
        Session.open(tmp_path / "s").load_stack()


def test_hdr_session_uncertainty_is_each_pixels_own_exposures(tmp_path):
    """The measurement model of an HDR session (what `slscan inspect SESSION` uses) decodes
    every exposure and fuses them as the scan did (it gave the whole stack to one decode and
    raised), and each point's depth noise is the one its chosen exposure's own decode predicts."""
    config = RigConfig.load(loaded_rig(tmp_path, small=True))
    patterns = PatternSet.load(config.patterns_path)
    with open_rig(config, scene=CONFIG_DIR / "scenes" / "sphere_plane.toml", seed=3) as rig:
        result = scan(rig, patterns, tmp_path / "s", exposure=ExposureRequest.parse("0.004,0.016"))
    session = Session.open(tmp_path / "s")
    again = decode_session(session)
    m = again.maps["vertical"]
    assert np.array_equal(m.coordinate, result.decoded.maps["vertical"].coordinate, equal_nan=True)
    rows, cols = np.nonzero(result.cloud.valid)
    pixels = np.stack([cols, rows], axis=1)
    index = m.exposure_index[rows, cols]
    assert set(np.unique(index)) == {0, 1}  # the bright plane from 4 ms, the sphere mostly from 16 ms
    sigma = session_uncertainty(session)(pixels).noise.sigma_z
    assert np.array_equal(sigma, session_uncertainty(session, result.decoded)(pixels).noise.sigma_z)
    model = session.rig_model()
    stacks = exposure_stacks(session, session.load_stack(), model)
    for i, stack in enumerate(stacks):  # each exposure decoded alone: the uncertainty its own scan would give
        own = decode(stack, patterns, session.bit_depth, model.projector.size)
        chosen = index == i
        assert own.valid[rows[chosen], cols[chosen]].all()
        expected = session_uncertainty(session, own)(pixels[chosen]).noise.sigma_z
        np.testing.assert_allclose(sigma[chosen], expected, rtol=1e-6)
    # a blank frame in the second exposure is named by its place in the session
    blank = stacks[1].copy()
    blank[3] = 100
    with pytest.raises(DecodeError, match=f"frame {patterns.n_frames + 3} .* is blank"):
        check_frames_fit(session, blank, model, patterns.n_frames)


def test_auto_exposure_capture_records_its_choice(tmp_path):
    """`--exposure auto` on the simulated rig (320 x 256 camera): the pre-capture's choice and
    reason are in the manifest and the frames are taken at the chosen exposure."""
    config = RigConfig.load(loaded_rig(tmp_path, small=True))
    patterns = PatternSet.load(config.patterns_path)
    with open_rig(config, scene=CONFIG_DIR / "scenes" / "sphere_plane.toml", seed=2) as rig:
        scan(rig, patterns, tmp_path / "s", exposure=ExposureRequest.parse("auto"))
    session = Session.open(tmp_path / "s")
    record = session.manifest.exposure
    assert record is not None and record.mode == "auto" and len(record.exposures_s) == 1 and "cover" in record.reason
    assert {f.exposure_s for f in session.manifest.frames} == set(record.exposures_s)
    assert record.predicted_coverage is not None and record.predicted_coverage > 0.9
    assert session.manifest.timings_s["exposure_plan"] > 0

