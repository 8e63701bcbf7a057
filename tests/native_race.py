"""The start-up race of `slscan demo`, reproduced: one thread imports extension modules
(holding the GIL while `dlopen` waits for the dynamic loader's lock) while another finds
and limits the native thread pools. Run as a script with the walker to use and the number
of rounds; it prints `done IMPORTS WALKS` when both threads finished. A walker that runs
Python under the loader's lock (threadpoolctl's `dl_iterate_phdr` callback) deadlocks
here; the caller's watchdog sees a script that never prints.

    python tests/native_race.py slscan|threadpoolctl ROUNDS FOLDER [--walk-on-thread]

`--walk-on-thread` swaps the roles: the main thread imports (as `slscan demo`'s did, importing
open3d) and a started thread walks (as its "load CAD" thread did).
"""

from __future__ import annotations

import importlib.util
import shutil
import sys
import tempfile
import threading
from pathlib import Path

import numpy  # noqa: F401  (a BLAS library loaded, as in every slscan process)

# a large extension module: its relocations keep the loader's lock held a while
EXTENSION = "unicodedata"


def copies(folder: Path, count: int) -> list[Path]:
    """`count` copies of the extension under distinct file names (each import a fresh dlopen)."""
    origin = importlib.util.find_spec(EXTENSION).origin
    out = []
    for k in range(count):
        path = folder / f"copy{k}" / Path(origin).name
        path.parent.mkdir()
        shutil.copyfile(origin, path)
        out.append(path)
    return out


def import_each(paths: list[Path], counter: list[int]) -> None:
    for path in paths:
        spec = importlib.util.spec_from_file_location(EXTENSION, path)
        assert spec is not None and spec.loader is not None
        spec.loader.exec_module(importlib.util.module_from_spec(spec))
        counter[0] += 1


def walker(kind: str):
    """One find-and-limit of the native pools, by slscan's module or by threadpoolctl."""
    if kind == "slscan":
        from scanner.native_threads import native_threads

        def walk() -> None:
            with native_threads(1, openmp=True):
                pass
    else:
        from threadpoolctl import threadpool_limits

        def walk() -> None:
            with threadpool_limits(limits=1):
                pass
    return walk


def main(kind: str, rounds: int, folder: Path, walk_on_thread: bool) -> None:
    """`folder`: where the copies go (the caller's: a killed run leaves them behind)."""
    walk = walker(kind)
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        paths = copies(Path(tmp), rounds)
        imported, walks = [0], [0]

        def walk_until(other: threading.Thread | None) -> None:
            while walks[0] < rounds or (other is not None and other.is_alive()):
                walk()
                walks[0] += 1

        if walk_on_thread:
            thread = threading.Thread(target=walk_until, args=(None,), daemon=True)
            thread.start()
            import_each(paths, imported)
            thread.join()
        else:
            thread = threading.Thread(target=import_each, args=(paths, imported), daemon=True)
            thread.start()
            walk_until(thread)
            thread.join()
    print(f"done {imported[0]} {walks[0]}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), Path(sys.argv[3]), "--walk-on-thread" in sys.argv[4:])
