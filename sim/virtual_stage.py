"""The simulated motion stage: it turns the scene.

`SimStage` is a `scanner.stage.Stage`: before a move's clock starts, `prepare(goal)` is
called on the caller's thread, which the simulated rig wires to render the scene with
everything the stage carries moved to the goal (`turned_scene`; the simulator's computing,
seconds at full resolution under load, must not count against the move's deadline); the
move takes |distance| / speed (on a timer thread), then `on_moved(positions)` is called,
which swaps the prepared scene in: the camera's next frames see the part from the new side.
While it moves, `position()` interpolates.

What the stage carries: every scene object except the reference plane (the bench behind
it). Where the axes are: the rig TOML's nominal `[stage.axes]` geometry (the simulator's
truth; a calibration file the rig names is what the *scanner* believes, and may be off).

Faults (`StageFaults`, or `--stage-fault` of `slscan scan`), moves counted from 0 since
the stage opened:
  alarm_at_move = k        move k trips a limit switch half-way: StageAlarm; the stage must
                           be homed again (when it requires homing)
  disconnect_at_move = k   the cable is pulled during move k: DeviceDisconnected, and every
                           later call raises it too
  silent_at_move = k       the controller stops answering during move k: its status fails
                           with DeviceTimeout at its deadline
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from scanner.errors import ConfigError, DeviceDisconnected, StageAlarm
from scanner.rig import Rig, RigConfig
from scanner.session import write_json
from scanner.stage import Axis, Stage
from scanner.status import Status
from sim.render import Renderer
from sim.scene import Scene

log = logging.getLogger(__name__)

STAGE_TRUTH_FILE = "ground_truth_stage.json"  # in each session: {"world_from_stage": 4x4}, the stage's true pose


@dataclass(frozen=True)
class StageFaults:
    """Faults the simulated stage injects (see the module docstring); move indices >= 0."""

    alarm_at_move: int | None = None
    disconnect_at_move: int | None = None
    silent_at_move: int | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 0):
                raise ValueError(f"{f.name} must be a move index >= 0 or None, got {v!r}")

    @classmethod
    def from_table(cls, table: Mapping[str, Any], path: object, prefix: str = "--stage-fault") -> StageFaults:
        known = {f.name for f in fields(cls)}
        for k, v in table.items():
            if k not in known:
                raise ConfigError(path, f"{prefix}.{k}", f"unknown stage fault; expected one of {sorted(known)}")
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ConfigError(path, f"{prefix}.{k}", f"must be a move index >= 0, got {v!r}")
        return cls(**dict(table))


def turned_scene(scene: Scene, world_from_stage: np.ndarray) -> Scene:
    """`scene` with every object the stage carries (all but the reference plane) moved by
    `world_from_stage` (4x4, mm)."""
    objects = tuple(replace(o, pose=world_from_stage @ o.pose) for o in scene.objects)
    return replace(scene, objects=objects)


class SimStage(Stage):
    """A simulated stage (see the module docstring)."""

    def __init__(self, name: str, axes: Sequence[Axis], settle_s: float = 0.0,
                 on_moved: Callable[[dict[str, float]], None] | None = None, faults: StageFaults | None = None,
                 prepare: Callable[[dict[str, float]], None] | None = None) -> None:
        super().__init__(name, axes, settle_s)
        self.faults = faults or StageFaults()
        self._prepare_goal = prepare
        self.moves = 0  # moves started since the stage opened
        self._on_moved = on_moved
        self._state = threading.Lock()
        self._position = dict.fromkeys(self.axes, 0.0)
        self._move: tuple[dict[str, float], dict[str, float], float, float] | None = None  # from, to, t0, t1
        self._timer: threading.Timer | None = None
        self._gone = False

    def _prepare(self, goal: dict[str, float]) -> None:
        self._check_connected()
        if self._prepare_goal is not None:
            self._prepare_goal(dict(goal))

    def _do_move(self, targets: dict[str, float], status: Status) -> None:
        self._check_connected()
        k, self.moves = self.moves, self.moves + 1
        start = self._do_position()
        goal = {**start, **targets}
        duration = max(abs(goal[n] - start[n]) / self.axes[n].speed for n in targets)
        if k == self.faults.alarm_at_move:
            half = {n: (start[n] + goal[n]) / 2 for n in goal}
            self._begin(start, half, duration / 2, lambda: self._fail(status, StageAlarm(
                self.name, f"alarm during move {k}: limit switch triggered (simulated); home the stage again")))
            return
        if k == self.faults.disconnect_at_move:
            self._begin(start, start, duration / 2, lambda: self._unplug(status))
            return
        if k == self.faults.silent_at_move:
            log.info("%s: injected fault: the controller stops answering during move %d", self.name, k)
            with self._state:
                self._move = (start, start, time.monotonic(), float("inf"))
            return  # never answers: the status's own deadline fails it with DeviceTimeout
        self._begin(start, goal, duration, lambda: self._arrived(goal, status))

    def _do_home(self, status: Status) -> None:
        self._check_connected()
        start = self._do_position()
        zero = dict.fromkeys(start, 0.0)
        duration = max(abs(start[n]) / self.axes[n].speed for n in start)
        self._begin(start, zero, duration, lambda: self._arrived(zero, status))

    def _do_position(self) -> dict[str, float]:
        self._check_connected()
        with self._state:
            if self._move is None:
                return dict(self._position)
            a, b, t0, t1 = self._move
        f = 1.0 if t1 <= t0 else min(1.0, (time.monotonic() - t0) / (t1 - t0))
        return {n: a[n] + (b[n] - a[n]) * f for n in a}

    def _do_stop(self) -> None:
        self._cancel()
        if not self._gone:
            here = self._do_position()
            with self._state:
                self._position, self._move = here, None

    def _do_shutdown(self) -> None:
        self._cancel()

    # internals

    def _check_connected(self) -> None:
        if self._gone:
            raise DeviceDisconnected(self.name, "stage disconnected (simulated); check its cable, then open the rig "
                                                "again")

    def _begin(self, start: dict[str, float], end: dict[str, float], duration: float, then: Callable[[], None]) -> None:
        now = time.monotonic()
        with self._state:
            self._move = (start, end, now, now + duration)
        timer = threading.Timer(duration, then)
        timer.daemon = True
        self._timer = timer
        timer.start()

    def _arrived(self, where: dict[str, float], status: Status) -> None:
        with self._state:
            self._position, self._move = dict(where), None
        try:
            if self._on_moved is not None:
                self._on_moved(dict(where))
        except Exception as exc:  # re-rendering failed: the move's status carries the error
            log.warning("%s: turning the scene failed", self.name, exc_info=True)
            status.set_exception(exc)
            return
        self._motion_ended(status)

    def _fail(self, status: Status, error: Exception) -> None:
        here = self._do_position()
        with self._state:
            self._position, self._move = here, None
        self._homed = False
        log.info("%s: injected fault: %s", self.name, error)
        status.set_exception(error)

    def _unplug(self, status: Status) -> None:
        log.info("%s: injected fault: the cable is pulled mid-move", self.name)
        self._gone = True
        status.set_exception(DeviceDisconnected(self.name, "stage disconnected during a move (simulated); check its "
                                                           "cable, then home it and scan again"))

    def _cancel(self) -> None:
        timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()

    def describe(self) -> dict[str, object]:
        f = self.faults
        return {**super().describe(), "simulated": True,
                "faults": {k.name: getattr(f, k.name) for k in fields(f) if getattr(f, k.name) is not None}}


def open_sim_stage(config: RigConfig, rig: Rig, faults: StageFaults | None = None) -> SimStage:
    """The simulated stage of `config`'s [stage] table, wired to turn `rig`'s scene: each
    move re-renders it with the carried objects at the stage's true pose (the TOML's
    nominal axes), and each later session gets that pose in STAGE_TRUTH_FILE."""
    stage_config = config.stage
    assert stage_config is not None  # and its driver "sim": a sim rig's only stage driver (refused at load else)
    base_scene: Scene = rig.extras["scene"]
    extras = rig.extras
    extras["world_from_stage"] = np.eye(4)
    prepared: dict[str, Any] = {}  # the scene rendered at the goal of the move under way

    def render(positions: dict[str, float]) -> None:
        world_from_stage = stage_config.nominal.world_from_stage(positions)
        old: Renderer = extras["renderer"]
        prepared.clear()
        prepared.update(positions=positions, world_from_stage=world_from_stage, renderer=Renderer(
            old.model, turned_scene(base_scene, world_from_stage), old.sensor, old.projector_blur_sigma_px))

    def turn(positions: dict[str, float]) -> None:
        at = prepared.get("positions", {})
        if at.keys() != positions.keys() or not all(abs(at[n] - positions[n]) < 1e-12 for n in positions):
            render(positions)  # not where the move was prepared for (not expected): render now
        renderer = prepared["renderer"]
        rig.camera.renderer = renderer  # type: ignore[attr-defined]  # a SimCamera
        extras.update(renderer=renderer, ground_truth=renderer.ground_truth,
                      world_from_stage=prepared["world_from_stage"])

    extras["session_files"].append(
        lambda root: write_json(root / STAGE_TRUTH_FILE, {"world_from_stage": extras["world_from_stage"]}))
    return SimStage("sim-stage", stage_config.axes, stage_config.settle_s, turn, faults, render)
