"""`slscan station`, `slscan results` and `slscan batch`: the bench station (slscan/station/)."""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

from scanner.errors import ScannerError
from slscan.exit_codes import Exit, for_parts
from slscan.options import OutputFlag, add_json, add_out, count_arg, plain_text_arg
from slscan.station import MEASUREMENT_NAMES


def _station_options(p: argparse.ArgumentParser, writes: bool = False) -> None:
    """The station config and data folder: `--out` for the station, which writes it
    (`--data` its deprecated alias), `--data` for the commands that read it."""
    p.add_argument("--config", type=Path, help="station config TOML (default: config/station/sim_bench.toml)")
    if writes:
        add_out(p, "the station's data folder to write (sessions, SQLite results, reports; default: the station "
                   "config's)", old=("--data",))
    else:
        p.add_argument("--data", help="the station's data folder to read (default: the station config's)")
    p.add_argument("--db", help="results database: sqlite:PATH or postgresql://... "
                                "(default: SQLite in the data folder)")


def _config(args: argparse.Namespace) -> Any:
    from slscan.station.app import override
    from slscan.station.station_config import DEFAULT_STATION, StationConfig

    data = args.out if args.command == "station" else args.data
    return override(StationConfig.load(args.config or DEFAULT_STATION), data, args.db)


def cmd_station(args: argparse.Namespace) -> int:
    if args.json and not args.auto:
        raise ScannerError("--json applies to --auto runs (the operator screen is the terminal)")
    if not args.auto and not (sys.stdin.isatty() and sys.stdout.isatty()):
        raise ScannerError("the operator screen needs a terminal; use --auto --parts N to run without one")
    from slscan.progress import ProgressLine  # the station's libraries after the refusals above (~1.5 s)
    from slscan.station.app import open_station, run_auto
    from slscan.station.measure import load_measurement

    config = _config(args)
    measurement = load_measurement(args.measurement) if args.measurement else None
    with open_station(args.program, config, args.operator or "", measurement, rig_path=args.rig) as run:
        if args.auto:
            return run_auto(run, args.parts if args.parts is not None else 1, progress=ProgressLine(),
                            as_json=args.json)
        from slscan.station.tui import run_tui

        return run_tui(run, args.parts)


def _utc_time(text: str) -> dt.datetime:
    """An ISO 8601 date or time, UTC unless it names its offset."""
    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not an ISO date/time such as 2026-11-23 or "
                                         f"2026-11-23T08:00") from None
    return t if t.tzinfo else t.replace(tzinfo=dt.UTC)


def _program_name(value: str | None) -> tuple[str | None, Any]:
    """A program filter given as a name or a program TOML: (name, loaded program or None)."""
    if value is None or not value.endswith(".toml"):
        return value, None
    from slscan.station.program import load_program

    program = load_program(value)
    return program.name, program


def _ids(text: str) -> frozenset[int]:
    """Result ids on the command line: "12-40", "3,5,7-9"."""
    out: set[int] = set()
    try:
        for part in text.split(","):
            lo, _, hi = part.strip().partition("-")
            first, last = int(lo), int(hi or lo)
            if first < 1 or last < first:
                raise ValueError
            out.update(range(first, last + 1))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of result ids such as 12-40 or 3,5,7-9") from None
    return frozenset(out)


def _exclusion(text: str) -> tuple[int, str]:
    """ID=REASON: a result the user leaves out of the statistics, and why."""
    rid, sep, why = text.partition("=")
    if not sep or not rid.strip().isdigit() or not why.strip():
        raise argparse.ArgumentTypeError(f"'{text}' is not RESULT_ID=REASON, e.g. 17=\"fixture loose\"")
    return int(rid), " ".join(why.split())


def _rules(text: str) -> tuple[int, ...]:
    """Nelson rules: "all" or numbers 1..8 such as 1,2,5,6."""
    if text.strip() == "all":
        return tuple(range(1, 9))
    try:
        rules = tuple(sorted({int(r) for r in text.split(",")}))
    except ValueError:
        rules = ()
    if not rules or not all(1 <= r <= 8 for r in rules):
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of Nelson rules 1..8 (e.g. 1,2,5,6) or 'all'")
    return rules


def _spc_options(args: argparse.Namespace, program: Any, exclusions: dict[int, Any]) -> Any:
    """The report's statistics options from the command line (frozen limits read here) and
    the exclusions recorded in the database (`results.Exclusion`: their reasons)."""
    from slscan.station.limits_file import load_limits
    from slscan.station.quality import SpcOptions
    from slscan.station.spc import DEFAULT_RULES

    frozen, source = load_limits(args.limits, program) if args.limits else ({}, "")
    return SpcOptions(exclusions={rid: e.reason for rid, e in exclusions.items()}, rules=args.rules or DEFAULT_RULES,
                      baseline=args.baseline, frozen=frozen, frozen_source=source)


def _record_exclusions(args: argparse.Namespace, url: str) -> None:
    """`--exclude ID=REASON` and `--include ID`: recorded in the results database (who: --by,
    else the login name; when: now), for every later report and export."""
    import getpass

    from slscan.station.results import open_results

    try:
        by = args.by or getpass.getuser()
    except (KeyError, OSError):
        raise ScannerError("slscan results --exclude: give who excludes with --by NAME (no login name here)") from None
    open_results(url, create=False).close()  # the database must exist: a mistyped folder is an error, not a new one
    with open_results(url) as store:
        for rid, why in args.exclude or []:
            print(f"excluded  result {rid}: {store.exclude(rid, why, by).shown()}", file=sys.stderr)
        for rid in args.include or []:
            print(f"included  result {rid}" + ("" if store.include(rid) else " (it was not excluded)"), file=sys.stderr)


def _check_results_args(args: argparse.Namespace, program: Any) -> None:
    """Refuse option combinations that cannot be honoured, before the database is opened."""
    writes = [flag for flag in ("csv", "report", "dfq") if getattr(args, flag)]
    if len(writes) > 1:
        raise ScannerError(f"slscan results: --{' and --'.join(writes)} all write to --out; give one per run")
    if (args.report or args.dfq) and not args.out:
        raise ScannerError(f"slscan results --{writes[0]}: give where it writes with --out "
                           + ("DIR" if args.report else "FILE.dfq"))
    if (args.report or args.dfq) and program is None:
        raise ScannerError(f"slscan results --{writes[0]}: give --program as the part program TOML (it has the "
                           "characteristics and tolerances)")
    spc = [f for f in ("baseline", "limits", "save_limits", "rules") if getattr(args, f)]
    if spc and not args.report:
        raise ScannerError(f"slscan results: --{spc[0].replace('_', '-')} applies to --report")
    if args.by and not args.exclude:
        raise ScannerError("slscan results: --by names who gives --exclude")
    if args.limits and (args.baseline or args.save_limits):
        raise ScannerError("slscan results: --limits uses frozen limits; --baseline and --save-limits make new ones")


def cmd_results(args: argparse.Namespace) -> int:
    from scanner.session import write_atomic
    from slscan.station.history_report import write_report
    from slscan.station.results import csv_text, open_results, write_csv

    name, program = _program_name(args.program)
    _check_results_args(args, program)
    config = _config(args)
    if args.exclude or args.include:
        _record_exclusions(args, config.database_url)
    with open_results(config.database_url, create=False) as store:
        excluded = store.exclusions()
        options = _spc_options(args, program, excluded) if args.report or args.dfq else None
        rows = store.results(program=name, serial=args.serial, status=args.status, since=args.since, limit=args.limit)
        values = store.values([r.id for r in rows])
        if args.exclusions:
            _list_exclusions(store, excluded, as_json=args.json)
        elif args.dfq:
            from slscan.station.dfq import dfq_text

            assert options is not None  # made for --dfq above
            text, n = dfq_text(program, rows, values, options.exclusions)
            _write_export(Path(args.out), lambda path: write_atomic(path, text.encode("utf-8")))
            print(f"wrote {n} values of {len(program.characteristics)} characteristics (AQDEF) to {args.out}",
                  file=sys.stderr)
        elif args.csv:
            if args.out in (None, "-"):
                write_csv(sys.stdout, rows, values)
            else:
                text, n = csv_text(rows, values)
                _write_export(Path(args.out), lambda path: write_atomic(path, text.encode()))
                print(f"wrote {n} lines ({len(rows)} results) to {args.out}", file=sys.stderr)
        elif args.json:
            results = [{**asdict(r), "values": [asdict(v) for v in values[r.id]],
                        "excluded": asdict(excluded[r.id]) if r.id in excluded else None} for r in rows]
            print(json.dumps({"where": store.where, "results": results}, default=str))
        else:
            print(f"{'id':>5} {'program':<14} {'serial':<24} {'att':>3} {'status':<10} {'finished (UTC)':<19}  values")
            for r in rows:
                vals = "  ".join(f"{v.characteristic}={v.value_mm:.4f}" if v.value_mm is not None else
                                 f"{v.characteristic}=<{v.limit_mm:.4f}" if v.limit_mm is not None else
                                 f"{v.characteristic}=--" for v in values[r.id])
                when = f"{r.finished_at:%Y-%m-%d %H:%M:%S}" if r.finished_at else ""
                print(f"{r.id:>5} {r.program:<14} {r.serial:<24} {r.attempt:>3} {r.status:<10} {when:<19}  {vals}"
                      + (f"  [{r.message}]" if r.message and r.status != "fail" else "")
                      + (f"  [excluded: {excluded[r.id].shown()}]" if r.id in excluded else ""))
            print(f"{len(rows)} results in {store.where}", file=sys.stderr)
        if args.report:
            assert options is not None  # made for --report above
            path = _write_export(Path(args.out), lambda folder: write_report(folder, program, rows, values,
                                                                              store.where, options))
            print(f"report {path}", file=sys.stderr)
            if args.save_limits:
                _save_limits(args, program, rows, values, options, store.where)
    return Exit.OK


def _list_exclusions(store: Any, excluded: dict[int, Any], *, as_json: bool) -> None:
    """`--exclusions`: every recorded exclusion with its result's serial (or one JSON document)."""
    serials = {rid: store.result(rid).serial for rid in excluded}
    if as_json:
        print(json.dumps({"where": store.where, "exclusions": [{**asdict(e), "serial": serials[rid]}
                                                               for rid, e in excluded.items()]}, default=str))
        return
    print(f"{'id':>5} {'serial':<24} {'excluded (UTC)':<16}  {'by':<12} reason")
    for rid, e in excluded.items():
        print(f"{rid:>5} {serials[rid]:<24} {e.excluded_at:%Y-%m-%d %H:%M}  {e.excluded_by:<12} {e.reason}")
    print(f"{len(excluded)} exclusions in {store.where}", file=sys.stderr)


def _save_limits(args: argparse.Namespace, program: Any, rows: Any, values: Any, options: Any, where: str) -> None:
    """Freeze the limits the report computed into --save-limits FILE; say which had none."""
    from slscan.station.limits_file import save_limits
    from slscan.station.quality import running_stats

    stats = running_stats(program, rows, values, options)
    chosen = f"{len(args.baseline)} results, ids {min(args.baseline)}..{max(args.baseline)}" if args.baseline else ""
    left_out = "; ".join(f"{rid} ({why})" for rid, why in sorted(options.exclusions.items()))
    source = (f"the baseline of {chosen} of {where}" if args.baseline else f"every result of {where}") + (
        f"; left out by the user: {left_out}" if left_out else "")
    missing = _write_export(Path(args.save_limits), lambda path: save_limits(
        path, program, {s.name: s.chart for s in stats.characteristics}, source))
    notes = {s.name: s.limits_note for s in stats.characteristics}
    print(f"limits frozen in {args.save_limits}" + "".join(f"; none for {name} ({notes[name]})" for name in missing),
          file=sys.stderr)


def _write_export(target: Path, write: Any) -> Any:
    """`write(target)`, an OS refusal (read-only folder, full disk, a file in the way) as one line."""
    try:
        return write(target)
    except OSError as exc:
        raise ScannerError(f"{exc.filename or target}: cannot write: {exc.strerror or exc}") from None


def check_part_folders(paths: list[str]) -> None:
    """Refuse a part or session folder that is not there (bad input, exit 2) before any work;
    one that is there but cannot be measured is that part's error in the batch (exit 4)."""
    missing = [p for p in paths if not Path(p).is_dir()]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise ScannerError(f"{missing[0]}: no such part or session folder{more}")


def cmd_batch(args: argparse.Namespace) -> int:
    from slscan.progress import ProgressLine
    from slscan.station.batch import print_summary, run_batch

    check_part_folders(args.sessions)
    config = _config(args) if args.store else None
    summary = run_batch(args.sessions, args.program, scheduler=args.scheduler, workers=args.workers,
                        store_config=config, progress=ProgressLine(), measurement=args.measurement, rig_path=args.rig)
    print_summary(summary, json_out=args.json)
    return for_parts(i.status for i in summary.items)


def register(sub: Any) -> None:
    s = sub.add_parser("station")
    s.add_argument("program", help="part program TOML (config/parts/*.toml)")
    _station_options(s, writes=True)
    s.add_argument("--rig", type=Path, help="rig TOML (default: the station config's)")
    s.add_argument("--operator", type=plain_text_arg, help="operator name stored with every result")
    s.add_argument("--parts", type=count_arg(1), help="stop after this many measured parts (>= 1)")
    s.add_argument("--auto", action="store_true", help="no operator: measure --parts parts one after the other")
    s.add_argument("--measurement", choices=sorted(MEASUREMENT_NAMES),
                   help="measuring step (default: the station config's)")
    add_json(s)
    s.set_defaults(func=cmd_station)

    r = sub.add_parser("results")
    _station_options(r)
    r.add_argument("--program", help="part program name, or its TOML (needed for --report)")
    r.add_argument("--serial", type=plain_text_arg, help="only the results of this part serial number")
    r.add_argument("--status", choices=("in_progress", "pass", "fail", "uncertain", "error", "aborted", "incomplete"),
                   help="only the results with this status")
    r.add_argument("--since", type=_utc_time,
                   help="ISO date/time (UTC unless it says), e.g. 2026-11-23 or 2026-11-23T08:00")
    r.add_argument("--limit", type=count_arg(0), help="only the newest N results (N >= 0)")
    r.add_argument("--csv", nargs="?", const=True, action=OutputFlag,
                   help="export CSV to --out FILE (default: standard output)")
    r.add_argument("--report", nargs="?", const=True, action=OutputFlag,
                   help="write the HTML report with control charts into the folder --out DIR")
    r.add_argument("--dfq", action="store_true", help="export the values as an AQDEF (Q-DAS) DFQ file to --out FILE")
    add_json(r)
    r.add_argument("--exclude", action="append", type=_exclusion, metavar="ID=REASON",
                   help="leave result ID out of the limits and capability, for the reason given: recorded in the "
                        "results database (who, when, why) for every later report (shown there) and export "
                        "(deactivated); repeat for more")
    r.add_argument("--by", type=plain_text_arg, metavar="NAME",
                   help="with --exclude: who excludes (default: the login name)")
    r.add_argument("--include", action="append", type=count_arg(1), metavar="ID",
                   help="lift the recorded exclusion of result ID; repeat for more")
    r.add_argument("--exclusions", action="store_true", help="list the recorded exclusions (who, when, why)")
    r.add_argument("--rules", type=_rules, metavar="N,N,...",
                   help="Nelson rules to flag (1..8 or 'all'; default 1,2,5,6, the Western Electric set)")
    r.add_argument("--baseline", type=_ids, metavar="IDS",
                   help="compute the control limits from these result ids only, e.g. 1-25")
    r.add_argument("--save-limits", metavar="FILE", help="with --report: freeze the limits computed into FILE (JSON)")
    r.add_argument("--limits", type=Path, metavar="FILE",
                   help="with --report: use the frozen limits of FILE (from --save-limits) instead of computing them")
    add_out(r, "where --csv, --dfq or --report writes (a CSV file, '-' for standard output, a DFQ file, or the "
               "report's folder)")
    r.set_defaults(func=cmd_results)

    b = sub.add_parser("batch")
    b.add_argument("sessions", nargs="+", help="part folders written by the station, or session folders")
    b.add_argument("--program", required=True, help="part program TOML to inspect against")
    b.add_argument("--scheduler", help="Dask scheduler address (tcp://host:8786); default: a local cluster")
    b.add_argument("--workers", type=int, default=2, help="local cluster: worker processes (default 2)")
    b.add_argument("--rig", type=Path, help="reconstruct with this rig's geometry (its calibration) instead of the "
                                            "one recorded at capture")
    b.add_argument("--store", action="store_true", help="store the re-inspection results (source 'batch')")
    _station_options(b)
    b.add_argument("--measurement", choices=sorted(MEASUREMENT_NAMES),
                   help="measuring step (default: the station config's)")
    b.add_argument("--json", action="store_true", help="print the summary as JSON")
    b.set_defaults(func=cmd_batch)
