"""A microcontroller trigger box over a serial line (reference firmware in firmware/triggerbox/).

Line protocol, version 2: ASCII, one command per line ending in "\\n" (the box also takes
"\\r\\n"), exactly one reply line per command. Times are integer microseconds.

    host                    box                                  meaning
    ID?                     ID SLSCAN-TRIGGERBOX <proto> <board>  identify
    PERIOD <us>             OK                                   pulse period, 100..10000000
    WIDTH <us>              OK                                   pulse width, 1..period-1
    ARM <n>                 OK                                   arm a train of n pulses, 1..1000000
    START                   OK                                   first pulse now, then one per period
    STOP                    OK                                   stop a running train (harmless otherwise)
    COUNT?                  COUNT <sent> <armed>                 pulses sent since ARM, pulses armed
    PRESSES?                PRESSES <n>                          presses of the input (the operator's
                                                                 foot switch), debounced, counted since
                                                                 the box started (protocol 2)
    (anything wrong)        ERR <code> <text>                    1 unknown command, 2 bad value,
                                                                 3 width not below period, 4 not armed,
                                                                 5 busy (a train is running)
    (after reset)           READY SLSCAN-TRIGGERBOX <proto>      printed once when the firmware starts

Boards whose USB-serial bridge resets the microcontroller when the port opens (Arduino
Uno/Nano through DTR) miss what is sent during their boot; `connect` therefore repeats
"ID?" until the box answers, taking a READY banner as the sign to ask again at once,
within `boot_timeout_s`. A broken link is dropped and reopened at the next call.

The box says nothing when a train ends, and polling COUNT? would interleave with the
commands of the caller, so the status `start()` returns finishes once the train's duration
((count - 1) periods + the pulse width) has passed after START; `pulses_sent` asks the box.

The input is an event counter rather than a message the box sends by itself, so every
reply still answers one command and no press is lost between two polls: `presses()`
returns the presses since its previous call. Protocol 1 (the same commands without
PRESSES?) is still driven; only `presses()` needs protocol 2.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from scanner.devices import TriggerSource
from scanner.drivers.registry import Driver, register
from scanner.drivers.transport import DropsLostPort, SerialLink, open_serial
from scanner.errors import DeviceError, DeviceTimeout, UnsupportedSetting
from scanner.schema import PositiveFloat, Schema, Str
from scanner.status import Status

if TYPE_CHECKING:
    from scanner.rig import RigConfig

log = logging.getLogger(__name__)

IDENTITY = "SLSCAN-TRIGGERBOX"
PROTOCOL = 2
INPUT_PROTOCOL = 2  # the first protocol with the input (PRESSES?)
BAUDRATE = 115200
ERROR_CODES = {1: "unknown command", 2: "bad value", 3: "width not below period", 4: "not armed", 5: "busy"}
_ID_RETRY_S = 0.3


def serial_opener(name: str, port: str, timeout_s: float = 0.5) -> Callable[[], SerialLink]:
    return lambda: open_serial(name, port, BAUDRATE, timeout_s)


class TriggerBox(DropsLostPort, TriggerSource):
    """Pulse trains from the reference trigger-box firmware, and presses of its input
    (see the module docstring)."""

    def __init__(self, open_port: Callable[[], SerialLink], name: str = "trigger-box", boot_timeout_s: float = 3.0,
                 timeout_s: float = 0.5) -> None:
        super().__init__(name)
        self.boot_timeout_s = boot_timeout_s
        self.timeout_s = timeout_s
        self.identity: dict[str, str] = {}
        self._open_port = open_port
        self._port: SerialLink | None = None
        self._presses_seen: int | None = None  # the box's press count at the last presses() call
        self._train_s = 0.0  # duration of the armed train: last pulse's end after START
        self._train_timer: threading.Timer | None = None  # finishes a started train's status
        self._connect()

    def ask(self, command: str) -> str:
        """Send one command line; its reply line (an ERR reply raises)."""
        self._check_alive()
        return self._ask(command)

    def presses(self) -> int:
        """Presses of the box's input (the foot switch) since the previous call; 0 at the
        first call, so presses before the station was ready never start a scan. A box
        that restarted counts from 0 again: its count is then taken as new presses."""
        self._check_alive()
        if int(self.identity.get("protocol", PROTOCOL)) < INPUT_PROTOCOL:
            raise UnsupportedSetting(self.name, f"firmware protocol {self.identity['protocol']} has no input (foot "
                                                f"switch); flash firmware/triggerbox from this slscan version")
        reply = self._ask("PRESSES?").split()
        if len(reply) != 2 or reply[0] != "PRESSES" or not reply[1].isdigit():
            raise DeviceError(self.name, f"unexpected reply to PRESSES?: {' '.join(reply)!r}")
        count, seen = int(reply[1]), self._presses_seen
        self._presses_seen = count
        if seen is None:
            return 0
        return count - seen if count >= seen else count

    def _do_arm(self, count: int, period_s: float, pulse_width_s: float) -> None:
        period_us, width_us = round(period_s * 1e6), round(pulse_width_s * 1e6)
        if not 100 <= period_us <= 10_000_000 or not 1 <= width_us < period_us or count > 1_000_000:
            raise UnsupportedSetting(self.name, f"pulse train outside the box's range: count {count} (<= 1000000), "
                                                f"period {period_us} us (100..10000000), width {width_us} us")
        self._ask(f"PERIOD {period_us}")
        self._ask(f"WIDTH {width_us}")
        self._ask(f"ARM {count}")
        self._train_s = ((count - 1) * period_us + width_us) / 1e6

    def _do_start(self, status: Status) -> None:
        self._ask("START")
        self._train_timer = threading.Timer(self._train_s, status.set_finished)
        self._train_timer.daemon = True
        self._train_timer.start()

    def _do_stop(self) -> None:
        self._cancel_train_timer()
        if not self._shut_down and self._port is not None:
            self._ask("STOP")

    def _do_pulses_sent(self) -> int:
        self._check_alive()
        reply = self._ask("COUNT?").split()
        if len(reply) != 3 or reply[0] != "COUNT" or not (reply[1].isdigit() and reply[2].isdigit()):
            raise DeviceError(self.name, f"unexpected reply to COUNT?: {' '.join(reply)!r}")
        return int(reply[1])

    def _do_shutdown(self) -> None:
        self._cancel_train_timer()
        try:
            if self._port is not None:
                self._ask("STOP")
        except DeviceError as exc:
            log.info("%s: could not stop the box while shutting down (%s); closing the port", self.name, exc)
        finally:
            self._drop()

    def describe(self) -> dict[str, object]:
        return {**super().describe(), **self.identity}

    # internals

    def _cancel_train_timer(self) -> None:
        timer, self._train_timer = self._train_timer, None
        if timer is not None:
            timer.cancel()

    def _connect(self) -> SerialLink:
        return self._handshake(b"ID?\n", "ID?", self._greeting, retry_s=_ID_RETRY_S, timeout_s=self.boot_timeout_s,
                               missing="no answer to ID?",
                               advice="is this the trigger box's port and is its firmware "
                                      "(firmware/triggerbox) flashed?")

    def _greeting(self, line: str) -> bool | None:
        """True on the board's identity line (checked); False on its boot line READY (ask again
        now); None: keep listening."""
        if line.startswith("ID "):
            self._check_identity(line)
            log.info("%s: connected, firmware protocol %s on %s", self.name, self.identity["protocol"],
                     self.identity["board"])
            return True
        return False if line.startswith("READY") else None

    def _check_identity(self, line: str) -> None:
        parts = line.split()
        if len(parts) < 4 or parts[1] != IDENTITY:
            raise DeviceError(self.name, f"device answered {line!r}: not an {IDENTITY}; check the port")
        if not parts[2].isdigit() or not 1 <= int(parts[2]) <= PROTOCOL:
            raise DeviceError(self.name, f"firmware speaks protocol {parts[2]}, this driver 1..{PROTOCOL}: flash "
                                         f"firmware/triggerbox from this slscan version")
        self.identity = {"protocol": parts[2], "board": parts[3]}

    def _ask(self, command: str) -> str:
        port = self._connect()
        log.debug("%s: > %s", self.name, command)
        self._send(port, command)
        end = time.monotonic() + self.timeout_s
        while True:
            line = self._readline(port)
            if line and not line.startswith("READY"):
                break
            if line.startswith("READY"):  # the box reset under us: it lost its settings
                raise DeviceError(self.name, f"the box restarted while handling {command!r}; check its power "
                                             f"supply, then scan again")
            if time.monotonic() >= end:
                self._drop()
                raise DeviceTimeout(self.name, f"no reply to {command!r}", self.timeout_s,
                                    "the link is reopened on the next call")
        log.debug("%s: < %s", self.name, line)
        if line.startswith("ERR"):
            parts = line.split(maxsplit=2)
            code = int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else 0
            text = parts[2] if len(parts) > 2 else ERROR_CODES.get(code, "error")
            raise DeviceError(self.name, f"{command!r} refused: error {code}, {text}")
        if command.endswith("?") or line == "OK":
            return line
        raise DeviceError(self.name, f"unexpected reply to {command!r}: {line!r}")

    def _send(self, port: SerialLink, command: str) -> None:
        self._write(port, command.encode("ascii") + b"\n", command)


class TriggerBoxSettings(Schema):
    """The [trigger_box] keys: its serial `port`, and how long it may take to answer after
    opening (`boot_timeout_s`, s)."""

    port: Str
    boot_timeout_s: PositiveFloat = 3.0


def open_trigger_box(config: RigConfig, settings: TriggerBoxSettings, transports: Mapping[str, Any]) -> TriggerBox:
    """The rig's trigger box; transports["trigger_box"] replaces the serial port."""
    opener = transports.get("trigger_box") or serial_opener("trigger-box", settings.port)
    return TriggerBox(opener, "trigger-box", settings.boot_timeout_s)


DRIVER = register(Driver("trigger_box", "triggerbox", "hardware", TriggerBoxSettings, open_trigger_box))
