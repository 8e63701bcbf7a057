"""Fake transports that play a scripted byte exchange, for protocol tests without hardware.

Like pymeasure's `expected_protocol`, a test lists what the host must send and what the
device answers; any other byte fails the test at once with both sides shown in hex, and
`expected_protocol` checks at the end that the whole script was played. Scripts can also
inject faults: a device that stays silent, NACKs, or is unplugged mid-sequence.

The fake cameras and display below stand for devices with their own timing (a streaming
camera, a vsync-locked display); they offer waits on their events (`FakeCapture.wait_frames`)
so tests synchronise on what happened rather than sleeping. `wait_bound_s` is the one
generous bound a test puts on a wait that must time out.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TypeVar

from scanner.devices import Camera, Frame
from scanner.errors import DeviceDisconnected, DeviceTimeout

T = TypeVar("T")

SILENT = None  # as a reply: the device does not answer (the host's read times out)


def wait_bound_s(timeout_s: float) -> float:
    """How long a test lets a wait with `timeout_s` take before calling it hung: several
    times the timeout and never under 5 s, so a loaded machine does not fail the test."""
    return max(5 * timeout_s, 5.0)


def grab_in_thread(camera: Camera, timeout_s: float) -> tuple[threading.Thread, list[object]]:
    """Run `camera.grab(timeout_s)` on a thread; return once the driver's `_do_grab` has been
    entered, so a test acts on a grab that is waiting without sleeping. The list receives
    the frame, or the exception the grab raised."""
    entered = threading.Event()
    inner = camera._do_grab

    def grab_signalling(timeout_s: float) -> Frame:
        entered.set()
        return inner(timeout_s)

    camera._do_grab = grab_signalling  # type: ignore[method-assign]  # the fake wraps this one camera's grab
    outcome: list[object] = []

    def grab() -> None:
        try:
            outcome.append(camera.grab(timeout_s))
        except BaseException as exc:
            outcome.append(exc)

    thread = threading.Thread(target=grab, name=f"{camera.name}-test-grab", daemon=True)
    thread.start()
    if not entered.wait(wait_bound_s(1.0)):
        raise AssertionError(f"{camera.name}: grab did not start")
    return thread, outcome


@dataclass(frozen=True)
class Unplug:
    """Script step: the device is unplugged; the host's next write or read fails."""


@dataclass(frozen=True)
class Exchange:
    """Script step: the host sends `sent` (one or more reports or bytes); the device then
    answers `reply` (reports or bytes), or nothing when `reply` is SILENT."""

    sent: bytes | tuple[bytes, ...]
    reply: bytes | tuple[bytes, ...] | None = ()

    @property
    def sent_parts(self) -> tuple[bytes, ...]:
        return self.sent if isinstance(self.sent, tuple) else (self.sent,)

    @property
    def reply_parts(self) -> tuple[bytes, ...]:
        if self.reply is None:
            return ()
        return self.reply if isinstance(self.reply, tuple) else (self.reply,)


Step = Exchange | Unplug


class ProtocolMismatch(AssertionError):
    """The host sent something other than the script says."""


class _Script:
    def __init__(self, steps: list[Step]) -> None:
        self.steps = deque(steps)
        self.played: list[Step] = []
        self.pending_sent: deque[bytes] = deque()
        self.unplugged = False

    def expect_write(self, data: bytes) -> Exchange:
        if self.unplugged:
            raise DeviceDisconnected("fake", "unplugged")
        if not self.pending_sent:
            if not self.steps:
                raise ProtocolMismatch(f"host sent {data.hex(' ')} after the end of the script")
            step = self.steps.popleft()
            self.played.append(step)
            if isinstance(step, Unplug):
                self.unplugged = True
                raise DeviceDisconnected("fake", "unplugged")
            self.pending_sent.extend(step.sent_parts)
        expected = self.pending_sent.popleft()
        if data != expected:
            raise ProtocolMismatch(f"step {len(self.played)}: host sent\n  {data.hex(' ')}\nexpected\n  "
                                   f"{expected.hex(' ')}")
        current = self.played[-1]
        assert isinstance(current, Exchange)
        return current

    def done(self) -> bool:
        return not self.steps and not self.pending_sent


class FakeHid:
    """A HID device (`transport.HidLink`) playing a script of report exchanges."""

    def __init__(self, steps: list[Step]) -> None:
        self._script = _Script(steps)
        self._replies: deque[bytes] = deque()
        self.closed = False

    def write(self, report: bytes, timeout_s: float) -> None:
        if len(report) != 64:
            raise ProtocolMismatch(f"HID report of {len(report)} bytes, expected 64")
        step = self._script.expect_write(bytes(report))
        if not self._script.pending_sent:
            self._replies.extend(step.reply_parts)

    def read(self, timeout_s: float) -> bytes:
        if self._script.unplugged:
            raise DeviceDisconnected("fake-hid", "unplugged")
        if not self._replies:
            raise DeviceTimeout("fake-hid", "no report", timeout_s)
        return self._replies.popleft()

    def close(self) -> None:
        self.closed = True

    def done(self) -> bool:
        return self._script.done() and not self._replies


class FakeSerial:
    """A serial port (`transport.SerialLink`) playing a script of line exchanges.

    Bytes in `realtime` are exchanges of their own, sent without a line end (a GRBL
    controller's real-time commands). `banner` is printed by the device `banner_delay_s` after
    the port opens (a board that resets when the port opens). `readline` waits at most `timeout` like pyserial."""

    def __init__(self, steps: list[Step], banner: bytes = b"", banner_delay_s: float = 0.0,
                 timeout: float | None = 0.2, realtime: bytes = b"") -> None:
        self._script = _Script(steps)
        self.timeout = timeout
        self._realtime = frozenset(realtime)  # bytes the device takes alone, without a line end (GRBL's ?, !, ^X)
        self._out = bytearray()
        self._written = bytearray()
        self._timed: list[tuple[float, bytes]] = [(time.monotonic() + banner_delay_s, banner)] if banner else []
        self.closed = False

    def write(self, data: bytes) -> int:
        if self._script.unplugged:
            import serial

            raise serial.SerialException("write failed: [Errno 5] Input/output error")
        for byte in data:
            if byte in self._realtime:
                self._play(bytes([byte]))
                continue
            self._written.append(byte)
            if byte == 0x0A:
                line, self._written = bytes(self._written), bytearray()
                self._play(line)
        return len(data)

    def _play(self, sent: bytes) -> None:
        """The host sent `sent` (a line, or a real-time byte): check it, queue the reply."""
        try:
            step = self._script.expect_write(sent)
        except DeviceDisconnected:
            import serial

            raise serial.SerialException("write failed: [Errno 5] Input/output error") from None
        if not self._script.pending_sent:
            self._out += b"".join(step.reply_parts)

    def readline(self) -> bytes:
        end = time.monotonic() + (self.timeout if self.timeout is not None else 1.0)
        while True:
            if self._script.unplugged:
                import serial

                raise serial.SerialException("device reports readiness to read but returned no data "
                                             "(device disconnected or multiple access on port?)")
            now = time.monotonic()
            for item in [t for t in self._timed if t[0] <= now]:
                self._timed.remove(item)
                self._out += item[1]
            if b"\n" in self._out:
                line, _, rest = bytes(self._out).partition(b"\n")
                self._out = bytearray(rest)
                return line + b"\n"
            if now >= end:
                return b""
            time.sleep(0.005)

    def reset_input_buffer(self) -> None:
        self._out.clear()

    def close(self) -> None:
        self.closed = True

    def done(self) -> bool:
        return self._script.done()


@contextlib.contextmanager
def expected_protocol(make_driver: Callable[[Callable[[], object]], T], *transports: FakeHid | FakeSerial
                      ) -> Iterator[T]:
    """Build a driver on fake transports (each call of the driver's `open` factory gets the
    next one: a reconnect uses the second) and check at exit that every script was played
    to its end."""
    queue = deque(transports)

    def opener() -> object:
        if not queue:
            raise DeviceDisconnected("fake", "no further transport scripted for a reconnect")
        return queue.popleft()

    driver = make_driver(opener)
    yield driver
    for i, t in enumerate(transports):
        if not t.done():
            raise ProtocolMismatch(f"transport {i}: the driver stopped before the end of the script")


# ------------------------------------------------------------------ cameras and displays


class FakeCapture:
    """A streaming UVC camera as `cv2.VideoCapture` shows it: `render(t)` gives the image
    exposed at monotonic time t; frames come every 1/fps s with a V4L2-style buffer
    timestamp (ms, end of exposure); `frames` counts them. `unplug()` makes the stream stop."""

    def __init__(self, render: Callable[[float], object], fps: float = 100.0, exposure_s: float = 0.001,
                 buffer_timestamps: bool = True) -> None:
        self.render, self.fps, self.exposure_s = render, fps, exposure_s
        self.buffer_timestamps = buffer_timestamps
        self.props: dict[int, float] = {}
        self.refused: set[int] = set()
        self.released = False
        self.frames = 0
        self._counted = threading.Condition()
        self._unplugged = False
        self._next = time.monotonic()
        self._last: tuple[object, float] | None = None

    def wait_frames(self, count: int, timeout_s: float) -> bool:
        """Wait at most `timeout_s` until the camera has streamed `count` frames in all."""
        with self._counted:
            return self._counted.wait_for(lambda: self.frames >= count, timeout_s)

    def isOpened(self) -> bool:
        return not self.released

    def set(self, prop: int, value: float) -> bool:
        if prop in self.refused:
            return False
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        import cv2

        if prop == cv2.CAP_PROP_POS_MSEC:
            return self._last[1] * 1e3 if self._last and self.buffer_timestamps else 0.0
        return self.props.get(prop, 0.0)

    def grab(self) -> bool:
        if self._unplugged or self.released:
            time.sleep(0.01)
            return False
        self._next = max(self._next + 1.0 / self.fps, time.monotonic())
        time.sleep(max(0.0, self._next - time.monotonic()))
        if self._unplugged or self.released:  # unplugged during the exposure: that frame never arrives
            return False
        end = time.monotonic()
        self._last = (self.render(end - self.exposure_s), end)
        with self._counted:
            self.frames += 1
            self._counted.notify_all()
        return True

    def retrieve(self) -> tuple[bool, object]:
        return (self._last is not None, self._last[0] if self._last else None)

    def release(self) -> None:
        self.released = True

    def unplug(self) -> None:
        self._unplugged = True


class _Node:
    def __init__(self, nodes: FakeNodeMap, name: str, value: object = None,
                 on_execute: Callable[[], None] | None = None) -> None:
        self._nodes, self._name, self._value, self._on_execute = nodes, name, value, on_execute

    @property
    def value(self) -> object:
        return self._value

    @value.setter
    def value(self, v: object) -> None:
        allowed = self._nodes.allowed.get(self._name)
        if allowed is not None and v not in allowed:
            raise ValueError(f"{self._name}: {v!r} not in {allowed}")
        self._value = v
        self._nodes.log.append((self._name, v))

    def execute(self) -> None:
        self._nodes.log.append((self._name, "execute"))
        if self._on_execute is not None:
            self._on_execute()


class FakeNodeMap:
    """GenICam features by SFNC name; `log` records every write and execute in order."""

    def __init__(self, features: dict[str, object], allowed: dict[str, tuple[object, ...]]) -> None:
        self.log: list[tuple[str, object]] = []
        self.allowed = allowed
        self._nodes = {name: _Node(self, name, value) for name, value in features.items()}

    def add(self, name: str, on_execute: Callable[[], None]) -> None:
        """A command feature (executed, no value)."""
        self._nodes[name] = _Node(self, name, on_execute=on_execute)

    def __getattr__(self, name: str) -> _Node:
        try:
            node: _Node = self.__dict__["_nodes"][name]
            return node
        except KeyError:
            raise AttributeError(name) from None


class _Payload:
    def __init__(self, image) -> None:
        self.components = [type("Component", (), {"data": image.ravel(), "width": image.shape[1],
                                                   "height": image.shape[0]})()]


class FakeBuffer:
    def __init__(self, owner: FakeAcquirer, image, frame_id: int, timestamp_ns: int) -> None:
        self._owner, self.payload, self.frame_id, self.timestamp_ns = owner, _Payload(image), frame_id, timestamp_ns

    def queue(self) -> None:
        self._owner.outstanding -= 1


class FakeAcquirer:
    """A harvesters ImageAcquirer: frames are exposed on `TriggerSoftware` (software
    trigger) or on `pulse()` (the hardware line), rendered by `render(t)`. The producer has
    `num_buffers` buffers; a buffer not handed back (`queue()`) is lost to it, and when
    none is free a triggered frame is dropped, as on a real producer. The device clock
    (ns, read by TimestampLatch and stamped on each frame) started 5 s before the host's
    monotonic clock read 0 + now, unless `device_clock_ns` gives it."""

    def __init__(self, render: Callable[[float], object], width: int, height: int,
                 device_clock_ns: Callable[[], int] | None = None) -> None:
        self.render = render
        self.nodes = FakeNodeMap(
            {"PixelFormat": "Mono8", "ExposureTime": 10000.0, "ExposureAuto": "Continuous", "AcquisitionMode":
             "Continuous", "TriggerSelector": "FrameStart", "TriggerMode": "Off", "TriggerSource": "Software",
             "TriggerActivation": "RisingEdge", "TimestampLatchValue": 0, "Width": width, "Height": height},
            {"PixelFormat": ("Mono8", "Mono12"), "TriggerSource": ("Software", "Line0", "Line1")})
        self.nodes.add("TriggerSoftware", self._software)
        self.nodes.add("TimestampLatch", self._latch)
        self.remote_device = type("Remote", (), {"node_map": self.nodes})()
        self.num_buffers = 8
        self.outstanding = 0
        self.dropped = 0
        self.closed = False
        self.gone = False
        self._acquiring = False
        self._queue: deque[FakeBuffer] = deque()
        self._frame_id = 100
        epoch = time.monotonic() - 5.0  # the device clock started 5 s before this host time
        self.device_clock_ns = device_clock_ns or (lambda: int((time.monotonic() - epoch) * 1e9))

    def is_acquiring(self) -> bool:
        return self._acquiring

    def start(self) -> None:
        self._check()
        self._acquiring = True

    def stop(self) -> None:
        self._check()
        self.outstanding -= len(self._queue)  # queued buffers go back to the producer
        self._queue.clear()
        self._acquiring = False

    def try_fetch(self, timeout: float = 0.0) -> FakeBuffer | None:
        end = time.monotonic() + timeout
        while True:
            self._check()
            if self._queue:
                return self._queue.popleft()
            if time.monotonic() >= end:
                return None
            time.sleep(0.001)

    def pulse(self) -> None:
        """A rising edge on the trigger line."""
        if self.nodes.TriggerMode.value == "On" and self.nodes.TriggerSource.value != "Software":
            self._expose()

    def unplug(self) -> None:
        self.gone = True

    def close(self) -> None:
        self.closed = True

    def _check(self) -> None:
        if self.gone:
            raise type("IoException", (Exception,), {})("device removed")

    def _software(self) -> None:
        self._check()
        if self.nodes.TriggerSource.value == "Software":
            self._expose()

    def _latch(self) -> None:
        self.nodes.TimestampLatchValue._value = self.device_clock_ns()

    def _expose(self) -> None:
        if not self._acquiring:
            return
        t = time.monotonic()
        self._frame_id += 1
        if self.outstanding >= self.num_buffers:
            self.dropped += 1  # no free buffer: the frame is lost, its id skipped
            return
        self.outstanding += 1
        image = self.render(t)
        self._queue.append(FakeBuffer(self, image, self._frame_id, self.device_clock_ns()))


class FakeDisplay:
    """A display backend whose `present` waits for a simulated vsync at `refresh_hz`: never
    sooner than one refresh after the previous present, later when the host is busy. It
    returns the time of its sync on the display's own clock, which counts one refresh per
    present (a fake display never misses a sync, however loaded the test machine), so the
    driver's vsync check sees `refresh_hz`. Without vsync a present returns at once, with the
    current time. `shown` lists (monotonic time, frame) of every present; `fail_after(n, exc)`
    makes the present after the next n raise `exc` (a display that fails mid-sequence)."""

    def __init__(self, size: tuple[int, int], refresh_hz: float = 240.0, vsync: bool = True) -> None:
        self.size, self.refresh_hz, self.vsync = size, refresh_hz, vsync
        self.shown: list[tuple[float, object]] = []
        self.closed = False
        self._next = self._clock0 = time.monotonic()
        self._syncs = 0
        self._failure: tuple[int, Exception] | None = None

    def fail_after(self, presents: int, exc: Exception) -> None:
        self._failure = (len(self.shown) + presents, exc)

    def present(self, rgb) -> float:
        if self._failure is not None and len(self.shown) >= self._failure[0]:
            raise self._failure[1]
        if not self.vsync:
            self.shown.append((time.monotonic(), rgb))
            return self.shown[-1][0]
        self._next = max(self._next + 1.0 / self.refresh_hz, time.monotonic())
        time.sleep(max(0.0, self._next - time.monotonic()))
        self.shown.append((time.monotonic(), rgb))
        self._syncs += 1
        return self._clock0 + self._syncs / self.refresh_hz

    def current(self) -> object:
        return self.shown[-1][1] if self.shown else None

    def close(self) -> None:
        self.closed = True


# ------------------------------------------------------------------ device emulators


class Dlpc350Emulator:
    """A LightCrafter 4500 that acknowledges every write and answers every read (version,
    status, validation done and clean): for conformance and rig tests that exercise the
    driver's behaviour rather than one exact exchange. `commands` logs (command, payload)."""

    def __init__(self) -> None:
        self.commands: list[tuple[int, bytes]] = []
        self._pending = bytearray()
        self._replies: deque[bytes] = deque()
        self.closed = False

    def write(self, report: bytes, timeout_s: float) -> None:
        self._pending += report
        length = int.from_bytes(self._pending[2:4], "little")
        if len(self._pending) < 4 + length:
            return  # continuation reports follow
        flags, seq = self._pending[0], self._pending[1]
        command = int.from_bytes(self._pending[4:6], "little")
        payload = bytes(self._pending[6:4 + length])
        self._pending.clear()
        self.commands.append((command, payload))
        data = bytes(16) if command == 0x0205 else b"\x00" if flags & 0x80 else b""
        self._replies.append((bytes([0, seq]) + len(data).to_bytes(2, "little") + data).ljust(64, b"\0"))

    def read(self, timeout_s: float) -> bytes:
        if not self._replies:
            raise DeviceTimeout("dlpc350-emulator", "no report", timeout_s)
        return self._replies.popleft()

    def close(self) -> None:
        self.closed = True


class TriggerBoxEmulator(FakeSerial):
    """The reference trigger-box firmware's line protocol, answered in software; a
    started train counts its pulses by elapsed time, `pressed` counts the foot switch's
    presses (protocol 2; `protocol=1` answers as the older firmware without the input)."""

    def __init__(self, protocol: int = 2) -> None:
        super().__init__([], timeout=0.05)
        self.period_us, self.width_us, self.armed = 50000, 100, 0
        self.started_at: float | None = None  # time.monotonic() of START
        self.protocol, self.pressed = protocol, 0
        self.lines: list[str] = []

    def write(self, data: bytes) -> int:
        for line in data.decode().splitlines():
            self.lines.append(line)
            self._out += (self._answer(line) + "\n").encode()
        return len(data)

    def done(self) -> bool:
        return True

    def _sent(self) -> int:
        if self.started_at is None:
            return 0
        return min(self.armed, 1 + int((time.monotonic() - self.started_at) * 1e6 // self.period_us))

    def _answer(self, line: str) -> str:
        cmd, _, arg = line.partition(" ")
        if cmd == "ID?":
            return f"ID SLSCAN-TRIGGERBOX {self.protocol} emulator"
        if cmd == "PRESSES?" and self.protocol >= 2:
            return f"PRESSES {self.pressed}"
        if cmd == "COUNT?":
            return f"COUNT {self._sent()} {self.armed}"
        if cmd == "STOP":
            self.started_at = None
            return "OK"
        if cmd == "START":
            if not self.armed:
                return "ERR 4 not armed"
            self.started_at = time.monotonic()
            return "OK"
        if cmd in ("PERIOD", "WIDTH", "ARM") and arg.isdigit():
            setattr(self, {"PERIOD": "period_us", "WIDTH": "width_us", "ARM": "armed"}[cmd], int(arg))
            return "OK" if cmd != "ARM" or self.width_us < self.period_us else "ERR 3 width not below period"
        return "ERR 1 unknown command"
