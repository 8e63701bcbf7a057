"""What stands on the bench: the rig, and on the simulator the part in front of it.

`Bench.view(part, view, views)` gives the open rig with the part placed for one view. A
hardware bench opens its rig once and keeps it; the operator places the part. A simulated
bench opens the simulated rig for each view with the next part of `sim.station_parts`'s
lineup in front of it (part k is lineup[k % len]) and saves that part's imposed defects
into every session (`sim_part.json`), so each result has its truth beside it.

The operator's start signal comes from the keyboard or from the bench: `start_pressed()`
reads the bench's start input (a foot switch). The simulated bench has a `SimFootSwitch`;
the trigger-box protocol (scanner/drivers/triggerbox.py) has no input line yet, so a
hardware bench reports no presses until it gets one.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from ..rig import Rig, RigConfig, open_rig
from ..session import write_json


class SimFootSwitch:
    """A simulated start input: `press()` from any thread, `pressed()` reads and clears it."""

    def __init__(self) -> None:
        self._event = threading.Event()

    def press(self) -> None:
        self._event.set()

    def pressed(self) -> bool:
        if self._event.is_set():
            self._event.clear()
            return True
        return False


class Bench:
    """A rig on a bench (see the module docstring). Use as a context manager."""

    def __init__(self, config: RigConfig, seed: int = 0) -> None:
        self.config = config
        self.seed = seed
        self.simulated = config.driver == "sim"
        self.switch = SimFootSwitch() if self.simulated else None
        self._rig: Rig | None = None

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._rig is not None:
            self._rig.shutdown()
            self._rig = None

    def describe(self) -> str:
        kind = "simulated" if self.simulated else self.config.driver
        return f"{self.config.name} ({kind}, {self.config.trigger} trigger; {self.config.path})"

    def start_pressed(self) -> bool:
        """Whether the bench's start input was pressed since the last call."""
        return self.switch.pressed() if self.switch is not None else False

    def sim_part(self, part: int) -> Any:
        """The simulated part number `part` (a `sim.station_parts.SimPart`); None on hardware."""
        if not self.simulated:
            return None
        from sim.station_parts import lineup

        parts = lineup()
        return parts[part % len(parts)]

    @contextmanager
    def view(self, part: int, view: int = 0, views: int = 1) -> Iterator[Rig]:
        """The rig with part number `part` (counted from 0 in this station run) placed for `view`."""
        if not self.simulated:
            if self._rig is None:
                self._rig = open_rig(self.config)
            yield self._rig
            return
        from sim.station_parts import TRUTH_FILE

        sim_part = self.sim_part(part)
        rig = open_rig(self.config, scene=sim_part.scene(view, views), seed=self.seed + part * views + view)
        truth = {**sim_part.as_dict(), "part": part, "view": view}
        rig.extras["session_files"].append(lambda root: write_json(Path(root) / TRUTH_FILE, truth))
        try:
            yield rig
        finally:
            rig.shutdown()
