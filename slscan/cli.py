"""The `slscan` command line: one parser, each command's arguments and function registered
by its module in `slscan.commands` (`register(subparsers)`); exit codes from the errors."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from scanner.errors import ScannerError
from scanner.session import disk_problem
from slscan.commands import COMMANDS


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="slscan", description="Structured-light 3D scanner for a bench station.")
    sub = p.add_subparsers(dest="command", required=True)
    for module in COMMANDS:
        module.register(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
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
