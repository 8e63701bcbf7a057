"""`slscan bench cad FILE [--copies 1,4,16]`: STEP reading time of files holding copies of
FILE, each read by `slscan cad` in a fresh process (beside `slscan cad`, which it times)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from slscan.exit_codes import Exit
from slscan.options import add_json


def cmd_cad_bench(args: argparse.Namespace) -> int:
    """STEP reading time for files holding 1, 4, 16 ... copies of one part, each read by
    `slscan cad` in a fresh process: wall and CPU s, peak memory, faces, and the time per
    face against the one-copy file (its peer in the same run), with the load average; with
    `--json` the table goes to stderr and its rows to stdout as one JSON document."""
    import os
    import subprocess
    import tempfile
    import time

    from OCP.Message import Message, Message_Gravity

    from inspection.cad import write_copies

    for printer in Message.DefaultMessenger_s().Printers():  # the STEP writer's statistics are not ours to print
        printer.SetTraceLevel(Message_Gravity.Message_Fail)
    counts = [int(c) for c in args.copies.split(",")]
    table = sys.stderr if args.json else sys.stdout
    rows: list[dict[str, Any]] = []
    load0 = os.getloadavg()
    print(f"{'copies':>6} {'MB':>6} {'faces':>6} {'wall s':>7} {'CPU s':>7} {'peak MB':>7} "
          f"{'CPU ms/face':>11} {'marginal':>8}  load average (1, 5, 15 min) before", file=table)
    first: tuple[int, float] | None = None
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            path = write_copies(args.file, n, Path(tmp) / f"copies_{n}.stp")
            load = os.getloadavg()
            t0 = time.perf_counter()
            proc = subprocess.Popen([sys.executable, "-m", "slscan", "cad", str(path), "--json"],
                                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
            out = proc.stdout.read() if proc.stdout is not None else b""  # PIPE: always there
            _, status, usage = os.wait4(proc.pid, 0)
            wall = time.perf_counter() - t0
            if status != 0:
                print(f"{n:>6}: slscan cad failed (wait status {status})", file=sys.stderr)
                return Exit.FAILED
            faces = len(json.loads(out)["faces"])
            cpu = usage.ru_utime + usage.ru_stime
            first = first or (faces, cpu)
            marginal = f"{1e3 * (cpu - first[1]) / (faces - first[0]):8.2f}" if faces > first[0] else f"{'':>8}"
            print(f"{n:>6} {path.stat().st_size / 1e6:6.1f} {faces:>6} {wall:7.2f} {cpu:7.2f} "
                  f"{usage.ru_maxrss / 1024:7.0f} {1e3 * cpu / faces:11.2f} {marginal}  "
                  + " ".join(f"{x:.2f}" for x in load), flush=True, file=table)
            rows.append({"copies": n, "bytes": path.stat().st_size, "faces": faces, "wall_s": wall, "cpu_s": cpu,
                         "peak_rss_mb": usage.ru_maxrss / 1024, "cpu_ms_per_face": 1e3 * cpu / faces,
                         "marginal_cpu_ms_per_face": 1e3 * (cpu - first[1]) / (faces - first[0])
                         if faces > first[0] else None, "load_average_before": load})
    print("marginal: CPU ms per face added over the first file (the fixed start-up of ~2 s excluded); "
          "a constant marginal cost is linear growth", file=table)
    load1 = os.getloadavg()
    print("load average after " + " ".join(f"{x:.2f}" for x in load1), file=table)
    if args.json:
        print(json.dumps({"status": "ok", "file": str(args.file), "rows": rows,
                          "load_average": {"start": load0, "end": load1}}))
    return Exit.OK


def register(sub: Any) -> None:
    cb = sub.add_parser("cad")
    cb.add_argument("file", help="STEP file of one part (e.g. ../shared/data/step/nist_ctc_01_asme1_rd.stp)")
    cb.add_argument("--copies", default="1,4,16", help="comma-separated copy counts (default 1,4,16)")
    add_json(cb)
    cb.set_defaults(func=cmd_cad_bench)
