"""Start-up time of the command line, run on purpose (not a test):

    python tests/startup_bench.py [--runs 5]

Wall time of `slscan --version`, `slscan --help` and a usage error (an unknown option) of
every command in `slscan.commands.COMMANDS`, each the median of `--runs` fresh processes,
beside its peer measured in the same run: a bare Python start (`python -c pass`); the load
average before and after."""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

from slscan.commands import COMMANDS

CASES = {"python -c pass": ["-c", "pass"], "slscan --version": ["-m", "slscan", "--version"],
         "slscan --help": ["-m", "slscan", "--help"],
         **{f"slscan {name} --bogus": ["-m", "slscan", name, "--bogus"] for name in COMMANDS}}


def median_wall(args: list[str], runs: int) -> float:
    """Median wall time (s) of `runs` fresh `python args` processes."""
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, *args], capture_output=True, timeout=120)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=5)
    runs = p.parse_args().runs
    print(f"load average before {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    peer = None
    for name, args in CASES.items():
        wall = median_wall(args, runs)
        peer = peer or wall
        print(f"{name:<28} median {wall * 1e3:7.0f} ms of {runs}  ({wall / peer:4.1f}x a bare Python start)",
              flush=True)
    print(f"load average after  {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
