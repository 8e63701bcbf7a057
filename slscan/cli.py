"""The `slscan` command line: one parser, each command's arguments and function registered
by its module in `slscan.commands` (`register(subparsers)`).

Conventions every command follows: `--help` shows what each option does and an example
(`slscan.examples`); output goes to `--out`; exit codes are those of `slscan.exit_codes`
(0 success, 1 a measured part or check fails, 2 usage or refused input, 3 device fault),
errors escaping a command mapped there; bare `slscan` prints the help on stdout and exits 0
(asking for help is not an error); `slscan --version` prints the package version and the
checkout's `git describe` when run from a git checkout.

Diagnostics go through `logging` (one logger per module, named after it) to stderr:
warnings by default, `-v` adds what the devices and the acquisition do (INFO), `-vv` or
`--log-level debug` every command exchanged with a device. The options are taken before or
after the command (`slscan -v scan ...`, `slscan scan -v ...`).
"""

from __future__ import annotations

import argparse
import io
import logging
import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, redirect_stdout
from pathlib import Path
from typing import TextIO

from scanner.errors import ScannerError, Terminated
from slscan.commands import COMMANDS, GROUP, GROUPS, MOVED, command_module, modules, table
from slscan.examples import epilog
from slscan.exit_codes import SUMMARY, Exit, for_error

LOG_LEVELS = ("debug", "info", "warning", "error")
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def _add_logging_options(parser: argparse.ArgumentParser, default: object) -> None:
    parser.add_argument("--log-level", choices=LOG_LEVELS, default=default,
                        help="diagnostics on stderr from this level on (default: warning)")
    parser.add_argument("-v", "--verbose", action="count", default=default,
                        help="more diagnostics on stderr: -v what the devices do, -vv every device exchange")
    parser.add_argument("-q", "--quiet", action="store_true", default=default,
                        help="errors only on stderr: no progress lines, no warnings (results still on stdout)")
    parser.add_argument("--log-file", metavar="FILE", type=Path, default=default,
                        help="also write the diagnostics to FILE, with times, from info on (or the level asked)")


def version() -> str:
    """`slscan X.Y.Z`, with `git describe` of the checkout the code runs from when it is one."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as package_version

    try:
        text = f"slscan {package_version('slscan')}"
    except PackageNotFoundError:
        text = "slscan (not installed)"
    root = Path(__file__).resolve().parents[1]
    try:
        git = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty", "--tags"],
                             capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return text
    return text + (f" (git {git.stdout.strip()})" if git.returncode == 0 and git.stdout.strip() else "")


class _Version(argparse.Action):
    """`--version`: computed only when asked (it runs git)."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS, *,
                 help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        print(version())
        parser.exit()


def commands(parser: argparse.ArgumentParser, prefix: str = "") -> dict[str, argparse.ArgumentParser]:
    """Every command's parser under `parser` by its full name ("scan", "devices
    lightcrafter-images"); argparse has no public way to list them."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found[prefix + name] = sub
                found.update(commands(sub, f"{prefix}{name} "))
    return found


class _Summarised:
    """The sub-command adder a command module's `register` is given: each command's one-line
    summary comes from its table, `slscan.commands.COMMANDS` or a group's (`BENCHES`)."""

    def __init__(self, sub: argparse._SubParsersAction, summaries: dict[str, tuple[str, str]] = COMMANDS) -> None:
        self.sub, self.summaries = sub, summaries

    def add_parser(self, name: str, **kw: object) -> argparse.ArgumentParser:
        return self.sub.add_parser(name, help=self.summaries[name][1], **kw)  # type: ignore[arg-type]  # argparse's options pass through


MEMBER = "group_member"  # where the parsed arguments keep the member of a group command (`slscan bench NAME`)


def chosen_command(argv: Sequence[str], group: str | None = None) -> str | None:
    """The command `argv` runs (of `group`: `argv` the words after it): its first word that
    names one (None: bare, --help, --version)."""
    return next((a for a in argv if a in table(group)), None)


def command_name(args: argparse.Namespace) -> str:
    """The command the parsed `args` run, as typed: "scan", "bench sim"."""
    member = getattr(args, MEMBER, None) if args.command in GROUPS else None
    return f"{args.command} {member}" if member else str(args.command)


def moved(argv: Sequence[str]) -> str | None:
    """The line refusing a former command's name in `argv` (`slscan.commands.MOVED`: the
    benches, now under `slscan bench`; `slscan bench coverage`, now `slscan coverage`),
    naming the command now; None when `argv` uses none."""
    word = next((a for a in argv if a in COMMANDS or a in MOVED), None)
    if word in GROUPS:
        rest = argv[list(argv).index(word) + 1:]
        member = next((a for a in rest if a in table(word) or f"{word} {a}" in MOVED), None)
        word = f"{word} {member}" if member else word
    if word is None or word not in MOVED or word in COMMANDS:
        return None
    now = MOVED[word]
    lists = "slscan bench --help lists the benches" if now.split()[0] in GROUPS else "slscan --help lists the commands"
    return f"slscan: error: `slscan {word}` is now `slscan {now}` ({lists})"


def _member_first(parser: argparse.ArgumentParser, argv: Sequence[str]) -> None:
    """A group command given an option of its own member before any member (`slscan bench
    --json`, the former decode benchmark): a usage error (exit 2) saying to name the member."""
    group = chosen_command(argv)
    if group not in GROUPS:
        return
    rest = argv[list(argv).index(group) + 1:]
    if chosen_command(rest, group) is not None:
        return
    own = {s for action in commands(parser)[group]._actions for s in action.option_strings}
    unknown = [a for a in rest if a.startswith("-") and a.split("=")[0] not in own
               and not (a[:2] in own and not a.startswith("--"))]  # -vv: short flags together
    if unknown:
        former = f" (the former `slscan {group}` is `slscan {MOVED[group]}`)" if group in MOVED else ""
        commands(parser)[group].error(f"{unknown[0]}: name the {group} to run first, `slscan {group} NAME "
                                      f"{unknown[0]} ...`{former}")


def _add_commands(sub: argparse._SubParsersAction, argv: Sequence[str] | None, group: str | None = None) -> None:
    """Under `sub`, the commands of `slscan` (or of `slscan GROUP`): every command's own parser,
    or, given the `argv` to parse, only the chosen command's (its module imported) and a name
    and summary for the others. A group command's parser holds its members' the same way."""
    summaries = table(group)
    chosen = chosen_command(argv, group) if argv is not None else None
    if argv is None:
        chosen_modules = modules(group)
    else:
        chosen_modules = [command_module(chosen, group)] if chosen and summaries[chosen][0] != GROUP else []
    for module in chosen_modules:
        module.register(_Summarised(sub, summaries))
    for name in GROUPS if group is None else ():
        if argv is None or name == chosen:
            members = sub.add_parser(name, help=summaries[name][1], description=summaries[name][1]).add_subparsers(
                dest=MEMBER, metavar="NAME", help=f"the {name} to run (each with its own --help)")
            _add_commands(members, None if argv is None else argv[list(argv).index(name) + 1:], name)
    for name, (_, summary) in summaries.items():
        if name not in sub.choices:
            sub.add_parser(name, help=summary, add_help=False)  # named only: this run does not use it


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The `slscan` parser: every command's own parser, or, given the `argv` to parse, only the
    chosen command's (its module imported) and a name and summary for the others, so
    `--version`, `--help` and usage errors import no command module."""
    p = argparse.ArgumentParser(prog="slscan", description="Structured-light 3D scanner for a bench station.",
                                epilog=SUMMARY + "\nslscan COMMAND --help shows each command's options and an "
                                       "example.", formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action=_Version, help="print the version (and git describe of a checkout) and exit")
    _add_logging_options(p, None)
    _add_commands(p.add_subparsers(dest="command", metavar="COMMAND"), argv)
    for name, command in commands(p).items():
        command.formatter_class = argparse.RawDescriptionHelpFormatter
        command.epilog = command.epilog or epilog(name)
        if " " not in name or name.split()[0] in GROUPS:  # given after the command: overrides the one before
            _add_logging_options(command, argparse.SUPPRESS)
    return p


def log_level(args: argparse.Namespace) -> int:
    """The root logger's level from --log-level, else from the -v count."""
    if args.log_level is not None:
        return getattr(logging, args.log_level.upper())
    if getattr(args, "quiet", False):
        return logging.ERROR
    return {None: logging.WARNING, 0: logging.WARNING, 1: logging.INFO}.get(args.verbose, logging.DEBUG)


def configure_logging(args: argparse.Namespace) -> logging.Handler | None:
    """stderr from the level asked (`log_level`); `--log-file` from info on (or a lower level
    asked): its handler, for the caller to remove; `-q` also silences the progress lines."""
    from slscan.progress import ProgressLine

    level = log_level(args)
    logging.basicConfig(level=level, stream=sys.stderr, format=LOG_FORMAT)  # no-op if configured
    ProgressLine.quiet = bool(getattr(args, "quiet", False))
    if getattr(args, "log_file", None) is not None:
        try:
            handler = logging.FileHandler(args.log_file, encoding="utf-8")
        except OSError as exc:
            raise ScannerError(f"--log-file {args.log_file}: cannot write: {exc.strerror or exc}") from None
        handler.setFormatter(logging.Formatter(LOG_FORMAT))
        handler.setLevel(min(level, logging.INFO))
        root = logging.getLogger()
        for h in root.handlers:
            if h is not handler and h.level == logging.NOTSET:
                h.setLevel(level)  # stderr keeps the level asked while the root passes info to the file
        root.setLevel(min(level, logging.INFO))
        root.addHandler(handler)
        return handler
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; its exit code (`slscan.exit_codes`)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    refusal = moved(argv)
    if refusal is not None:
        print(refusal, file=sys.stderr)
        return Exit.USAGE
    parser = build_parser(argv)
    _member_first(parser, argv)
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:  # bare `slscan` or `slscan bench`: the help, not an error
        (commands(parser).get(args.command, parser) if args.command else parser).print_help()
        return Exit.OK
    try:
        log_file = configure_logging(args)
    except ScannerError as exc:
        print(f"slscan {command_name(args)}: error: {exc}", file=sys.stderr)
        return Exit.USAGE
    from slscan.library_logs import hold_to

    hold_to(log_level(args))  # Dask, Rerun and Open3D at the level asked (a full disk: three Rerun lines otherwise)
    from scanner.native_threads import size_opencv_pool

    size_opencv_pool()  # on the main thread before any command's threads start; never at import
    try:
        with terminate_as_interrupt():
            return _run(args)
    finally:
        if log_file is not None:
            logging.getLogger().removeHandler(log_file)
            log_file.close()


def run() -> None:
    """The program (`slscan`, `python -m slscan`): `main`, then exit with its code. A
    recording whose writer stopped (a full disk) would hold the interpreter's exit forever
    in its destructor: the process then ends without tearing it down."""
    code = main()
    recordings = sys.modules.get("scanner.session_recording")
    if recordings is not None and recordings.ABANDONED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


def _terminate(signum: int, frame: object) -> None:
    raise Terminated(signal.Signals(signum).name)


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """While held (on the main thread), SIGTERM stops the command as Ctrl-C does: the
    station marks its cycle aborted and keeps the session, a capture keeps its frames."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextmanager
def json_stdout() -> Iterator[None]:
    """While held, what libraries write to the stdout descriptor goes to stderr
    (`inspection.views.quiet.stdout_to_stderr`: Open3D's warnings cannot break the JSON), while
    `sys.stdout`, where a command prints its JSON, keeps writing where it did: our own stdout
    (a copy of its descriptor), or the stream a caller put there in-process."""
    from inspection.views.quiet import stdout_to_stderr

    sys.stdout.flush()
    try:
        own = sys.stdout.fileno() == 1
    except (AttributeError, OSError, ValueError):
        own = False
    target = os.fdopen(os.dup(1), "w", encoding="utf-8") if own else sys.stdout
    try:
        with stdout_to_stderr(), _c_streams_flushed(), redirect_stdout(_LibraryLinesApart(target)):
            yield
    finally:
        if own:
            target.close()


class _LibraryLinesApart(io.TextIOBase):
    """`sys.stdout` under `json_stdout`: the command's own writes go to `target`; lines a
    library prints through Python's `sys.stdout` (Open3D's, by pybind11: "[Open3D WARNING] ...",
    coloured) go to stderr, each with the line end written after it."""

    MARKERS = ("[Open3D ",)

    def __init__(self, target: TextIO) -> None:
        super().__init__()
        self.target, self.in_library_line = target, False

    def write(self, text: str) -> int:
        plain = re.sub(r"\x1b\[[0-9;]*m", "", text)
        if self.in_library_line or plain.startswith(self.MARKERS):
            sys.stderr.write(text)
            self.in_library_line = not text.endswith("\n")
            return len(text)
        return self.target.write(text)

    def flush(self) -> None:
        self.target.flush()


@contextmanager
def _c_streams_flushed() -> Iterator[None]:
    """On leaving, flush the C library's stdio buffers: a native library's line (Open3D's
    warnings) held in its buffer while stdout is a pipe goes where the descriptor points
    now, not onto the JSON once the descriptor is restored."""
    try:
        yield
    finally:
        import ctypes

        ctypes.CDLL(None).fflush(None)


def _run(args: argparse.Namespace) -> int:
    try:
        if getattr(args, "json", False):
            with json_stdout():
                return int(args.func(args))
        return int(args.func(args))
    except ScannerError as exc:
        print(f"\nslscan {command_name(args)}: error: {exc}", file=sys.stderr)
        return for_error(exc)
    except OSError as exc:  # the file system refused (full disk, read-only or missing folder): one line
        from scanner.session import disk_problem

        print(f"\nslscan {command_name(args)}: error: {disk_problem(exc)}", file=sys.stderr)
        return Exit.USAGE
    except KeyboardInterrupt as exc:
        why = f" ({exc})" if str(exc) else ""
        print(f"\nslscan {command_name(args)}: interrupted{why}; frames already captured are kept", file=sys.stderr)
        return Exit.INTERRUPTED


if __name__ == "__main__":
    run()
