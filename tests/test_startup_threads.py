"""The start-ups that deadlocked, run many times under a watchdog (slow: ~2-4 s a start):
`slscan demo`'s (Open3D imported first on the main thread, as the demo does; then the "load
CAD" thread reads the STEP model, prepares its registration target and limits the native
pools, as the inspection does, while the main thread imports the scan's libraries: the
simulator, OpenCV's users, Rerun) and the station's (its cycle thread imports the inspection and limits the pools while
the main thread imports the operator screen). Each start is a fresh process: the loader's
lock and the import state start clean each time, as they do for a user.

    SLSCAN_STARTS=200 python -m pytest -m slow tests/test_startup_threads.py -s
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]
STARTS = int(os.environ.get("SLSCAN_STARTS", "200"))
WATCHDOG_S = 120.0  # a start takes 2-4 s at load 1, ~15 s at load 30: 120 s is a hang

DEMO = """
import threading
from concurrent.futures import ThreadPoolExecutor
from scanner.native_threads import native_threads
from slscan.commands.scan import load_demo_part

def cad():
    model, tolerances, program = load_demo_part()
    with native_threads(1):
        return len(model.faces)

import open3d  # noqa: F401  (first, on the main thread, as cmd_demo does)

with ThreadPoolExecutor(1, thread_name_prefix="load CAD") as pool:
    faces = pool.submit(cad)
    import scanner.pipeline, scanner.session_recording, sim.virtual_rig  # noqa: E401,F401  racing the thread
    import rerun  # noqa: F401
    print("done", faces.result(), flush=True)
"""

STATION = """
import threading
from scanner.native_threads import native_threads

out = []
def cycle():
    import inspection.inspect_scan  # noqa: F401  (what the cycle thread imports first)
    with native_threads(1, openmp=True):
        out.append(1)

t = threading.Thread(target=cycle, daemon=True)
t.start()
import slscan.station.tui  # noqa: F401  (the operator screen, on the main thread: curses and the station)
import open3d  # noqa: F401
t.join()
print("done", len(out), flush=True)
"""


@pytest.mark.parametrize("name, code", [("demo", DEMO), ("station", STATION)])
def test_start_up_threads_never_deadlock(name: str, code: str) -> None:
    hung, started = [], time.perf_counter()
    for k in range(STARTS):
        try:
            p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=WATCHDOG_S,
                               cwd=ROOT)
        except subprocess.TimeoutExpired:
            hung.append(k)
            continue
        assert p.returncode == 0 and p.stdout.startswith("done"), p.stderr[-2000:]
    print(f"{name}: {STARTS} starts, {len(hung)} hung, {time.perf_counter() - started:.0f} s, load "
          f"{os.getloadavg()[0]:.1f}")
    assert hung == []
