"""What stands on the bench: the rig, and on the simulator the part in front of it.

`Bench.view(part, view, views)` gives the open rig with the part placed for one view;
`Bench.on_stage(part)` the rig with the part on its stage (turntable), for all the views the
stage turns it through. A hardware bench opens its rig once and keeps it; the operator
places the part. A simulated bench opens the simulated rig for each view (each part on a
stage) with the next part of `sim.station_parts`'s lineup in front of it (part k is
lineup[k % len]; on a rig with a stage it stands on the platter, and the lineup is the
turntable's, `lineup(chamfer=True)`) and saves that part's imposed
defects into every session (`sim_part.json`), so each result has its truth beside it.

The operator's start signal comes from the keyboard or from the bench: `start_pressed()`
reads the foot switch on the trigger box's input (protocol 2, `presses()` of
scanner/drivers/triggerbox.py). On hardware that is the rig's trigger box, when the rig
has one; the simulated bench keeps one `sim.virtual_devices.SimTriggerBox` for the whole run
(`switch`; `switch.press()` presses its foot switch), as its rigs come and go per part.
Call it between cycles only: the scan talks to the same box.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from scanner.errors import ScannerError
from scanner.rig import Rig, RigConfig, open_rig
from scanner.session import write_json


@runtime_checkable
class StartInput(Protocol):
    """A foot switch on a trigger box's input: presses since the previous call."""

    def presses(self) -> int: ...


class Bench:
    """A rig on a bench (see the module docstring). Use as a context manager."""

    def __init__(self, config: RigConfig, seed: int = 0, **rig_options: Any) -> None:
        """`rig_options` go to `open_rig` for a hardware rig (e.g. the drivers' transports)."""
        self.config = config
        self.seed = seed
        self.rig_options = rig_options
        self.simulated = config.driver == "sim"
        self.switch: Any = None  # the simulated bench's trigger box (its input is the foot switch)
        self.input_problem = ""  # why the foot switch stopped being read ("" while it works)
        self._input: StartInput | None = None
        self._rig: Rig | None = None
        if self.simulated:
            from sim.virtual_devices import SimTriggerBox

            self.switch = SimTriggerBox("sim-bench-trigger-box")
            self._input = self.switch
            self.switch.presses()  # presses before the station was ready do not count

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._rig is not None:
            self._rig.shutdown()
            self._rig = None
        if self.switch is not None:
            self.switch.shutdown()

    def describe(self) -> str:
        kind = "simulated" if self.simulated else self.config.driver
        return f"{self.config.name} ({kind}, {self.config.trigger} trigger; {self.config.path})"

    def start_pressed(self) -> bool:
        """Whether the foot switch was pressed since the last call (several presses count
        as one start). On hardware the first call opens the rig; a trigger box without an
        input, or one that fails, leaves the keyboard as the only start (`input_problem`
        says why) rather than stopping the station."""
        try:
            if not self.simulated and self._input is None and not self.input_problem:
                trigger = self._hardware_rig().trigger
                if not isinstance(trigger, StartInput):
                    self.input_problem = f"rig {self.config.name} has no trigger box: no foot switch"
                    return False
                self._input = trigger
                trigger.presses()  # the first reading: presses before the station was ready do not count
            return self._input is not None and self._input.presses() > 0
        except ScannerError as exc:
            self._input, self.input_problem = None, f"foot switch not read: {exc}"
            return False

    def _hardware_rig(self) -> Rig:
        if self._rig is None:
            self._rig = open_rig(self.config, **self.rig_options)
        return self._rig

    def sim_part(self, part: int) -> Any:
        """The simulated part number `part` (a `sim.station_parts.SimPart`); None on hardware."""
        if not self.simulated:
            return None
        from sim.station_parts import lineup

        parts = lineup(chamfer=self.config.stage is not None)  # the turntable's parts: their chamfers lobed
        return parts[part % len(parts)]

    @contextmanager
    def view(self, part: int, view: int = 0, views: int = 1) -> Iterator[Rig]:
        """The rig with part number `part` (counted from 0 in this station run) placed for `view`."""
        if not self.simulated:
            yield self._hardware_rig()
            return
        sim_part = self.sim_part(part)
        with self._sim_rig(sim_part.scene(view, views), self.seed + part * views + view,
                           {**sim_part.as_dict(), "part": part, "view": view}) as rig:
            yield rig

    @contextmanager
    def on_stage(self, part: int) -> Iterator[Rig]:
        """The rig with part number `part` standing on its stage (a rig with a [stage]), which
        turns it between views; on the simulator the part stands on the platter's axis."""
        if not self.simulated:
            yield self._hardware_rig()
            return
        assert self.config.stage is not None, "on_stage needs a rig with a [stage]"
        sim_part = self.sim_part(part)
        with self._sim_rig(sim_part.on_stage(self.config.stage.nominal), self.seed + part,
                           {**sim_part.as_dict(), "part": part}) as rig:
            yield rig

    @contextmanager
    def _sim_rig(self, scene: Any, seed: int, truth: dict[str, Any]) -> Iterator[Rig]:
        """The simulated rig looking at `scene`, writing `truth` into every session."""
        from sim.station_parts import TRUTH_FILE

        rig = open_rig(self.config, scene=scene, seed=seed)
        rig.extras["session_files"].append(lambda root: write_json(Path(root) / TRUTH_FILE, truth))
        try:
            yield rig
        finally:
            rig.shutdown()
