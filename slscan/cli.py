"""The `slscan` command line: one parser, each command's arguments and function registered
by its module in `slscan.commands` (`register(subparsers)`); exit codes from the errors.

Diagnostics go through `logging` (one logger per module, named after it) to stderr:
warnings by default, `-v` adds what the devices and the acquisition do (INFO), `-vv` or
`--log-level debug` every command exchanged with a device. The options are taken before or
after the command (`slscan -v scan ...`, `slscan scan -v ...`).
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Sequence

from scanner.errors import ScannerError
from scanner.session import disk_problem
from slscan.commands import COMMANDS

LOG_LEVELS = ("debug", "info", "warning", "error")
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def _add_logging_options(parser: argparse.ArgumentParser, default: object) -> None:
    parser.add_argument("--log-level", choices=LOG_LEVELS, default=default,
                        help="diagnostics on stderr from this level on (default: warning)")
    parser.add_argument("-v", "--verbose", action="count", default=default,
                        help="more diagnostics on stderr: -v what the devices do, -vv every device exchange")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="slscan", description="Structured-light 3D scanner for a bench station.")
    _add_logging_options(p, None)
    sub = p.add_subparsers(dest="command", required=True)
    for module in COMMANDS:
        module.register(sub)
    for command in sub.choices.values():
        _add_logging_options(command, argparse.SUPPRESS)  # given after the command: overrides the one before
    return p


def log_level(args: argparse.Namespace) -> int:
    """The root logger's level from --log-level, else from the -v count."""
    if args.log_level is not None:
        return getattr(logging, args.log_level.upper())
    return {None: logging.WARNING, 0: logging.WARNING, 1: logging.INFO}.get(args.verbose, logging.DEBUG)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=log_level(args), stream=sys.stderr, format=LOG_FORMAT)  # no-op if configured
    try:
        return args.func(args)
    except ScannerError as exc:
        print(f"\nslscan {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the file system refused (full disk, read-only or missing folder): one line
        print(f"\nslscan {args.command}: error: {disk_problem(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nslscan {args.command}: interrupted; frames already captured are kept", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
