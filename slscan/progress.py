"""Progress of long work as the command line shows it."""

from __future__ import annotations

import sys
from typing import Any


class ProgressLine:
    """A one-line progress display on stderr (plain lines when stderr is not a terminal)."""

    def __init__(self, stream: Any = sys.stderr) -> None:
        self.stream = stream
        self.tty = stream.isatty()
        self.last = ""

    def __call__(self, stage: str, done: int, total: int) -> None:
        bar = "#" * int(20 * done / max(total, 1))
        line = f"{stage:<12}[{bar:<20}] {done}/{total}"
        if self.tty:
            self.stream.write("\r" + line.ljust(len(self.last)))
            if stage == "done":
                self.stream.write("\n")
        elif stage != self.last.split(" ")[0] or done == total:
            self.stream.write(line + "\n")
        self.stream.flush()
        self.last = line
