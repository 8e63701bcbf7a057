"""How many threads the native libraries' own pools run (BLAS, OpenCV), set without the
dynamic loader's lock.

threadpoolctl finds the loaded BLAS libraries with `dl_iterate_phdr` and a Python
callback. The callback runs holding the loader's lock and needs the GIL, while a thread
importing an extension module holds the GIL and waits in `dlopen` for that lock: a walk on
one thread racing an import on another deadlocks both (`slscan demo` hung in about one run
of six: `@threadpool_limits.wrap` built its controller when the CAD thread imported
`inspection.inspect_scan` while the main thread imported open3d).

Here the loaded libraries are found in `/proc/self/maps` (a file read, no lock held), opened
with `RTLD_NOLOAD` (a library not loaded is not loaded) and their own thread-count
functions called. No lock is ever held while Python code runs, and nothing happens at
import: the limits are set per call (`native_threads`) or once by the command line on its
main thread (`size_opencv_pool`). BLAS thread counts are process-wide.
"""

from __future__ import annotations

import ctypes
import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

# (set, get) thread-count symbols of the BLAS builds wheels ship (OpenBLAS with its
# scipy-openblas prefixes and 64-bit suffix, BLIS, MKL) and of the OpenMP runtimes
_SYMBOLS = {
    "blas": (("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
             ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
             ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
             ("openblas_set_num_threads", "openblas_get_num_threads"),
             ("bli_thread_set_num_threads", "bli_thread_get_num_threads"),
             ("MKL_Set_Num_Threads", "MKL_Get_Max_Threads")),
    "openmp": (("omp_set_num_threads", "omp_get_max_threads"),),
}
_NAMES = {"blas": ("openblas", "blis", "mkl_rt"), "openmp": ("libgomp", "libomp", "libiomp")}
_RTLD_NOLOAD = getattr(os, "RTLD_NOLOAD", 4)
_lock = threading.Lock()


@dataclass(frozen=True)
class NativePool:
    """One loaded library's thread pool ("blas" or "openmp") and its thread-count functions.
    OpenMP's count is the calling thread's (each thread has its own)."""

    kind: str
    path: str
    set_threads: Callable[[int], None]
    get_threads: Callable[[], int]


def _mapped_libraries() -> set[str]:
    """Paths of the shared libraries mapped into this process now."""
    try:
        lines = Path("/proc/self/maps").read_text().splitlines()
    except OSError:  # not Linux: no pools are found, and nothing is limited
        return set()
    fields = (line.split(None, 5) for line in lines)
    return {f[5] for f in fields if len(f) == 6 and ".so" in f[5]}


def _open(kind: str, path: str) -> NativePool | None:
    try:
        lib = ctypes.CDLL(path, mode=_RTLD_NOLOAD)
    except OSError:  # unmapped since, or not a library
        return None
    for set_name, get_name in _SYMBOLS[kind]:
        setter, getter = getattr(lib, set_name, None), getattr(lib, get_name, None)
        if setter is not None and getter is not None:
            setter.argtypes, setter.restype = [ctypes.c_int], None
            getter.argtypes, getter.restype = [], ctypes.c_int
            return NativePool(kind, path, setter, getter)
    return None


_known: dict[tuple[str, str], NativePool | None] = {}  # every library looked at, None: not a pool of that kind


def loaded_pools(kinds: tuple[str, ...] = ("blas",)) -> list[NativePool]:
    """The thread pools of every loaded library of these kinds (numpy, scipy and OpenCV
    each bundle their own OpenBLAS; Open3D brings OpenMP). Each library's name is looked
    at once: a call costs the read of the map, not a look at its hundred-odd libraries
    (40 ms a call when the renderer limited BLAS per scene, with Open3D loaded)."""
    paths = _mapped_libraries()
    with _lock:
        for kind in kinds:
            for path in paths:
                if (kind, path) not in _known:
                    named = any(n in Path(path).name.lower() for n in _NAMES[kind])
                    _known[kind, path] = _open(kind, path) if named else None
        return [pool for (kind, _), pool in _known.items() if pool is not None and kind in kinds]


@contextmanager
def native_threads(count: int, *, openmp: bool = False) -> Iterator[None]:
    """Every loaded BLAS library (and with `openmp`, the OpenMP runtimes, for the calling
    thread) on `count` threads inside, each restored to its own count after. BLAS counts are
    process-wide: a limit set here also holds for other threads meanwhile."""
    pools = loaded_pools(("blas", "openmp") if openmp else ("blas",))
    before = [pool.get_threads() for pool in pools]
    for pool in pools:
        pool.set_threads(count)
    try:
        yield
    finally:
        for pool, n in zip(pools, before):
            pool.set_threads(n)


def size_opencv_pool() -> None:
    """OpenCV's thread pool sized to the CPUs this process may run on (left at its default,
    the pool showed 3x run-to-run swings in decode time on a 2-core VM, `slscan bench decode`).
    Called once by the command line on its main thread, not at import."""
    import cv2

    cv2.setNumThreads(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


@contextmanager
def opencv_threads(count: int) -> Iterator[None]:
    """OpenCV's pool on `count` threads inside, restored after (process-wide)."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(count)
    try:
        yield
    finally:
        cv2.setNumThreads(before)
