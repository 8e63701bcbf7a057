"""`slscan bench batch`: `slscan batch` timed serially and on a local Dask cluster, and the
two runs' results compared (exit 1 when they disagree)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from slscan.commands.station import check_part_folders
from slscan.exit_codes import Exit
from slscan.options import add_json
from slscan.station import MEASUREMENT_NAMES


def cmd_batch_bench(args: argparse.Namespace) -> int:
    import os

    from slscan.station.batch import compare, run_batch

    check_part_folders(args.sessions)
    text = sys.stderr if args.json else sys.stdout  # --json: the figures as one document on stdout
    runs, loads = {}, {}
    for label, workers in (("serial", 0), (f"dask, {args.workers} local workers", args.workers)):
        load = loads[label] = os.getloadavg()
        runs[label] = run_batch(args.sessions, args.program, workers=workers, measurement=args.measurement)
        counts = runs[label].counts()
        print(f"{label:<24} wall {runs[label].wall_s:8.2f} s  ({len(args.sessions)} parts: {counts['pass']} pass, "
              f"{counts['fail']} fail, {counts['error']} failed; load average before "
              f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f})", file=text, flush=True)
    serial, dask = runs.values()
    differ, worst, where = compare(serial, dask)
    if args.json:
        print(json.dumps({"runs": {k: {"wall_s": r.wall_s, "counts": r.counts(), "load_before": loads[k]}
                                   for k, r in runs.items()}, "agree": not differ, "differences": differ,
                          "largest_value_difference_mm": worst, "where": where,
                          "speed_up": serial.wall_s / dask.wall_s, "load_after": os.getloadavg()}))
        return Exit.OK if not differ else Exit.FAILED
    print(f"results agree: {'yes' if not differ else 'NO'} (statuses and messages of {len(serial.items)} parts; "
          f"largest value difference {worst * 1e3:.4f} um" + (f", {where}" if where else "") + f"); speed-up "
          f"{serial.wall_s / dask.wall_s:.2f}x; load average after {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for line in differ:
        print("DIFFERS " + line)
    return Exit.OK if not differ else Exit.FAILED


def register(sub: Any) -> None:
    bb = sub.add_parser("batch")
    bb.add_argument("sessions", nargs="+", help="part folders written by the station, or session folders")
    bb.add_argument("--program", required=True, help="part program TOML to inspect against")
    bb.add_argument("--workers", type=int, default=2, help="local cluster worker processes (default 2)")
    bb.add_argument("--measurement", choices=sorted(MEASUREMENT_NAMES), help="measuring step (default: inspection)")
    add_json(bb)
    bb.set_defaults(func=cmd_batch_bench)
