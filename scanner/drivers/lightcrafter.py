"""TI DLP LightCrafter 4500 (DLPC350 controller) behind the Projector interface.

Commands and their bytes come from `lightcrafter_protocol` (where every fact is cited);
this module sequences them. Every write asks for a reply, so a NACK is seen at the
command that caused it; every read waits at most `timeout_s`; validation polls at most
`validate_timeout_s`.

Pattern sources and wirings (rig TOML `projector.source`, `rig.trigger`):
  flash  The 8-bit patterns are stored in the projector's flash, three to a 24-bit image
         (export them with `slscan devices lightcrafter-images`, add them to a firmware
         image with TI's LightCrafter 4500 GUI; `projector.flash_images_sha256` then names
         them and a scan whose patterns differ is refused). One LUT entry per pattern
         shows its bit planes in sequence; TRIG_OUT1 rises at the start of each pattern
         and exposes the camera.
           trigger "internal" (wiring `projector`): `run_sequence(period)` programs the
             pattern period and starts; the DLPC350 times every pattern and reports
             nothing when done, so the status it returns finishes N periods after START.
           trigger "external" (wiring `trigger_box`): every LUT entry waits for a rising
             edge on TRIG_IN1; `load_patterns` leaves the sequence started and waiting.
           `show(k)` (wiring `software`): a one-entry LUT repeating pattern k.
  video  The projector shows the green plane of its HDMI input as an 8-bit pattern on every
         VSYNC; `show(k)` puts pattern k on that input through a `VideoOutput` (an
         `hdmi.HdmiDisplay` on the LightCrafter's display). Wiring `software` only.

The DMD is 912 x 1140 diamond pixels: patterns are re-sampled for it on loading
(`lightcrafter_images.diamond_resample`).

If the USB link breaks the driver drops it and opens it again at the next call, so the
next scan reconnects after a replug.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Annotated, Any, Literal, Protocol

import numpy as np
from pydantic import Field

from scanner.devices import Projector
from scanner.drivers import lightcrafter_protocol as p
from scanner.drivers.hdmi import LatencyFrames, open_display
from scanner.drivers.lightcrafter_images import PATTERNS_PER_IMAGE, diamond_resample, fingerprint, pack_rgb24
from scanner.drivers.registry import Driver, Triggers, register
from scanner.drivers.transport import HidLink
from scanner.errors import ConfigError, DeviceDisconnected, DeviceError, DeviceTimeout, UnsupportedSetting
from scanner.schema import Float, Int, PositiveFloat, Schema, Str
from scanner.status import Status

if TYPE_CHECKING:
    from scanner.rig import RigConfig

log = logging.getLogger(__name__)

SOURCES = ("flash", "video")
TRIGGERS = ("internal", "external")
_POLL_S = 0.01


class VideoOutput(Protocol):
    """Where the LightCrafter's video-port input comes from (an HDMI output of this host)."""

    refresh_hz: float

    def show(self, image: np.ndarray) -> None: ...

    def close(self) -> None: ...


def open_usb(name: str = "lightcrafter4500", serial_number: str | None = None) -> Callable[[], HidLink]:
    """A factory opening the LightCrafter's HID interface through libusb ([PYC] endpoints)."""
    from scanner.drivers.transport import PyUsbHid

    return lambda: PyUsbHid.open(name, p.VENDOR_ID, p.PRODUCT_ID, serial_number=serial_number)


class LightCrafter4500(Projector):
    """A LightCrafter 4500 running 8-bit pattern sequences (see the module docstring)."""

    def __init__(self, open_link: Callable[[], HidLink], name: str = "lightcrafter4500", *,
                 source: str = "flash", trigger: str = "internal", period_s: float = 0.05,
                 flash_first_image: int = 0, flash_images_sha256: str | None = None, leds: str = "white",
                 led_currents: tuple[int, int, int] | None = None,
                 trig_out1_delays_us: tuple[float, float] = (0.0, 0.0), trig_out2_delay_us: float = 0.0,
                 trig_in1_delay_us: float = 0.0, odd_row_shift: float = 0.5,
                 video: VideoOutput | None = None, timeout_s: float = 1.0, validate_timeout_s: float = 2.0) -> None:
        super().__init__(name, p.WIDTH, p.HEIGHT)
        if source not in SOURCES:
            raise UnsupportedSetting(name, f"pattern source '{source}' is not one of {SOURCES}")
        if trigger not in TRIGGERS:
            raise UnsupportedSetting(name, f"trigger '{trigger}' is not one of {TRIGGERS}")
        if leds not in p.LEDS:
            raise UnsupportedSetting(name, f"LEDs '{leds}' not one of {sorted(p.LEDS)}")
        if source == "video" and video is None:
            raise UnsupportedSetting(name, "the video source needs a video output (projector.video_display)")
        self.source, self.trigger = source, trigger
        self.period_s = period_s
        self.flash_first_image = flash_first_image
        self.flash_images_sha256 = flash_images_sha256
        self.leds = p.LEDS[leds]
        self.led_currents = led_currents
        self.trig_out1_delays_us = trig_out1_delays_us
        self.trig_out2_delay_us = trig_out2_delay_us
        self.trig_in1_delay_us = trig_in1_delay_us
        self.odd_row_shift = odd_row_shift
        self.timeout_s = timeout_s
        self.validate_timeout_s = validate_timeout_s
        self.warnings: list[str] = []
        self._video = video
        self._open_link = open_link
        self._link: HidLink | None = None
        self._seq = 0
        self._patterns: np.ndarray | None = None
        self._programmed: str | None = None  # "sequence", "single", "video" or None
        self._sequence_timer: threading.Timer | None = None  # finishes a running sequence's status
        self._connect()

    # ------------------------------------------------------------------ commands

    def command(self, command: p.Command, payload: bytes = b"") -> None:
        """Send a write command and check its acknowledgement (NACK -> DeviceError)."""
        self._check_alive()
        self._transact(command, payload, read=False)

    def query(self, command: p.Command, params: bytes = b"") -> bytes:
        """Send a read command; the reply's data bytes."""
        self._check_alive()
        return self._transact(command, params, read=True)

    def version(self) -> dict[str, str]:
        return p.parse_version(self.query(p.Command.GET_VERSION))

    def status(self) -> dict[str, int]:
        return {"hardware": self.query(p.Command.STATUS_HARDWARE)[0], "system": self.query(p.Command.STATUS_SYSTEM)[0],
                "main": self.query(p.Command.STATUS_MAIN)[0]}

    def set_standby(self, standby: bool) -> None:
        """Power control: standby powers the DMD interface down; leave it before sending data."""
        self.command(p.Command.POWER_CONTROL, p.power(standby))

    def set_led_currents(self, red: int, green: int, blue: int) -> None:
        self.command(p.Command.LED_CURRENT, p.led_currents(red, green, blue))
        self.led_currents = (red, green, blue)

    def start(self) -> None:
        self.command(p.Command.START_STOP, bytes([p.Action.START]))

    def pause(self) -> None:
        self.command(p.Command.START_STOP, bytes([p.Action.PAUSE]))

    def stop(self) -> None:
        self.command(p.Command.START_STOP, bytes([p.Action.STOP]))

    def validate(self) -> list[str]:
        """Validate the programmed sequence, polling until the controller has finished
        (at most `validate_timeout_s`); errors raise, warnings are returned and kept."""
        self.command(p.Command.LUT_VALIDATE, b"\x00")
        end = time.monotonic() + self.validate_timeout_s
        while True:
            status = self.query(p.Command.LUT_VALIDATE)[0]
            if not status & p.VALIDATION_BUSY:
                break
            if time.monotonic() > end:
                raise DeviceTimeout(self.name, "pattern LUT validation (0x1A1A) still busy", self.validate_timeout_s,
                                    "power-cycle the projector")
            time.sleep(_POLL_S)
        problems = p.validation_problems(status)
        errors = [text for severity, text in problems if severity == "error"]
        if errors:
            raise DeviceError(self.name, f"pattern sequence refused by validation (status 0x{status:02X}): "
                                         f"{'; '.join(errors)}; check period_s, the camera exposure and the "
                                         f"projector settings in the rig TOML")
        self.warnings = [text for severity, text in problems if severity == "warning"]
        for text in self.warnings:
            log.warning("%s: sequence validation warning: %s", self.name, text)
        return self.warnings

    def program(self, entries: list[p.LutEntry], images: list[int], mode: p.TriggerMode, *, source: p.PatternSource,
                repeat: bool, exposure_us: int, period_us: int) -> None:
        """The full set-up of a pattern sequence, in the order of TI's API: stop, pattern
        mode, source, trigger mode, timing, LUT configuration, trigger lines, LEDs, pattern
        LUT and image LUT through the mailbox, then validation. Does not start."""
        c = p.Command
        self.stop()
        self.command(c.DISPLAY_MODE, p.display_mode(pattern=True))
        self.command(c.PATTERN_SOURCE, bytes([source]))
        self.command(c.TRIGGER_MODE, bytes([mode]))
        self.command(c.EXPOSURE_PERIOD, p.exposure_period(exposure_us, period_us))
        self.command(c.PATTERN_CONFIG, p.pattern_config(len(entries), repeat, len(entries), len(images)))
        self.command(c.TRIG_OUT1, p.trig_out1(False, *self.trig_out1_delays_us))
        self.command(c.TRIG_OUT2, p.trig_out2(False, self.trig_out2_delay_us))
        self.command(c.TRIG_IN1_DELAY, p.trig_in1_delay(self.trig_in1_delay_us))
        if self.led_currents is not None:
            self.command(c.LED_CURRENT, p.led_currents(*self.led_currents))
        self._mailbox(p.Mailbox.PATTERN_LUT, p.pattern_lut(entries))
        if source is p.PatternSource.FLASH:
            self._mailbox(p.Mailbox.IMAGE_LUT, p.image_lut(images))
        self.validate()

    # ------------------------------------------------------------------ Projector

    def _do_load_patterns(self, patterns: np.ndarray) -> None:
        stack = diamond_resample(patterns, self.odd_row_shift)
        self._programmed = None
        if self.source == "video":
            self._patterns = stack
            self._program_video()
            return
        n = len(stack)
        if n > 128:
            raise UnsupportedSetting(self.name, f"{n} patterns: the pattern LUT holds at most 128")
        sha = fingerprint(pack_rgb24(stack))
        if sha != self.flash_images_sha256:
            raise UnsupportedSetting(self.name, (
                f"the projector's flash does not hold these {n} patterns (their images have fingerprint {sha}, "
                f"the rig TOML says {self.flash_images_sha256 or 'nothing'}): run `slscan devices "
                f"lightcrafter-images --rig <rig.toml> --out <dir>`, add the images to the firmware with TI's "
                f"LightCrafter 4500 GUI from flash image {self.flash_first_image} on, then set "
                f"projector.flash_images_sha256 = \"{sha}\""))
        self._patterns = stack
        self._program_sequence(self.period_s)
        if self.trigger == "external":
            self.start()  # waits for TRIG_IN1 edges from the trigger box

    def _do_show(self, k: int) -> None:
        if self.source == "video":
            assert self._patterns is not None and self._video is not None
            rgb = np.zeros((p.HEIGHT, p.WIDTH, 3), dtype=np.uint8)
            rgb[..., 1] = self._patterns[k]  # the green plane: pattern number 0 of the LUT
            self._video.show(rgb)
            return
        period_us = self._period_us(self.period_s)
        entry = p.LutEntry(p.LutTrigger.INTERNAL, k % PATTERNS_PER_IMAGE, leds=self.leds, buffer_swap=True)
        self.program([entry], [self.flash_first_image + k // PATTERNS_PER_IMAGE], p.TriggerMode.INTERNAL_OR_EXTERNAL,
                     source=p.PatternSource.FLASH, repeat=True, exposure_us=period_us, period_us=period_us)
        self._programmed = "single"
        self.start()

    def _do_blank(self) -> None:
        if self.source == "video":
            assert self._video is not None
            self._video.show(np.zeros((p.HEIGHT, p.WIDTH, 3), dtype=np.uint8))
        elif self._link is not None:
            self.stop()

    def _do_run_sequence(self, period_s: float, on_pattern: Callable[[int], None] | None, status: Status) -> None:
        if on_pattern is not None:
            raise UnsupportedSetting(self.name, "the DLPC350 times the sequence itself: no per-pattern callback")
        if self.source == "video" or self.trigger == "external":
            raise UnsupportedSetting(self.name, f"run_sequence needs source 'flash' with trigger 'internal' "
                                                f"(this projector: source '{self.source}', trigger '{self.trigger}')")
        if self._programmed != "sequence" or period_s != self.period_s:
            self._program_sequence(period_s)
        self.start()
        self._sequence_timer = threading.Timer(self.n_patterns * period_s, status.set_finished)
        self._sequence_timer.daemon = True
        self._sequence_timer.start()

    def _do_stop_sequence(self) -> None:
        self._cancel_sequence_timer()
        if not self._shut_down and self._link is not None:
            self.stop()

    def _do_shutdown(self) -> None:
        self._cancel_sequence_timer()
        try:
            if self._link is not None:
                self._transact(p.Command.START_STOP, bytes([p.Action.STOP]), read=False)
        except DeviceError as exc:
            log.info("%s: could not stop the projector while shutting down (%s); closing the link", self.name, exc)
        finally:
            self._drop_link()
            if self._video is not None:
                self._video.close()

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "source": self.source, "trigger": self.trigger,
                "flash_first_image": self.flash_first_image, "flash_images_sha256": self.flash_images_sha256,
                "led_currents": self.led_currents, "validation_warnings": list(self.warnings)}

    # ------------------------------------------------------------------ internals

    def _program_sequence(self, period_s: float) -> None:
        assert self._patterns is not None
        n = len(self._patterns)
        trig = p.LutTrigger.INTERNAL if self.trigger == "internal" else p.LutTrigger.EXTERNAL_POSITIVE
        entries = [p.LutEntry(trig, k % PATTERNS_PER_IMAGE, leds=self.leds, buffer_swap=k % PATTERNS_PER_IMAGE == 0)
                   for k in range(n)]
        images = [self.flash_first_image + i for i in range(-(-n // PATTERNS_PER_IMAGE))]
        period_us = self._period_us(period_s)
        self.program(entries, images, p.TriggerMode.INTERNAL_OR_EXTERNAL, source=p.PatternSource.FLASH, repeat=False,
                     exposure_us=period_us, period_us=period_us)
        self.period_s = period_s
        self._programmed = "sequence"

    def _program_video(self) -> None:
        """One LUT entry: the green plane of each input frame, started by its VSYNC ([PYC]
        pattern_mode uses an external-positive entry under VSYNC trigger mode)."""
        assert self._video is not None
        period_us = int(1e6 / self._video.refresh_hz)
        entry = p.LutEntry(p.LutTrigger.EXTERNAL_POSITIVE, 0, leds=self.leds)
        self.program([entry], [0], p.TriggerMode.VSYNC, source=p.PatternSource.VIDEO, repeat=True,
                     exposure_us=period_us, period_us=period_us)
        self._programmed = "video"
        self.start()

    def _cancel_sequence_timer(self) -> None:
        timer, self._sequence_timer = self._sequence_timer, None
        if timer is not None:
            timer.cancel()

    def _period_us(self, period_s: float) -> int:
        period_us = round(period_s * 1e6)
        if period_us < p.EXPOSURE_GAP_US:
            raise UnsupportedSetting(self.name, f"pattern period {period_s} s is too short")
        return period_us

    def _mailbox(self, box: p.Mailbox, data: bytes) -> None:
        self.command(p.Command.MAILBOX_CONTROL, bytes([box]))
        self.command(p.Command.MAILBOX_ADDRESS, p.mailbox_address(0))
        self.command(p.Command.MAILBOX_DATA, data)
        self.command(p.Command.MAILBOX_CONTROL, bytes([p.Mailbox.CLOSED]))

    def _connect(self) -> HidLink:
        if self._link is None:
            self._link = self._open_link()
            self._seq = 0
            log.info("%s: USB link opened", self.name)
        return self._link

    def _drop_link(self) -> None:
        link, self._link = self._link, None
        self._programmed = None
        if link is not None:
            link.close()
            log.info("%s: USB link closed", self.name)

    def _transact(self, command: p.Command, payload: bytes, read: bool) -> bytes:
        link = self._connect()
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFF
        what = f"command 0x{int(command):04X} ({command.name})"
        log.debug("%s: %s %s, payload %s", self.name, "read" if read else "write", what, payload.hex(" ") or "none")
        try:
            for report in p.frame(command, payload, seq, read):
                link.write(report, self.timeout_s)
            first = link.read(self.timeout_s)
            header = p.parse_header(first)
            reports = [first] + [link.read(self.timeout_s) for _ in range(header.continuation_reports)]
        except DeviceDisconnected:
            self._drop_link()
            raise
        except DeviceTimeout as exc:
            self._drop_link()  # the link is out of step: reopen it next time
            raise DeviceTimeout(self.name, f"no reply to {what}", exc.timeout_s,
                                "the USB link is reopened on the next call") from None
        if header.seq != seq:
            self._drop_link()
            raise DeviceError(self.name, f"reply to {what} carries sequence byte {header.seq}, expected {seq}: "
                                         f"the USB link is out of step; it is reopened on the next call")
        if header.nack or (read and header.length == 0):
            raise DeviceError(self.name, f"{what} was refused (NACK); the projector may be in the wrong mode "
                                         f"or the value out of range (payload {payload.hex(' ') or 'none'})")
        return p.reply_data(reports, header)


Byte = Annotated[int, Field(strict=True, ge=0, le=255)]


class LightCrafterSettings(Schema):
    """The [projector] keys of a LightCrafter 4500 (see the module docstring): the pattern
    `source`; for "flash" the first image holding the patterns and their fingerprint; the
    LEDs and their PWM currents (bytes as sent); trigger delays (us); the diamond rows'
    shift (px); the USB serial (None: the first found); for "video" the display of its HDMI
    input, its refresh rate (Hz) and latency (refreshes)."""

    source: Literal["flash", "video"] = "flash"
    flash_first_image: Annotated[int, Field(strict=True, ge=0)] = 0
    flash_images_sha256: Str | None = None
    leds: Str = "white"
    led_currents: Annotated[list[Byte], Field(min_length=3, max_length=3)] | None = None
    trig_out1_delays_us: Annotated[list[Float], Field(min_length=2, max_length=2)] = Field(
        default_factory=lambda: [0.0, 0.0])
    trig_out2_delay_us: Float = 0.0
    trig_in1_delay_us: Float = 0.0
    odd_row_shift: Float = 0.5
    usb_serial: Str | None = None
    video_display: Int = 1
    refresh_hz: PositiveFloat = 60.0
    latency_frames: LatencyFrames = 2


def open_lightcrafter(config: RigConfig, settings: LightCrafterSettings,
                      transports: Mapping[str, Any]) -> LightCrafter4500:
    """The rig's LightCrafter, externally triggered in wiring `trigger_box`; transports
    "projector" (the USB link) and "display" (the video source's backend) replace the devices."""
    lens = config.file.projector
    if (lens.width, lens.height) != (p.WIDTH, p.HEIGHT):
        raise ConfigError(config.path, "projector.width", f"the LightCrafter 4500 DMD is {p.WIDTH}x{p.HEIGHT} "
                                                          f"(diamond pixels); the rig says {lens.width}x{lens.height}")
    video = None
    if settings.source == "video":
        video = open_display(settings.video_display, settings.refresh_hz, settings.latency_frames, transports)
    opener = transports.get("projector") or open_usb("lightcrafter4500", settings.usb_serial)
    currents, delays = settings.led_currents, settings.trig_out1_delays_us
    try:
        return LightCrafter4500(
            opener, "lightcrafter4500", source=settings.source,
            trigger="external" if config.trigger == "trigger_box" else "internal", period_s=config.period_s,
            flash_first_image=settings.flash_first_image, flash_images_sha256=settings.flash_images_sha256,
            leds=settings.leds, led_currents=(currents[0], currents[1], currents[2]) if currents else None,
            trig_out1_delays_us=(delays[0], delays[1]), trig_out2_delay_us=settings.trig_out2_delay_us,
            trig_in1_delay_us=settings.trig_in1_delay_us, odd_row_shift=settings.odd_row_shift, video=video)
    except BaseException:
        if video is not None:
            video.close()
        raise


def _triggers(settings: LightCrafterSettings) -> Triggers:
    if settings.source == "video":
        return Triggers(refusal="a LightCrafter on its video port runs wiring 'software' only; use projector.source "
                                "= 'flash' for hardware-timed sequences")
    return Triggers(input=True, output="pulse")


DRIVER = register(Driver("projector", "lightcrafter4500", "hardware", LightCrafterSettings, open_lightcrafter,
                         triggers=_triggers))
