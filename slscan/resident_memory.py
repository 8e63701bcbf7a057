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


def _status_mib(*keys: str, status: Path = _STATUS) -> tuple[float, ...]:
    """The named lines of /proc/self/status (MiB), read at one instant; NaN where missing."""
    found: dict[str, float] = {}
    with suppress(OSError):
        for line in status.read_text().splitlines():
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
# The probe that shows a reset takes: a block touched, freed (it is above glibc's largest mmap
# threshold, 32 MiB, so freeing unmaps it), then a reset, after which the high-water mark must
# have fallen by at least half the block. A sandbox whose resident set does not fall when memory is
# unmapped (seen on CI: VmRSS and VmHWM equal and never falling) fails it, as does a kernel that
# ignores the write.
_PROBE_MIB = 64


class StagePeaks:
    """Each stage's peak resident memory (MiB), by name, in the order run; None ("not measured")
    for every stage when a probe shows the high-water mark cannot be reset to the resident set
    (no /proc/self/clear_refs, a kernel that ignores it, or a sandbox whose resident set does not
    fall when memory is freed): there VmHWM is the run's peak, not the stage's. The reason is in
    `not_measured`."""

    def __init__(self, *, clear_refs: Path = _CLEAR, status: Path = _STATUS) -> None:
        self.peaks: dict[str, float | None] = {}
        self.not_measured: str | None = None
        self._clear_refs = clear_refs
        self._status = status
        self._probed = False

    def _read(self, *keys: str) -> tuple[float, ...]:
        return _status_mib(*keys, status=self._status)

    def _write_reset(self) -> bool:
        try:
            self._clear_refs.write_text("5")
        except OSError as e:
            self.not_measured = f"the high-water mark cannot be reset ({self._clear_refs}: {e.strerror})"
            return False
        return True

    def _probe(self) -> bool:
        """Touch and free a block of _PROBE_MIB, reset, and check the high-water mark fell."""
        block = b"\x01" * (_PROBE_MIB << 20)  # every page written
        (peak,) = self._read("VmHWM")
        del block
        if not self._write_reset():
            return False
        hwm, rss = self._read("VmHWM", "VmRSS")
        if not (peak - hwm >= _PROBE_MIB / 2 and hwm - rss <= _RESET_SLACK_MIB):
            self.not_measured = (f"after touching and freeing {_PROBE_MIB} MiB and writing "
                                 f"{self._clear_refs}, the high-water mark went from {peak:.0f} to "
                                 f"{hwm:.0f} MiB (resident set {rss:.0f} MiB): this system does not "
                                 "reset it to the resident set")
            return False
        return True

    def _reset(self) -> bool:
        """Reset the high-water mark to the resident set now; True when the probe showed it can."""
        if not self._probed:
            self._probed = True
            if not self._probe():
                return False
        return self.not_measured is None and self._write_reset()

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
                self.peaks[name] = max(earlier, round(self._read("VmHWM")[0], 1))
