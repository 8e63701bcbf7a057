"""Command-line option conventions shared by every command: one spelling for output
options (`--out`) and for method names (`sac-ia`), older spellings kept as hidden,
deprecated aliases that still work and say what to write instead."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any


def warn_deprecated(old: str, new: str) -> None:
    """One line on stderr: `old` still works, `new` is the spelling to use."""
    print(f"slscan: warning: {old} is deprecated; use {new}", file=sys.stderr)


class DeprecatedOption(argparse.Action):
    """An old option name kept working: stores into the new option's `dest` after a
    warning; hidden from --help (`help=argparse.SUPPRESS`)."""

    def __init__(self, option_strings: Sequence[str], dest: str, new: str, **kw: Any) -> None:
        kw.setdefault("help", argparse.SUPPRESS)
        super().__init__(option_strings, dest, **kw)
        self.new = new

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        warn_deprecated(option_string or self.option_strings[0], self.new)
        setattr(namespace, self.dest, values)


def add_out(parser: argparse.ArgumentParser, help: str, *, old: Sequence[str] = (), **kw: Any) -> None:
    """The command's output option `--out` (help text required), with `old` option names
    (e.g. `--data`) as deprecated aliases."""
    parser.add_argument("--out", help=help, **kw)
    for name in old:
        extra = {k: v for k, v in kw.items() if k in ("type", "metavar")}
        parser.add_argument(name, dest="out", action=DeprecatedOption, new="--out", **extra)


def method_name(canonical: Sequence[str], deprecated: Mapping[str, str]) -> Callable[[str], str]:
    """An argparse `type` taking a method name: one of `canonical`, or an old spelling in
    `deprecated` (old -> canonical) accepted with a warning. Pair with `choices=canonical`,
    so --help lists only the canonical spellings."""

    def parse(text: str) -> str:
        if text in deprecated:
            warn_deprecated(f"the method name '{text}'", f"'{deprecated[text]}'")
            return deprecated[text]
        return text

    parse.__name__ = "method name"  # argparse names the type in its error messages
    return parse


COARSE_METHODS = ("sac-ia", "ransac", "ndt")
"""Coarse registration methods as the command line spells them (`register --coarse`,
`pose --method`)."""
OLD_METHOD_NAMES = {"sacia": "sac-ia", "sac_ia": "sac-ia"}
coarse_method = method_name(COARSE_METHODS, OLD_METHOD_NAMES)


class OutputFlag(argparse.Action):
    """A flag choosing what a command writes to `--out` (`results --csv`); its older form
    with the file as its value (`--csv FILE`) still works, with a warning, as
    `--csv --out FILE`. Add it with `nargs="?"` and `const=True`."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        if values is not self.const:
            warn_deprecated(f"{option_string} {values}", f"{option_string} --out {values}")
            namespace.out = values
        setattr(namespace, self.dest, True)


def plain_text_arg(value: str) -> str:
    """An argparse type for free text (a serial, an operator's name): plain text only
    (`scanner.schema.plain_text`), else argparse's usage error naming the character."""
    from scanner.schema import plain_text

    try:
        return plain_text(value, "the value")
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def count_arg(minimum: int) -> Callable[[str], int]:
    """An argparse type for a whole number >= `minimum` (`--parts 0` or `-1` is refused)."""
    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
        if n < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {n}")
        return n
    return parse


PAPERS = ("a4", "letter")
"""`--paper` as the command line spells it (`inspection.report_pdf.PAPERS`: A4, Letter)."""


def add_paper(parser: argparse.ArgumentParser) -> None:
    """`--paper a4|letter`: the size of the PDF report the command prints (default a4); hold
    it around the command with `on_paper(args.paper)`."""
    parser.add_argument("--paper", choices=PAPERS, default="a4", help="paper of the PDF report (default a4)")


@contextmanager
def on_paper(paper: str) -> Iterator[None]:
    """While held, PDF reports print on `paper` (`--paper`'s spelling)."""
    from inspection.report_pdf import PAPERS as REPORT_PAPERS
    from inspection.report_pdf import on_paper as report_on_paper

    with report_on_paper(dict(zip(PAPERS, REPORT_PAPERS, strict=True))[paper]):
        yield


def add_json(parser: argparse.ArgumentParser) -> None:
    """`--json`: the result as one JSON document alone on stdout (`slscan.cli.json_stdout`
    sends what libraries write there to stderr)."""
    parser.add_argument("--json", action="store_true",
                        help="print the result as one JSON document on stdout (progress and messages on stderr)")
