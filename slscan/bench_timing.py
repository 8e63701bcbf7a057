"""Timing for the benchmarks: the median wall and processor seconds of repeated calls (the
processor time counts every thread's; on a loaded machine the wall time says how the load was
shared, the processor time what the call costs)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def median_times(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Median (wall, processor) seconds of `repeats` calls of `fn`."""
    wall, cpu = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return statistics.median(wall), statistics.median(cpu)
