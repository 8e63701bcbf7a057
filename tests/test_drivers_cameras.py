"""UVC and GenICam cameras and the HDMI projector on fake devices: settings written,
stale frames never returned, buffers handed back, bounded waits, unplug and reconnect,
sequence statuses carrying the projector thread's error, and the optional extras
reported by name when missing. No test measures wall time: waits that must time out are
bounded generously (`wait_bound_s`), and tests synchronise on events, never on sleeps."""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest

from scanner.devices import TriggerType
from scanner.drivers.genicam import GenICamCamera, harvester_opener
from scanner.drivers.hdmi import HdmiDisplay, HdmiProjector, PygameBackend
from scanner.drivers.testing import FakeAcquirer, FakeCapture, FakeDisplay, grab_in_thread, wait_bound_s
from scanner.drivers.uvc import UvcCamera
from scanner.errors import DeviceDisconnected, DeviceError, DeviceTimeout, UnsupportedSetting, WaitTimeout

# ---------------------------------------------------------------------------------- UVC


class Scene:
    """What the camera sees: a uniform image of value `level`, changed by the test."""

    def __init__(self) -> None:
        self.level = 10

    def render(self, t: float) -> np.ndarray:
        return np.full((8, 12, 3), self.level, np.uint8)


@pytest.mark.parametrize("buffer_timestamps", [True, False])
def test_uvc_never_returns_a_frame_exposed_before_the_trigger(buffer_timestamps: bool) -> None:
    scene = Scene()
    cap = FakeCapture(scene.render, fps=200, buffer_timestamps=buffer_timestamps)
    cam = UvcCamera(lambda: cap, "uvc", 12, 8, fps=200)
    cam.arm(5)
    assert cap.wait_frames(10, wait_bound_s(0.05))  # the stream runs: older frames pile up showing level 10
    for k in range(5):
        scene.level = 20 + 40 * k
        t = time.monotonic()
        cam.trigger()
        f = cam.grab(1.0)
        assert (f.index, int(f.image[0, 0]), f.image.shape, f.pattern_index) == (k, 20 + 40 * k, (8, 12), None)
        assert f.timestamp_s >= t
    cam.shutdown()
    assert cap.released


def test_uvc_settings_and_refusals() -> None:
    import cv2

    cap = FakeCapture(Scene().render)
    cam = UvcCamera(lambda: cap, "uvc", 12, 8, gain=4.0)
    cam.set_exposure(0.005)
    assert cap.props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1 and cap.props[cv2.CAP_PROP_EXPOSURE] == 50  # 100 us units
    assert cap.props[cv2.CAP_PROP_GAIN] == 4.0
    cap.refused.add(cv2.CAP_PROP_EXPOSURE)
    with pytest.raises(UnsupportedSetting, match="does not take a manual exposure"):
        cam.set_exposure(0.01)
    with pytest.raises(UnsupportedSetting, match="rising_edge not supported"):
        cam.set_trigger(TriggerType.RISING_EDGE)
    with pytest.raises(UnsupportedSetting, match="trigger mode 'burst' is not one of"):
        cam.set_trigger(TriggerType.SOFTWARE, "burst")  # type: ignore[arg-type]
    cam.shutdown()


def test_uvc_untriggered_timeout_unplug_and_reconnect() -> None:
    caps = [FakeCapture(Scene().render), FakeCapture(Scene().render)]
    cam = UvcCamera(lambda: caps.pop(0), "uvc", 12, 8)
    cam.arm(2)
    with pytest.raises(WaitTimeout, match="uvc: stopped waiting for frame 0 after 0.1 s; it was never triggered"):
        cam.grab(0.1)
    cam.trigger()
    cam.grab(1.0)
    first = cam._cap
    first.unplug()
    cam.trigger()
    # a lost stream is reported as such, not by waiting out the (long) grab timeout
    with pytest.raises(DeviceDisconnected, match="camera stopped streaming"):
        cam.grab(600.0)
    assert first.released
    cam.arm(1)  # reopens
    cam.trigger()
    assert cam.grab(1.0).index == 0
    cam.shutdown()


def test_uvc_grab_waits_for_a_trigger_from_another_thread() -> None:
    """An HDMI projector's trigger output triggers the camera from the sequence thread,
    possibly after the acquisition has started waiting for the frame."""
    scene = Scene()
    cap = FakeCapture(scene.render, fps=200)
    cam = UvcCamera(lambda: cap, "uvc", 12, 8, fps=200)
    cam.arm(1)
    waiter, got = grab_in_thread(cam, 600.0)
    scene.level = 99
    cam.trigger()
    waiter.join(wait_bound_s(1.0))
    assert not waiter.is_alive() and got[0].index == 0 and int(got[0].image[0, 0]) == 99
    cam.shutdown()


# ------------------------------------------------------------------------------ GenICam


def genicam(acq: FakeAcquirer, **kw) -> GenICamCamera:
    return GenICamCamera(lambda: (acq, acq.close), "gencam", 6, 4, trigger_line="Line1", **kw)


def render(t: float) -> np.ndarray:
    return np.full((4, 6), int(t * 1000) % 200, np.uint8)


def test_genicam_writes_sfnc_features_in_order() -> None:
    acq = FakeAcquirer(render, 6, 4)
    cam = genicam(acq)
    cam.set_bit_depth(12)
    cam.set_exposure(0.002)
    cam.set_trigger(TriggerType.RISING_EDGE)
    assert acq.nodes.log == [
        ("ExposureAuto", "Off"), ("AcquisitionMode", "Continuous"), ("PixelFormat", "Mono8"),
        ("ExposureTime", 10000.0), ("PixelFormat", "Mono12"), ("ExposureTime", 2000.0),
        ("TriggerSelector", "FrameStart"), ("TriggerMode", "On"), ("TriggerSource", "Line1"),
        ("TriggerActivation", "RisingEdge")]
    with pytest.raises(UnsupportedSetting, match="PixelFormat = 'Mono10' refused"):
        cam.set_bit_depth(10)


class SteppingClock:
    """A device clock (ns) that advances 2 s at each reading: the latch at arm reads
    100 s, frame k is stamped 102 + 2 k s, whatever the host's clock does meanwhile."""

    def __init__(self) -> None:
        self.readings = 0

    def __call__(self) -> int:
        self.readings += 1
        return (98 + 2 * self.readings) * 10 ** 9


def test_genicam_software_trigger_and_timestamps() -> None:
    acq = FakeAcquirer(render, 6, 4, device_clock_ns=SteppingClock())
    cam = genicam(acq)
    before = time.monotonic()
    cam.arm(3)
    after = time.monotonic()
    assert acq.num_buffers == 3 + 4
    frames = []
    for k in range(3):
        cam.trigger()
        frames.append(cam.grab(0.5))
        assert frames[-1].index == k and frames[-1].image.shape == (4, 6)
    assert acq.outstanding == 0
    # device ticks mapped through the latch taken at arm (host time within [before, after]):
    # frame k is 2 (k + 1) s after the latch on the device clock, hence on the host clock
    stamps = np.array([f.timestamp_s for f in frames])
    assert np.allclose(np.diff(stamps), 2.0, atol=1e-6)
    assert before + 2 <= stamps[0] <= after + 2
    with pytest.raises(DeviceError, match="software trigger refused"):
        cam.trigger()


def test_genicam_hardware_trigger_hands_every_buffer_back() -> None:
    acq = FakeAcquirer(render, 6, 4)
    cam = genicam(acq)
    cam.set_trigger(TriggerType.RISING_EDGE)
    cam.arm(40)
    for k in range(40):  # many more frames than buffers: only possible if each is re-queued
        acq.pulse()
        assert cam.grab(0.5).index == k
        assert acq.outstanding == 0
    assert acq.dropped == 0
    timeout = 0.1
    t0 = time.monotonic()
    with pytest.raises(WaitTimeout, match="gencam: stopped waiting for frame 40 after 0.1 s; it waits for a "
                                          "trigger edge on Line1"):
        cam.grab(timeout)
    assert timeout <= time.monotonic() - t0 < wait_bound_s(timeout)


def test_genicam_arm_discards_stale_buffers_and_reports_gaps() -> None:
    acq = FakeAcquirer(render, 6, 4)
    cam = genicam(acq)
    cam.set_trigger(TriggerType.RISING_EDGE)
    cam.arm(2)
    acq.pulse()  # a frame left over from an aborted sequence
    cam.arm(2)
    acq.pulse()
    assert cam.grab(0.5).index == 0  # the stale buffer was flushed by the re-arm
    acq.num_buffers = 1
    acq.outstanding = 1  # a buffer the producer does not have back: the next frame is lost
    acq.pulse()
    acq.outstanding = 0
    acq.pulse()
    assert cam.grab(0.5).index == 2  # index 1 skipped: the acquisition reports FrameDropped


def test_genicam_unplug_then_reopen() -> None:
    first, second = FakeAcquirer(render, 6, 4), FakeAcquirer(render, 6, 4)
    acqs = [first, second]
    cam = GenICamCamera(lambda: (acqs[0], acqs.pop(0).close), "gencam", 6, 4)
    cam.arm(1)
    first.unplug()
    with pytest.raises(DeviceDisconnected, match="camera lost while waiting for frame 0"):
        cam.grab(0.2)
    assert first.closed
    cam.arm(1)
    cam.trigger()
    assert cam.grab(0.5).index == 0


def test_genicam_producer_timeout_is_a_device_timeout_not_a_wait_timeout() -> None:
    """The GenTL producer reports that the device timed out: the other kind of timeout,
    naming the camera and the wait, and the camera is kept (not dropped as lost)."""
    acq = FakeAcquirer(render, 6, 4)
    cam = genicam(acq)
    cam.arm(1)

    def producer_timeout(timeout: float = 0.0) -> None:
        raise type("TimeoutException", (Exception,), {})("GC_ERR_TIMEOUT")

    acq.try_fetch = producer_timeout  # type: ignore[method-assign]
    with pytest.raises(DeviceTimeout, match="gencam: device timeout: waiting for frame 0: TimeoutException: "
                                            "GC_ERR_TIMEOUT") as exc:
        cam.grab(0.5)
    assert not isinstance(exc.value, WaitTimeout) and exc.value.timeout_s is None and not acq.closed


def test_missing_extras_name_the_install_command(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "harvesters", None)
    monkeypatch.setitem(sys.modules, "harvesters.core", None)
    with pytest.raises(DeviceError, match=r"pip install slscan\[genicam\]"):
        harvester_opener("gencam", "/opt/producer.cti")()
    monkeypatch.setitem(sys.modules, "pygame", None)
    with pytest.raises(DeviceError, match=r"pip install slscan\[hdmi\]"):
        PygameBackend("hdmi", 1)


# --------------------------------------------------------------------------------- HDMI


def hdmi(refresh_hz: float = 240.0, latency: int = 2) -> tuple[HdmiProjector, FakeDisplay]:
    fake = FakeDisplay((16, 8), refresh_hz)
    return HdmiProjector(HdmiDisplay(fake, "hdmi", refresh_hz, latency)), fake


def test_hdmi_show_returns_once_the_pattern_is_on_display() -> None:
    proj, fake = hdmi()
    patterns = np.stack([np.full((8, 16), v, np.uint8) for v in (10, 20, 30)])
    proj.load_patterns(patterns)
    before = len(fake.shown)
    proj.show(1)
    assert len(fake.shown) - before == 3  # one present plus two of latency
    assert fake.current().shape == (8, 16, 3) and int(fake.current()[0, 0, 0]) == 20
    proj.blank()
    assert int(fake.current().max()) == 0


def test_hdmi_sequence_holds_each_pattern_and_fires_trigger_out() -> None:
    proj, fake = hdmi()
    patterns = np.stack([np.full((8, 16), v, np.uint8) for v in (10, 20, 30)])
    proj.load_patterns(patterns)
    fired: list[tuple[int, int]] = []
    proj.connect_trigger_out(lambda: fired.append((len(fake.shown), int(fake.current()[0, 0, 0]))))
    start = len(fake.shown)
    status = proj.run_sequence(6 / 240.0)  # 6 refreshes per pattern
    status.wait(wait_bound_s(1.0))
    assert status.done and status.success
    shown = [int(f[0, 0, 0]) for _, f in fake.shown[start:]]
    assert shown == [10] * 6 + [20] * 6 + [30] * 6 + [0]
    assert fired == [(start + 3, 10), (start + 9, 20), (start + 15, 30)]  # after 1 + 2 latency presents
    with pytest.raises(UnsupportedSetting, match="must exceed the display latency"):
        proj.run_sequence(2 / 240.0)


def test_hdmi_sequence_status_carries_the_display_failure() -> None:
    proj, fake = hdmi()
    proj.load_patterns(np.stack([np.full((8, 16), v, np.uint8) for v in (10, 20, 30)]))
    fake.fail_after(8, RuntimeError("video signal lost"))  # during pattern 1 (6 presents per pattern)
    status = proj.run_sequence(6 / 240.0)
    with pytest.raises(DeviceError, match="hdmi-projector: pattern sequence failed at pattern 1: RuntimeError: "
                                          "video signal lost") as exc:
        status.wait(wait_bound_s(1.0))
    assert status.done and not status.success and status.exception() is exc.value
    assert isinstance(exc.value.__cause__, RuntimeError)
    proj.shutdown()


def test_hdmi_sequence_status_carries_the_trigger_output_error() -> None:
    """The camera a trigger output drives fails: its own error, as it is, ends the sequence."""
    proj, fake = hdmi()
    proj.load_patterns(np.stack([np.full((8, 16), v, np.uint8) for v in (10, 20, 30)]))
    fired: list[int] = []

    def camera_trigger() -> None:
        fired.append(1)
        if len(fired) == 2:
            raise DeviceDisconnected("gencam", "camera lost while executing TriggerSoftware")

    proj.connect_trigger_out(camera_trigger)
    status = proj.run_sequence(6 / 240.0)
    with pytest.raises(DeviceDisconnected, match="gencam: camera lost"):
        status.wait(wait_bound_s(1.0))
    assert len(fired) == 2  # the sequence ended there: pattern 2 was never shown
    assert all(int(f[0, 0, 0]) != 30 for _, f in fake.shown)
    proj.shutdown()


def test_hdmi_without_vsync_is_refused() -> None:
    with pytest.raises(DeviceError, match="vsync is not in effect"):
        HdmiDisplay(FakeDisplay((16, 8), 240.0, vsync=False), "hdmi", 240.0)
