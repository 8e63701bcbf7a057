"""Shared fixtures: small analytic rigs and one small simulated session."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from scanner.geometry import RigModel
from scanner.rig import RigConfig


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


_EXIT_STATUS = {"status": 0}


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    _EXIT_STATUS["status"] = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config: pytest.Config) -> None:
    """Leave as soon as pytest has reported and cleaned up: Rerun's exit-time flush of the
    recordings the tests opened can deadlock the interpreter's shutdown (seen once: a
    fresh clone's default run hung after its summary, 264 RecordingStream threads waiting,
    which CI would only end at its time limit)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(_EXIT_STATUS["status"])
