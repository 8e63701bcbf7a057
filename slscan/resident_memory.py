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


def _status_mib(*keys: str) -> tuple[float, ...]:
    """The named lines of /proc/self/status (MiB), read at one instant; NaN where missing."""
    found: dict[str, float] = {}
    with suppress(OSError):
        for line in _STATUS.read_text().splitlines():
            key, _, value = line.partition(":")
            if key in keys:
                found[key] = int(value.split()[0]) / 1024.0
    return tuple(found.get(k, float("nan")) for k in keys)


def resident_mib() -> float:
    """The resident set now (MiB; NaN where /proc is not there)."""
    return _status_mib("VmRSS")[0]


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


# A reset high-water mark reads as the resident set at that instant; both come from one read of
# /proc/self/status, so they differ only by pages another thread touched in between (a few).
_RESET_SLACK_MIB = 4.0


class StagePeaks:
    """Each stage's peak resident memory (MiB), by name, in the order run; None ("not measured")
    for a stage whose start could not reset the high-water mark (a kernel or sandbox without
    /proc/self/clear_refs, seen on CI: there VmHWM is the run's peak, not the stage's), with the
    reason in `not_measured`."""

    def __init__(self, *, clear_refs: Path = _CLEAR) -> None:
        self.peaks: dict[str, float | None] = {}
        self.not_measured: str | None = None
        self._clear_refs = clear_refs

    def _reset(self) -> bool:
        """Reset the high-water mark to the resident set now; True when the kernel shows it did."""
        try:
            self._clear_refs.write_text("5")
        except OSError as e:
            self.not_measured = f"the high-water mark cannot be reset ({self._clear_refs}: {e.strerror})"
            return False
        hwm, rss = _status_mib("VmHWM", "VmRSS")
        if not hwm - rss <= _RESET_SLACK_MIB:
            self.not_measured = (f"writing {self._clear_refs} left the high-water mark at {hwm:.0f} MiB, "
                                 f"above the resident set's {rss:.0f} MiB: this kernel does not reset it")
            return False
        return True

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        reset = self._reset()
        try:
            yield
        finally:
            earlier = self.peaks.get(name, 0.0)
            if not reset or earlier is None:
                self.peaks[name] = None
            else:
                self.peaks[name] = max(earlier, round(_status_mib("VmHWM")[0], 1))
