"""DLPC350 (TI DLP LightCrafter 4500) USB HID protocol: pure byte encoding and decoding.

No I/O here: `scanner.drivers.lightcrafter` sends what this module builds. Every fact is
cited; the sources, read (not copied) while writing this module:

  [API]  TI's LightCrafter 4500 host API, `dlpc350_api.cpp` / `dlpc350_api.h`
         (Copyright 2015 Texas Instruments; BSD-style licence), as published in the
         repository cryeo/lightcrafter, folder lightcrafter/dlpc/. Its comments give the
         USB command of each API call as "CMD2, CMD3" and refer to the DLPC350
         Programmer's Guide (TI DLPU010) by table number.
  [API13] The 2013 edition of the same TI API (`API.cpp`, repository jaybo/LightCrafter4500).
  [PYC]  pycrafter4500 (repository SivyerLab/pyCrafter4500, pycrafter4500/pycrafter4500.py):
         a pyusb driver; shows the bytes on the wire (no report-id byte with pyusb,
         interrupt endpoints 0x01 OUT / 0x81 IN, flag bytes 0xC0 read / 0x40 write).
  [G900] TI DLPC900 Programmer's Guide (DLPU018J) section 1.2, "USB Interface": the same
         HID transaction format in TI's next controller (64-byte reports, only the first
         carrying the header; the reply echoes the host's sequence byte).
  [E2E]  TI E2E forum thread 451589, "LED polarity discrepancy between manual and
         effective behaviour" (LightCrafter 4500 LED currents).

Message layout ([API] `hidMessageStruct`, [G900] 1.2.1):
    byte 0      flags: bit 7 read (1) / write (0), bit 6 reply wanted, bit 5 NACK (set by
                the device on error), bits 2:0 destination (0 = projector control)
    byte 1      sequence byte, echoed in the reply
    bytes 2-3   length, little-endian: bytes that follow (the 2 command bytes + payload
                for a command; the data bytes for a reply)
    bytes 4-5   the 16-bit command CMD2 << 8 | CMD3, little-endian (so CMD3 goes first)
    bytes 6-    payload
A message longer than one 64-byte report continues, without a header, in further reports;
the last one is zero-padded ([API] `DLPC350_SendMsg`, [G900] 1.2.1). A reply is read the
same way; its NACK bit, or a zero length on a read, means the command failed ([API]
`DLPC350_Read`, `DLPC350_Write`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

VENDOR_ID = 0x0451  # [API] MY_VID / [PYC] usb.core.find(idVendor=0x0451, idProduct=0x6401)
PRODUCT_ID = 0x6401
REPORT_SIZE = 64  # [API] USB_MAX_PACKET_SIZE; [G900] "limited to 64 bytes in both directions"
HEADER_SIZE = 4
MAX_MESSAGE = 512  # [API] HID_MESSAGE_MAX_SIZE (the controller's command buffer)

FLAG_READ = 0x80
FLAG_REPLY = 0x40
FLAG_NACK = 0x20

WIDTH, HEIGHT = 912, 1140  # [API] DLPC350_SetMode: pattern mode "pixel resolution of 912 x 1140"

# Trigger edge delays count in steps of 107.2 ns, 0xBB meaning 0 ([API] DLPC350_SetTrigOutConfig:
# "0x00 = -20.05 us ... 0xBB = 0.00 us ... 0xD5 = +2.787 us"; DLPC350_SetTrigIn1Delay: "0 = 0 ns,
# each bit adds 107.2 ns", bits 18:0 valid).
DELAY_STEP_US = 0.1072
TRIG_OUT_ZERO = 0xBB
TRIG_OUT_MAX = 0xD5
TRIG_IN_MAX = 0x7FFFF

EXPOSURE_GAP_US = 230  # [API] SetExposure_FramePeriod: exposure == period, or <= period - 230 us


class Command(IntEnum):
    """USB commands, CMD2 << 8 | CMD3 ([API] CmdList and each API call's "(USB: CMD2, CMD3)")."""

    POWER_CONTROL = 0x0200  # DLPC350_SetPowerMode: 1 byte, 1 = standby, 0 = normal
    GET_VERSION = 0x0205  # DLPC350_GetVersion: reply 4 x uint32 (application, API, SW config, sequence config)
    LED_CURRENT = 0x0B01  # DLPC350_SetLedCurrents: 3 bytes red, green, blue PWM
    STATUS_HARDWARE = 0x1A0A  # DLPC350_GetStatus: reply 1 byte
    STATUS_SYSTEM = 0x1A0B
    STATUS_MAIN = 0x1A0C
    LUT_VALIDATE = 0x1A1A  # DLPC350_ValidatePatLutData: write 1 byte, then read status until bit 7 clears
    DISPLAY_MODE = 0x1A1B  # DLPC350_SetMode: 1 byte, 1 = pattern display, 0 = video
    TRIG_OUT1 = 0x1A1D  # DLPC350_SetTrigOutConfig(1): invert, rising delay, falling delay
    TRIG_OUT2 = 0x1A1E  # DLPC350_SetTrigOutConfig(2): invert, rising delay (CmdList length 2)
    PATTERN_SOURCE = 0x1A22  # DLPC350_SetPatternDisplayMode: 0 = video port, 3 = flash
    TRIGGER_MODE = 0x1A23  # DLPC350_SetPatternTriggerMode: 0 = VSYNC, 1 = internal or external (TRIG_IN)
    START_STOP = 0x1A24  # DLPC350_PatternDisplay: 0 stop, 1 pause, 2 start
    EXPOSURE_PERIOD = 0x1A29  # DLPC350_SetExposure_FramePeriod: uint32 exposure us, uint32 period us
    PATTERN_CONFIG = 0x1A31  # DLPC350_SetPatternConfig: entries-1, repeat, trig-out-2 count-1, images-1
    MAILBOX_ADDRESS = 0x1A32  # DLPC350_MailboxSetAddr: 1 byte, 0..127
    MAILBOX_CONTROL = 0x1A33  # DLPC350_OpenMailbox / CloseMailbox: 0 close, 1 image LUT, 2 pattern LUT
    MAILBOX_DATA = 0x1A34  # DLPC350_SendPatLut / SendImageLut
    TRIG_IN1_DELAY = 0x1A35  # DLPC350_SetTrigIn1Delay: uint32, bits 18:0


class PatternSource(IntEnum):
    VIDEO = 0  # "streamed through the 24-bit RGB/FPD-link interface" [API] SetPatternDisplayMode
    FLASH = 3  # "fetched from flash memory"


class TriggerMode(IntEnum):
    VSYNC = 0  # "VSYNC serves to trigger the pattern display sequence" [API] SetPatternTriggerMode
    INTERNAL_OR_EXTERNAL = 1  # "Internally or Externally (through TRIG_IN1 and TRIG_IN2) generated trigger"


class LutTrigger(IntEnum):
    """Per-pattern trigger type in the pattern LUT ([API] DLPC350_AddToPatLut, TrigType)."""

    INTERNAL = 0
    EXTERNAL_POSITIVE = 1
    EXTERNAL_NEGATIVE = 2
    NONE = 3  # continue from the previous pattern


class Action(IntEnum):
    STOP = 0  # "the next Start restarts the sequence from the beginning" [API] PatternDisplay
    PAUSE = 1  # "the next Start re-displays the current pattern"
    START = 2


class Mailbox(IntEnum):
    CLOSED = 0
    IMAGE_LUT = 1
    PATTERN_LUT = 2


LEDS = {"none": 0, "red": 1, "green": 2, "yellow": 3, "blue": 4, "magenta": 5, "cyan": 6, "white": 7}
# [API] AddToPatLut LEDSelect: b0 red, b1 green, b2 blue.

# Validation status bits ([API] DLPC350_ValidatePatLutData / CheckPatLutValidate).
VALIDATION_BUSY = 0x80
VALIDATION_PROBLEMS = {
    0: ("error", "exposure or frame period settings are invalid"),
    1: ("error", "pattern numbers in the LUT are invalid"),
    2: ("error", "continuous TRIG_OUT1 request or overlapping black sectors (the camera would not see one "
                 "edge per pattern)"),
    3: ("warning", "post vector was not inserted prior to an external triggered vector"),
    4: ("warning", "frame period and exposure differ by less than 230 us"),
}


@dataclass(frozen=True)
class LutEntry:
    """One pattern LUT entry ([API] DLPC350_AddToPatLut, Programmer's Guide table 2-65).

    `pattern`: bit-plane group of the current 24-bit image (for 8-bit patterns 0 = green,
    1 = red, 2 = blue: "Channel A as Green, Channel B as Red, Channel C as Blue", [API]
    DLPC350_SetDataChannelSwap; [PYC] pattern_mode uses 0, 1, 2 for 8-bit patterns);
    `buffer_swap`: move on to the next image of the image LUT at this pattern."""

    trigger: LutTrigger
    pattern: int
    bit_depth: int = 8
    leds: int = LEDS["white"]
    invert: bool = False
    insert_black: bool = False
    buffer_swap: bool = False
    trig_out_prev: bool = False

    def encode(self) -> bytes:
        """3 bytes: trigger (1:0) | pattern (7:2); bit depth (3:0) | LEDs (6:4); flags
        invert, insert black, buffer swap, TRIG_OUT1 continued (bits 0..3) ([API] lutWord)."""
        if not 0 <= self.pattern <= 24:  # [API] "if(PatNum > 24) return -1"
            raise ValueError(f"pattern number {self.pattern} outside 0..24")
        if not 1 <= self.bit_depth <= 8:
            raise ValueError(f"bit depth {self.bit_depth} outside 1..8")
        if not 0 <= self.leds <= 7:
            raise ValueError(f"LED select {self.leds} outside 0..7")
        word = (int(self.trigger) & 3) | (self.pattern << 2) | (self.bit_depth << 8) | (self.leds << 12)
        word |= (self.invert << 16) | (self.insert_black << 17) | (self.buffer_swap << 18) | (self.trig_out_prev << 19)
        return word.to_bytes(3, "little")


# ------------------------------------------------------------------------------ framing


def frame(command: Command | int, payload: bytes, seq: int, read: bool = False) -> list[bytes]:
    """The 64-byte reports carrying one command (a reply is always requested, so every
    write is acknowledged and a NACK is seen)."""
    body = int(command).to_bytes(2, "little") + bytes(payload)
    if len(body) > MAX_MESSAGE:
        raise ValueError(f"command 0x{int(command):04X}: {len(body)} bytes exceed the {MAX_MESSAGE}-byte buffer")
    flags = FLAG_REPLY | (FLAG_READ if read else 0)
    message = bytes([flags, seq & 0xFF]) + len(body).to_bytes(2, "little") + body
    n = math.ceil(len(message) / REPORT_SIZE)
    message = message.ljust(n * REPORT_SIZE, b"\0")
    return [message[i * REPORT_SIZE:(i + 1) * REPORT_SIZE] for i in range(n)]


@dataclass(frozen=True)
class ReplyHeader:
    flags: int
    seq: int
    length: int

    @property
    def nack(self) -> bool:
        return bool(self.flags & FLAG_NACK)

    @property
    def continuation_reports(self) -> int:
        """Further reports holding the rest of the reply's data."""
        return max(0, math.ceil((self.length - (REPORT_SIZE - HEADER_SIZE)) / REPORT_SIZE))


def parse_header(report: bytes) -> ReplyHeader:
    if len(report) < HEADER_SIZE:
        raise ValueError(f"reply of {len(report)} bytes is shorter than the 4-byte header")
    return ReplyHeader(report[0], report[1], int.from_bytes(report[2:4], "little"))


def reply_data(reports: list[bytes], header: ReplyHeader) -> bytes:
    """The `header.length` data bytes spread over the reply's reports."""
    data = reports[0][HEADER_SIZE:] + b"".join(reports[1:])
    return bytes(data[:header.length])


# ------------------------------------------------------------------------------ payloads


def power(standby: bool) -> bytes:
    return bytes([1 if standby else 0])


def display_mode(pattern: bool) -> bytes:
    return bytes([1 if pattern else 0])


def exposure_period(exposure_us: int, period_us: int) -> bytes:
    """[API] SetExposure_FramePeriod: "Either the exposure time must be equivalent to the
    frame period, or the exposure time must be less than the frame period by 230 us"."""
    if not (exposure_us == period_us or 0 < exposure_us <= period_us - EXPOSURE_GAP_US):
        raise ValueError(f"exposure {exposure_us} us must equal the period {period_us} us or be at least "
                         f"{EXPOSURE_GAP_US} us shorter")
    if period_us >= 2 ** 32:
        raise ValueError(f"period {period_us} us does not fit 32 bits")
    return exposure_us.to_bytes(4, "little") + period_us.to_bytes(4, "little")


def pattern_config(n_entries: int, repeat: bool, trig_out2_every: int, n_images: int) -> bytes:
    """[API] SetPatternConfig: each count is sent minus one ("0 means 1"); entries 1..128
    ([API] GetPatLut: "numEntries > 128"), TRIG_OUT2 every 1..256 patterns, images 1..64."""
    if not 1 <= n_entries <= 128:
        raise ValueError(f"{n_entries} LUT entries: the pattern LUT holds 1..128")
    if not 1 <= trig_out2_every <= 256:
        raise ValueError(f"TRIG_OUT2 period {trig_out2_every} outside 1..256 patterns")
    if not 1 <= n_images <= 64:
        raise ValueError(f"{n_images} image LUT entries outside 1..64")
    return bytes([n_entries - 1, 1 if repeat else 0, trig_out2_every - 1, n_images - 1])


def mailbox_address(address: int) -> bytes:
    if not 0 <= address <= 127:  # [API] MailboxSetAddr "0-127"
        raise ValueError(f"mailbox address {address} outside 0..127")
    return bytes([address])


def pattern_lut(entries: list[LutEntry]) -> bytes:
    """Mailbox data for the pattern LUT: 3 bytes per entry, in order ([API] SendPatLut)."""
    return b"".join(e.encode() for e in entries)


def image_lut(indices: list[int]) -> bytes:
    """Mailbox data for the image LUT: one flash image index per byte ([API] SendImageLut,
    which sends a LUT of exactly two entries in swapped order; reproduced here)."""
    if not 1 <= len(indices) <= 64 or any(not 0 <= i <= 255 for i in indices):
        raise ValueError(f"image LUT {indices}: 1..64 flash image indices 0..255")
    return bytes([indices[1], indices[0]] if len(indices) == 2 else indices)


def trig_out_delay(delay_us: float) -> int:
    """Delay register value for TRIG_OUT1/2 edges: 0xBB + delay / 107.2 ns, within -20.05..+2.79 us."""
    value = TRIG_OUT_ZERO + round(delay_us / DELAY_STEP_US)
    if not 0 <= value <= TRIG_OUT_MAX:
        raise ValueError(f"trigger-out delay {delay_us} us outside -20.05..+2.787 us")
    return value


def trig_out1(invert: bool, rising_us: float, falling_us: float) -> bytes:
    return bytes([1 if invert else 0, trig_out_delay(rising_us), trig_out_delay(falling_us)])


def trig_out2(invert: bool, rising_us: float) -> bytes:
    return bytes([1 if invert else 0, trig_out_delay(rising_us)])


def trig_in1_delay(delay_us: float) -> bytes:
    value = round(delay_us / DELAY_STEP_US)
    if not 0 <= value <= TRIG_IN_MAX:
        raise ValueError(f"TRIG_IN1 delay {delay_us} us outside 0..{TRIG_IN_MAX * DELAY_STEP_US:.0f} us")
    return value.to_bytes(4, "little")


def led_currents(red: int, green: int, blue: int) -> bytes:
    """PWM duty bytes 0..255 per LED ([API] SetLedCurrents). On LightCrafter 4500 boards the
    effective polarity has been reported inverted (0xFF = off, [E2E]); the bytes are sent
    as given, so check the brightness on the bench."""
    values = (red, green, blue)
    if any(not 0 <= v <= 255 for v in values):
        raise ValueError(f"LED currents {values} outside 0..255")
    return bytes(values)


def validation_problems(status: int) -> list[tuple[str, str]]:
    """(severity, text) for every problem bit set in a validation status byte."""
    return [VALIDATION_PROBLEMS[b] for b in sorted(VALIDATION_PROBLEMS) if status & (1 << b)]


def parse_version(data: bytes) -> dict[str, str]:
    """[API] GetVersion: four uint32, each bits 31:24 major, 23:16 minor, 15:0 patch."""
    if len(data) < 16:
        raise ValueError(f"version reply of {len(data)} bytes, expected 16")
    names = ("application", "api", "software_config", "sequence_config")
    out = {}
    for i, name in enumerate(names):
        v = int.from_bytes(data[4 * i:4 * i + 4], "little")
        out[name] = f"{v >> 24}.{(v >> 16) & 0xFF}.{v & 0xFFFF}"
    return out
