"""`slscan import LEFT RIGHT`: a binocular capture rendered as SLMaster makes one (its 12-step phase
+ complementary Gray-code rows from sim/foreign_patterns.py, written from SLMaster's formulas and
shown without gamma pre-compensation on a 1920 x 1080 projector, 8-bit BMP frames named 1.bmp ..
18.bmp), with the stereo calibration as SLMaster writes it (caliInfo.yml: M1/D1, M2/D2, Rlr/Tlr,
S, R1/R2/P1/P2/Q), imported with config/patterns/slmaster_complementary_12x32.toml (its
conventions given, checked against each camera's frames); the cloud judged against the
simulator's truth. (Left to be detected, the phase origin and pixel centre are refused as
ambiguous at this camera size: the Gray-code edges of uncompensated fringes seen 5 projector
pixels to a camera pixel; scanner/convention_detection.py.) Cameras at 400 x 320 keep it to seconds."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from scanner.config import CONFIG_DIR
from scanner.errors import CalibrationFileError, SessionError
from scanner.pointcloud import read_ply_pixels
from scanner.rig import RigConfig, open_rig
from sim.evaluate import Truth, smooth_region
from sim.foreign_patterns import slmaster_complementary
from sim.stereo_bench import binocular_rig, render_rows, write_slmaster_caliinfo
from sim.stereo_truth import seen_by
from slscan.commands.import_binocular import import_binocular

SCENE = CONFIG_DIR / "scenes" / "sphere_plane.toml"
PATTERNS = CONFIG_DIR / "patterns" / "slmaster_complementary_12x32.toml"


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    tmp = tmp_path_factory.mktemp("slmaster_bino")
    config = RigConfig.load(binocular_rig(tmp, 400, 320, projector=(1920, 1080, 1.0)))
    seed = int(np.random.SeedSequence().entropy % 2 ** 31)
    print(f"seed {seed}")
    rows = slmaster_complementary(1920)
    with open_rig(config, scene=SCENE, seed=seed) as rig:
        stacks = render_rows(rig, rows, 8, np.random.default_rng(seed))
        truths = rig.extras["ground_truths"]
    folders = []
    for name, stack in stacks.items():
        folder = tmp / name
        folder.mkdir()
        for k, frame in enumerate(stack):
            cv2.imwrite(str(folder / f"{k + 1}.bmp"), frame)
        folders.append(folder)
    calib = write_slmaster_caliinfo(tmp / "caliInfo.yml", config.stereo_model(nominal=True), (400, 320))
    return tmp, folders, calib, PATTERNS, truths


def test_the_imported_cloud_against_the_truth(capture: tuple) -> None:
    tmp, folders, calib, patterns, truths = capture
    scan, detections = import_binocular(folders, patterns, (1920, 1080), tmp / "session", [calib])
    found = {f.key: f.value for f in detections[0].findings}
    print(found)
    assert found["phase_origin"] == pytest.approx(-np.pi) and found["gray_code"] == "complementary"
    assert {f.key: f.source for f in detections[0].findings}["phase_origin"] == "given"
    stored = read_ply_pixels(scan.cloud_path)
    assert stored is not None
    points, pixels = stored.points, stored.pixels
    header = scan.cloud_path.read_bytes()[:1000].decode("latin-1")
    assert "frame: camera 'left', unit: mm" in header
    gt = Truth.of(truths["left"])
    depth = np.full(gt.depth.shape, np.nan)
    depth[pixels[:, 1], pixels[:, 0]] = points[:, 2]
    region = smooth_region(gt) & seen_by(truths["left"], truths["right"])
    sel = region & np.isfinite(depth)
    err = (depth - gt.depth)[sel]
    sigma = scan.result.depth_sigma_mm[sel]
    rms, bound = float(np.sqrt(np.mean(err ** 2))), float(np.sqrt(np.mean(sigma.astype(np.float64) ** 2)))
    print(f"imported cloud: depth error RMS {rms * 1e3:.1f} um (predicted {bound * 1e3:.1f}) over {sel.sum()} px, "
          f"mean {err.mean() * 1e3:+.2f} um, {sel.sum() / region.sum():.3f} of the region; {scan.result.checks}")
    # the fringes are shown without gamma compensation: their harmonics must not read as noise (the gradient
    # gate, whose steps are here >10 sigma, would refuse them)
    assert sel.sum() > 0.95 * region.sum()
    assert scan.result.checks["low_gradient"] < 1e-3 * scan.result.checks["pixels_with_coordinate"]
    assert rms <= 1.1 * bound and abs(err.mean()) < 0.2 * rms
    assert rms < 0.03  # the real noise: both cameras' 8-bit frames of 60 px fringe periods
    beyond = np.isfinite(depth) & ~(np.abs(depth - gt.depth) <= 5 * scan.result.depth_sigma_mm)
    assert beyond.sum() < 2e-3 * np.isfinite(depth).sum()


def test_what_the_binocular_import_refuses(capture: tuple) -> None:
    tmp, folders, calib, patterns, _ = capture
    with pytest.raises(SessionError, match="needs the stereo calibration"):
        import_binocular(folders, patterns, (1920, 1080), tmp / "s1", [])
    short = tmp / "short"
    short.mkdir()
    for f in sorted(folders[1].iterdir())[:-1]:
        (short / f.name).write_bytes(f.read_bytes())
    with pytest.raises(SessionError, match="holds 18 frames, .* 17"):
        import_binocular([folders[0], short], patterns, (1920, 1080), tmp / "s2", [calib])
    mono = tmp / "mono.yml"
    fs = cv2.FileStorage(str(mono), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", np.eye(3))
    fs.release()
    with pytest.raises(CalibrationFileError, match="key 'D1' missing"):
        import_binocular(folders, patterns, (1920, 1080), tmp / "s3", [mono])
