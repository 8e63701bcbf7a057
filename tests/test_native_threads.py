"""Native thread pools: limited without the loader-lock deadlock, and never touched at import.

The peer for what the limits do is threadpoolctl, asked on one thread with nothing else
running (where its walk is safe)."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("scanner", "calibration", "inspection", "sim", "slscan")
RACE = Path(__file__).with_name("native_race.py")
ROUNDS = 250  # imports racing walks per run (each import a fresh dlopen of a 1.2 MB extension)


def _run(code: str, timeout: float = 120) -> str:
    """`code` run by a fresh interpreter, BLAS's thread count its own (not the test workers' 1: conftest)."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout, cwd=ROOT,
                       env=env)
    assert p.returncode == 0, p.stderr[-2000:]
    return p.stdout


@pytest.mark.parametrize("walk_on_thread", [False, True], ids=["walk-on-main", "walk-on-thread"])
def test_limits_racing_imports_never_deadlock(walk_on_thread: bool, tmp_path: Path) -> None:
    """ROUNDS extension imports on one thread against ROUNDS finds-and-limits on the other,
    under a watchdog. With threadpoolctl as the walker the same script deadlocked in 2 of 3
    runs of 300 rounds within 60 s (gdb: the walker in its dl_iterate_phdr callback waiting for the GIL, the
    importer in dlopen holding it)."""
    args = [sys.executable, str(RACE), "slscan", str(ROUNDS), str(tmp_path)] + (["--walk-on-thread"] * walk_on_thread)
    try:
        p = subprocess.run(args, capture_output=True, text=True, timeout=90, cwd=ROOT)
    except subprocess.TimeoutExpired:
        pytest.fail(f"deadlock: {ROUNDS} imports racing the native-thread limits did not finish in 90 s")
    assert p.returncode == 0, p.stderr[-2000:]
    done, imported, walks = p.stdout.split()
    assert done == "done" and int(imported) == ROUNDS and int(walks) >= ROUNDS


def test_limits_reach_every_blas_and_are_restored() -> None:
    """Inside `native_threads(1)` every BLAS library threadpoolctl finds (numpy's, scipy's,
    OpenCV's OpenBLAS) runs one thread; after, each has its own count back."""
    out = _run("""
import cv2, numpy, scipy.linalg
from threadpoolctl import threadpool_info
from scanner.native_threads import native_threads
blas = lambda: {d['filepath']: d['num_threads'] for d in threadpool_info() if d['user_api'] == 'blas'}
before = blas()
with native_threads(1):
    inside = blas()
after = blas()
print(len(before), set(inside.values()) == {1}, inside.keys() == before.keys(), after == before,
      max(before.values()))
""")
    count, all_one, same_libs, restored, most = out.split()
    assert int(count) >= 3 and all_one == "True" and same_libs == "True" and restored == "True"
    assert int(most) > 1  # the limit was a change (this machine has 2 cores)


def test_importing_the_product_sets_no_thread_count() -> None:
    """Importing every product module leaves BLAS and OpenCV thread counts as they were:
    no limit is set at import, where it would race other threads' imports."""
    out = _run(f"""
import importlib, pkgutil, cv2, numpy, scipy.linalg
from threadpoolctl import threadpool_info
state = lambda: (cv2.getNumThreads(), sorted((d['filepath'], d['num_threads']) for d in threadpool_info()))
before = state()
for package in {PRODUCT!r}:
    for m in pkgutil.walk_packages(importlib.import_module(package).__path__, package + '.'):
        if m.name not in ('slscan.__main__',):
            importlib.import_module(m.name)
print(state() == before)
""", timeout=300)
    assert out.strip() == "True"


def test_no_module_uses_threadpoolctl() -> None:
    """threadpoolctl's walk is the deadlock; the product limits threads only through
    `scanner.native_threads`."""
    users = []
    for package in PRODUCT:
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                users += [f"{path.relative_to(ROOT)}:{node.lineno}" for n in names if n.startswith("threadpoolctl")]
    assert users == []
