"""One interface contract, run against the simulated devices and the real drivers on fake
transports: what acquisition relies on must hold for every camera, projector and
trigger source alike. Also the contract itself: every `_do_*` a driver must implement is
abstract, long actions return a status carrying their own error, and the two timeout
kinds are distinct and name the device and the wait.

(The exact byte exchanges of each driver are in the test_drivers_* files.)"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from session_support import SCENE, small_rig_toml

from scanner.devices import Camera, Projector, TriggerMode, TriggerSource, TriggerType
from scanner.drivers.genicam import GenICamCamera
from scanner.drivers.hdmi import HdmiDisplay, HdmiProjector
from scanner.drivers.lightcrafter import LightCrafter4500
from scanner.drivers.lightcrafter_images import diamond_resample, fingerprint, pack_rgb24
from scanner.drivers.testing import (
    Dlpc350Emulator,
    FakeAcquirer,
    FakeCapture,
    FakeDisplay,
    TriggerBoxEmulator,
    wait_bound_s,
)
from scanner.drivers.triggerbox import TriggerBox
from scanner.drivers.uvc import UvcCamera
from scanner.errors import DeviceDisconnected, DeviceError, DeviceTimeout, UnsupportedSetting, WaitTimeout
from scanner.rig import RigConfig, open_rig
from scanner.status import Status
from sim.virtual_devices import SimProjector, SimTriggerBox

PATTERNS = np.stack([np.full((1140, 912), v, np.uint8) for v in (0, 60, 120, 180)])
PERIOD_S = 0.01  # sequences and pulse trains below: 5 refreshes of the fake 500 Hz display

# What a driver must implement, written out here (not read from the classes under test).
CAMERA_METHODS = {"_do_set_bit_depth", "_do_set_exposure", "_do_set_trigger", "_do_arm", "_do_disarm",
                  "_do_trigger", "_do_grab", "_do_shutdown"}
PROJECTOR_METHODS = {"_do_load_patterns", "_do_show", "_do_blank", "_do_run_sequence", "_do_stop_sequence",
                     "_do_shutdown"}
TRIGGER_SOURCE_METHODS = {"_do_arm", "_do_start", "_do_stop", "_do_pulses_sent", "_do_shutdown"}


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
        flashed = fingerprint(pack_rgb24(diamond_resample(PATTERNS)))
        proj = LightCrafter4500(Dlpc350Emulator, flash_images_sha256=flashed)
    else:
        proj = HdmiProjector(HdmiDisplay(FakeDisplay((912, 1140), 500.0), "hdmi", 500.0, 1))
    yield proj
    proj.shutdown()


@pytest.fixture(params=["sim", "triggerbox"])
def trigger_source(request: pytest.FixtureRequest) -> Iterator[TriggerSource]:
    box: TriggerSource = SimTriggerBox() if request.param == "sim" else TriggerBox(TriggerBoxEmulator)
    yield box
    box.shutdown()


# ----------------------------------------------------------------------- the contract


def _without(base: type, methods: set[str], missing: str) -> type:
    """A subclass of `base` implementing every method of `methods` but `missing`."""
    body: dict[str, Callable[..., None]] = {m: (lambda self, *a: None) for m in methods if m != missing}
    return type(f"Forgot{missing}", (base,), body)


@pytest.mark.parametrize("base, methods, args", [
    (Camera, CAMERA_METHODS, ("cam", 4, 3)),
    (Projector, PROJECTOR_METHODS, ("proj", 4, 3)),
    (TriggerSource, TRIGGER_SOURCE_METHODS, ("box",)),
])
def test_a_driver_missing_any_do_method_cannot_be_instantiated(base: type, methods: set[str], args: tuple) -> None:
    assert set(base.__abstractmethods__) == methods
    _without(base, methods, "")(*args)  # all implemented: instantiates
    for missing in sorted(methods):
        with pytest.raises(TypeError, match=missing):
            _without(base, methods, missing)(*args)


def test_only_implemented_trigger_modes_exist() -> None:
    assert [m.value for m in TriggerMode] == ["once"]


def test_status_finishes_once_and_runs_callbacks() -> None:
    status = Status("dev", "thing")
    seen: list[bool] = []
    status.add_callback(lambda s: seen.append(s.success))
    assert not status.done and status.exception() is None
    status.set_finished()
    status.set_exception(DeviceError("dev", "too late"))  # the first outcome wins
    status.wait(1.0)
    status.add_callback(lambda s: seen.append(s.success))  # already done: called at once
    assert status.done and status.success and seen == [True, True]


def test_status_carries_the_error_raised_in_the_device_thread() -> None:
    """A projector's sequence thread fails: the waiter gets that error itself."""
    status = Status("hdmi-projector", "pattern sequence")
    error = DeviceError("hdmi-projector", "pattern sequence failed at pattern 3: RuntimeError: display lost")
    thread = threading.Thread(target=status.set_exception, args=(error,))
    thread.start()
    with pytest.raises(DeviceError) as exc:
        status.wait(wait_bound_s(1.0))
    thread.join()
    assert exc.value is error and status.exception() is error and status.done and not status.success


def test_the_two_timeout_kinds_are_distinct_and_name_the_device_and_the_wait() -> None:
    assert not issubclass(WaitTimeout, DeviceTimeout) and not issubclass(DeviceTimeout, WaitTimeout)
    assert issubclass(WaitTimeout, DeviceError) and issubclass(DeviceTimeout, DeviceError)
    # the caller stops waiting: a status still running
    running = Status("trigger-box", "pulse train (5 pulses)")
    with pytest.raises(WaitTimeout) as waited:
        running.wait(0.05)
    assert str(waited.value) == ("trigger-box: stopped waiting for pulse train (5 pulses) after 0.05 s; it is "
                                 "still running")
    assert (waited.value.device, waited.value.awaited, waited.value.timeout_s) == (
        "trigger-box", "pulse train (5 pulses)", 0.05)
    assert not running.done  # the action goes on: a later wait can still succeed
    running.set_finished()
    running.wait(1.0)
    # the device is detected to time out: a status past its deadline fails by itself
    late = Status("sim-projector", "pattern sequence", deadline_s=0.05)
    with pytest.raises(DeviceTimeout) as timed_out:
        late.wait(wait_bound_s(0.05))
    assert str(timed_out.value).startswith("sim-projector: device timeout: pattern sequence not finished after "
                                           "0.05 s")
    assert late.done and not late.success and timed_out.value.device == "sim-projector"


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


def test_camera_wait_is_bounded_and_a_wait_timeout(camera: Camera) -> None:
    camera.arm(1)
    timeout = 0.2
    t0 = time.monotonic()
    with pytest.raises(WaitTimeout, match=f"{camera.name}: stopped waiting for .*frame.* 0 after 0.2 s") as exc:
        camera.grab(timeout)
    assert timeout <= time.monotonic() - t0 < wait_bound_s(timeout)
    assert (exc.value.device, exc.value.timeout_s) == (camera.name, timeout)
    with pytest.raises(ValueError, match="finite"):
        camera.grab(0)


def test_camera_describes_what_it_applied(camera: Camera) -> None:
    lo, hi = camera.exposure_range_s
    exposure = min(hi, max(lo, 0.004))
    camera.set_exposure(exposure)
    camera.set_bit_depth(8)  # every camera here has 8 bits
    camera.set_trigger(TriggerType.SOFTWARE, TriggerMode.ONCE)
    d = camera.describe()
    assert (d["exposure_s"], d["bit_depth"], d["trigger_type"], d["trigger_mode"]) == (exposure, 8, "software", "once")


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
    with pytest.raises(DeviceDisconnected):
        camera.grab(1.0)


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


def test_projector_sequence_status_finishes(projector: Projector) -> None:
    projector.load_patterns(PATTERNS)
    status = projector.run_sequence(PERIOD_S)
    assert status.device == projector.name and "pattern sequence" in status.action
    status.wait(wait_bound_s(4 * PERIOD_S))
    assert status.success
    projector.run_sequence(PERIOD_S).wait(wait_bound_s(4 * PERIOD_S))  # and again


def test_projector_stopped_sequence_fails_its_status(projector: Projector) -> None:
    projector.load_patterns(PATTERNS)
    status = projector.run_sequence(1.0)  # 4 s: stopped long before it ends
    with pytest.raises(UnsupportedSetting, match="still running"):  # one sequence at a time
        projector.run_sequence(1.0)
    projector.stop_sequence()
    assert status.done and not status.success
    with pytest.raises(DeviceError, match=rf"{projector.name}: pattern sequence \(4 patterns every 1 s\) stopped "
                                          r"before it had run"):
        status.wait(1.0)
    second = projector.run_sequence(1.0)
    projector.show(1)  # showing a pattern stops the sequence too
    assert second.done and not second.success and projector.current_pattern == 1


def test_projector_shutdown_is_idempotent_and_final(projector: Projector) -> None:
    projector.load_patterns(PATTERNS)
    status = projector.run_sequence(1.0)
    projector.shutdown()
    projector.shutdown()
    projector.stop_sequence()
    with pytest.raises(DeviceDisconnected, match=rf"{projector.name}: pattern sequence \(4 patterns every 1 s\) "
                                                 r"ended: the device was shut down while it ran"):
        status.wait(1.0)
    with pytest.raises(DeviceDisconnected):
        projector.load_patterns(PATTERNS)


# ----------------------------------------------------------------------- trigger sources


def test_trigger_source_runs_a_pulse_train(trigger_source: TriggerSource) -> None:
    with pytest.raises(UnsupportedSetting):
        trigger_source.arm(3, 0.01, 0.02)  # width not below period
    with pytest.raises(UnsupportedSetting, match="not armed"):
        trigger_source.start()
    trigger_source.arm(3, PERIOD_S)
    status = trigger_source.start()
    assert status.device == trigger_source.name and "pulse train" in status.action
    status.wait(wait_bound_s(3 * PERIOD_S))
    assert status.success and trigger_source.pulses_sent == 3
    with pytest.raises(UnsupportedSetting, match="not armed"):  # one start per arm
        trigger_source.start()
    trigger_source.stop()
    assert status.success  # stopping after the end changes nothing


def test_trigger_source_stopped_train_fails_its_status(trigger_source: TriggerSource) -> None:
    trigger_source.arm(100, 1.0)
    status = trigger_source.start()
    trigger_source.stop()
    with pytest.raises(DeviceError, match=rf"{trigger_source.name}: pulse train \(100 pulses every 1 s\) stopped "
                                          r"before every pulse was sent"):
        status.wait(1.0)


def test_trigger_source_shutdown_is_idempotent_and_final(trigger_source: TriggerSource) -> None:
    trigger_source.arm(100, 1.0)
    status = trigger_source.start()
    trigger_source.shutdown()
    trigger_source.shutdown()
    trigger_source.stop()
    with pytest.raises(DeviceDisconnected, match=r"pulse train \(100 pulses every 1 s\) ended: the device was shut "
                                                 r"down while it ran"):
        status.wait(1.0)
    with pytest.raises(DeviceDisconnected):
        trigger_source.arm(1, 0.01)


def test_sim_trigger_source_status_carries_an_input_error() -> None:
    """What a connected input raises ends the simulated train and is what its waiter gets."""
    box = SimTriggerBox()
    pulses: list[int] = []

    def input_line() -> None:
        pulses.append(1)
        if len(pulses) == 2:
            raise DeviceDisconnected("sim-camera", "camera disconnected")

    box.connect(input_line)
    box.arm(5, PERIOD_S)
    status = box.start()
    with pytest.raises(DeviceDisconnected, match="sim-camera: camera disconnected"):
        status.wait(wait_bound_s(5 * PERIOD_S))
    assert len(pulses) == 2 and box.pulses_sent == 2
    box.shutdown()

