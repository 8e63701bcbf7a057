"""`slscan devices`: the listing (on a machine without the devices) and the LightCrafter
flash-image export whose fingerprint the driver then accepts."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from session_support import SCENE, small_rig_toml

from scanner.config import CONFIG_DIR
from scanner.drivers.lightcrafter import LightCrafter4500
from scanner.drivers.testing import Dlpc350Emulator
from scanner.patterns import PatternSet
from scanner.rig import RigConfig
from slscan import cli
from slscan.commands import devices

LCR = CONFIG_DIR / "rigs" / "lightcrafter_uvc_box.toml"


def test_devices_lists_every_kind_and_says_what_is_missing(capsys: pytest.CaptureFixture,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(devices.os, "access", lambda path, mode: False)
    monkeypatch.setattr(devices.glob, "glob", lambda pattern: ["/dev/video7"])
    assert cli.main(["devices"]) == 0
    out = capsys.readouterr().out
    for title in ("cameras (V4L2):", "GenICam cameras:", "USB projectors:", "displays:", "serial ports:"):
        assert title in out
    assert "/dev/video7" in out and "sudo usermod -aG video $USER" in out
    assert "--cti <producer.cti>" in out


def test_lightcrafter_images_fingerprint_is_accepted_by_the_driver(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture) -> None:
    assert cli.main(["devices", "lightcrafter-images", "--rig", str(LCR), "--out", str(tmp_path / "img")]) == 0
    out = capsys.readouterr().out
    sha = out.split('flash_images_sha256 = "')[1].split('"')[0]
    assert sorted(p.name for p in (tmp_path / "img").iterdir()) == [
        "flash_images.json", "slscan_00.bmp", "slscan_01.bmp", "slscan_02.bmp", "slscan_03.bmp"]
    config = RigConfig.load(LCR)
    patterns = PatternSet.load(config.patterns_path).render(912, 1140, config.nominal_model().projector_gamma)
    lcr = LightCrafter4500(Dlpc350Emulator, flash_images_sha256=sha)
    lcr.load_patterns(patterns)  # the same fingerprint: accepted
    lcr.shutdown()
    import cv2

    bmp = cv2.imread(str(tmp_path / "img" / "slscan_00.bmp"), cv2.IMREAD_UNCHANGED)
    assert bmp.shape == (1140, 912, 3) and np.array_equal(bmp[0, :, 1], patterns[0, 0])  # pattern 0 in green


@pytest.mark.parametrize("argv, level", [
    (["devices"], logging.WARNING),
    (["-v", "devices"], logging.INFO),
    (["devices", "-vv"], logging.DEBUG),
    (["--log-level", "error", "devices"], logging.ERROR),
    (["-vv", "devices", "--log-level", "info"], logging.INFO),  # the level named wins over the count
])
def test_log_level_options(argv: list[str], level: int) -> None:
    assert cli.log_level(cli.build_parser().parse_args(argv)) == level


def test_device_life_cycle_is_logged_per_module(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from scanner.rig import open_rig

    caplog.set_level(logging.DEBUG)
    with open_rig(RigConfig.load(small_rig_toml(tmp_path, trigger="projector")), scene=SCENE) as rig:
        rig.projector.load_patterns(np.zeros((2, rig.projector.height, rig.projector.width), np.uint8))
        rig.projector.run_sequence(0.01).wait(5.0)
    by_module = {(r.name, r.levelname) for r in caplog.records}
    assert {("sim.virtual_rig", "INFO"), ("sim.virtual_devices", "INFO"), ("scanner.devices", "INFO"),
            ("scanner.status", "DEBUG")} <= by_module
    messages = [r.getMessage() for r in caplog.records]
    assert "sim-projector: sequence of 2 patterns every 0.01 s started" in messages
    assert "sim-camera: shut down" in messages and "sim-projector: shut down" in messages
