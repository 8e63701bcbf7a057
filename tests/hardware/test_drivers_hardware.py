"""The conformance checks and a full scan on the real rig named with --rig (see conftest).
Skipped, with the reason, when no rig is given or its devices cannot be opened."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from scanner.errors import DeviceError
from scanner.patterns import PatternSet
from scanner.pipeline import capture
from scanner.rig import Rig, RigConfig, open_rig
from scanner.session import SessionWriter


@pytest.fixture(scope="module")
def rig(hardware_rig_path: Path) -> Iterator[Rig]:
    config = RigConfig.load(hardware_rig_path)
    if config.driver != "hardware":
        pytest.skip(f"{hardware_rig_path} is not a hardware rig (driver '{config.driver}')")
    try:
        opened = open_rig(config)
    except DeviceError as exc:
        pytest.skip(f"hardware test: devices of {hardware_rig_path} not available: {exc}")
    yield opened
    opened.shutdown()


def test_camera_grabs_software_triggered_frames(rig: Rig) -> None:
    from scanner.devices import TriggerType

    previous = rig.camera.trigger_type
    rig.camera.set_trigger(TriggerType.SOFTWARE)
    try:
        rig.camera.arm(2)
        frames = []
        for _ in range(2):
            rig.camera.trigger()
            frames.append(rig.camera.grab(rig.config.timeout_s))
        assert [f.index for f in frames] == [0, 1] and frames[1].timestamp_s > frames[0].timestamp_s
        assert frames[0].image.shape == (rig.camera.height, rig.camera.width)
    finally:
        rig.camera.disarm()
        rig.camera.set_trigger(previous)


def test_trigger_source_counts_its_pulses(rig: Rig) -> None:
    if rig.trigger is None:
        pytest.skip("hardware test: this rig has no trigger box")
    from scanner.drivers.testing import wait_bound_s

    rig.trigger.arm(5, 0.01)
    rig.trigger.start().wait(wait_bound_s(0.05))
    assert rig.trigger.pulses_sent == 5


def test_full_capture_passes_every_synchronisation_check(rig: Rig, tmp_path: Path) -> None:
    patterns = PatternSet.load(rig.config.patterns_path)
    session = capture(rig, patterns, SessionWriter.create(tmp_path / "s"))
    assert len(session.manifest.frames) == patterns.n_frames
