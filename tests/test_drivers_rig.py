"""The `hardware` rig driver on fake transports: the example rig TOMLs open with the right
devices and wiring, impossible wirings are refused naming the key, and a whole
acquisition runs through an HDMI projector and a GenICam camera."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from driver_rigs import LCR, lcr_transports, variant

from scanner.acquisition import AcquisitionSettings, acquire, acquire_images
from scanner.config import CONFIG_DIR
from scanner.devices import TriggerType
from scanner.drivers.genicam import GenICamCamera
from scanner.drivers.hdmi import HdmiProjector
from scanner.drivers.lightcrafter import LightCrafter4500
from scanner.drivers.testing import FakeAcquirer, FakeCapture, FakeDisplay
from scanner.drivers.triggerbox import TriggerBox
from scanner.drivers.uvc import UvcCamera
from scanner.errors import ConfigError
from scanner.patterns import PatternSet
from scanner.rig import open_rig

HDMI = CONFIG_DIR / "rigs" / "hdmi_genicam.toml"


def test_lightcrafter_uvc_example_opens_with_software_wiring(tmp_path: Path) -> None:
    with open_rig(variant(tmp_path, LCR), transports=lcr_transports()) as rig:
        assert isinstance(rig.projector, LightCrafter4500) and isinstance(rig.camera, UvcCamera)
        assert rig.trigger is None and rig.camera.trigger_type is TriggerType.SOFTWARE
        assert rig.projector.trigger == "internal" and rig.model.projector.width == 912


def test_lightcrafter_with_trigger_box_and_genicam(tmp_path: Path) -> None:
    config = variant(tmp_path, LCR, ('trigger = "software"', 'trigger = "trigger_box"'),
                     ('driver = "uvc"', 'driver = "genicam"\ncti = "/x.cti"'),
                     ("exposure_s = 0.02", "exposure_s = 0.05"))
    with open_rig(config, transports=lcr_transports(FakeAcquirer(lambda t: np.zeros((720, 1280), np.uint8), 1280,
                                                                 720))) as rig:
        assert isinstance(rig.trigger, TriggerBox) and rig.projector.trigger == "external"
        assert isinstance(rig.camera, GenICamCamera) and rig.camera.trigger_type is TriggerType.RISING_EDGE


@pytest.mark.parametrize("source, edits, key, message", [
    (LCR, [('trigger = "software"', 'trigger = "projector"')], "rig.trigger", "UVC camera has no trigger input"),
    (HDMI, [('trigger = "projector"', 'trigger = "trigger_box"'), ('driver = "genicam"', 'driver = "genicam"')],
     "rig.trigger", "HDMI projector has no trigger input"),
    (LCR, [('source = "flash"', 'source = "video"'), ('driver = "uvc"', 'driver = "genicam"\ncti = "/x.cti"'),
           ('trigger = "software"', 'trigger = "projector"')], "rig.trigger", "video port runs wiring 'software'"),
    (LCR, [("width = 912", "width = 1024")], "projector.width", "DMD is 912x1140"),
    (LCR, [('exposure_s = 0.02', 'exposure_s = 0.2'), ('trigger = "software"', 'trigger = "trigger_box"'),
           ('driver = "uvc"', 'driver = "genicam"\ncti = "/x.cti"')], "camera.exposure_s", "longer than the pattern"),
])
def test_impossible_rigs_are_refused_naming_the_key(tmp_path: Path, source: Path, edits: list, key: str,
                                                    message: str) -> None:
    config = variant(tmp_path, source, *edits)
    acq = FakeAcquirer(lambda t: np.zeros((720, 1280), np.uint8), 1280, 720)
    with pytest.raises(ConfigError, match=message) as exc:
        open_rig(config, transports={**lcr_transports(acq), "display": FakeDisplay((1920, 1080), 500.0)})
    assert exc.value.key == key and str(config.path) in str(exc.value)


def test_hdmi_genicam_rig_acquires_a_verified_sequence(tmp_path: Path) -> None:
    """The camera sees the projector's window directly (scaled to its sensor): the window
    runs the sequence and software-triggers the camera once each pattern is on display."""
    display = FakeDisplay((1920, 1080), 500.0)

    def render(t: float) -> np.ndarray:
        shown = display.current()
        light = np.zeros((1080, 1920)) if shown is None else (shown[..., 0] / 255.0) ** 2.2  # display gamma
        return np.rint(cv2.resize(200 + 3000 * light, (320, 256), interpolation=cv2.INTER_AREA)).astype(np.uint16)

    acq = FakeAcquirer(render, 320, 256)
    acq.nodes.allowed["PixelFormat"] = ("Mono8", "Mono12")
    config = variant(tmp_path, HDMI, ("width = 2448", "width = 320"), ("height = 2048", "height = 256"),
                     ("refresh_hz = 60.0", "refresh_hz = 500.0"), ("period_s = 0.1", "period_s = 0.02"),
                     ("exposure_s = 0.03", "exposure_s = 0.001"))
    patterns = PatternSet.load(CONFIG_DIR / "patterns" / "heterodyne_3x4.toml")
    with open_rig(config, transports={"camera": lambda: (acq, acq.close), "display": display}) as rig:
        assert isinstance(rig.projector, HdmiProjector) and rig.camera.trigger_type is TriggerType.SOFTWARE
        frames = []
        stack = acquire(rig, patterns, AcquisitionSettings.for_rig(rig), lambda k, f: frames.append(f))
    assert stack.shape == (12, 256, 320) and [f.index for f in frames] == list(range(12))
    assert acq.outstanding == 0 and acq.dropped == 0


def test_camera_unplugged_mid_scan_keeps_frames_then_next_scan_reconnects(tmp_path: Path) -> None:
    from scanner.errors import DeviceDisconnected, IncompleteSession
    from scanner.pipeline import capture
    from scanner.session import Session, SessionWriter

    display = FakeDisplay((1920, 1080), 500.0)

    def render(t: float) -> np.ndarray:
        shown = display.current()
        light = np.zeros((1080, 1920)) if shown is None else (shown[..., 0] / 255.0) ** 2.2
        return np.rint(cv2.resize(200 + 3000 * light, (320, 256), interpolation=cv2.INTER_AREA)).astype(np.uint16)

    first, second = FakeAcquirer(render, 320, 256), FakeAcquirer(render, 320, 256)
    for acq in (first, second):
        acq.nodes.allowed["PixelFormat"] = ("Mono8", "Mono12")
    pending = [first, second]
    grabs = {"n": 0}
    real_try_fetch = first.try_fetch

    def unplug_after_five(timeout: float = 0.0):
        grabs["n"] += 1
        if grabs["n"] == 6:
            first.unplug()
        return real_try_fetch(timeout=timeout)

    first.try_fetch = unplug_after_five
    config = variant(tmp_path, HDMI, ("width = 2448", "width = 320"), ("height = 2048", "height = 256"),
                     ("refresh_hz = 60.0", "refresh_hz = 500.0"), ("period_s = 0.1", "period_s = 0.02"),
                     ("exposure_s = 0.03", "exposure_s = 0.001"), ('trigger = "projector"', 'trigger = "software"'))
    patterns = PatternSet.load(CONFIG_DIR / "patterns" / "heterodyne_3x4.toml")
    with open_rig(config, transports={"camera": lambda: (pending[0], pending.pop(0).close), "display": display}) as rig:
        with pytest.raises(DeviceDisconnected, match="camera lost while waiting for frame 5"):
            capture(rig, patterns, SessionWriter.create(tmp_path / "a"))
        with pytest.raises(IncompleteSession, match="5 raw frame"):
            Session.open(tmp_path / "a")
        session = capture(rig, patterns, SessionWriter.create(tmp_path / "b"))  # reopened at the next arm
    assert len(session.manifest.frames) == 12 and first.closed


def _display_render(display: FakeDisplay):
    """What the camera sees of the projector's window: its light, gamma 2.2, at 320 x 256."""

    def render(t: float) -> np.ndarray:
        shown = display.current()
        light = np.zeros((1080, 1920)) if shown is None else (shown[..., 0] / 255.0) ** 2.2
        return np.rint(cv2.resize(200 + 3000 * light, (320, 256), interpolation=cv2.INTER_AREA)).astype(np.uint16)

    return render


HDMI_SMALL = (("width = 2448", "width = 320"), ("height = 2048", "height = 256"),
              ("refresh_hz = 60.0", "refresh_hz = 500.0"), ("period_s = 0.1", "period_s = 0.02"),
              ("exposure_s = 0.03", "exposure_s = 0.001"))


def test_hdmi_display_failing_mid_sequence_is_reported_as_itself(tmp_path: Path) -> None:
    """The window's sequence thread dies: the acquisition reports the projector's error
    (not a camera that saw no frame), with every frame exposed before it delivered."""
    from scanner.errors import DeviceError, WaitTimeout

    display = FakeDisplay((1920, 1080), 500.0)
    acq = FakeAcquirer(_display_render(display), 320, 256)
    acq.nodes.allowed["PixelFormat"] = ("Mono8", "Mono12")
    patterns = PatternSet.load(CONFIG_DIR / "patterns" / "heterodyne_3x4.toml")
    with open_rig(variant(tmp_path, HDMI, *HDMI_SMALL), transports={"camera": lambda: (acq, acq.close),
                                                                    "display": display}) as rig:
        fired: list[int] = []
        rig.projector.connect_trigger_out(lambda: fired.append(1))
        display.fail_after(25, RuntimeError("HDMI cable unplugged"))  # 10 presents per pattern: during pattern 2
        frames: list[int] = []
        with pytest.raises(DeviceError) as exc:
            acquire(rig, patterns, AcquisitionSettings.for_rig(rig), lambda k, f: frames.append(k))
    assert not isinstance(exc.value, WaitTimeout)
    assert str(exc.value) == ("hdmi-projector: pattern sequence failed at pattern 2: RuntimeError: HDMI cable "
                              "unplugged")
    assert frames == list(range(len(fired))) == [0, 1, 2]


def test_hdmi_projector_triggers_a_uvc_camera_from_its_thread(tmp_path: Path) -> None:
    """Wiring `projector` with a UVC camera: the window's thread software-triggers the
    camera once each pattern is on display, while the acquisition already waits for it;
    every frame passes the index and timestamp checks. (What each frame shows is not
    judged here: the fake camera's exposures follow the host's scheduling, not a sensor's.)"""
    display = FakeDisplay((1920, 1080), 500.0)
    cap = FakeCapture(lambda t: np.zeros((256, 320, 3), np.uint8), fps=500.0)
    config = variant(tmp_path, HDMI, *HDMI_SMALL, ("bit_depth = 12", "bit_depth = 8"),
                     ('driver = "genicam"', 'driver = "uvc"\nfps = 500.0'))
    images = np.stack([np.full((1080, 1920), 20 * k, np.uint8) for k in range(6)])
    with open_rig(config, transports={"camera": lambda: cap, "display": display}) as rig:
        assert isinstance(rig.camera, UvcCamera) and rig.camera.trigger_type is TriggerType.SOFTWARE
        frames: list[int] = []
        stack = acquire_images(rig, images, AcquisitionSettings.for_rig(rig), lambda k, f: frames.append(f.index))
    assert stack.shape == (6, 256, 320) and frames == list(range(6))
