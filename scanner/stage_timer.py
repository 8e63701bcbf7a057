"""Wall and CPU seconds per stage of a run, for `result.json` and the reports.

CPU time is the whole process's (every thread, user + system): on a loaded machine wall
time stretches while CPU time stays near what the work costs, so the two side by side say
whether a slow run was slow work or a busy machine."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager


class StageTimer:
    """Times named stages in the order they run; a stage timed twice adds up."""

    def __init__(self) -> None:
        self.wall_s: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str, clock: Callable[[], float] = time.process_time) -> Iterator[None]:
        """Time the `with` block as stage `name` (also when it raises); `clock`: the CPU
        clock (`time.thread_time` for a stage that runs beside others in its own thread)."""
        w0, c0 = time.perf_counter(), clock()
        try:
            yield
        finally:
            self.wall_s[name] = self.wall_s.get(name, 0.0) + time.perf_counter() - w0
            self.cpu_s[name] = self.cpu_s.get(name, 0.0) + clock() - c0

    def rounded(self, digits: int = 4) -> tuple[dict[str, float], dict[str, float]]:
        """(wall, CPU) seconds per stage, rounded for a report."""
        return ({k: round(v, digits) for k, v in self.wall_s.items()},
                {k: round(v, digits) for k, v in self.cpu_s.items()})
