"""Shared fixtures: small analytic rigs and one small simulated session; and every Rerun
recording a test leaves behind released, so the test process ends as any other does."""

from __future__ import annotations

import gc
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import recording_support

from scanner.geometry import RigModel
from scanner.rig import RigConfig


def pytest_configure(config: pytest.Config) -> None:
    """In an xdist worker (`-n 2`: one per core), BLAS on one thread: the libraries loaded
    already (numpy's) set so, those loaded later and the programs the tests start by the
    environment. A second BLAS thread has no core of its own there and only spins."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        return
    from scanner.native_threads import loaded_pools

    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    for pool in loaded_pools():
        pool.set_threads(1)


@pytest.fixture(scope="session")
def bench_model() -> RigModel:
    """The default simulated rig's nominal geometry."""
    return RigConfig.load().nominal_model()


@pytest.fixture(scope="session")
def small_rig(bench_model: RigModel) -> RigModel:
    """The default rig with a 320 x 256 camera (same field of view)."""
    return bench_model.with_camera_size(320, 256)


@pytest.fixture(scope="module")
def clean_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One small simulated scan (320 x 256, 12 frames), copied by each test that edits it.
    (Imported here: the scanner's pipeline loads only for the modules that ask for it.)"""
    from session_support import scan_small_session

    return scan_small_session(tmp_path_factory.mktemp("clean"))


@pytest.fixture(autouse=True)
def _recordings_abandoned_by_the_test() -> Iterator[None]:
    """After a test that made a recording's writer stall or fail: the recordings the product
    gave up on (`session_recording.ABANDONED`, kept open so the process could end by
    `os._exit`) disconnected, and Rerun's exit handler, which giving up unregisters, back.
    A recording that does not disconnect fails this test, once, and is kept apart (`recording_support.STUCK`):
    neither the module's release nor the exit handler waits on it (they would never end)."""
    yield
    recording_support.release_abandoned_recordings()


@pytest.fixture(autouse=True, scope="module")
def _recordings_released_after_the_module() -> Iterator[None]:
    """After each module, the native side of the recordings its tests closed released. Rerun
    0.41 keeps every stream (two threads each) after its last reference is gone, until
    `rerun.init` or its exit handler flushes them all; a whole run's worth (264) once hung
    the process after the summary. (The blueprint stream each `send_blueprint` makes stays
    even so: nothing reachable holds it.)"""
    yield
    if "rerun" in sys.modules and not recording_support.STUCK:
        import rerun_bindings

        gc.collect()  # the last references to closed streams (cycles, tracebacks)
        rerun_bindings.flush_and_cleanup_orphaned_recordings()


@pytest.hookimpl(optionalhook=True)  # without xdist (-p no:xdist) the hook is unknown
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """`--dist loadfile` with the longest tests sent out first, each alone (`scheduling`)."""
    if config.getoption("dist") != "loadfile":
        return None
    from scheduling import LongestFirst

    return LongestFirst(config, log)
