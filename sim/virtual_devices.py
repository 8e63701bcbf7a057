"""Simulated projector, camera and trigger box behind the scanner's device interfaces.

The camera is coupled to the projector (as slmsuite's simulated camera): each exposure
renders whatever the projector shows at the instant of the trigger. Wiring is by plain
callbacks standing for cables: `SimProjector.connect_trigger_out(cb)` (the projector's
trigger output, pulsed at the start of each pattern of `run_sequence`),
`SimTriggerBox.connect(cb)` (the box's output), and the inputs `SimCamera.trigger_in()`
(the camera's hardware trigger line, rising edge) and `SimProjector.trigger_in()` (the
projector's external trigger input: advance to the next pattern).

Threads: the projector's sequence and the trigger box each run on their own thread and
complete the status `run_sequence` / `start` returned: finished after the last pattern's
period (the projector then goes dark) or the last pulse; failed with the error of a
connected input or `on_pattern` callback, which also ends the sequence (as an HDMI
projector's thread ends on its error). The camera renders on a worker thread (a trigger
only snapshots the projector state and queues the exposure, so a fast pulse train never
blocks on rendering). Every wait is finite and interruptible by `shutdown()`; after
`shutdown()` every public call raises DeviceDisconnected, while pulses arriving on a dead
device's input are ignored (a cable to a dead device does not throw into the device
driving it).

Camera behaviour:
  - `arm(n)` flushes queued and in-flight frames, restarts the frame counter at 0 and
    accepts n triggers; extra hardware triggers are ignored (counted in
    `ignored_triggers`), an extra or unarmed software trigger raises DeviceError.
  - Hardware pulses are ignored (counted) while the trigger type is SOFTWARE.
  - A frame is delivered no earlier than its exposure end; `grab` waits at most its
    timeout and raises WaitTimeout naming the camera and the expected frame index. The
    simulator's own rendering time is not device time: `grab`'s timeout does not run
    while the renderer works (a loaded machine renders slowly, a real camera would not),
    bounded by RENDER_ALLOWANCE_S so a stuck renderer still ends the wait.
  - `wait_delivered(n, timeout_s)` waits until n frames are ready to grab (for tests that
    need a frame delivered but not yet grabbed, without sleeping).
  - Noise is deterministic: frame k of the a-th arming uses seed (seed, a, k).

Faults (`Faults`, or `[sim.faults]` in the rig TOML), frame indices counted since `arm`:
  drop_frame = k          frame k is lost in transport; the counter still advances, so the
                          next delivered frame has index k + 1.
  delay_frame = k, delay_s = d
                          frame k is delivered d seconds late (later frames queue behind it,
                          as on a stalled transport).
  stale_frame = k         instead of frame k the previous buffer is delivered again (same
                          image, index and pattern as the frame before; across an `arm`,
                          the last frame of the previous acquisition). No effect if the
                          camera never delivered a frame.
  disconnect_after = n    once n frames have been delivered (counted from when the faults
                          were set) the camera is gone: frames already delivered can still
                          be grabbed, then every grab (including ones already waiting) and
                          every other call raises DeviceDisconnected.
  repeat = false          frame faults fire once, the first time their frame index comes up
                          (a retry then succeeds); true: at every arming.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from scanner import schema
from scanner.devices import Camera, Frame, Projector, TriggerSource, TriggerType
from scanner.drivers.simulator import FaultsTable
from scanner.errors import ConfigError, DeviceDisconnected, DeviceError, UnsupportedSetting, WaitTimeout
from scanner.status import Status
from sim.render import Renderer

if TYPE_CHECKING:
    from scanner.rig import RigConfig

log = logging.getLogger(__name__)

_JOIN_TIMEOUT_S = 5.0
RENDER_ALLOWANCE_S = 120.0  # longest a grab waits on the simulator's own rendering (s)


# ------------------------------------------------------------------------------ faults


@dataclass(frozen=True)
class Faults:
    """Transport and device faults the simulated camera injects (see the module docstring)."""

    drop_frame: int | None = None
    delay_frame: int | None = None
    delay_s: float = 0.0
    disconnect_after: int | None = None
    stale_frame: int | None = None
    repeat: bool = False

    def __post_init__(self) -> None:
        for name in ("drop_frame", "delay_frame", "disconnect_after", "stale_frame"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 0):
                raise ValueError(f"{name} must be a frame count/index >= 0 or None, got {v!r}")
        if self.delay_frame is not None and not self.delay_s > 0:
            raise ValueError("delay_frame needs delay_s > 0 (how late the frame arrives)")
        if self.delay_s < 0:
            raise ValueError("delay_s must be >= 0")

    @property
    def any(self) -> bool:
        return any(getattr(self, n) is not None
                   for n in ("drop_frame", "delay_frame", "disconnect_after", "stale_frame"))

    @classmethod
    def of(cls, table: FaultsTable | None, path: object, prefix: str = "sim.faults") -> Faults:
        """From a validated [sim.faults] table (None: no faults); errors name the file and key."""
        if table is None:
            return cls()
        if table.delay_frame is not None and not table.delay_s > 0:
            raise ConfigError(path, f"{prefix}.delay_s", "delay_frame needs delay_s > 0 (seconds late)")
        return cls(**table.model_dump())

    @classmethod
    def from_table(cls, table: Mapping[str, Any], path: str, prefix: str = "sim.faults") -> Faults:
        """From a [sim.faults] table as given (the command line's `--fault`s)."""
        return cls.of(schema.parse(FaultsTable, table, path, prefix), path, prefix)

    @classmethod
    def from_config(cls, config: RigConfig) -> Faults:
        """From the optional [sim.faults] table of a rig (validated at load)."""
        return cls.of(config.devices["rig"].settings.faults, config.path)


class _Ticker:
    """A background thread that calls `tick(i)` for i = 0..count-1, one call every
    `period_s` (the first at once), then `done()` one period after the last unless stopped,
    and then finishes `status`. An exception from `tick` or `done` ends the ticking and
    fails `status` with it; stopping leaves `status` to the caller."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self, count: int, period_s: float, tick: Callable[[int], None], status: Status,
              done: Callable[[], None] | None = None) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(count, period_s, tick, done, status, self._stop),
                                        name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(_JOIN_TIMEOUT_S)

    def _run(self, count: int, period: float, tick: Callable[[int], None], done: Callable[[], None] | None,
             status: Status, stop: threading.Event) -> None:
        t0 = time.monotonic()
        try:
            for i in range(count):
                if stop.wait(max(0.0, t0 + i * period - time.monotonic())):
                    return
                tick(i)
            if done is not None:
                if stop.wait(max(0.0, t0 + count * period - time.monotonic())):
                    return
                done()
        except Exception as exc:  # a connected input or callback failed: the action ends with its error
            log.info("%s: ended by an error: %s", self.name, exc)
            status.set_exception(exc)
            return
        status.set_finished()


# --------------------------------------------------------------------------- projector


class SimProjector(Projector):
    """A projector showing uint8 patterns; `displayed()` is what the camera sees."""

    def __init__(self, name: str = "sim-projector", width: int = 912, height: int = 1140) -> None:
        super().__init__(name, width, height)
        self._state = threading.Lock()
        self._patterns: np.ndarray | None = None
        self._next_external = 0
        self._outputs: list[Callable[[], None]] = []
        self._sequence = _Ticker(f"{name}-sequence")

    # wiring and inputs
    def connect_trigger_out(self, callback: Callable[[], None]) -> None:
        """Connect a listener (e.g. `SimCamera.trigger_in`) to the trigger output."""
        self._check_alive()
        self._outputs.append(callback)

    def trigger_in(self) -> None:
        """External trigger input (a rising edge): show the next pattern. After
        `load_patterns` or `blank` that is pattern 0; after pattern k it is k + 1 (wrapping).
        Ignored when shut down or when no patterns are loaded."""
        if self._shut_down:
            return
        with self._state:
            if self._patterns is None or len(self._patterns) == 0:
                return
            k = self._next_external % len(self._patterns)
            self._current = k
            self._next_external = k + 1

    def displayed(self) -> tuple[int | None, np.ndarray | None]:
        """(index, image) of the pattern on display at this instant; (None, None) when dark."""
        with self._state:
            k = self._current
            if k is None or self._patterns is None:
                return None, None
            return k, self._patterns[k]

    # driver methods
    def _do_stop_sequence(self) -> None:
        """Stop a running sequence (the current pattern stays on)."""
        self._sequence.stop()

    def _do_load_patterns(self, patterns: np.ndarray) -> None:
        self._sequence.stop()  # a sequence outliving its status (past its deadline) stops too
        stack = np.array(patterns, dtype=np.uint8, copy=True)
        stack.setflags(write=False)
        with self._state:
            self._patterns = stack
            self._n_patterns = len(stack)
            self._current = None
            self._next_external = 0

    def _display(self, k: int | None) -> None:
        """Put pattern k (None: dark) on display; the next external trigger shows k + 1."""
        with self._state:
            self._current = k
            self._next_external = 0 if k is None else k + 1

    def _do_show(self, k: int) -> None:
        self._sequence.stop()
        self._display(k)

    def _do_blank(self) -> None:
        self._sequence.stop()
        self._display(None)

    def _do_run_sequence(self, period_s: float, on_pattern: Callable[[int], None] | None, status: Status) -> None:
        with self._state:
            n = len(self._patterns)  # type: ignore[arg-type]  # loaded: run_sequence checked it

        def tick(k: int) -> None:
            self._display(k)
            for cb in list(self._outputs):
                cb()
            if on_pattern is not None:
                on_pattern(k)

        # the last pattern stays up for its period, then the projector goes dark
        self._sequence.start(n, period_s, tick, status, lambda: self._display(None))

    def _do_shutdown(self) -> None:
        self._sequence.stop()

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "simulated": True}


# ------------------------------------------------------------------------------ camera


@dataclass(frozen=True)
class _Job:
    generation: int
    index: int
    pattern_index: int | None
    pattern: np.ndarray | None
    timestamp_s: float
    exposure_s: float
    bit_depth: int


class SimCamera(Camera):
    """A camera rendering the scene lit by `projector`'s current pattern (see the module
    docstring for triggering, timing and faults)."""

    supported_bit_depths = (8, 10, 12)
    supported_trigger_types = (TriggerType.SOFTWARE, TriggerType.RISING_EDGE)

    def __init__(self, name: str, renderer: Renderer, projector: SimProjector, faults: Faults | None = None,
                 seed: int = 0) -> None:
        h, w = renderer.shape
        super().__init__(name, w, h)
        if (projector.height, projector.width) != renderer.projector_shape:
            raise ValueError(f"projector {projector.width}x{projector.height} does not match the renderer's "
                             f"{renderer.projector_shape[1]}x{renderer.projector_shape[0]}")
        self.renderer = renderer
        self.projector = projector
        self.seed = int(seed)
        self._cv = threading.Condition()
        self._jobs: deque[_Job] = deque()
        self._frames: deque[Frame] = deque()
        self._generation = 0
        self._armed = 0
        self._triggered = 0
        self._expected = 0
        self._delivered = 0
        self._gone = False
        self._last_frame: Frame | None = None
        self._faults = Faults()
        self._spent: set[str] = set()
        self._stop = threading.Event()
        self._render_s = 0.0  # total time spent in the renderer (s), for grab's device-time deadline
        self._render_start: float | None = None  # monotonic start of the render in progress
        self.ignored_triggers = 0
        self.render_error: BaseException | None = None  # set if rendering ever failed (the camera is then gone)
        self.set_faults(faults or Faults())
        self._worker = threading.Thread(target=self._work, name=f"{name}-render", daemon=True)
        self._worker.start()
        log.info("%s: simulated camera %dx%d opened (seed %d%s)", name, w, h, self.seed,
                 f", faults {self._faults}" if self._faults.any else "")

    # faults
    @property
    def faults(self) -> Faults:
        return self._faults

    def set_faults(self, faults: Faults) -> None:
        """Replace the injected faults; restarts their bookkeeping (spent faults, the
        delivered-frame count for `disconnect_after`)."""
        self._check_alive()
        with self._cv:
            self._faults = faults
            self._spent = set()
            self._delivered = 0
            if faults.disconnect_after == 0:
                self._go_away()

    @property
    def is_connected(self) -> bool:
        return not (self._gone or self._shut_down)

    # hardware trigger line
    def trigger_in(self) -> None:
        """A rising edge on the trigger input: starts an exposure when the camera is armed
        and set to RISING_EDGE; otherwise ignored (counted in `ignored_triggers`)."""
        if self._shut_down:
            return
        index, image = self.projector.displayed()
        stamp = time.monotonic()
        with self._cv:
            if self._gone or self._trigger_type is not TriggerType.RISING_EDGE or not self._can_trigger():
                self.ignored_triggers += 1
                return
            self._queue(index, image, stamp)

    # driver methods
    def _do_trigger(self) -> None:
        index, image = self.projector.displayed()
        stamp = time.monotonic()
        with self._cv:
            self._check_connected()
            if not self._can_trigger():
                problem = ("not armed: call arm(n_frames) first" if self._armed == 0 else
                           f"all {self._armed} frames of this arming are already triggered; arm again")
                raise DeviceError(self.name, f"software trigger refused: {problem}")
            self._queue(index, image, stamp)

    def _do_arm(self, n_frames: int) -> None:
        with self._cv:
            self._check_connected()
            self._generation += 1
            self._frames.clear()
            self._jobs.clear()
            self._armed = n_frames
            self._triggered = 0
            self._expected = 0

    def _do_disarm(self) -> None:
        with self._cv:
            self._armed = 0

    def wait_delivered(self, count: int, timeout_s: float) -> bool:
        """Wait at most `timeout_s` until `count` frames are ready to grab; True if they are."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while len(self._frames) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._gone or self._shut_down:
                    return False
                self._cv.wait(remaining)
            return True

    def _do_grab(self, timeout_s: float) -> Frame:
        start = time.monotonic()
        with self._cv:
            rendered_at_start = self._render_clock(start)
            while True:
                if self._shut_down:
                    raise DeviceDisconnected(self.name, "camera was shut down while waiting for a frame")
                if self._frames:
                    frame = self._frames.popleft()
                    self._expected = frame.index + 1
                    return frame
                if self._gone:
                    why = f"rendering failed ({self.render_error})" if self.render_error else "camera disconnected"
                    raise DeviceDisconnected(self.name, f"{why} (expected frame index {self._expected}); "
                                                        "check the cable and power, then open the rig again")
                now = time.monotonic()
                device_time = (now - start) - (self._render_clock(now) - rendered_at_start)
                remaining = min(timeout_s - device_time, start + timeout_s + RENDER_ALLOWANCE_S - now)
                if remaining <= 0:
                    if self._triggered <= self._expected:
                        why = ("it was never triggered" + (" (the camera waits for a rising edge on its trigger "
                               "input: is the projector sequence or trigger box running?)"
                               if self._trigger_type is TriggerType.RISING_EDGE else " (call trigger())"))
                    else:
                        why = "it was triggered but not delivered"
                    raise WaitTimeout(self.name, f"frame index {self._expected}", timeout_s,
                                      f"{self._triggered} of {self._armed} frames triggered since arm; {why}")
                self._cv.wait(remaining)

    def _render_clock(self, now: float) -> float:  # holds _cv
        """Seconds spent rendering so far, the render in progress included."""
        return self._render_s + (now - self._render_start if self._render_start is not None else 0.0)

    def _do_set_bit_depth(self, bits: int) -> None:
        self._check_connected()

    def _do_set_exposure(self, seconds: float) -> None:
        self._check_connected()

    def _do_set_trigger(self, ttype: TriggerType) -> None:
        self._check_connected()

    def _do_shutdown(self) -> None:
        self._stop.set()
        with self._cv:
            self._jobs.clear()
            self._cv.notify_all()
        if self._worker is not threading.current_thread():
            self._worker.join(_JOIN_TIMEOUT_S)

    def describe(self) -> dict[str, object]:
        f = self._faults
        return {**super().describe(), "simulated": True, "seed": self.seed,
                "faults": {k.name: getattr(f, k.name) for k in fields(f)} if f.any else {}}

    # internals (callers hold self._cv where noted)
    def _check_connected(self) -> None:
        if self._gone:
            raise DeviceDisconnected(self.name, "camera disconnected; check the cable and power, then open the rig "
                                                "again")

    def _can_trigger(self) -> bool:  # holds _cv
        return self._armed > 0 and self._triggered < self._armed

    def _queue(self, index: int | None, image: np.ndarray | None, stamp: float) -> None:  # holds _cv
        self._jobs.append(_Job(self._generation, self._triggered, index, image, stamp, self._exposure_s,
                               self._bit_depth))
        self._triggered += 1
        self._cv.notify_all()

    def _go_away(self) -> None:  # holds _cv
        if not self._gone:
            log.info("%s: disconnected (simulated)", self.name)
        self._gone = True
        self._jobs.clear()
        self._cv.notify_all()

    def _fires(self, name: str, index: int) -> bool:  # holds _cv
        if getattr(self._faults, name) != index:
            return False
        key = name if not self._faults.repeat else f"{name}@{self._generation}"
        if key in self._spent:
            return False
        self._spent.add(key)
        log.info("%s: injected fault %s at frame %d", self.name, name, index)
        return True

    def _work(self) -> None:
        while True:
            with self._cv:
                while not self._jobs and not self._stop.is_set():
                    self._cv.wait()
                if self._stop.is_set():
                    return
                job = self._jobs.popleft()
            try:
                self._expose(job)
            except Exception as exc:  # rendering failed: surface it as a lost device, never hang
                log.warning("%s: rendering frame %d failed; the camera is gone", self.name, job.index, exc_info=True)
                with self._cv:
                    self.render_error = exc
                    self._go_away()

    def _expose(self, job: _Job) -> None:
        rng = np.random.default_rng([self.seed, job.generation, job.index])
        with self._cv:
            self._render_start = time.monotonic()
        try:
            image = self.renderer.render(job.pattern, job.exposure_s, job.bit_depth, rng)
        finally:
            with self._cv:
                self._render_s += time.monotonic() - self._render_start
                self._render_start = None
        if self._stop.wait(max(0.0, job.timestamp_s + job.exposure_s - time.monotonic())):
            return
        frame = Frame(image=image, index=job.index, pattern_index=job.pattern_index, timestamp_s=job.timestamp_s,
                      exposure_s=job.exposure_s, bit_depth=job.bit_depth)
        with self._cv:
            if job.generation != self._generation or self._gone:
                return  # flushed by arm, or the device is gone
            if self._fires("drop_frame", job.index):
                return
            if self._fires("stale_frame", job.index) and self._last_frame is not None:
                frame = self._last_frame
            delay = self._faults.delay_s if self._fires("delay_frame", job.index) else 0.0
        if delay and self._stop.wait(delay):
            return
        with self._cv:
            if job.generation != self._generation or self._gone:
                return
            self._frames.append(frame)
            self._last_frame = frame
            self._delivered += 1
            self._cv.notify_all()
            n = self._faults.disconnect_after
            if n is not None and self._delivered >= n:
                self._go_away()


# ------------------------------------------------------------------------ trigger box


class SimTriggerBox(TriggerSource):
    """A pulse generator: once armed and started, calls every connected output `count`
    times, one pulse every `period_s` (the first at start). Its input (the operator's foot
    switch, firmware protocol 2) counts `press()`es; `presses()` reads them as the
    driver's `TriggerBox.presses()` does."""

    def __init__(self, name: str = "sim-trigger-box") -> None:
        super().__init__(name)
        self._outputs: list[Callable[[], None]] = []
        self._train: tuple[int, float] = (0, 0.0)
        self._sent = 0
        self._pulses = _Ticker(f"{name}-pulses")
        self._input_lock = threading.Lock()
        self._pressed = 0  # presses counted since the box started
        self._presses_seen: int | None = None

    def press(self) -> None:
        """The foot switch is pressed once (a debounced press on the box's input); from any
        thread, never raising (a switch does not throw into a dead box)."""
        with self._input_lock:
            self._pressed += 1

    def presses(self) -> int:
        """Presses since the previous call; 0 at the first call (as the driver)."""
        self._check_alive()
        with self._input_lock:
            count, seen = self._pressed, self._presses_seen
            self._presses_seen = count
        return 0 if seen is None else count - seen

    def connect(self, callback: Callable[[], None]) -> None:
        """Connect an input (e.g. `SimProjector.trigger_in`, `SimCamera.trigger_in`);
        each pulse reaches the outputs in the order they were connected."""
        self._check_alive()
        self._outputs.append(callback)

    def _do_stop(self) -> None:
        self._pulses.stop()

    def _do_arm(self, count: int, period_s: float, pulse_width_s: float) -> None:
        if self._running is not None and not self._running.done:
            raise UnsupportedSetting(self.name, "a pulse train is running; wait for its status or call stop()")
        self._train = (count, period_s)
        self._sent = 0

    def _do_start(self, status: Status) -> None:
        count, period = self._train
        self._pulses.start(count, period, self._pulse, status)

    def _pulse(self, i: int) -> None:
        self._sent += 1  # the pulse is out, whatever its inputs make of it
        for cb in list(self._outputs):
            cb()

    def _do_pulses_sent(self) -> int:
        return self._sent

    def _do_shutdown(self) -> None:
        self._pulses.stop()

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "simulated": True}
