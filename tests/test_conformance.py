"""One interface contract, run against the simulated devices and the real drivers on fake
transports: what acquisition relies on must hold for every camera, projector and
trigger source alike."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
from test_session import SCENE, small_rig_toml

from scanner.devices import Camera, Projector, TriggerSource, TriggerType
from scanner.drivers.genicam import GenICamCamera
from scanner.drivers.hdmi import HdmiDisplay, HdmiProjector
from scanner.drivers.lightcrafter import LightCrafter4500
from scanner.drivers.lightcrafter_images import diamond_resample, fingerprint, pack_rgb24
from scanner.drivers.testing import Dlpc350Emulator, FakeAcquirer, FakeCapture, FakeDisplay, TriggerBoxEmulator
from scanner.drivers.triggerbox import TriggerBox
from scanner.drivers.uvc import UvcCamera
from scanner.errors import DeviceDisconnected, DeviceError, DeviceTimeout, UnsupportedSetting
from scanner.rig import RigConfig, open_rig
from sim.virtual_devices import SimProjector, SimTriggerBox

PATTERNS = np.stack([np.full((1140, 912), v, np.uint8) for v in (0, 60, 120, 180)])


@pytest.fixture(params=["sim", "uvc", "genicam"])
def camera(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Camera]:
    if request.param == "sim":
        rig = open_rig(RigConfig.load(small_rig_toml(tmp_path, trigger="software")), scene=SCENE)
        rig.camera.set_trigger(TriggerType.SOFTWARE)
        yield rig.camera
        rig.shutdown()
        return
    if request.param == "uvc":
        cam: Camera = UvcCamera(lambda: FakeCapture(lambda t: np.zeros((48, 64, 3), np.uint8), fps=200), "uvc",
                                64, 48, fps=200)
    else:
        acq = FakeAcquirer(lambda t: np.zeros((48, 64), np.uint8), 64, 48)
        cam = GenICamCamera(lambda: (acq, acq.close), "genicam", 64, 48)
    yield cam
    cam.shutdown()


@pytest.fixture(params=["sim", "lightcrafter4500", "hdmi"])
def projector(request: pytest.FixtureRequest) -> Iterator[Projector]:
    if request.param == "sim":
        proj: Projector = SimProjector("sim-projector", 912, 1140)
    elif request.param == "lightcrafter4500":
        proj = LightCrafter4500(Dlpc350Emulator, flash_images_sha256=fingerprint(pack_rgb24(diamond_resample(PATTERNS))))
    else:
        proj = HdmiProjector(HdmiDisplay(FakeDisplay((912, 1140), 500.0), "hdmi", 500.0, 1))
    yield proj
    proj.shutdown()


@pytest.fixture(params=["sim", "triggerbox"])
def trigger_source(request: pytest.FixtureRequest) -> Iterator[TriggerSource]:
    box: TriggerSource = SimTriggerBox() if request.param == "sim" else TriggerBox(TriggerBoxEmulator)
    yield box
    box.shutdown()


# ------------------------------------------------------------------------------ cameras


def test_camera_software_sequence(camera: Camera) -> None:
    camera.arm(3)
    last = -np.inf
    for k in range(3):
        camera.trigger()
        f = camera.grab(2.0)
        assert f.index == k and f.image.shape == (camera.height, camera.width) and f.bit_depth == camera.bit_depth
        assert f.timestamp_s > last and int(f.image.max(initial=0)) < 2 ** f.bit_depth
        last = f.timestamp_s
    with pytest.raises(DeviceError, match="software trigger refused"):
        camera.trigger()
    camera.disarm()


def test_camera_wait_is_bounded(camera: Camera) -> None:
    camera.arm(1)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=camera.name):
        camera.grab(0.2)
    assert time.monotonic() - t0 < 1.0
    with pytest.raises(ValueError, match="finite"):
        camera.grab(0)


def test_camera_refuses_bad_settings(camera: Camera) -> None:
    with pytest.raises(UnsupportedSetting, match="bit depth 3"):
        camera.set_bit_depth(3)
    with pytest.raises(UnsupportedSetting, match="exposure"):
        camera.set_exposure(1e4)
    with pytest.raises(ValueError):
        camera.arm(0)
    assert {"name", "type", "width", "height", "bit_depth", "exposure_s"} <= set(camera.describe())


def test_camera_shutdown_is_idempotent_and_final(camera: Camera) -> None:
    camera.shutdown()
    camera.shutdown()
    camera.disarm()  # harmless after shutdown
    with pytest.raises(DeviceDisconnected):
        camera.arm(1)


# ---------------------------------------------------------------------------- projectors


def test_projector_shows_loaded_patterns(projector: Projector) -> None:
    with pytest.raises(UnsupportedSetting, match="patterns must be uint8"):
        projector.load_patterns(PATTERNS[:, :100])
    with pytest.raises(UnsupportedSetting, match="patterns must be uint8"):
        projector.load_patterns(PATTERNS.astype(np.uint16))
    projector.load_patterns(PATTERNS)
    assert projector.n_patterns == 4 and projector.current_pattern is None
    projector.show(2)
    assert projector.current_pattern == 2
    with pytest.raises(ValueError, match="out of range"):
        projector.show(4)
    projector.blank()
    assert projector.current_pattern is None
    projector.stop_sequence()  # harmless when nothing runs


def test_projector_sequence_needs_patterns(projector: Projector) -> None:
    with pytest.raises(UnsupportedSetting, match="no patterns loaded"):
        projector.run_sequence(0.05)


def test_projector_shutdown_is_idempotent_and_final(projector: Projector) -> None:
    projector.shutdown()
    projector.shutdown()
    projector.stop_sequence()
    with pytest.raises(DeviceDisconnected):
        projector.load_patterns(PATTERNS)


# ----------------------------------------------------------------------- trigger sources


def test_trigger_source_runs_a_pulse_train(trigger_source: TriggerSource) -> None:
    with pytest.raises(UnsupportedSetting):
        trigger_source.arm(3, 0.01, 0.02)  # width not below period
    trigger_source.arm(3, 0.01)
    trigger_source.start()
    end = time.monotonic() + 1.0
    while trigger_source.pulses_sent < 3 and time.monotonic() < end:
        time.sleep(0.01)
    assert trigger_source.pulses_sent == 3
    trigger_source.stop()


def test_trigger_source_shutdown_is_idempotent_and_final(trigger_source: TriggerSource) -> None:
    trigger_source.shutdown()
    trigger_source.shutdown()
    trigger_source.stop()
    with pytest.raises(DeviceDisconnected):
        trigger_source.arm(1, 0.01)
