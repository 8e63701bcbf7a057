"""Native libraries' prints kept off standard output: Open3D writes its warnings there from
C++, past Python's `sys.stdout`, and a command printing JSON needs stdout for JSON alone."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager, redirect_stdout


@contextmanager
def stdout_to_stderr() -> Iterator[None]:
    """For the duration, whatever is written to file descriptor 1 (C and Python alike) goes
    to standard error instead: warnings stay visible and stdout stays clean."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        with redirect_stdout(sys.stderr):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
