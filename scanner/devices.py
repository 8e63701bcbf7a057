"""Device interfaces: camera, projector and trigger source.

Modelled on python-microscope's `abc.py`: each public method checks state and arguments,
then calls a `_do_*` method that a driver (real or simulated) implements. Every `_do_*` is
abstract: a driver that leaves one out cannot be instantiated, so no setting is recorded
as applied (in a session manifest) that no driver applied. A driver without a feature
says so in its own `_do_*` (an explicit no-op with the reason, or UnsupportedSetting).

Long actions, which run on after the call returns (`Projector.run_sequence`,
`TriggerSource.start`), return a `scanner.status.Status`: the driver completes it, with the
error that ended the action if one did, and the base class fails a status still running
when the action is stopped or the device shut down. Every wait has a finite timeout: a wait
the caller gave up raises WaitTimeout, a device that did not answer or finish in time
raises DeviceTimeout (both in `scanner.errors`). `shutdown()` is idempotent; devices are
context managers. Trigger *type* (what edge starts an exposure) is separate from trigger
*mode* (how many frames per trigger; one per trigger is the only mode implemented).
"""

from __future__ import annotations

import abc
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np

from scanner.errors import DeviceDisconnected, DeviceError, UnsupportedSetting
from scanner.status import Status

log = logging.getLogger(__name__)

# A sequence or pulse train still running after this many times its nominal duration plus the
# slack has stopped advancing: its status fails with DeviceTimeout. Generous, so that a loaded
# host (a thread scheduled late) is never taken for a hung device; a camera waiting for frames
# notices a stalled sequence sooner, through its own timeout.
SEQUENCE_DEADLINE_FACTOR = 5.0
SEQUENCE_DEADLINE_SLACK_S = 10.0  # s


class TriggerType(Enum):
    """What starts an exposure."""

    SOFTWARE = "software"
    RISING_EDGE = "rising_edge"
    FALLING_EDGE = "falling_edge"


class TriggerMode(Enum):
    """How many exposures one trigger starts. Only ONCE is implemented (by every camera);
    a mode joins this list with the first driver that implements it."""

    ONCE = "once"  # one frame per trigger


@dataclass(frozen=True, eq=False)
class Frame:
    """One camera image and what is known about it.

    `index`: the camera's own frame counter since arming (a gap means a dropped frame);
    `pattern_index`: the pattern the projector showed during the exposure, where the
    device can know it (None otherwise); `timestamp_s`: monotonic seconds at exposure
    start; `exposure_s`: exposure time in seconds; `bit_depth`: significant bits of `image`.
    """

    image: np.ndarray
    index: int
    pattern_index: int | None
    timestamp_s: float
    exposure_s: float
    bit_depth: int


class Device(abc.ABC):
    """Common life cycle: usable until `shutdown()`; shutting down twice is harmless."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._shut_down = False
        self._lock = threading.RLock()
        self._running: Status | None = None  # the long action (sequence, pulse train) in progress

    def __enter__(self) -> Device:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    @property
    def is_shut_down(self) -> bool:
        return self._shut_down

    def shutdown(self) -> None:
        """Release the device; a long action still running fails with DeviceDisconnected.
        Safe to call any number of times."""
        with self._lock:
            if self._shut_down:
                return
            self._shut_down = True
            try:
                self._do_shutdown()
            finally:
                self._end_running(DeviceDisconnected, "ended: the device was shut down while it ran")
                log.info("%s: shut down", self.name)

    def _check_alive(self) -> None:
        if self._shut_down:
            raise DeviceDisconnected(self.name, "device has been shut down; create or reconnect it before use")

    def describe(self) -> dict[str, object]:
        """Settings worth recording in a session manifest."""
        return {"name": self.name, "type": type(self).__name__}

    def _start_running(self, action: str, nominal_s: float) -> Status:
        """A status for a long action expected to take `nominal_s`; it fails as a device
        timeout if not finished well after that (see SEQUENCE_DEADLINE_*)."""
        if self._running is not None and not self._running.done:
            raise UnsupportedSetting(self.name, f"{self._running.action} is still running; wait for its status or "
                                                f"stop it first")
        deadline = SEQUENCE_DEADLINE_FACTOR * nominal_s + SEQUENCE_DEADLINE_SLACK_S
        self._running = Status(self.name, action, deadline)
        return self._running

    def _end_running(self, error: type[DeviceError], why: str) -> None:
        """Fail the long action's status, if still running (stopped, shut down), with
        `error` saying "<device>: <action> <why>"."""
        status = self._running
        if status is not None and not status.done:
            status.set_exception(error(self.name, f"{status.action} {why}"))
            log.info("%s: %s %s", self.name, status.action, why)

    @abc.abstractmethod
    def _do_shutdown(self) -> None: ...


class Camera(Device):
    """An area camera delivering frames of `width` x `height` at `bit_depth` bits."""

    supported_bit_depths: tuple[int, ...] = (8,)
    supported_trigger_types: tuple[TriggerType, ...] = (TriggerType.SOFTWARE,)
    exposure_range_s: tuple[float, float] = (1e-5, 10.0)

    def __init__(self, name: str, width: int, height: int) -> None:
        super().__init__(name)
        self.width = width
        self.height = height
        self._bit_depth = self.supported_bit_depths[0]
        self._exposure_s = 0.01
        self._trigger_type = TriggerType.SOFTWARE
        self._trigger_mode = TriggerMode.ONCE

    @property
    def bit_depth(self) -> int:
        return self._bit_depth

    def set_bit_depth(self, bits: int) -> None:
        self._check_alive()
        if bits not in self.supported_bit_depths:
            raise UnsupportedSetting(self.name, f"bit depth {bits} not supported; "
                                                f"choose one of {self.supported_bit_depths}")
        self._do_set_bit_depth(bits)
        self._bit_depth = bits

    @property
    def exposure_s(self) -> float:
        return self._exposure_s

    def set_exposure(self, seconds: float) -> None:
        self._check_alive()
        lo, hi = self.exposure_range_s
        if not lo <= seconds <= hi:
            raise UnsupportedSetting(self.name, f"exposure {seconds * 1e3:.4g} ms outside "
                                                f"{lo * 1e3:.4g}..{hi * 1e3:.4g} ms")
        self._do_set_exposure(seconds)
        self._exposure_s = seconds

    @property
    def trigger_type(self) -> TriggerType:
        return self._trigger_type

    @property
    def trigger_mode(self) -> TriggerMode:
        return self._trigger_mode

    def set_trigger(self, ttype: TriggerType, tmode: TriggerMode = TriggerMode.ONCE) -> None:
        self._check_alive()
        if ttype not in self.supported_trigger_types:
            raise UnsupportedSetting(self.name, f"trigger type {ttype.value} not supported; choose one of "
                                                f"{[t.value for t in self.supported_trigger_types]}")
        if not isinstance(tmode, TriggerMode):
            raise UnsupportedSetting(self.name, f"trigger mode {tmode!r} is not one of "
                                                f"{[m.value for m in TriggerMode]}")
        self._do_set_trigger(ttype)
        self._trigger_type, self._trigger_mode = ttype, tmode

    def arm(self, n_frames: int) -> None:
        """Prepare to deliver `n_frames` frames: discards any buffered (stale) frame and
        restarts the frame counter at 0."""
        self._check_alive()
        if n_frames < 1:
            raise ValueError("n_frames must be >= 1")
        self._do_arm(n_frames)

    def disarm(self) -> None:
        if not self._shut_down:
            self._do_disarm()

    def trigger(self) -> None:
        """Software trigger: start one exposure now."""
        self._check_alive()
        if self._trigger_type is not TriggerType.SOFTWARE:
            raise UnsupportedSetting(self.name, "software trigger requested but the camera waits for a hardware "
                                                "trigger")
        self._do_trigger()

    def grab(self, timeout_s: float) -> Frame:
        """The next frame, waiting at most `timeout_s`; raises WaitTimeout when none came
        (it may still come: a later grab can return it)."""
        self._check_alive()
        if not timeout_s > 0:
            raise ValueError("timeout_s must be > 0: waits are always finite")
        return self._do_grab(timeout_s)

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "width": self.width, "height": self.height, "bit_depth": self.bit_depth,
                "exposure_s": self.exposure_s, "trigger_type": self.trigger_type.value,
                "trigger_mode": self.trigger_mode.value}

    @abc.abstractmethod
    def _do_set_bit_depth(self, bits: int) -> None: ...

    @abc.abstractmethod
    def _do_set_exposure(self, seconds: float) -> None: ...

    @abc.abstractmethod
    def _do_set_trigger(self, ttype: TriggerType) -> None: ...

    @abc.abstractmethod
    def _do_arm(self, n_frames: int) -> None: ...

    @abc.abstractmethod
    def _do_disarm(self) -> None: ...

    @abc.abstractmethod
    def _do_trigger(self) -> None: ...

    @abc.abstractmethod
    def _do_grab(self, timeout_s: float) -> Frame: ...


class Projector(Device):
    """A projector showing a loaded stack of 8-bit patterns, either one at a time on
    command (`show`) or as a timed sequence that emits a trigger per pattern."""

    def __init__(self, name: str, width: int, height: int) -> None:
        super().__init__(name)
        self.width = width
        self.height = height
        self._n_patterns = 0
        self._current: int | None = None

    @property
    def n_patterns(self) -> int:
        return self._n_patterns

    @property
    def current_pattern(self) -> int | None:
        """Index of the pattern on display, None when dark."""
        return self._current

    def load_patterns(self, patterns: np.ndarray) -> None:
        """Load an (N, height, width) uint8 stack (stopping a running sequence)."""
        self._check_alive()
        patterns = np.asarray(patterns)
        if patterns.ndim != 3 or patterns.shape[1:] != (self.height, self.width) or patterns.dtype != np.uint8:
            raise UnsupportedSetting(self.name, f"patterns must be uint8 (N, {self.height}, {self.width}); "
                                                f"got {patterns.dtype} {patterns.shape}")
        self._stop_running_sequence()
        self._do_load_patterns(patterns)
        self._n_patterns = patterns.shape[0]
        self._current = None
        log.debug("%s: %d patterns loaded", self.name, self._n_patterns)

    def show(self, k: int) -> None:
        """Display pattern k until told otherwise (stopping a running sequence)."""
        self._check_alive()
        if not 0 <= k < self._n_patterns:
            raise ValueError(f"pattern {k} out of range 0..{self._n_patterns - 1}")
        self._stop_running_sequence()
        self._do_show(k)
        self._current = k

    def blank(self) -> None:
        """Go dark (stopping a running sequence)."""
        self._check_alive()
        self._stop_running_sequence()
        self._do_blank()
        self._current = None

    def run_sequence(self, period_s: float, on_pattern: Callable[[int], None] | None = None) -> Status:
        """Show every loaded pattern in order, one per `period_s`, pulsing the trigger output
        at the start of each. Returns once the sequence has started, with the status that
        finishes when it has run (or fails with the error that ended it)."""
        self._check_alive()
        if self._n_patterns == 0:
            raise UnsupportedSetting(self.name, "no patterns loaded")
        if not period_s > 0:
            raise UnsupportedSetting(self.name, f"sequence period must be > 0 s, got {period_s}")
        status = self._start_running(f"pattern sequence ({self._n_patterns} patterns every {period_s:.3g} s)",
                                     self._n_patterns * period_s)
        try:
            self._do_run_sequence(period_s, on_pattern, status)
        except BaseException as exc:
            status.set_exception(exc)
            raise
        log.info("%s: sequence of %d patterns every %.3g s started", self.name, self._n_patterns, period_s)
        return status

    def stop_sequence(self) -> None:
        """Stop a running sequence, if any (its status fails as stopped); harmless otherwise
        and after shutdown."""
        self._do_stop_sequence()
        self._end_running(DeviceError, "stopped before it had run")

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "width": self.width, "height": self.height, "n_patterns": self._n_patterns}

    def _stop_running_sequence(self) -> None:
        if self._running is not None and not self._running.done:
            self.stop_sequence()

    @abc.abstractmethod
    def _do_load_patterns(self, patterns: np.ndarray) -> None: ...

    @abc.abstractmethod
    def _do_show(self, k: int) -> None: ...

    @abc.abstractmethod
    def _do_blank(self) -> None: ...

    @abc.abstractmethod
    def _do_run_sequence(self, period_s: float, on_pattern: Callable[[int], None] | None, status: Status) -> None:
        """Start the sequence; complete `status` when it has run (`set_finished`) or with
        the error that ended it (`set_exception`). Stop and shutdown are handled by the base."""

    @abc.abstractmethod
    def _do_stop_sequence(self) -> None: ...


class TriggerSource(Device):
    """A box that emits `count` pulses of `pulse_width_s` every `period_s` once started."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self._armed: tuple[int, float, float] | None = None

    def arm(self, count: int, period_s: float, pulse_width_s: float = 1e-4) -> None:
        self._check_alive()
        if count < 1 or period_s <= 0 or not 0 < pulse_width_s < period_s:
            raise UnsupportedSetting(self.name, f"bad pulse train: count={count}, period={period_s} s, "
                                                f"width={pulse_width_s} s")
        self._do_arm(count, period_s, pulse_width_s)
        self._armed = (count, period_s, pulse_width_s)

    def start(self) -> Status:
        """Start the armed pulse train (one start per arm). Returns once it has started,
        with the status that finishes when every pulse has been sent."""
        self._check_alive()
        if self._armed is None:
            raise UnsupportedSetting(self.name, "not armed: call arm(count, period_s) before start()")
        count, period, width = self._armed
        status = self._start_running(f"pulse train ({count} pulses every {period:.3g} s)", (count - 1) * period + width)
        self._armed = None
        try:
            self._do_start(status)
        except BaseException as exc:
            status.set_exception(exc)
            raise
        log.info("%s: train of %d pulses every %.3g s started", self.name, count, period)
        return status

    def stop(self) -> None:
        """Stop a running pulse train, if any (its status fails as stopped); harmless
        otherwise and after shutdown."""
        self._do_stop()
        self._end_running(DeviceError, "stopped before every pulse was sent")

    @property
    def pulses_sent(self) -> int:
        return self._do_pulses_sent()

    @abc.abstractmethod
    def _do_arm(self, count: int, period_s: float, pulse_width_s: float) -> None: ...

    @abc.abstractmethod
    def _do_start(self, status: Status) -> None:
        """Start the armed train; complete `status` once every pulse has been sent (or with
        the error that ended the train). Stop and shutdown are handled by the base."""

    @abc.abstractmethod
    def _do_stop(self) -> None: ...

    @abc.abstractmethod
    def _do_pulses_sent(self) -> int: ...
