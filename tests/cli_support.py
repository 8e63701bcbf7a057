"""The command line run in-process, as the tests drive it."""

from __future__ import annotations

import io
from contextlib import redirect_stderr, redirect_stdout

from slscan import cli


def run(*argv: str) -> tuple[int, str, str]:
    """The command line in-process: exit code (a SystemExit's too), stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = cli.main(list(argv))
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
    return int(code), out.getvalue(), err.getvalue()


def run_cli(*argv: str) -> tuple[int, str]:
    """The command line in-process: exit code and stderr; a traceback fails the test."""
    code, _, err = run(*argv)
    return code, err
