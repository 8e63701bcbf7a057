"""GRBL stage driver: the exact serial exchanges (after GRBL 1.1's interface document),
homing, the controller's error and alarm replies, silence, a cable pulled mid-move and a
target past the travel. No hardware needed, no wall time measured (waits that must time
out are bounded by `wait_bound_s`)."""

from __future__ import annotations

import math
import time

import pytest

from scanner import devices
from scanner.drivers import grbl
from scanner.drivers.grbl import GrblStage
from scanner.drivers.grbl_emulator import GrblEmulator
from scanner.drivers.testing import SILENT, Exchange, FakeSerial, Unplug, expected_protocol, wait_bound_s
from scanner.errors import DeviceDisconnected, DeviceError, DeviceTimeout, NotHomed, OutOfTravel, StageAlarm
from scanner.stage import Axis, AxisKind

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"
HELLO = Exchange(b"\x18", BANNER)
AT_0 = Exchange(b"?", b"<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n")
AT_45 = Exchange(b"?", b"<Idle|MPos:45.000,0.000,0.000|FS:0,0>\r\n")
MOVE_45 = [Exchange(b"G21G90G0X45.000\n", b"ok\r\n"), Exchange(b"G4P0.01\n", b"ok\r\n"), AT_45]
TURNTABLE = Axis("turntable", AxisKind.ROTARY, (math.radians(-370), math.radians(370)), math.radians(90))
REALTIME = b"?!\x18"
REPLY_TIMEOUT_S = 0.2  # the driver's reply timeout in these tests


def port(script: list, **kw) -> FakeSerial:
    return FakeSerial(script, realtime=REALTIME, timeout=kw.pop("timeout", 0.05), **kw)


def stage(opener, axes=(TURNTABLE,), **kw) -> GrblStage:
    return GrblStage(opener, list(axes), {a.name: letter for a, letter in zip(axes, "XYZ")},
                     units_per_turn={"turntable": 360.0},
                     boot_timeout_s=kw.pop("boot_timeout_s", 1.0), timeout_s=kw.pop("timeout_s", REPLY_TIMEOUT_S), **kw)


def test_connect_move_and_position_exchange() -> None:
    script = [HELLO, AT_0, *MOVE_45, AT_45]
    with expected_protocol(stage, port(script)) as s:
        assert s.identity == {"firmware": "Grbl 1.1h"}
        status = s.move_to({"turntable": math.radians(45)})
        status.wait(wait_bound_s(1.0))
        assert status.success
        assert s.position()["turntable"] == pytest.approx(math.radians(45), abs=1e-9)


def test_two_axes_move_in_one_block_and_linear_axis_in_mm() -> None:
    slide = Axis("slide", AxisKind.LINEAR, (0.0, 200.0), 20.0)
    script = [HELLO, Exchange(b"?", b"<Idle|MPos:0.000,10.000,0.000|FS:0,0>\r\n"),
              Exchange(b"G21G90G0X90.000Y25.500\n", b"ok\r\n"), Exchange(b"G4P0.01\n", b"ok\r\n"),
              Exchange(b"?", b"<Idle|MPos:90.000,25.500,0.000|FS:0,0>\r\n")]
    with expected_protocol(lambda o: stage(o, (TURNTABLE, slide)), port(script)) as s:
        s.move_to({"turntable": math.pi / 2, "slide": 25.5}).wait(wait_bound_s(1.0))


def test_work_position_is_machine_position_minus_the_work_offset() -> None:
    script = [HELLO, Exchange(b"?", b"<Idle|MPos:50.000,0.000,0.000|FS:0,0|WCO:5.000,0.000,0.000>\r\n"),
              Exchange(b"?", b"<Idle|MPos:60.000,0.000,0.000|FS:0,0>\r\n"),  # WCO kept from the last report
              Exchange(b"?", b"<Idle|WPos:-3.000,0.000,0.000|FS:0,0>\r\n")]
    with expected_protocol(stage, port(script)) as s:
        assert [round(math.degrees(s.position()["turntable"]), 6) for _ in range(3)] == [45.0, 55.0, -3.0]


def test_board_resetting_on_open_is_reset_again_until_it_answers(monkeypatch: pytest.MonkeyPatch) -> None:
    # the first soft reset is lost while the bootloader runs; GRBL prints its banner once booted
    monkeypatch.setattr(grbl, "_RESET_RETRY_S", 0.1)
    script = [Exchange(b"\x18", SILENT), HELLO]
    with expected_protocol(lambda o: stage(o, boot_timeout_s=30.0), port(script)) as s:
        assert s.identity["firmware"] == "Grbl 1.1h"


def test_silent_port_times_out_within_boot_timeout() -> None:
    script = [Exchange(b"\x18", SILENT)] * 20
    boot_timeout = 0.5
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="grbl-stage: device timeout: no GRBL welcome banner after a soft reset "
                                            "after 0.5 s; is this the stage controller's port") as exc:
        stage(lambda: port(script), boot_timeout_s=boot_timeout)
    assert boot_timeout <= time.monotonic() - t0 < wait_bound_s(boot_timeout)  # fired, and not hung
    assert exc.value.timeout_s == boot_timeout


def test_old_grbl_is_refused() -> None:
    with pytest.raises(DeviceError, match="runs GRBL 0.9j; this driver needs 1.1"):
        stage(lambda: port([Exchange(b"\x18", b"\r\nGrbl 0.9j ['$' for help]\r\n")]))


def test_target_past_the_travel_is_refused_before_anything_is_sent() -> None:
    with expected_protocol(stage, port([HELLO])) as s:
        with pytest.raises(OutOfTravel, match="grbl-stage: turntable: target 400 deg is outside its travel -370 deg "
                                              "\\.\\. 370 deg; nothing was moved"):
            s.move_to({"turntable": math.radians(400)})
        with pytest.raises(DeviceError, match="no axis named 'tilt'"):
            s.move_to({"tilt": 0.1})


def test_error_reply_names_the_block_and_the_meaning() -> None:
    script = [HELLO, AT_0, Exchange(b"G21G90G0X45.000\n", b"error:9\r\n")]
    with expected_protocol(stage, port(script)) as s:
        with pytest.raises(DeviceError, match="'G21G90G0X45.000' refused: error 9, G-code locked out during alarm"):
            s.move_to({"turntable": math.radians(45)})
        assert not s.moving  # the refused move's status failed with it: the stage is free again


def test_hard_limit_alarm_mid_move_fails_the_move_and_the_link_is_reset() -> None:
    first = port([HELLO, AT_0, Exchange(b"G21G90G0X45.000\n", b"ok\r\n"),
                  Exchange(b"G4P0.01\n", b"ALARM:1\r\n[MSG:Reset to continue]\r\n")])
    second = port([HELLO, Exchange(b"?", b"<Idle|MPos:12.000,0.000,0.000|FS:0,0>\r\n")])
    with expected_protocol(stage, first, second) as s:
        status = s.move_to({"turntable": math.radians(45)})
        with pytest.raises(StageAlarm, match="alarm 1 during 'G4P0.01': hard limit triggered; machine position is "
                                             "likely lost"):
            status.wait(wait_bound_s(1.0))
        assert first.closed
        assert math.degrees(s.position()["turntable"]) == pytest.approx(12.0)  # a new link, after a soft reset


def test_no_reply_times_out_and_reconnects() -> None:
    first = port([HELLO, AT_0, Exchange(b"G21G90G0X45.000\n", SILENT)])
    second = port([HELLO, AT_0, *MOVE_45])
    with expected_protocol(stage, first, second) as s:
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="grbl-stage: device timeout: no reply to 'G21G90G0X45.000' after "
                                                "0.2 s; the link is reopened"):
            s.move_to({"turntable": math.radians(45)})
        assert time.monotonic() - t0 < wait_bound_s(REPLY_TIMEOUT_S)  # not hung
        assert first.closed
        s.move_to({"turntable": math.radians(45)}).wait(wait_bound_s(1.0))


def test_end_of_move_never_reported_fails_the_status_at_its_deadline(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(devices, "SEQUENCE_DEADLINE_SLACK_S", 0.3)
    script = [HELLO, AT_0, Exchange(b"G21G90G0X45.000\n", b"ok\r\n"), Exchange(b"G4P0.01\n", SILENT)]
    with expected_protocol(stage, port(script)) as s:
        status = s.move_to({"turntable": math.radians(45)})  # nominal 0.5 s: deadline 5 x 0.5 + 0.3 s
        # the status's own deadline and the driver's wait for G4's ok end together: either names the wait
        with pytest.raises(DeviceTimeout, match="grbl-stage: device timeout: (move \\(turntable to 45 deg\\) not "
                                                "finished|no reply to 'G4P0.01') after 2.8 s"):
            status.wait(wait_bound_s(2.8))


def test_unplugged_before_the_end_of_the_move_then_reconnects() -> None:
    first = port([HELLO, AT_0, Exchange(b"G21G90G0X45.000\n", b"ok\r\n"), Unplug()])
    second = port([HELLO, AT_45])
    with expected_protocol(stage, first, second) as s:
        status = s.move_to({"turntable": math.radians(45)})
        with pytest.raises(DeviceDisconnected, match="serial link lost sending 'G4P0.01'"):
            status.wait(wait_bound_s(1.0))
        assert math.degrees(s.position()["turntable"]) == pytest.approx(45.0)


def test_homing_is_required_first_then_moves_are_allowed() -> None:
    homed = Axis("turntable", AxisKind.ROTARY, TURNTABLE.limits, TURNTABLE.speed, requires_homing=True)
    script = [Exchange(b"\x18", BANNER + b"[MSG:'$H'|'$X' to unlock]\r\n"),
              Exchange(b"$H\n", b"ok\r\n"), AT_0,
              AT_0, *MOVE_45]
    with expected_protocol(lambda o: stage(o, (homed,)), port(script)) as s:
        with pytest.raises(NotHomed, match="turntable must be homed before it moves"):
            s.move_to({"turntable": math.radians(45)})
        s.home().wait(wait_bound_s(1.0))
        assert s.homed and s.messages == ["'$H'|'$X' to unlock"]
        s.move_to({"turntable": math.radians(45)}).wait(wait_bound_s(1.0))


def test_homing_not_enabled_in_the_controller_is_named() -> None:
    with expected_protocol(stage, port([HELLO, Exchange(b"$H\n", b"error:5\r\n")])) as s:
        with pytest.raises(DeviceError, match="'\\$H' refused: error 5, homing cycle is not enabled in the "
                                              "controller's settings \\(\\$22\\)"):
            s.home().wait(wait_bound_s(1.0))
        assert not s.homed


def test_controller_restarting_mid_move_is_reported() -> None:
    script = [HELLO, AT_0, Exchange(b"G21G90G0X45.000\n", b"ok\r\n"), Exchange(b"G4P0.01\n", BANNER)]
    with (expected_protocol(stage, port(script)) as s,
          pytest.raises(DeviceError, match="the controller restarted while handling 'G4P0.01'")):
        s.move_to({"turntable": math.radians(45)}).wait(wait_bound_s(1.0))


# ------------------------------------------------------------------ on the emulator


def emulated(emulator: GrblEmulator, axes=(TURNTABLE,)) -> GrblStage:
    return stage(lambda: emulator, axes)


def test_emulator_stop_mid_move_sends_feed_hold_and_reset() -> None:
    emulator = GrblEmulator(rate=10.0)  # 10 degrees/s: a 90 degree move takes 9 s
    s = emulated(emulator)
    status = s.move_to({"turntable": math.radians(90)})
    s.stop()
    with pytest.raises(DeviceError, match="move \\(turntable to 90 deg\\) stopped before it had finished"):
        status.wait(wait_bound_s(1.0))
    assert emulator.lines[-2:] == ["!", "^X"]
    assert 0 <= math.degrees(s.position()["turntable"]) < 90  # stopped on the way, position kept
    s.shutdown()


def test_emulator_cable_pulled_mid_move_fails_in_bounded_time() -> None:
    emulator = GrblEmulator(rate=90.0)
    emulator.unplug_at = 0.5
    s = emulated(emulator)
    t0 = time.monotonic()
    with pytest.raises(DeviceDisconnected, match="grbl-stage: serial link lost"):
        s.move_to({"turntable": math.radians(90)}).wait(wait_bound_s(1.0))
    assert time.monotonic() - t0 < wait_bound_s(1.0)
    s.shutdown()


def test_emulator_soft_limit_of_the_controller_is_an_alarm() -> None:
    emulator = GrblEmulator(soft_limits={"X": (-180.0, 180.0)})  # tighter than the rig's travel
    s = emulated(emulator)
    with pytest.raises(StageAlarm, match="alarm 2 during 'G21G90G0X270.000': motion target exceeds machine travel"):
        s.move_to({"turntable": math.radians(270)})
    assert not s.moving
    s.shutdown()


def test_emulator_homing_then_moves_and_shutdown_is_final() -> None:
    homed = Axis("turntable", AxisKind.ROTARY, TURNTABLE.limits, math.radians(360), requires_homing=True)
    emulator = GrblEmulator(homing=True)
    s = emulated(emulator, (homed,))
    s.home().wait(wait_bound_s(1.0))
    for deg in (45, 90, -30):
        s.move_to({"turntable": math.radians(deg)}).wait(wait_bound_s(1.0))
        assert math.degrees(s.position()["turntable"]) == pytest.approx(deg, abs=1e-3)
    s.shutdown()
    s.shutdown()
    with pytest.raises(DeviceDisconnected):
        s.position()


def test_devices_probe_names_a_grbl_controller(monkeypatch: pytest.MonkeyPatch) -> None:
    from slscan.commands import devices as devices_command

    monkeypatch.setattr(grbl, "serial_opener", lambda name, port, timeout_s=0.2: GrblEmulator)
    assert devices_command._probe_stage("/dev/ttyUSB0") == ('Grbl 1.1h motion controller  (driver grbl: a turntable '
                                                            'or slide; [stage] driver = "grbl")')
    monkeypatch.setattr(grbl, "serial_opener", lambda name, port, timeout_s=0.2: lambda: port_silent())
    assert devices_command._probe_stage("/dev/ttyUSB0", boot_timeout_s=0.3) is None


def port_silent() -> FakeSerial:
    return port([Exchange(b"\x18", SILENT)] * 100)
