"""Shared fixtures: small analytic rigs and fringe stacks with known truth."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from scanner.geometry import RigModel
from scanner.patterns import PatternSet
from scanner.rig import RigConfig


@pytest.fixture(scope="session")
def bench_model() -> RigModel:
    """The default simulated rig's nominal geometry."""
    return RigConfig.load().nominal_model()


@pytest.fixture(scope="session")
def small_rig(bench_model: RigModel) -> RigModel:
    """The default rig with a 320 x 256 camera (same field of view)."""
    return bench_model.with_camera_size(320, 256)


def fringe_stack(u: np.ndarray, patterns: PatternSet, extent: int, amplitude: float = 1200.0,
                 offset: float = 1500.0, noise: float = 0.0, seed: int = 0, bits: int = 12) -> np.ndarray:
    """Frames for projector coordinates `u` (H, W) along the coded axis, as the camera
    would see them (no blur), with Gaussian noise of `noise` DN."""
    rng = np.random.default_rng(seed)
    out = []
    for s in patterns.frames():
        profile = patterns.profile(s, extent)
        shown = np.interp(u, np.arange(extent), profile)
        img = offset + amplitude * (2 * shown - 1) + rng.normal(0, noise, u.shape) if noise else \
            offset + amplitude * (2 * shown - 1)
        out.append(np.clip(np.rint(img), 0, 2 ** bits - 1).astype(np.uint16))
    return np.stack(out)


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
