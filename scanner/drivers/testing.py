"""Fake transports that play a scripted byte exchange, for protocol tests without hardware.

Like pymeasure's `expected_protocol`, a test lists what the host must send and what the
device answers; any other byte fails the test at once with both sides shown in hex, and
`expected_protocol` checks at the end that the whole script was played. Scripts can also
inject faults: a device that stays silent, NACKs, or is unplugged mid-sequence.
"""

from __future__ import annotations

import contextlib
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Iterator, TypeVar

from ..errors import DeviceDisconnected, DeviceTimeout

T = TypeVar("T")

SILENT = None  # as a reply: the device does not answer (the host's read times out)


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
            raise ProtocolMismatch(f"step {len(self.played)}: host sent\n  {data.hex(' ')}\nexpected\n  {expected.hex(' ')}")
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
            raise DeviceTimeout("fake-hid", f"no report within {timeout_s} s")
        return self._replies.popleft()

    def close(self) -> None:
        self.closed = True

    def done(self) -> bool:
        return self._script.done() and not self._replies


class FakeSerial:
    """A serial port (`transport.SerialLink`) playing a script of line exchanges.

    `banner` is printed by the device `banner_delay_s` after the port opens (a board that
    resets when the port opens). `readline` waits at most `timeout` like pyserial."""

    def __init__(self, steps: list[Step], banner: bytes = b"", banner_delay_s: float = 0.0,
                 timeout: float | None = 0.2) -> None:
        self._script = _Script(steps)
        self.timeout = timeout
        self._out = bytearray()
        self._written = bytearray()
        self._timed: list[tuple[float, bytes]] = [(time.monotonic() + banner_delay_s, banner)] if banner else []
        self.closed = False

    def write(self, data: bytes) -> int:
        if self._script.unplugged:
            import serial

            raise serial.SerialException("write failed: [Errno 5] Input/output error")
        self._written += data
        while b"\n" in self._written:
            line, _, rest = bytes(self._written).partition(b"\n")
            self._written = bytearray(rest)
            try:
                step = self._script.expect_write(line + b"\n")
            except DeviceDisconnected:
                import serial

                raise serial.SerialException("write failed: [Errno 5] Input/output error") from None
            if not self._script.pending_sent:
                self._out += b"".join(step.reply_parts)
        return len(data)

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
