"""LightCrafter 4500 (DLPC350) driver: the exact USB HID reports of every command, of a
complete phase-shift sequence set-up, and the injected faults. No hardware needed."""

from __future__ import annotations

import time

import numpy as np
import pytest

from scanner.config import CONFIG_DIR
from scanner.drivers import lightcrafter_protocol as p
from scanner.drivers.lightcrafter import LightCrafter4500
from scanner.drivers.lightcrafter_images import diamond_resample, fingerprint, pack_rgb24
from scanner.drivers.testing import SILENT, Exchange, FakeHid, ProtocolMismatch, Unplug, expected_protocol, wait_bound_s
from scanner.errors import DeviceDisconnected, DeviceError, DeviceTimeout, UnsupportedSetting
from scanner.patterns import PatternSet

PATTERNS = PatternSet.load(CONFIG_DIR / "patterns" / "heterodyne_3x4.toml").render(912, 1140, 2.2)
SHA = fingerprint(pack_rgb24(diamond_resample(PATTERNS)))


def rep(hexstr: str) -> bytes:
    """One 64-byte report from hex, zero-padded."""
    return bytes.fromhex(hexstr).ljust(64, b"\0")


def ack(seq: int, flags: int = 0x00) -> bytes:
    return rep(f"{flags:02x} {seq:02x} 00 00")


def w(seq: int, body: str) -> Exchange:
    """A write with reply wanted (flags 0x40), its length computed from `body` by hand-counted hex."""
    n = len(bytes.fromhex(body))
    return Exchange(rep(f"40 {seq:02x} {n:02x} 00 {body}"), ack(seq))


def lcr(opener, **kw) -> LightCrafter4500:
    return LightCrafter4500(opener, flash_images_sha256=SHA, **kw)


# one entry per pattern: internal trigger, pattern 0/1/2 (green, red, blue), 8 bits (0x08), white
# LEDs (0x70), buffer swap (byte 2 = 0x04) on the first pattern of each 24-bit image
LUT_12 = " ".join(["00 78 04", "04 78 00", "08 78 00"] * 4)
SETUP_12 = [  # the complete phase-shift set-up for 12 patterns, 50 ms period, flash images 0..3
    w(0, "24 1a 00"),  # 0x1A24 pattern display: stop
    w(1, "1b 1a 01"),  # 0x1A1B display mode: pattern
    w(2, "22 1a 03"),  # 0x1A22 pattern source: flash
    w(3, "23 1a 01"),  # 0x1A23 trigger mode 1: internal/external
    w(4, "29 1a 50 c3 00 00 50 c3 00 00"),  # 0x1A29 exposure 50000 us, period 50000 us
    w(5, "31 1a 0b 00 0b 03"),  # 0x1A31 12 entries, once, TRIG_OUT2 every 12, 4 images
    w(6, "1d 1a 00 bb bb"),  # 0x1A1D TRIG_OUT1 active high, no delays
    w(7, "1e 1a 00 bb"),  # 0x1A1E TRIG_OUT2 active high, no delay
    w(8, "35 1a 00 00 00 00"),  # 0x1A35 TRIG_IN1 delay 0
    w(9, "33 1a 02"),  # mailbox: open pattern LUT
    w(10, "32 1a 00"),  # mailbox address 0
    w(11, f"34 1a {LUT_12}"),  # 36 bytes of pattern LUT
    w(12, "33 1a 00"),  # mailbox: close
    w(13, "33 1a 01"),  # mailbox: open image LUT
    w(14, "32 1a 00"),
    w(15, "34 1a 00 01 02 03"),  # flash images 0, 1, 2, 3
    w(16, "33 1a 00"),
    w(17, "1a 1a 00"),  # 0x1A1A validate
    Exchange(rep("c0 12 02 00 1a 1a"), rep("00 12 01 00 00")),  # read status: done, no problem
]


def test_framing_splits_long_messages_into_continuation_reports() -> None:
    data = bytes(range(90))
    reports = p.frame(p.Command.MAILBOX_DATA, data, seq=7)
    assert reports == [rep("40 07 5c 00 34 1a" + data[:58].hex()), rep(data[58:].hex())]
    assert p.parse_header(rep("20 07 00 00")).nack and p.parse_header(rep("00 01 9c 00")).continuation_reports == 2


@pytest.mark.parametrize("call, body", [
    (lambda d: d.stop(), "24 1a 00"),
    (lambda d: d.pause(), "24 1a 01"),
    (lambda d: d.start(), "24 1a 02"),
    (lambda d: d.set_standby(True), "00 02 01"),
    (lambda d: d.set_standby(False), "00 02 00"),
    (lambda d: d.set_led_currents(10, 20, 255), "01 0b 0a 14 ff"),
    (lambda d: d.command(p.Command.DISPLAY_MODE, p.display_mode(False)), "1b 1a 00"),
    (lambda d: d.command(p.Command.PATTERN_SOURCE, bytes([p.PatternSource.VIDEO])), "22 1a 00"),
    (lambda d: d.command(p.Command.TRIGGER_MODE, bytes([p.TriggerMode.VSYNC])), "23 1a 00"),
    (lambda d: d.command(p.Command.EXPOSURE_PERIOD, p.exposure_period(9770, 10000)), "29 1a 2a 26 00 00 10 27 00 00"),
    (lambda d: d.command(p.Command.PATTERN_CONFIG, p.pattern_config(24, True, 3, 8)), "31 1a 17 01 02 07"),
    (lambda d: d.command(p.Command.TRIG_OUT1, p.trig_out1(True, -2.144, 1.072)), "1d 1a 01 a7 c5"),
    (lambda d: d.command(p.Command.TRIG_OUT2, p.trig_out2(False, 0.5360)), "1e 1a 00 c0"),
    (lambda d: d.command(p.Command.TRIG_IN1_DELAY, p.trig_in1_delay(10.72)), "35 1a 64 00 00 00"),
    (lambda d: d.command(p.Command.MAILBOX_CONTROL, bytes([p.Mailbox.PATTERN_LUT])), "33 1a 02"),
    (lambda d: d.command(p.Command.MAILBOX_ADDRESS, p.mailbox_address(5)), "32 1a 05"),
    (lambda d: d.command(p.Command.MAILBOX_DATA, p.pattern_lut([p.LutEntry(
        p.LutTrigger.EXTERNAL_POSITIVE, 24, 1, p.LEDS["blue"], invert=True, insert_black=True, trig_out_prev=True)])),
     "34 1a 61 41 0b"),
    (lambda d: d.command(p.Command.MAILBOX_DATA, p.image_lut([5, 6])), "34 1a 06 05"),  # TI's 2-entry swap
    (lambda d: d.command(p.Command.MAILBOX_DATA, p.image_lut([5, 6, 7])), "34 1a 05 06 07"),
])
def test_each_write_command_sends_exact_report(call, body: str) -> None:
    with expected_protocol(lcr, FakeHid([w(0, body)])) as d:
        call(d)


def test_reads_decode_version_and_status() -> None:
    version = "00 00 00 03 02 00 01 04 00 00 00 01 00 00 05 02"  # uint32 LE: major 31:24, minor 23:16, patch 15:0
    script = [Exchange(rep("c0 00 02 00 05 02"), rep(f"00 00 10 00 {version}")),
              Exchange(rep("c0 01 02 00 0a 1a"), rep("00 01 01 00 01")),
              Exchange(rep("c0 02 02 00 0b 1a"), rep("00 02 01 00 01")),
              Exchange(rep("c0 03 02 00 0c 1a"), rep("00 03 01 00 02"))]
    with expected_protocol(lcr, FakeHid(script)) as d:
        assert d.version() == {"application": "3.0.0", "api": "4.1.2", "software_config": "1.0.0",
                               "sequence_config": "2.5.0"}
        assert d.status() == {"hardware": 1, "system": 1, "main": 2}


def test_validation_polls_until_done_and_reports_warnings() -> None:
    script = [w(0, "1a 1a 00"),
              Exchange(rep("c0 01 02 00 1a 1a"), rep("00 01 01 00 80")),  # busy
              Exchange(rep("c0 02 02 00 1a 1a"), rep("00 02 01 00 80")),
              Exchange(rep("c0 03 02 00 1a 1a"), rep("00 03 01 00 10"))]  # done, warning bit 4
    with expected_protocol(lcr, FakeHid(script)) as d:
        assert d.validate() == ["frame period and exposure differ by less than 230 us"]


def test_complete_phase_shift_sequence_setup_run_and_stop() -> None:
    script = SETUP_12 + [w(19, "24 1a 02"), w(20, "24 1a 00"), w(21, "24 1a 00")]
    with expected_protocol(lcr, FakeHid(script)) as d:
        d.load_patterns(PATTERNS)  # programs and validates, does not start
        status = d.run_sequence(0.05)  # start; the DLPC350 runs 12 patterns of 50 ms by itself
        d.stop_sequence()
        assert status.done and not status.success
        with pytest.raises(DeviceError, match=r"lightcrafter4500: pattern sequence \(12 patterns every 0.05 s\) "
                                              r"stopped before it had run"):
            status.wait(1.0)
        d.shutdown()  # stop once more, then release the link


def test_sequence_status_finishes_after_its_patterns_have_run() -> None:
    """The DLPC350 reports nothing at the end of a sequence: the status finishes once N
    periods have passed after START, with no further exchange on the link."""
    script = SETUP_12 + [w(19, "24 1a 02"), w(20, "24 1a 00")]
    with expected_protocol(lcr, FakeHid(script)) as d:
        d.load_patterns(PATTERNS)
        status = d.run_sequence(0.05)
        status.wait(wait_bound_s(12 * 0.05))
        assert status.success
        d.shutdown()


def test_external_trigger_sequence_waits_for_trig_in() -> None:
    lut = " ".join(["01 78 04", "05 78 00", "09 78 00"] * 4)  # trigger type 1: external positive edge
    script = [s if i != 11 else w(11, f"34 1a {lut}") for i, s in enumerate(SETUP_12)] + [w(19, "24 1a 02")]
    with expected_protocol(lambda o: lcr(o, trigger="external"), FakeHid(script)) as d:
        d.load_patterns(PATTERNS)  # started: each TRIG_IN1 rising edge shows the next pattern
        with pytest.raises(UnsupportedSetting, match="trigger 'internal'"):
            d.run_sequence(0.05)


def test_software_wiring_shows_one_pattern_repeating() -> None:
    patterns = PATTERNS[:8]
    sha = fingerprint(pack_rgb24(diamond_resample(patterns)))
    setup8 = list(SETUP_12)
    setup8[5] = w(5, "31 1a 07 00 07 02")  # 8 entries, 3 images
    setup8[11] = w(11, "34 1a " + " ".join((["00 78 04", "04 78 00", "08 78 00"] * 3)[:8]))
    setup8[15] = w(15, "34 1a 01 02 03")  # flash images from 1 on
    show7 = [w(19, "24 1a 00"), w(20, "1b 1a 01"), w(21, "22 1a 03"), w(22, "23 1a 01"),
             w(23, "29 1a 50 c3 00 00 50 c3 00 00"),
             w(24, "31 1a 00 01 00 00"),  # 1 entry, repeated, 1 image
             w(25, "1d 1a 00 bb bb"), w(26, "1e 1a 00 bb"), w(27, "35 1a 00 00 00 00"),
             w(28, "33 1a 02"), w(29, "32 1a 00"), w(30, "34 1a 04 78 04"), w(31, "33 1a 00"),  # pattern 1: red
             w(32, "33 1a 01"), w(33, "32 1a 00"), w(34, "34 1a 03"), w(35, "33 1a 00"),  # image 1 + 7 // 3
             w(36, "1a 1a 00"), Exchange(rep("c0 25 02 00 1a 1a"), rep("00 25 01 00 00")),
             w(38, "24 1a 02")]
    with expected_protocol(lambda o: LightCrafter4500(o, flash_images_sha256=sha, flash_first_image=1),
                           FakeHid(setup8 + show7)) as d:
        d.load_patterns(patterns)
        d.show(7)
        assert d.current_pattern == 7


def test_patterns_are_resampled_for_the_diamond_array() -> None:
    stack = np.tile((2 * np.arange(912)) % 256, (1140, 1)).astype(np.uint8)[None]  # 2 per column
    out = diamond_resample(stack)
    assert np.array_equal(out[0, 0::2], stack[0, 0::2])  # even rows as computed
    assert np.array_equal(out[0, 1, :100], 2 * np.arange(100) + 1)  # odd rows half a column further
    horizontal = np.repeat(np.arange(1140, dtype=np.uint8)[:, None] % 200, 912, axis=1)[None]
    assert np.array_equal(diamond_resample(horizontal), horizontal)  # constant rows are unchanged


def test_flash_images_must_match_the_patterns() -> None:
    with (expected_protocol(lambda o: LightCrafter4500(o, flash_images_sha256="0" * 64), FakeHid([])) as d,
          pytest.raises(UnsupportedSetting, match=f'slscan devices lightcrafter-images.*{SHA}')):
        d.load_patterns(PATTERNS)


def test_nack_names_the_command() -> None:
    script = [Exchange(rep("40 00 03 00 24 1a 02"), ack(0, flags=0x20))]
    with (expected_protocol(lcr, FakeHid(script)) as d,
          pytest.raises(DeviceError, match=r"command 0x1A24 \(START_STOP\) was refused \(NACK\)")):
        d.start()


def test_validation_error_refuses_the_sequence() -> None:
    script = [w(0, "1a 1a 00"), Exchange(rep("c0 01 02 00 1a 1a"), rep("00 01 01 00 03"))]
    with (expected_protocol(lcr, FakeHid(script)) as d,
          pytest.raises(DeviceError, match="exposure or frame period settings are invalid; pattern numbers")):
        d.validate()


def test_validation_that_never_finishes_times_out_in_bounded_time() -> None:
    busy = [w(0, "1a 1a 00")] + [Exchange(rep(f"c0 {s:02x} 02 00 1a 1a"), rep(f"00 {s:02x} 01 00 80"))
                                 for s in range(1, 256)]
    timeout = 0.1
    d = LightCrafter4500(lambda: FakeHid(busy), flash_images_sha256=SHA, validate_timeout_s=timeout)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"lightcrafter4500: device timeout: pattern LUT validation \(0x1A1A\) "
                                            r"still busy after 0.1 s; power-cycle"):
        d.validate()
    assert timeout <= time.monotonic() - t0 < wait_bound_s(timeout)


def test_silent_device_times_out_and_link_is_reopened() -> None:
    first = FakeHid([Exchange(rep("40 00 03 00 24 1a 02"), SILENT)])
    second = FakeHid([w(0, "24 1a 02")])
    with expected_protocol(lcr, first, second) as d:
        with pytest.raises(DeviceTimeout, match=r"lightcrafter4500: device timeout: no reply to command 0x1A24 "
                                                r"\(START_STOP\) after 1 s; the USB link is reopened"):
            d.start()
        assert first.closed
        d.start()  # the next call reconnects (sequence bytes restart at 0)


def test_unplugged_mid_setup_then_reconnects_for_next_scan() -> None:
    first = FakeHid(SETUP_12[:6] + [Unplug()])
    second = FakeHid(SETUP_12 + [w(19, "24 1a 02")])
    with expected_protocol(lcr, first, second) as d:
        with pytest.raises(DeviceDisconnected):
            d.load_patterns(PATTERNS)
        d.load_patterns(PATTERNS)
        d.run_sequence(0.05)


def test_wrong_sequence_byte_in_reply_is_refused() -> None:
    with (expected_protocol(lcr, FakeHid([Exchange(rep("40 00 03 00 24 1a 00"), ack(5))])) as d,
          pytest.raises(DeviceError, match="sequence byte 5, expected 0")):
        d.stop()


def test_fake_reports_any_deviation() -> None:
    with (pytest.raises(ProtocolMismatch, match="expected\n  40 00 03 00 24 1a 00"),
          expected_protocol(lcr, FakeHid([w(0, "24 1a 00")])) as d):
        d.start()
