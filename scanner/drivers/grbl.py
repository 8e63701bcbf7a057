"""A GRBL-based motion controller (a turntable, a linear slide) over a serial line.

GRBL 1.1's public line protocol (grbl/grbl doc/markdown/interface.md, commands.md): the host
sends one line and waits for its response, `ok` or `error:N`; push messages may come at any
time (`ALARM:N`, `[MSG:...]`, the welcome banner `Grbl 1.1h ['$' for help]`); real-time
commands are single bytes sent without a line end and never answered with `ok`:

    host                      controller                            here
    0x18 (soft reset)         Grbl 1.1h ['$' for help]             connect: the banner names the version
                              [MSG:'$H'|'$X' to unlock]            (homing enabled: locked until homed)
    G21G90G0X45.000           ok                                   a rapid move in mm (or turntable units)
    G4P0.01                   ok  (once the planner is empty)      wait for the motion to end
    ?                         <Idle|MPos:45.000,0.000,0.000|FS:0,0>  state and position
    $H                        ok  (after the cycle)                homing
    !                         (none)                               feed hold (stop), then 0x18

Errors: `error:N` refuses a line (the G-code or setting named, with GRBL's own meaning of
N); `ALARM:N` stops the machine and locks it (1 hard limit, 2 soft limit, 3 reset while
moving, 6..9 homing failed): raised as `StageAlarm`, the link is reset at the next call and
the axes count as not homed. A controller that does not answer within `timeout_s` (the end
of a move: within the move's deadline) raises DeviceTimeout and the link is reopened at the
next call; a vanished port raises DeviceDisconnected.

Units: GRBL counts in its own units per axis (mm for a slide; for a turntable whatever its
steps/unit setting makes them, degrees when `$100` is steps per degree): `units_per_turn`
converts a rotary axis (rad here). A status report gives `MPos` or `WPos` (`$10`); work
positions are used, MPos minus the last `WCO` the controller sent.

Boards whose USB-serial bridge resets the microcontroller when the port opens (Arduino
Uno/Nano) boot for a second or two: `connect` repeats the soft reset until the banner comes,
within `boot_timeout_s`.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Literal

import serial

from scanner.drivers.registry import Driver, register
from scanner.drivers.transport import DropsLostPort, SerialLink, open_serial
from scanner.errors import ConfigError, DeviceError, DeviceTimeout, StageAlarm
from scanner.schema import PositiveFloat, Schema, Str
from scanner.stage import Axis, AxisKind, Stage
from scanner.stage_model import StageConfig
from scanner.status import Status

if TYPE_CHECKING:
    from scanner.rig import RigConfig

log = logging.getLogger(__name__)

BAUDRATE = 115200
RESET = b"\x18"
STATUS = b"?"
FEED_HOLD = b"!"
LETTERS = "XYZABC"  # the order of coordinates in a status report
_RESET_RETRY_S = 0.5
_BANNER = re.compile(r"^Grbl(?:HAL)? (\d+)\.(\d+)(\w*)")
_POSITION = re.compile(r"^(MPos|WPos|WCO):(.*)$")

ERRORS = {1: "G-code words consist of a letter and a value; letter was not found",
          2: "numeric value format is not valid or missing an expected value",
          3: "'$' system command not recognised or supported", 4: "negative value for an expected positive value",
          5: "homing cycle is not enabled in the controller's settings ($22)",
          8: "'$' command only valid when idle", 9: "G-code locked out during alarm or jog state",
          11: "line too long", 15: "target exceeds machine travel", 20: "unsupported or invalid G-code command",
          22: "feed rate has not yet been set", 33: "invalid motion target"}
ALARMS = {1: "hard limit triggered; machine position is likely lost, home again",
          2: "motion target exceeds machine travel (soft limit)",
          3: "reset while in motion; position is likely lost, home again",
          6: "homing failed: reset during the cycle", 7: "homing failed: safety door opened",
          8: "homing failed: could not clear the limit switch when pulling off",
          9: "homing failed: limit switch not found within the search distance"}
_POSITION_LOST = {1, 3, 6, 7, 8, 9}  # after these, the axes must be homed again


def serial_opener(name: str, port: str, timeout_s: float = 0.2) -> Callable[[], SerialLink]:
    return lambda: open_serial(name, port, BAUDRATE, timeout_s)


class GrblStage(DropsLostPort, Stage):
    """A stage whose axes are driven by a GRBL 1.1 controller (see the module docstring).

    `letters` maps each axis name to the controller axis driving it; `units_per_turn`
    gives, for each rotary axis, the controller's units per full turn (360: degrees)."""

    def __init__(self, open_port: Callable[[], SerialLink], axes: Sequence[Axis], letters: Mapping[str, str],
                 *, units_per_turn: Mapping[str, float] | None = None, name: str = "grbl-stage", settle_s: float = 0.0,
                 boot_timeout_s: float = 5.0, timeout_s: float = 1.0) -> None:
        super().__init__(name, axes, settle_s)
        turns = dict(units_per_turn or {})
        for axis in self.axes.values():
            letter = letters.get(axis.name)
            if letter is None or letter not in LETTERS:
                raise ValueError(f"{name}: axis {axis.name} needs a controller letter, one of {LETTERS}")
            if axis.kind is AxisKind.ROTARY and not turns.get(axis.name, 360.0) > 0:
                raise ValueError(f"{name}: units_per_turn of {axis.name} must be > 0")
        if len({letters[a] for a in self.axes}) != len(self.axes):
            raise ValueError(f"{name}: two axes on one controller letter: {dict(letters)}")
        self.letters = {a: letters[a] for a in self.axes}
        self._scale = {a.name: (turns.get(a.name, 360.0) / (2 * math.pi) if a.kind is AxisKind.ROTARY else 1.0)
                       for a in self.axes.values()}
        self.boot_timeout_s = boot_timeout_s
        self.timeout_s = timeout_s
        self.identity: dict[str, str] = {}
        self.messages: list[str] = []  # the controller's [MSG:...] push messages, in order
        self._open_port = open_port
        self._port: SerialLink | None = None
        self._io = threading.RLock()  # one exchange at a time (a move's thread holds it to the end)
        self._wco = [0.0] * len(LETTERS)
        self._worker: threading.Thread | None = None
        with self._io:
            self._connect()

    def ask(self, line: str, timeout_s: float | None = None) -> None:
        """Send one line (a G-code block or `$` command) and wait for its `ok`."""
        self._check_alive()
        self._check_idle()
        with self._io:
            self._ask(line, self.timeout_s if timeout_s is None else timeout_s)

    def describe(self) -> dict[str, object]:
        return {**super().describe(), **self.identity, "letters": self.letters}

    # driver methods

    def _do_move(self, targets: dict[str, float], status: Status) -> None:
        words = "".join(f"{self.letters[n]}{v * self._scale[n]:.3f}" for n, v in targets.items())
        with self._io:  # the block is refused (error:N) or planned (ok) at once
            self._ask(f"G21G90G0{words}", self.timeout_s)
        self._finish_on_thread(status, "G4P0.01", targets)  # its ok comes once the planner is empty

    def _do_home(self, status: Status) -> None:
        self._finish_on_thread(status, "$H", {})  # its ok comes after the cycle

    def _do_position(self) -> dict[str, float]:
        if not self._io.acquire(timeout=self.timeout_s):
            raise DeviceError(self.name, "the stage is moving: its position is known once the move has ended")
        try:
            return self._report()[1]
        finally:
            self._io.release()

    def _do_stop(self) -> None:
        port = self._port
        if port is None:
            return
        try:  # real-time bytes go out at once, whoever holds the exchange
            port.write(FEED_HOLD)
            port.write(RESET)
        except (serial.SerialException, OSError) as exc:
            log.info("%s: could not stop the controller (%s)", self.name, exc)
        worker = self._worker
        if worker is not None and worker is not threading.current_thread():
            worker.join(self.timeout_s + self.boot_timeout_s)
        with self._io:
            self._drop()  # the reset leaves a banner and possibly an alarm: start afresh at the next call
        self._homed = False

    def _do_shutdown(self) -> None:
        if self.moving:
            self._do_stop()
        with self._io:
            self._drop()

    # internals

    def _finish_on_thread(self, status: Status, line: str, targets: dict[str, float]) -> None:
        """On a thread: send `line`, whose ok means the motion has ended (within the
        action's deadline), check the controller is idle with the axes at `targets`, and
        complete `status` (after the settle time) or fail it with what went wrong."""

        def finish() -> None:
            try:
                with self._io:
                    self._ask(line, self.action_deadline_s)
                    state, where = self._report()
                if state != "Idle":
                    raise DeviceError(self.name, f"the controller reports {state!r} after {line!r}, not Idle")
                for n, v in targets.items():
                    if abs(where[n] - v) > self.axes[n].tolerance:
                        raise DeviceError(self.name, f"{n} stopped at {self.axes[n].text(where[n])}, not at its "
                                                     f"target {self.axes[n].text(v)}")
            except BaseException as exc:
                status.set_exception(exc)
                return
            self._motion_ended(status)

        self._worker = threading.Thread(target=finish, name=f"{self.name}-motion", daemon=True)
        self._worker.start()

    def _report(self) -> tuple[str, dict[str, float]]:
        """Ask for a status report: (state, work position of every axis)."""
        port = self._connect()
        log.debug("%s: > ?", self.name)
        self._write(port, STATUS, "?")
        end = time.monotonic() + self.timeout_s
        while True:
            line = self._readline(port)
            if line.startswith("<") and line.endswith(">"):
                break
            if line:
                self._push(line, "?")
            elif time.monotonic() >= end:
                self._drop()
                raise DeviceTimeout(self.name, "no status report after '?'", self.timeout_s,
                                    "the link is reopened on the next call")
        log.debug("%s: < %s", self.name, line)
        fields = line[1:-1].split("|")
        state = fields[0].split(":")[0]
        coords: dict[str, list[float]] = {}
        for f in fields[1:]:
            m = _POSITION.match(f)
            if m:
                try:
                    coords[m.group(1)] = [float(x) for x in m.group(2).split(",")]
                except ValueError:
                    raise DeviceError(self.name, f"unreadable status report {line!r}") from None
        if "WCO" in coords:
            self._wco[:len(coords["WCO"])] = coords["WCO"]
        if "WPos" in coords:
            work = coords["WPos"]
        elif "MPos" in coords:
            work = [m - w for m, w in zip(coords["MPos"], self._wco)]
        else:
            raise DeviceError(self.name, f"status report without a position: {line!r}")
        where = {}
        for n, letter in self.letters.items():
            i = LETTERS.index(letter)
            if i >= len(work):
                raise DeviceError(self.name, f"status report has no {letter} axis (for {n}): {line!r}")
            where[n] = work[i] / self._scale[n]
        return state, where

    def _connect(self) -> SerialLink:
        return self._handshake(RESET, "soft reset", self._greeting, retry_s=_RESET_RETRY_S,
                               timeout_s=self.boot_timeout_s,
                               missing="no GRBL welcome banner after a soft reset",
                               advice="is this the stage controller's port, at 115200 baud, with GRBL 1.1 flashed?")

    def _greeting(self, line: str) -> bool | None:
        """True on GRBL's welcome banner (its version checked); None: keep listening."""
        m = _BANNER.match(line)
        if m:
            self._check_version(m)
            return True
        return None

    def _check_version(self, m: re.Match[str]) -> None:
        major, minor = int(m.group(1)), int(m.group(2))
        if (major, minor) < (1, 1):
            raise DeviceError(self.name, f"controller runs GRBL {major}.{minor}{m.group(3)}; this driver needs 1.1 "
                                         f"or later (its status reports); flash GRBL 1.1")
        self.identity = {"firmware": m.group(0)}
        log.info("%s: connected, %s", self.name, m.group(0))

    def _ask(self, line: str, timeout_s: float) -> None:
        port = self._connect()
        log.debug("%s: > %s", self.name, line)
        self._write(port, line.encode("ascii") + b"\n", line)
        end = time.monotonic() + timeout_s
        while True:
            reply = self._readline(port)
            if reply == "ok":
                log.debug("%s: < ok", self.name)
                return
            if reply.startswith("error:"):
                code = reply[6:]
                meaning = ERRORS.get(int(code), "see GRBL's error codes") if code.isdigit() else code
                raise DeviceError(self.name, f"{line!r} refused: error {code}, {meaning}")
            if reply:
                self._push(reply, line)
            elif time.monotonic() >= end:
                self._drop()
                raise DeviceTimeout(self.name, f"no reply to {line!r}", timeout_s,
                                    "the link is reopened on the next call")

    def _push(self, message: str, during: str) -> None:
        """A push message that came while waiting for a reply to `during`."""
        log.debug("%s: < %s", self.name, message)
        if message.startswith("ALARM:"):
            code = message[6:]
            meaning = ALARMS.get(int(code), "see GRBL's alarm codes") if code.isdigit() else code
            self._drop()  # GRBL locks out motion until reset: the next call starts afresh
            if not code.isdigit() or int(code) in _POSITION_LOST:
                self._homed = False
            raise StageAlarm(self.name, f"alarm {code} during {during!r}: {meaning}")
        if _BANNER.match(message):
            self._drop()
            self._homed = False
            raise DeviceError(self.name, f"the controller restarted while handling {during!r}; check its power "
                                         f"supply, then home it and scan again")
        if message.startswith("[MSG:"):
            self.messages.append(message[5:-1])
            log.info("%s: controller says: %s", self.name, message[5:-1])



def identify(port: str, boot_timeout_s: float = 2.5) -> str:
    """The firmware banner of a GRBL controller on serial `port` ("Grbl 1.1h"); DeviceError
    (DeviceTimeout, DeviceDisconnected) when no GRBL 1.1 answers there."""
    probe = GrblStage(serial_opener("probe", port), [Axis("probe", AxisKind.ROTARY)], {"probe": "X"}, name="probe",
                      boot_timeout_s=boot_timeout_s)
    try:
        return probe.identity["firmware"]
    finally:
        probe.shutdown()


def open_grbl_stage(config: StageConfig, opener: Callable[[], SerialLink] | None = None) -> GrblStage:
    """The GRBL stage of a rig TOML's [stage] table (`scanner.stage_model`), its keys
    validated by `GrblSettings` and, per axis, `GrblAxisSettings`. `opener` replaces the
    serial port (tests, the emulator)."""
    p, settings = config.path, config.settings
    letters, turns = {}, {}
    for i, (axis, own) in enumerate(zip(config.axes, config.axis_settings)):
        pre = f"stage.axes[{i}]"
        letter = own.letter if own.letter is not None else LETTERS[i] if i < 3 else None
        if letter is None:
            raise ConfigError(p, f"{pre}.letter", f"required key is missing (past the third axis); one of {LETTERS}")
        if axis.kind is AxisKind.LINEAR and "units_per_turn" in own.model_fields_set:
            raise ConfigError(p, f"{pre}.units_per_turn", "a linear axis has no units_per_turn")
        letters[axis.name], turns[axis.name] = letter, own.units_per_turn
    if len(set(letters.values())) != len(letters):
        raise ConfigError(p, "stage.axes", f"two axes on one controller letter: {letters}")
    if opener is None:
        opener = serial_opener("grbl-stage", settings.port, min(settings.timeout_s, 0.2))
    return GrblStage(opener, config.axes, letters, units_per_turn=turns, name="grbl-stage", settle_s=config.settle_s,
                     boot_timeout_s=settings.boot_timeout_s,
                     timeout_s=settings.timeout_s)


class GrblSettings(Schema):
    """The [stage] keys of a GRBL controller: its serial port, how long it may take to
    answer after opening and to answer a command (s)."""

    port: Str
    boot_timeout_s: PositiveFloat = 5.0
    timeout_s: PositiveFloat = 1.0


class GrblAxisSettings(Schema):
    """The [[stage.axes]] keys of a GRBL axis: the controller axis driving it (default X,
    Y, Z in order) and, for a rotary axis, the controller's units per turn (360: degrees)."""

    letter: Literal["X", "Y", "Z", "A", "B", "C"] | None = None  # LETTERS
    units_per_turn: PositiveFloat = 360.0


def _open(config: RigConfig, settings: GrblSettings, transports: Mapping[str, Any]) -> GrblStage:
    """The rig's GRBL stage; transports["stage"] replaces the serial port."""
    assert config.stage is not None  # the hardware rig opens a stage driver only for a [stage] table
    return open_grbl_stage(config.stage, transports.get("stage"))


DRIVER = register(Driver("stage", "grbl", "hardware", GrblSettings, _open, axis_settings=GrblAxisSettings))
