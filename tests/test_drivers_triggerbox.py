"""Trigger box driver: the exact serial line exchanges, the board resetting on port open,
error replies, silence and an unplugged cable. No hardware needed, no wall time measured."""

from __future__ import annotations

import time

import pytest

from scanner.drivers import triggerbox
from scanner.drivers.testing import SILENT, Exchange, FakeSerial, Unplug, expected_protocol, wait_bound_s
from scanner.drivers.triggerbox import TriggerBox
from scanner.errors import DeviceDisconnected, DeviceError, DeviceTimeout, UnsupportedSetting

HELLO = Exchange(b"ID?\n", b"ID SLSCAN-TRIGGERBOX 2 rp2040\n")
HELLO_V1 = Exchange(b"ID?\n", b"ID SLSCAN-TRIGGERBOX 1 avr\n")  # firmware without the input
ARM_12 = [Exchange(b"PERIOD 50000\n", b"OK\n"), Exchange(b"WIDTH 100\n", b"OK\n"), Exchange(b"ARM 12\n", b"OK\n")]


def box(opener, **kw) -> TriggerBox:
    return TriggerBox(opener, boot_timeout_s=kw.pop("boot_timeout_s", 1.0), timeout_s=kw.pop("timeout_s", 0.2), **kw)


def test_arm_start_count_stop_exchange() -> None:
    script = [HELLO,
              Exchange(b"PERIOD 50000\n", b"OK\n"), Exchange(b"WIDTH 100\n", b"OK\n"), Exchange(b"ARM 12\n", b"OK\n"),
              Exchange(b"START\n", b"OK\n"),
              Exchange(b"COUNT?\n", b"COUNT 5 12\n"),
              Exchange(b"STOP\n", b"OK\n"),
              Exchange(b"STOP\n", b"OK\n")]  # shutdown stops once more
    with expected_protocol(box, FakeSerial(script)) as b:
        assert b.describe()["board"] == "rp2040"
        b.arm(12, 0.05, 1e-4)
        b.start()
        assert b.pulses_sent == 5
        b.stop()
        b.shutdown()


def test_board_resetting_on_open_is_asked_again_at_its_banner(monkeypatch: pytest.MonkeyPatch) -> None:
    # the first ID? is lost while the bootloader runs; the READY banner comes 0.1 s after opening.
    # The retry window outlasts the boot timeout, so only asking again at the banner can succeed.
    monkeypatch.setattr(triggerbox, "_ID_RETRY_S", 600.0)
    script = [Exchange(b"ID?\n", SILENT), HELLO]
    port = FakeSerial(script, banner=b"\x00\xffREADY SLSCAN-TRIGGERBOX 2\r\n", banner_delay_s=0.1, timeout=0.05)
    with expected_protocol(lambda o: box(o, boot_timeout_s=30.0), port) as b:
        assert b.identity == {"protocol": "2", "board": "rp2040"}


def test_silent_port_times_out_within_boot_timeout() -> None:
    script = [Exchange(b"ID?\n", SILENT)] * 20
    boot_timeout = 0.5
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="trigger-box: device timeout: no answer to ID\\? after 0.5 s; is this "
                                            ".*firmware/triggerbox") as exc:
        TriggerBox(lambda: FakeSerial(script, timeout=0.05), boot_timeout_s=boot_timeout)
    assert boot_timeout <= time.monotonic() - t0 < wait_bound_s(boot_timeout)
    assert (exc.value.device, exc.value.timeout_s) == ("trigger-box", boot_timeout)


def test_wrong_device_or_protocol_is_refused() -> None:
    with pytest.raises(DeviceError, match="not an SLSCAN-TRIGGERBOX"):
        TriggerBox(lambda: FakeSerial([Exchange(b"ID?\n", b"ID OTHER-THING 1 x\n")]))
    with pytest.raises(DeviceError, match="protocol 3, this driver 1..2"):
        TriggerBox(lambda: FakeSerial([Exchange(b"ID?\n", b"ID SLSCAN-TRIGGERBOX 3 avr\n")]))


def test_error_reply_names_the_command() -> None:
    script = [HELLO, Exchange(b"PERIOD 50000\n", b"OK\n"), Exchange(b"WIDTH 100\n", b"OK\n"),
              Exchange(b"ARM 12\n", b"ERR 5 busy\n")]
    with (expected_protocol(box, FakeSerial(script)) as b,
          pytest.raises(DeviceError, match="'ARM 12' refused: error 5, busy")):
        b.arm(12, 0.05, 1e-4)


def test_out_of_range_train_is_refused_before_sending() -> None:
    with expected_protocol(box, FakeSerial([HELLO])) as b, pytest.raises(UnsupportedSetting, match="period 50 us"):
        b.arm(3, 50e-6, 1e-6)


def test_no_reply_times_out_and_reconnects() -> None:
    first = FakeSerial([HELLO, *ARM_12, Exchange(b"START\n", SILENT)], timeout=0.05)
    second = FakeSerial([HELLO, *ARM_12, Exchange(b"START\n", b"OK\n")])  # a new link: armed again
    with expected_protocol(box, first, second) as b:
        b.arm(12, 0.05, 1e-4)
        with pytest.raises(DeviceTimeout, match="trigger-box: device timeout: no reply to 'START' after 0.2 s; the "
                                                "link is reopened"):
            b.start()
        assert first.closed
        with pytest.raises(UnsupportedSetting, match="not armed"):  # one start per arm: refused before sending
            b.start()
        b.arm(12, 0.05, 1e-4)
        b.start()


def test_unplugged_mid_sequence_then_reconnects() -> None:
    first = FakeSerial([HELLO, Exchange(b"PERIOD 50000\n", b"OK\n"), Unplug()])
    second = FakeSerial([HELLO, Exchange(b"PERIOD 50000\n", b"OK\n"), Exchange(b"WIDTH 100\n", b"OK\n"),
                         Exchange(b"ARM 12\n", b"OK\n")])
    with expected_protocol(box, first, second) as b:
        with pytest.raises(DeviceDisconnected, match="serial link lost sending 'WIDTH 100'"):
            b.arm(12, 0.05, 1e-4)
        b.arm(12, 0.05, 1e-4)


def test_box_restarting_mid_command_is_reported() -> None:
    script = [HELLO, *ARM_12, Exchange(b"START\n", b"READY SLSCAN-TRIGGERBOX 2\n")]
    with expected_protocol(box, FakeSerial(script)) as b:
        b.arm(12, 0.05, 1e-4)
        with pytest.raises(DeviceError, match="restarted while handling 'START'"):
            b.start()


def test_foot_switch_presses_are_counted_between_polls() -> None:
    # the box counts presses since it started; the driver reports those since its last poll
    script = [HELLO,
              Exchange(b"PRESSES?\n", b"PRESSES 4\n"),   # first poll: the baseline, presses before it do not count
              Exchange(b"PRESSES?\n", b"PRESSES 4\n"),
              Exchange(b"PRESSES?\n", b"PRESSES 5\n"),
              Exchange(b"PRESSES?\n", b"PRESSES 7\n"),
              Exchange(b"STOP\n", b"OK\n")]
    with expected_protocol(box, FakeSerial(script)) as b:
        assert [b.presses() for _ in range(4)] == [0, 0, 1, 2]
        b.shutdown()


def test_foot_switch_count_of_a_restarted_box_is_all_new() -> None:
    first = FakeSerial([HELLO, Exchange(b"PRESSES?\n", b"PRESSES 9\n"), Unplug()])
    second = FakeSerial([HELLO, Exchange(b"PRESSES?\n", b"PRESSES 1\n")])  # it rebooted: counts from 0 again
    with expected_protocol(box, first, second) as b:
        assert b.presses() == 0
        with pytest.raises(DeviceDisconnected, match="serial link lost sending 'PRESSES\\?'"):
            b.presses()
        assert b.presses() == 1


def test_foot_switch_on_protocol_1_firmware_is_refused_without_asking() -> None:
    script = [HELLO_V1, Exchange(b"COUNT?\n", b"COUNT 0 0\n")]
    with expected_protocol(box, FakeSerial(script)) as b:
        assert b.pulses_sent == 0  # protocol 1 still drives pulse trains
        with pytest.raises(UnsupportedSetting, match="firmware protocol 1 has no input .*flash firmware/triggerbox"):
            b.presses()


def test_garbled_press_count_is_an_error() -> None:
    with (expected_protocol(box, FakeSerial([HELLO, Exchange(b"PRESSES?\n", b"PRESSES x\n")])) as b,
          pytest.raises(DeviceError, match="unexpected reply to PRESSES\\?: 'PRESSES x'")):
        b.presses()


def test_simulated_box_counts_its_foot_switch_like_the_driver() -> None:
    from sim.virtual_devices import SimTriggerBox

    sim = SimTriggerBox()
    sim.press()  # before the first poll: not counted
    assert sim.presses() == 0
    sim.press()
    sim.press()
    assert (sim.presses(), sim.presses()) == (2, 0)
    sim.shutdown()
    sim.press()  # a switch does not throw into a dead box
    with pytest.raises(DeviceDisconnected):
        sim.presses()
