"""A rig with two cameras, end to end on the simulator: the rig file's [[cameras]], every camera
rendered from its own pose with its own noise, captured together into one session
(frames/<camera>/...), decoded per camera, matched and triangulated; judged against the
simulator's per-camera ground truth. Small cameras (400 x 320) keep it to seconds."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from scanner.binocular_pipeline import process_binocular, scan_binocular
from scanner.binocular_session import camera_session, record
from scanner.config import CONFIG_DIR
from scanner.errors import ConfigError, FrameDropped, IncompleteSession
from scanner.patterns import PatternSet
from scanner.rig import RigConfig, open_rig
from scanner.session import Session
from sim.evaluate import Truth, smooth_region
from sim.stereo_bench import binocular_rig
from sim.stereo_truth import seen_by
from sim.virtual_devices import Faults

SCENE = CONFIG_DIR / "scenes" / "sphere_plane.toml"


def small_rig(tmp: Path, **edits: str) -> Path:
    return binocular_rig(tmp, 400, 320, edits=edits)


@pytest.fixture(scope="module")
def scanned(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    tmp = tmp_path_factory.mktemp("binocular")
    config = RigConfig.load(small_rig(tmp))
    seed = int(np.random.SeedSequence().entropy % 2 ** 31)
    print(f"seed {seed}")
    with open_rig(config, scene=SCENE, seed=seed) as rig:
        scan = scan_binocular(rig, PatternSet.load(config.patterns_path), tmp / "session", calibrated=True)
        truths = rig.extras["ground_truths"]
    return scan, truths


def test_the_session_holds_every_camera_and_decodes_again(scanned: tuple) -> None:
    scan, _ = scanned
    root = scan.session.root
    projector = scan.session.rig_model().projector.size  # the Gray code's bits follow the projector's width
    n = PatternSet.load(CONFIG_DIR / "patterns" / "slmaster_complementary_12x32.toml").for_projector(projector).n_frames
    for name in ("left", "right"):
        assert len(list((root / "frames" / name).glob("frame_*.png"))) == n
    manifest = json.loads((root / "manifest.json").read_text())
    assert manifest["cameras"] == ["left", "right"]
    assert manifest["stereo_model"]["names"] == ["left", "right"]
    session = Session.open(root)
    rec = record(session)
    assert rec.projector_calibrated
    right = camera_session(session, "right")
    assert right.load_stack().shape == (n, 320, 400)
    again = process_binocular(session)
    assert np.array_equal(np.isnan(again.result.cloud.points), np.isnan(scan.result.cloud.points))
    assert np.nanmax(np.abs(again.result.cloud.points - scan.result.cloud.points)) == 0.0
    figures = json.loads((root / "outputs" / "binocular.json").read_text())
    assert figures["calibration"]["included"] is False  # the rig file's nominal geometry states no covariance
    assert figures["calibration"]["term"].startswith("not included")
    header = (root / "outputs" / "cloud.ply").read_bytes()[:800].decode("latin-1")
    assert "unit: mm" in header and "frame: camera 'left'" in header


def test_depth_against_the_simulators_truth(scanned: tuple) -> None:
    """Over the left camera's smooth lit pixels that the right camera sees too, the depth error
    is no larger than the predicted noise from both cameras' decoded phase noise, and unbiased;
    points beyond 5 sigma elsewhere are below 0.1 % (one fringe orientation: a left point the
    right cannot see may match another surface, scanner/binocular.py); the camera-projector
    rays meet the binocular points (the projector's model is the simulator's truth here)."""
    scan, truths = scanned
    gt = Truth.of(truths["left"])
    cloud, sigma = scan.result.cloud, scan.result.depth_sigma_mm
    all_err = cloud.points[..., 2] - gt.depth
    beyond = cloud.valid & ~(np.abs(all_err) <= 5 * sigma)
    print(f"{beyond.sum()} of {cloud.valid.sum()} points beyond 5 sigma")
    assert beyond.sum() < 1e-3 * cloud.valid.sum()
    sel = smooth_region(gt) & cloud.valid & seen_by(truths['left'], truths['right'])
    err = (cloud.points[..., 2] - gt.depth)[sel].astype(np.float64)
    rms, pred = np.sqrt(np.mean(err ** 2)), np.sqrt(np.mean(sigma[sel].astype(np.float64) ** 2))
    print(f"depth error RMS {rms * 1e3:.2f} um over {sel.sum()} px, predicted {pred * 1e3:.2f} um; "
          f"{scan.result.checks}; three rays {scan.three_rays}")
    assert sel.sum() > 0.5 * gt.lit.sum()
    assert 0.5 * pred < rms <= 1.05 * pred
    assert abs(err.mean()) < 0.2 * rms
    assert abs(scan.three_rays["projector_residual_median_px"]) < 0.01


def test_a_dropped_frame_of_either_camera_leaves_an_incomplete_session(tmp_path: Path) -> None:
    config = RigConfig.load(small_rig(tmp_path))
    with open_rig(config, scene=SCENE, seed=1, faults=Faults(drop_frame=4)) as rig, pytest.raises(FrameDropped):
        scan_binocular(rig, PatternSet.load(config.patterns_path), tmp_path / "session")
    with pytest.raises(IncompleteSession):
        Session.open(tmp_path / "session")
    assert json.loads((tmp_path / "session" / "error.json").read_text())["stage"] == "capture"


def test_rig_files_with_cameras_are_checked(tmp_path: Path) -> None:
    assert RigConfig.load().camera_names == ("camera",)  # the one-camera file as it is
    bad = {
        "first camera": ('name = "left"\n', 'name = "left"\nposition_mm = [1.0, 0.0, 0.0]\n'),
        "repeat": ('name = "right"', 'name = "left"'),
        "need position_mm": ("position_mm = [200.0, 0.0, 0.0]   # in the left camera's frame", ""),
    }
    for why, (old, new) in bad.items():
        with pytest.raises(ConfigError, match=re.escape(why) if why != "repeat" else "repeat"):
            RigConfig.load(small_rig(tmp_path, **{old: new}))
    text = small_rig(tmp_path).read_text() + "\n[camera]\nwidth = 10\nheight = 10\nhfov_deg = 20.0\n"
    (tmp_path / "both.toml").write_text(text)
    with pytest.raises(ConfigError, match="one of them"):
        RigConfig.load(tmp_path / "both.toml")
