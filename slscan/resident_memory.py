"""Peak resident memory per stage of a benchmark (Linux): the kernel's high-water mark of this
process's resident set (VmHWM), reset at the start of each stage through /proc/self/clear_refs, so
each stage's figure is its own peak (interpreter, libraries and whatever earlier stages still hold
included), not the run's."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

_STATUS = Path("/proc/self/status")
_CLEAR = Path("/proc/self/clear_refs")


def _status_mib(key: str) -> float:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def resident_mib() -> float:
    """The resident set now (MiB; NaN where /proc is not there)."""
    return _status_mib("VmRSS")


def release_memory() -> None:
    """Give what the process no longer uses back to the system: collect the reference cycles
    (a closed simulated rig's renderers wait in them for the cyclic collector), then ask glibc to
    return its arenas' free pages (`malloc_trim`: without it a closed 1.3 MP binocular scene left
    ~0.7 GB resident, freed but kept by the allocator, and a run of scenes grew by ~0.9 GB each)."""
    gc.collect()
    name = ctypes.util.find_library("c")
    if name:
        with suppress(OSError, AttributeError):  # not glibc
            ctypes.CDLL(name).malloc_trim(0)


class StagePeaks:
    """Each stage's peak resident memory (MiB), by name, in the order run."""

    def __init__(self) -> None:
        self.peaks: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        with suppress(OSError):
            _CLEAR.write_text("5")  # reset the high-water mark to the resident set now
        try:
            yield
        finally:
            self.peaks[name] = max(self.peaks.get(name, 0.0), round(_status_mib("VmHWM"), 1))
