"""The motion stage interface: rotary and linear axes that carry the part between views.

In the style of `scanner.devices` (after python-microscope): each public method checks
state and arguments, then calls a `_do_*` method every driver implements (all abstract).
A stage has named axes (`Axis`: rotary in rad, linear in mm, each with its travel, its
nominal speed and whether it must be homed before it moves). Moves and homing run on
after the call and return a `scanner.status.Status`:

    stage.move_to({"turntable": math.radians(45)}).wait(30.0)   # raises the move's own error
    stage.home().wait(60.0)
    stage.position()                                            # {"turntable": 0.785...}

The status finishes once the controller reports the motion ended *and* the stage's settle
time has passed (vibration dies down before a view is captured); it fails with the error
that ended the move (an alarm, a lost link) and, on its own, with DeviceTimeout when the
move runs far past its nominal duration (`scanner.devices.SEQUENCE_DEADLINE_*`: a stalled
or silent controller is detected whoever waits). A target outside an axis's travel is
refused before anything is sent (`OutOfTravel`), as is a move of an axis that needs homing
before it was homed (`NotHomed`). `stop()` stops a move (its status fails as stopped);
`shutdown()` is idempotent and final, like every device's.

Real driver: `scanner.drivers.grbl` (a GRBL-based turntable over a serial line); simulated:
`sim.virtual_stage`. Where the axes are in space (to turn a stage position into a pose of
the part) is `scanner.stage_model`.
"""

from __future__ import annotations

import abc
import logging
import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import Enum

from scanner import devices
from scanner.devices import Device
from scanner.errors import DeviceDisconnected, DeviceError, NotHomed, OutOfTravel, UnsupportedSetting
from scanner.status import Status

log = logging.getLogger(__name__)


class AxisKind(Enum):
    """A rotary axis turns (positions in rad); a linear one slides (positions in mm)."""

    ROTARY = "rotary"
    LINEAR = "linear"


@dataclass(frozen=True)
class Axis:
    """One stage axis. `limits`: its travel (rad or mm; infinite for an endless turntable);
    `speed`: nominal speed (rad/s or mm/s), for the move's expected duration; `tolerance`:
    how close a reported position must be to the target (rad or mm); `requires_homing`: it
    refuses to move until homed (a controller that lost its position at power-up)."""

    name: str
    kind: AxisKind
    limits: tuple[float, float] = (-math.inf, math.inf)
    speed: float = math.radians(30.0)
    tolerance: float = math.radians(0.01)
    requires_homing: bool = False

    def __post_init__(self) -> None:
        lo, hi = self.limits
        if not lo < hi:
            raise ValueError(f"axis {self.name}: limits {self.limits} must be increasing")
        if not (self.speed > 0 and math.isfinite(self.speed)):
            raise ValueError(f"axis {self.name}: speed must be > 0 and finite, got {self.speed}")
        if not self.tolerance > 0:
            raise ValueError(f"axis {self.name}: tolerance must be > 0, got {self.tolerance}")

    @property
    def unit(self) -> str:
        return "rad" if self.kind is AxisKind.ROTARY else "mm"

    def text(self, value: float) -> str:
        """A position for people: degrees for a rotary axis, mm for a linear one."""
        if self.kind is AxisKind.ROTARY:
            return f"{math.degrees(value):.6g} deg"
        return f"{value:.6g} mm"


class Stage(Device):
    """A motion stage with named axes (see the module docstring)."""

    def __init__(self, name: str, axes: Sequence[Axis], settle_s: float = 0.0) -> None:
        super().__init__(name)
        if not axes:
            raise ValueError(f"{name}: a stage needs at least one axis")
        if len({a.name for a in axes}) != len(axes):
            raise ValueError(f"{name}: axis names must be unique, got {[a.name for a in axes]}")
        if not settle_s >= 0:
            raise ValueError(f"{name}: settle time must be >= 0 s, got {settle_s}")
        self.axes: dict[str, Axis] = {a.name: a for a in axes}
        self.settle_s = float(settle_s)
        self._homed = False
        self._settle_timer: threading.Timer | None = None
        self.action_deadline_s = 0.0  # how long the running move or homing may take before it has failed (s)

    @property
    def homed(self) -> bool:
        return self._homed

    @property
    def moving(self) -> bool:
        """True while a move or homing is running."""
        return self._running is not None and not self._running.done

    def move_to(self, targets: Mapping[str, float]) -> Status:
        """Move the named axes to `targets` (rad or mm); the other axes stay. Returns once
        the move has started, with the status that finishes when it has ended and settled."""
        self._check_alive()
        self._check_idle()
        if not targets:
            raise UnsupportedSetting(self.name, "a move needs at least one axis target")
        goal: dict[str, float] = {}
        for axis_name, value in targets.items():
            axis = self.axes.get(axis_name)
            if axis is None:
                raise UnsupportedSetting(self.name, f"no axis named {axis_name!r}; axes: {sorted(self.axes)}")
            value = float(value)
            if not math.isfinite(value):
                raise UnsupportedSetting(self.name, f"{axis_name}: target {value} is not a finite position")
            lo, hi = axis.limits
            if not lo <= value <= hi:
                raise OutOfTravel(self.name, f"{axis_name}: target {axis.text(value)} is outside its travel "
                                             f"{axis.text(lo)} .. {axis.text(hi)}; nothing was moved")
            if axis.requires_homing and not self._homed:
                raise NotHomed(self.name, f"{axis_name} must be homed before it moves (its position is unknown "
                                          f"since power-up); call home() first")
            goal[axis_name] = value
        here = self.position()
        self._prepare({**here, **goal})
        nominal = max(abs(goal[n] - here[n]) / self.axes[n].speed for n in goal) + self.settle_s
        what = ", ".join(f"{n} to {self.axes[n].text(v)}" for n, v in goal.items())
        status = self._start_action(f"move ({what})", nominal)
        try:
            self._do_move(goal, status)
        except BaseException as exc:
            status.set_exception(exc)
            raise
        log.info("%s: move started: %s", self.name, what)
        return status

    def home(self) -> Status:
        """Run the homing cycle (every axis to its reference switch); afterwards axes that
        require homing may move. Returns the status of the cycle."""
        self._check_alive()
        self._check_idle()
        self._prepare(dict.fromkeys(self.axes, 0.0))
        status = self._start_action("homing cycle", max(_homing_s(a) for a in self.axes.values()) + self.settle_s)
        status.add_callback(self._on_homed)
        try:
            self._do_home(status)
        except BaseException as exc:
            status.set_exception(exc)
            raise
        log.info("%s: homing started", self.name)
        return status

    def position(self) -> dict[str, float]:
        """Every axis's current position (rad or mm), as the stage reports it."""
        self._check_alive()
        return self._do_position()

    def stop(self) -> None:
        """Stop a move or homing, if any (its status fails as stopped); harmless otherwise
        and after shutdown."""
        self._cancel_settle()
        self._end_running(DeviceError, "stopped before it had finished")  # first: the driver's stop may fail it too
        if not self._shut_down:
            self._do_stop()

    def shutdown(self) -> None:
        """As every device's; a move or homing still running fails first, so that what the
        driver's stop provokes (a controller's reset) is not taken for its cause."""
        if not self._shut_down:
            self._end_running(DeviceDisconnected, "ended: the device was shut down while it ran")
        super().shutdown()

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "settle_s": self.settle_s, "homed": self._homed,
                "axes": {a.name: {"kind": a.kind.value, "unit": a.unit, "limits": list(a.limits)}
                         for a in self.axes.values()}}

    # for drivers

    def _prepare(self, goal: dict[str, float]) -> None:
        """Work before a move or homing toward `goal` (every axis, rad or mm) starts its
        clock: nothing for a real stage. The simulated one renders the turned scene here,
        so that the simulator's own computing never counts against the move's deadline."""

    def _start_action(self, action: str, nominal_s: float) -> Status:
        status = self._start_running(action, nominal_s)
        self.action_deadline_s = devices.SEQUENCE_DEADLINE_FACTOR * nominal_s + devices.SEQUENCE_DEADLINE_SLACK_S
        return status

    def _motion_ended(self, status: Status) -> None:
        """The controller reports the motion over: `status` finishes after the settle time."""
        if self.settle_s <= 0:
            status.set_finished()
            return
        timer = threading.Timer(self.settle_s, status.set_finished)
        timer.daemon = True
        self._settle_timer = timer
        timer.start()

    def _cancel_settle(self) -> None:
        timer, self._settle_timer = self._settle_timer, None
        if timer is not None:
            timer.cancel()

    def _on_homed(self, status: Status) -> None:
        if status.success:
            self._homed = True

    def _check_idle(self) -> None:
        if self.moving:
            assert self._running is not None
            raise UnsupportedSetting(self.name, f"{self._running.action} is still running; wait for its status or "
                                                f"stop it first")

    @abc.abstractmethod
    def _do_move(self, targets: dict[str, float], status: Status) -> None:
        """Start moving to `targets` (checked, in rad or mm); call `_motion_ended(status)`
        when the controller reports the motion over, or `status.set_exception(...)` with the
        error that ended it. Stop and shutdown are handled by the base."""

    @abc.abstractmethod
    def _do_home(self, status: Status) -> None:
        """Start the homing cycle; complete `status` as `_do_move` does."""

    @abc.abstractmethod
    def _do_position(self) -> dict[str, float]: ...

    @abc.abstractmethod
    def _do_stop(self) -> None: ...


def _homing_s(axis: Axis) -> float:
    """Nominal duration of an axis's homing (s): a search over 1.5 times its travel (a full
    turn, or 1 m, when endless), as GRBL searches."""
    span = axis.limits[1] - axis.limits[0]
    if not math.isfinite(span):
        span = 2 * math.pi if axis.kind is AxisKind.ROTARY else 1000.0
    return 1.5 * span / axis.speed
