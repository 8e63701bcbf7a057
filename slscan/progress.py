"""Progress of long work as the command line shows it: a live bar on a terminal, and
on anything else (a log file, a pipe, a CI job) one line when a stage starts and one when
it finishes, with its count and elapsed time, never a bar frozen at `0/1`.

Callers report `progress(stage, done, total)`: a stage starts with its first call
(`done` 0 or more); it finishes when `done == total` for a counted stage (`total` > 1), or
when the next stage starts (a stage reported only as `0/1`, as the pipeline's load/decode/
write are); the stage `done` ends the run."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any


class ProgressLine:
    """Progress on `stream` (stderr by default): a one-line bar when it is a terminal, plain
    start/finish lines otherwise. `clock` (s) is replaceable for tests. `quiet` (the command
    line's -q) silences every instance."""

    quiet = False

    def __init__(self, stream: Any = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = sys.stderr if stream is None else stream  # the one in use now, not at import
        self.tty = self.stream.isatty()
        self.clock = clock
        self.started = clock()
        self.stage: str | None = None  # the open stage, its start time and last count
        self.stage_t0 = 0.0
        self.count = (0, 0)
        self.last = ""

    def __call__(self, stage: str, done: int, total: int) -> None:
        if self.quiet:
            return
        now = self.clock()
        if stage != self.stage:
            self._finish(now)
            if stage == "done":
                self._write(f"{'done':<12}all stages in {now - self.started:.2f} s", final=True)
                return
            self.stage, self.stage_t0 = stage, now
            if not self.tty:
                self._write(f"{stage:<12}started" + (f", {total} steps" if total > 1 else ""))
        self.count = (done, total)
        if self.tty:
            bar = "#" * int(20 * done / max(total, 1))
            self._write(f"{stage:<12}[{bar:<20}] {done}/{total}  {now - self.stage_t0:.1f} s")
        if total > 1 and done >= total:
            self._finish(now)

    def _finish(self, now: float) -> None:
        """Close the open stage with its count and elapsed time."""
        if self.stage is None:
            return
        done, total = self.count
        counted = f"{done}/{total} steps " if total > 1 else ""
        self._write(f"{self.stage:<12}finished {counted}in {now - self.stage_t0:.2f} s", final=True)
        self.stage = None

    def _write(self, line: str, final: bool = False) -> None:
        if self.tty:
            self.stream.write("\r" + line.ljust(len(self.last)) + ("\n" if final else ""))
            self.last = "" if final else line
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
