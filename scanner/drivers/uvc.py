"""UVC (USB Video Class) cameras through OpenCV's V4L2 backend, software-triggered.

A UVC camera streams continuously and has no trigger input, so a "software trigger" here
means: the next frame whose exposure started after `trigger()` was called. `grab` waits
(within its timeout) for the trigger too, so a trigger from another thread (an HDMI
projector's trigger output, wiring `projector`) may come after the grab started. While armed, a
reader thread takes every frame the camera streams and keeps only the newest (the V4L2
queue is also cut to one buffer), so nothing older than the trigger is ever returned:
a frame is accepted only if its exposure started after the trigger, judged from the V4L2
buffer timestamp (CLOCK_MONOTONIC, the clock of `time.monotonic()`) minus the exposure,
or, where the backend gives none, from the time it arrived minus exposure and one frame
interval. `Frame.timestamp_s` is that exposure start.

Exposure and gain are set where the device takes them (V4L2 manual exposure is in units
of 100 us); a setting the device ignores raises UnsupportedSetting. Frames are 8-bit luma,
the only bit depth, and the software trigger is the only trigger type.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from scanner.devices import Camera, Frame, TriggerType
from scanner.drivers.registry import Driver, Triggers, register
from scanner.errors import DeviceDisconnected, DeviceError, UnsupportedSetting, WaitTimeout
from scanner.schema import Float, Int, PositiveFloat, Schema, Str

if TYPE_CHECKING:
    from scanner.rig import RigConfig

log = logging.getLogger(__name__)

_JOIN_S = 2.0


class Capture(Protocol):
    """The part of `cv2.VideoCapture` this driver uses."""

    def isOpened(self) -> bool: ...

    def set(self, prop: int, value: float) -> bool: ...

    def get(self, prop: int) -> float: ...

    def grab(self) -> bool: ...

    def retrieve(self) -> tuple[bool, Any]: ...

    def release(self) -> None: ...


def v4l2_opener(name: str, device: str | int, width: int, height: int, fps: float,
                read_timeout_s: float = 1.0) -> Callable[[], Capture]:
    """A factory opening `device` (/dev/videoN or N) with V4L2 at the given mode."""

    def open_capture() -> Capture:
        import cv2

        cap = cv2.VideoCapture(device, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise DeviceDisconnected(name, f"cannot open video device {device}: is it plugged in and free? "
                                           f"(`slscan devices` lists cameras; if it exists, add yourself to the "
                                           f"'video' group: sudo usermod -aG video $USER, then log in again)")
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*"YUYV"))  # uncompressed: no JPEG artefacts
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        cap.set(cv2.CAP_PROP_FPS, fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, read_timeout_s * 1000)
        return cap

    return open_capture


class UvcCamera(Camera):
    """A UVC camera (see the module docstring); `fps` is the streaming rate it was opened at."""

    supported_bit_depths = (8,)
    supported_trigger_types = (TriggerType.SOFTWARE,)
    exposure_range_s = (1e-4, 1.0)

    def __init__(self, open_capture: Callable[[], Capture], name: str, width: int, height: int, fps: float = 30.0,
                 gain: float | None = None) -> None:
        super().__init__(name, width, height)
        import cv2

        self._cv2 = cv2
        self.fps = fps
        self.gain = gain
        self._open_capture = open_capture
        self._cap: Capture | None = None
        self._cv = threading.Condition()
        self._latest: tuple[np.ndarray, float, bool] | None = None  # image, time, from a buffer timestamp
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._lost: str | None = None
        self._triggers: list[float] = []
        self._armed = 0
        self._delivered = 0
        self._connect()

    # driver methods
    def _do_set_bit_depth(self, bits: int) -> None:
        pass  # 8-bit luma is the only format (supported_bit_depths): nothing to switch

    def _do_set_exposure(self, seconds: float) -> None:
        cv2 = self._cv2
        cap = self._connect()
        if not (cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1) and cap.set(cv2.CAP_PROP_EXPOSURE, round(seconds * 1e4))):
            raise UnsupportedSetting(self.name, "this camera does not take a manual exposure through V4L2; use "
                                                "`v4l2-ctl -d <device> --list-ctrls` to see what it offers")

    def _do_set_trigger(self, ttype: TriggerType) -> None:
        pass  # the software trigger (the only type, checked by the base) needs no device setting

    def _do_arm(self, n_frames: int) -> None:
        cap = self._connect()
        self._stop_reader()
        with self._cv:
            self._latest, self._lost = None, None
            self._triggers, self._armed, self._delivered = [], n_frames, 0
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, args=(cap, self._stop), name=f"{self.name}-reader",
                                        daemon=True)
        self._reader.start()

    def _do_disarm(self) -> None:
        self._stop_reader()
        with self._cv:
            self._armed = 0

    def _do_trigger(self) -> None:
        with self._cv:
            if self._armed == 0 or len(self._triggers) >= self._armed:
                raise DeviceError(self.name, "software trigger refused: not armed, or every frame of this arming "
                                             "is already triggered; arm again")
            self._triggers.append(time.monotonic())
            self._cv.notify_all()

    def _do_grab(self, timeout_s: float) -> Frame:
        end = time.monotonic() + timeout_s
        with self._cv:
            k = self._delivered
            while k >= len(self._triggers):  # a trigger from another thread may still come
                remaining = end - time.monotonic()
                if remaining <= 0:
                    raise WaitTimeout(self.name, f"frame {k}", timeout_s, "it was never triggered (call trigger())")
                self._cv.wait(remaining)
            t_trigger = self._triggers[k]
            while True:
                if self._lost is not None:
                    lost = self._lost
                    self._drop()
                    raise DeviceDisconnected(self.name, f"camera stopped streaming ({lost}); check the cable, then "
                                                        f"scan again (the driver reopens it)")
                if self._latest is not None:
                    image, stamp, from_buffer = self._latest
                    start = stamp - self._exposure_s - (0.0 if from_buffer else 1.0 / self.fps)
                    self._latest = None
                    if start >= t_trigger:
                        self._delivered += 1
                        return Frame(image=image, index=k, pattern_index=None, timestamp_s=start,
                                     exposure_s=self._exposure_s, bit_depth=8)
                    log.debug("%s: frame exposed %.4f s before trigger %d dropped", self.name, t_trigger - start, k)
                    continue  # exposed before the trigger: stale, dropped
                remaining = end - time.monotonic()
                if remaining <= 0:
                    raise WaitTimeout(self.name, f"a frame exposed after trigger {k}", timeout_s,
                                      f"the camera streams at {self.fps} fps: is it still running?")
                self._cv.wait(remaining)

    def _do_shutdown(self) -> None:
        self._stop_reader()
        self._drop()

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "fps": self.fps, "gain": self.gain}

    # internals
    def _connect(self) -> Capture:
        if self._cap is None:
            cap = self._open_capture()
            if self.gain is not None and not cap.set(self._cv2.CAP_PROP_GAIN, self.gain):
                cap.release()
                raise UnsupportedSetting(self.name, f"gain {self.gain} not taken by this camera")
            self._cap = cap
            log.info("%s: opened (%dx%d at %g fps)", self.name, self.width, self.height, self.fps)
        return self._cap

    def _drop(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()
            log.info("%s: closed (reopened at the next call)", self.name)

    def _stop_reader(self) -> None:
        self._stop.set()
        reader, self._reader = self._reader, None
        if reader is not None and reader is not threading.current_thread():
            reader.join(_JOIN_S)

    def _read(self, cap: Capture, stop: threading.Event) -> None:
        cv2 = self._cv2
        while not stop.is_set():
            ok = cap.grab()
            arrived = time.monotonic()
            if ok:
                ok, image = cap.retrieve()
            if not ok:
                log.info("%s: the stream stopped", self.name)
                with self._cv:
                    self._lost = "no frame from the device"
                    self._cv.notify_all()
                return
            buffer_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
            with self._cv:
                from_buffer = 0.0 <= arrived - buffer_ms / 1e3 < 1.0  # a CLOCK_MONOTONIC stamp just before arrival
                self._latest = (np.ascontiguousarray(gray, dtype=np.uint8),
                                buffer_ms / 1e3 if from_buffer else arrived, from_buffer)
                self._cv.notify_all()


class UvcSettings(Schema):
    """The [camera] keys of a UVC camera: `device` a V4L2 path or index, `fps` the streaming
    rate (frames/s), `gain` the device's own units (None: left as it is)."""

    device: Str | Int = "/dev/video0"
    fps: PositiveFloat = 30.0
    gain: Float | None = None


def open_uvc(config: RigConfig, settings: UvcSettings, transports: Mapping[str, Any]) -> UvcCamera:
    """The rig's UVC camera; transports["camera"] replaces the V4L2 capture opener."""
    lens = config.file.first_camera
    opener = transports.get("camera") or v4l2_opener("uvc-camera", settings.device, lens.width, lens.height,
                                                      settings.fps)
    return UvcCamera(opener, "uvc-camera", lens.width, lens.height, settings.fps, settings.gain)


DRIVER = register(Driver(
    "camera", "uvc", "hardware", UvcSettings, open_uvc,
    triggers=lambda settings: Triggers(refusal="a UVC camera has no trigger input, so wiring '{wiring}' cannot "
                                               "expose it; use 'software' (or an HDMI projector with 'projector')")))
