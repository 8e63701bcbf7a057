"""Per-stage peak resident memory (slscan/resident_memory.py) against arrays of known size."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from slscan.resident_memory import StagePeaks, release_memory, resident_mib

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self")


def test_each_stage_reports_its_own_peak() -> None:
    """A stage touching 200 MiB peaks at least that above the resident set before it; the next
    stage, allocating nothing, peaks below that stage's peak (the high-water mark was reset)."""
    peaks = StagePeaks()
    release_memory()
    before = resident_mib()
    with peaks.stage("big"):
        block = np.ones(200 * 2 ** 20 // 8)  # 200 MiB, every page touched
        del block
    with peaks.stage("small"):
        pass
    assert peaks.peaks["big"] >= before + 190
    assert peaks.peaks["small"] < peaks.peaks["big"] - 150
