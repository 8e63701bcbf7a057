"""A GRBL 1.1 controller answered in software, for rig and conformance tests of the stage.

It speaks the subset of the protocol `scanner.drivers.grbl` uses (see that module): the
banner after a soft reset, `G0` rapid moves that take distance / `rate` seconds (a status
report during the move gives the interpolated position, `G4`'s ok comes when the move
would have ended), `$H` homing (to 0), `$X` unlock, `?` reports, `!` feed hold, and the
errors and alarms a real controller gives: `error:9` for motion while alarmed, `error:5`
for `$H` without homing enabled, `ALARM:2` for a target past its soft limits. Faults for
tests: `hard_limit_at` (the next move trips a limit switch at that fraction of its
travel: ALARM:1), `unplug_at` (the cable is pulled at that fraction of the next move),
`silent` (the controller stops answering). `lines` logs every line and real-time byte.
"""

from __future__ import annotations

import time

from scanner.drivers.testing import FakeSerial

LETTERS = "XYZ"


class GrblEmulator(FakeSerial):
    """A 3-axis GRBL 1.1 controller (see the module docstring). `rate`: units/s of every
    axis; `homing`: homing enabled (locked after reset until `$H` or `$X`); `soft_limits`:
    letter -> (lo, hi) travel in its units, refused with ALARM:2."""

    def __init__(self, rate: float = 3600.0, homing: bool = False,
                 soft_limits: dict[str, tuple[float, float]] | None = None, version: str = "1.1h") -> None:
        super().__init__([], timeout=0.05, realtime=b"?!\x18")
        self.rate, self.homing, self.soft_limits, self.version = rate, homing, dict(soft_limits or {}), version
        self.lines: list[str] = []
        self.hard_limit_at: float | None = None
        self.unplug_at: float | None = None
        self.silent = False
        self.state = "Alarm" if homing else "Idle"
        self._from = [0.0] * 3
        self._to = [0.0] * 3
        self._t0 = self._t1 = time.monotonic()
        self._unplug_time: float | None = None

    def done(self) -> bool:
        return True

    def position(self) -> list[float]:
        """Where the axes are now (units), along a running move."""
        now = time.monotonic()
        f = 1.0 if now >= self._t1 else max(0.0, (now - self._t0) / (self._t1 - self._t0))
        if self.state == "Run" and f >= 1.0:
            self.state = "Idle"
        return [a + (b - a) * f for a, b in zip(self._from, self._to)]

    def write(self, data: bytes) -> int:
        self._check_plug()
        if self._script.unplugged:
            return super().write(data)  # raises as a vanished port does
        for byte in data:
            if byte in self._realtime:
                self.lines.append(chr(byte) if byte != 0x18 else "^X")
                self._reply(self._realtime_answer(byte))
                continue
            self._written.append(byte)
            if byte == 0x0A:
                line, self._written = self._written.decode().strip(), bytearray()
                self.lines.append(line)
                self._reply(self._answer(line))
        return len(data)

    def readline(self) -> bytes:
        self._check_plug()
        return super().readline()

    # internals

    def _check_plug(self) -> None:
        if self._unplug_time is not None and time.monotonic() >= self._unplug_time:
            self._script.unplugged = True

    def _reply(self, text: str | tuple[float, str]) -> None:
        if self.silent or not text:
            return
        if isinstance(text, tuple):
            self._timed.append((text[0], text[1].encode()))
        else:
            self._out += text.encode()

    def _realtime_answer(self, byte: int) -> str:
        if byte == ord("?"):
            pos = self.position()
            return f"<{self.state}|MPos:{pos[0]:.3f},{pos[1]:.3f},{pos[2]:.3f}|FS:0,0>\r\n"
        if byte == ord("!"):
            self._stop_here()
            if self.state == "Run":
                self.state = "Hold"
            return ""
        # soft reset: a reset while moving loses the position (alarm 3); otherwise kept
        moving = self.state in ("Run", "Hold") and time.monotonic() < self._t1
        self._stop_here()
        self._timed.clear()
        self._out.clear()
        banner = f"\r\nGrbl {self.version} ['$' for help]\r\n"
        if moving and self.state == "Run":
            self.state = "Alarm"
            return banner + "ALARM:3\r\n"
        self.state = "Alarm" if self.homing else "Idle"
        return banner + ("[MSG:'$H'|'$X' to unlock]\r\n" if self.homing else "")

    def _answer(self, line: str) -> str | tuple[float, str]:
        if line == "":
            return "ok\r\n"
        if line == "$H":
            if not self.homing:
                return "error:5\r\n"
            duration = max(abs(p) for p in self.position()) / self.rate + 0.01
            self._start_move([0.0, 0.0, 0.0], duration)
            self.state = "Idle"
            return (self._t1, "ok\r\n")
        if line == "$X":
            self.state = "Idle" if self.state == "Alarm" else self.state
            return "[MSG:Caution: Unlocked]\r\nok\r\n"
        if line.startswith("G4"):
            return (max(self._t1, time.monotonic()), "ok\r\n")
        if "G0" in line:
            return self._rapid(line)
        return "error:20\r\n"

    def _rapid(self, line: str) -> str | tuple[float, str]:
        if self.state == "Alarm":
            return "error:9\r\n"
        words = line.split("G0", 1)[1]
        target = list(self.position())
        for i, letter in enumerate(LETTERS):
            if letter in words:
                rest = words.split(letter, 1)[1]
                number = rest[:next((k for k, c in enumerate(rest) if c.isalpha()), len(rest))]
                try:
                    target[i] = float(number)
                except ValueError:
                    return "error:2\r\n"
        for letter, (lo, hi) in self.soft_limits.items():
            if not lo <= target[LETTERS.index(letter)] <= hi:
                self.state = "Alarm"
                return "ALARM:2\r\n[MSG:Reset to continue]\r\n"
        here = self.position()
        duration = max(abs(b - a) for a, b in zip(here, target)) / self.rate
        if self.hard_limit_at is not None:
            f, self.hard_limit_at = self.hard_limit_at, None
            stop_at = [a + (b - a) * f for a, b in zip(here, target)]
            self._start_move(stop_at, duration * f)
            self.state = "Alarm"
            return "ok\r\n" if duration == 0 else self._at_end("ALARM:1\r\n[MSG:Reset to continue]\r\n")
        if self.unplug_at is not None:
            self._unplug_time = time.monotonic() + duration * self.unplug_at
            self.unplug_at = None
        self._start_move(target, duration)
        self.state = "Run" if duration > 0 else "Idle"
        return "ok\r\n"

    def _at_end(self, text: str) -> str:
        self._timed.append((self._t1, text.encode()))
        return "ok\r\n"

    def _start_move(self, target: list[float], duration: float) -> None:
        self._from = self.position()
        self._to = list(target)
        self._t0 = time.monotonic()
        self._t1 = self._t0 + max(duration, 0.0)

    def _stop_here(self) -> None:
        here = self.position()
        self._from = self._to = here
        self._t0 = self._t1 = time.monotonic()
