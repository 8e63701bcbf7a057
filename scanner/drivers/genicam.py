"""GenICam cameras (GigE Vision, USB3 Vision) through harvesters, an optional extra.

    pip install slscan[genicam]     # harvesters, plus the camera maker's GenTL producer (.cti)

Features are the SFNC names (PixelFormat, ExposureTime, TriggerSelector/Mode/Source/
Activation, TriggerSoftware, Gain). Hardware triggering takes one frame per edge on
`trigger_line`; software triggering executes TriggerSoftware.

Buffers: `arm(n)` restarts acquisition (which discards every queued, stale buffer) with
at least n + 4 buffers announced, so a whole sequence fits even if the host is slow, and
every fetched buffer is copied and handed back to the producer at once, so it never runs
out of buffers. `grab` uses `try_fetch` with the caller's timeout. The frame index comes
from the producer's frame id where it has one (a gap is a dropped frame), else a counter.
Timestamps: the device's, mapped to the host clock through a timestamp latch taken at
`arm` where the camera has TimestampLatch, else the arrival time minus the exposure.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from scanner.devices import Camera, Frame, TriggerType
from scanner.drivers.registry import Driver, Triggers, register
from scanner.errors import DeviceDisconnected, DeviceError, DeviceTimeout, UnsupportedSetting, WaitTimeout
from scanner.schema import Float, Schema, Str

if TYPE_CHECKING:
    from scanner.rig import RigConfig

log = logging.getLogger(__name__)

PIXEL_FORMATS = {8: "Mono8", 10: "Mono10", 12: "Mono12", 16: "Mono16"}
EXTRA_BUFFERS = 4


Opened = tuple[Any, Callable[[], None]]  # an ImageAcquirer and what closes it


def harvester_opener(name: str, cti_file: str, serial_number: str | None = None) -> Callable[[], Opened]:
    """A factory returning an opened harvesters ImageAcquirer and its closer."""

    def open_acquirer() -> Opened:
        try:
            from harvesters.core import Harvester
        except ImportError:
            raise DeviceError(name, "GenICam cameras need the optional extra: pip install slscan[genicam]") from None
        h = Harvester()
        h.add_file(cti_file, check_existence=True)
        h.update()
        if not h.device_info_list:
            h.reset()
            raise DeviceDisconnected(name, f"no GenICam camera found through {cti_file}; check the cable, power and "
                                           f"network (`slscan devices` lists what the producer sees)")
        try:
            ia = h.create({"serial_number": serial_number} if serial_number else 0)
        except Exception as exc:  # harvesters raises ValueError / genicam access errors here
            h.reset()
            raise DeviceError(name, f"cannot open the GenICam camera ({exc}); is another program using it?") from None

        def close() -> None:
            ia.destroy()
            h.reset()

        return ia, close

    return open_acquirer


class GenICamCamera(Camera):
    """A GenICam area camera (see the module docstring)."""

    supported_bit_depths = tuple(PIXEL_FORMATS)
    supported_trigger_types = (TriggerType.SOFTWARE, TriggerType.RISING_EDGE, TriggerType.FALLING_EDGE)
    exposure_range_s = (1e-5, 10.0)

    def __init__(self, open_acquirer: Callable[[], Opened], name: str, width: int, height: int,
                 trigger_line: str = "Line0", gain_db: float | None = None) -> None:
        super().__init__(name, width, height)
        self.trigger_line = trigger_line
        self.gain_db = gain_db
        self._open = open_acquirer
        self._ia: Any = None
        self._close: Callable[[], None] | None = None
        self._armed = 0
        self._triggered = 0
        self._delivered = 0
        self._first_id: int | None = None
        self._clock: tuple[float, int] | None = None  # (host s, device ns) latched at arm
        self._connect()

    @property
    def nodes(self) -> Any:
        return self._connect().remote_device.node_map

    # driver methods
    def _do_set_bit_depth(self, bits: int) -> None:
        self._set("PixelFormat", PIXEL_FORMATS[bits])

    def _do_set_exposure(self, seconds: float) -> None:
        self._set("ExposureTime", seconds * 1e6)

    def _do_set_trigger(self, ttype: TriggerType) -> None:
        self._set("TriggerSelector", "FrameStart")
        self._set("TriggerMode", "On")
        if ttype is TriggerType.SOFTWARE:
            self._set("TriggerSource", "Software")
        else:
            self._set("TriggerSource", self.trigger_line)
            self._set("TriggerActivation", "RisingEdge" if ttype is TriggerType.RISING_EDGE else "FallingEdge")

    def _do_arm(self, n_frames: int) -> None:
        ia = self._connect()
        try:
            if ia.is_acquiring():
                ia.stop()  # drops whatever was queued: no stale buffer survives an arm
            ia.num_buffers = n_frames + EXTRA_BUFFERS
            ia.start()
        except Exception as exc:
            raise self._error(exc, "starting acquisition") from None
        self._armed, self._triggered, self._delivered, self._first_id = n_frames, 0, 0, None
        self._clock = self._latch()

    def _do_disarm(self) -> None:
        self._armed = 0
        if self._ia is not None:
            try:
                self._ia.stop()
            except Exception as exc:  # the camera is gone: reopen it at the next arm
                log.warning("%s: stopping acquisition failed (%s: %s); the camera is reopened at the next arm",
                            self.name, type(exc).__name__, exc)
                self._drop()

    def _do_trigger(self) -> None:
        if self._armed == 0 or self._triggered >= self._armed:
            raise DeviceError(self.name, "software trigger refused: not armed, or every frame of this arming is "
                                         "already triggered; arm again")
        try:
            self.nodes.TriggerSoftware.execute()
        except Exception as exc:
            raise self._error(exc, "executing TriggerSoftware") from None
        self._triggered += 1

    def _do_grab(self, timeout_s: float) -> Frame:
        ia = self._connect()
        try:
            buffer = ia.try_fetch(timeout=timeout_s)
        except Exception as exc:
            raise self._error(exc, f"waiting for frame {self._delivered}") from None
        if buffer is None:
            why = ("it waits for a trigger edge on " + self.trigger_line
                   if self._trigger_type is not TriggerType.SOFTWARE else "was trigger() called?")
            raise WaitTimeout(self.name, f"frame {self._delivered}", timeout_s, why)
        arrived = time.monotonic()
        try:
            component = buffer.payload.components[0]
            image = np.array(component.data, copy=True).reshape(component.height, component.width)
            frame_id = getattr(buffer, "frame_id", None)
            stamp_ns = getattr(buffer, "timestamp_ns", None)
        finally:
            buffer.queue()  # back to the producer at once
        if frame_id is not None and self._first_id is None:
            self._first_id = frame_id
        index = frame_id - self._first_id if frame_id is not None and self._first_id is not None else self._delivered
        self._delivered += 1
        if self._clock is not None and stamp_ns is not None:
            stamp = self._clock[0] + (stamp_ns - self._clock[1]) / 1e9
        else:
            stamp = arrived - self._exposure_s
        return Frame(image=image, index=index, pattern_index=None, timestamp_s=stamp, exposure_s=self._exposure_s,
                     bit_depth=self._bit_depth)

    def _do_shutdown(self) -> None:
        self._drop()

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "trigger_line": self.trigger_line, "gain_db": self.gain_db}

    # internals
    def _connect(self) -> Any:
        if self._ia is None:
            self._ia, self._close = self._open()
            log.info("%s: opened", self.name)
            try:
                self._set("ExposureAuto", "Off", optional=True)
                if self.gain_db is not None:
                    self._set("GainAuto", "Off", optional=True)
                    self._set("Gain", self.gain_db)
                self._set("AcquisitionMode", "Continuous", optional=True)
                self._set("PixelFormat", PIXEL_FORMATS[self._bit_depth])
                self._set("ExposureTime", self._exposure_s * 1e6)
            except BaseException:
                self._drop()
                raise
        return self._ia

    def _set(self, feature: str, value: Any, optional: bool = False) -> None:
        nodes = self._ia.remote_device.node_map
        node = getattr(nodes, feature, None)
        if node is None:
            if optional:
                return
            raise UnsupportedSetting(self.name, f"the camera has no {feature} feature")
        try:
            node.value = value
        except Exception as exc:
            raise UnsupportedSetting(self.name, f"{feature} = {value!r} refused by the camera ({exc})") from None

    def _latch(self) -> tuple[float, int] | None:
        nodes = self._ia.remote_device.node_map
        latch, latched = getattr(nodes, "TimestampLatch", None), getattr(nodes, "TimestampLatchValue", None)
        if latch is None or latched is None:
            return None
        before = time.monotonic()
        latch.execute()
        after = time.monotonic()
        return (before + after) / 2, int(latched.value)

    def _drop(self) -> None:
        close, self._ia, self._close = self._close, None, None
        if close is not None:
            log.info("%s: closed", self.name)
            try:
                close()
            except Exception as exc:  # genicam's own exception types; the camera is already gone
                log.debug("%s: closing raised %s: %s (ignored: the camera is gone)", self.name, type(exc).__name__, exc)

    def _error(self, exc: Exception, doing: str) -> DeviceError:
        kind = type(exc).__name__
        if "Timeout" in kind:  # the producer reports the device timed out (it says not after how long)
            return DeviceTimeout(self.name, f"{doing}: {kind}: {exc}", None)
        self._drop()
        return DeviceDisconnected(self.name, f"camera lost while {doing} ({kind}: {exc}); check the cable, then "
                                             f"scan again (the driver reopens it)")


class GenICamSettings(Schema):
    """The [camera] keys of a GenICam camera: `cti` the maker's GenTL producer, `serial`
    (empty or absent: the first camera found), `trigger_line` its hardware trigger input,
    `gain_db` (None: left as it is)."""

    cti: Str
    serial: Str | None = None
    trigger_line: Str = "Line0"
    gain_db: Float | None = None


def open_genicam(config: RigConfig, settings: GenICamSettings, transports: Mapping[str, Any]) -> GenICamCamera:
    """The rig's GenICam camera; transports["camera"] replaces the harvesters opener."""
    lens = config.file.first_camera
    opener = transports.get("camera") or harvester_opener("genicam-camera", settings.cti, settings.serial)
    return GenICamCamera(opener, "genicam-camera", lens.width, lens.height, settings.trigger_line, settings.gain_db)


DRIVER = register(Driver("camera", "genicam", "hardware", GenICamSettings, open_genicam,
                         triggers=lambda settings: Triggers(input=True)))
