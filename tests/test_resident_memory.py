"""Per-stage peak resident memory (slscan/resident_memory.py) against arrays of known size."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slscan.resident_memory import StagePeaks, release_memory, resident_mib

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self")


def _big_then_small(peaks: StagePeaks) -> float:
    """Run a stage touching 200 MiB, then one allocating nothing; the resident set before (MiB)."""
    release_memory()
    before = resident_mib()
    with peaks.stage("big"):
        block = np.ones(200 * 2 ** 20 // 8)  # 200 MiB, every page touched
        del block
    with peaks.stage("small"):
        pass
    return before


def test_each_stage_reports_its_own_peak_or_says_it_cannot() -> None:
    """Where the kernel resets the high-water mark, a stage touching 200 MiB peaks at least that
    above the resident set before it and the next stage, allocating nothing, peaks below it; where
    it does not (CI's sandbox), both stages are "not measured" with the reason, never the run's peak
    under a stage's name. Run in a process of its own: in a test worker, threads left by other
    tests allocate too, and the resident set is the process's."""
    run = subprocess.run([sys.executable, __file__], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1])
    out = json.loads(run.stdout.splitlines()[-1])
    if out["not_measured"] is None:
        big, small = out["peaks"]["big"], out["peaks"]["small"]
        assert big is not None and small is not None
        assert big >= out["before"] + 190
        assert small < big - 150
    else:
        assert out["peaks"] == {"big": None, "small": None}
        assert "high-water mark" in out["not_measured"]


def test_a_reset_that_does_not_take_is_not_measured(tmp_path: Path) -> None:
    """A clear_refs that accepts the write but resets nothing (a plain file here): the probe's
    freed block stays in the high-water mark, so no stage is measured."""
    peaks = StagePeaks(clear_refs=tmp_path / "clear_refs")
    _big_then_small(peaks)
    assert peaks.peaks == {"big": None, "small": None}
    assert peaks.not_measured is not None and "does not reset it" in peaks.not_measured


def test_a_resident_set_that_never_falls_is_not_measured(tmp_path: Path) -> None:
    """CI's sandbox: VmRSS and VmHWM read equal and do not fall when memory is freed, so the
    high-water mark always "equals the resident set" yet holds the run's peak. The probe sees no
    fall after freeing its block and no stage is measured."""
    status = tmp_path / "status"
    status.write_text("VmHWM:\t 2286592 kB\nVmRSS:\t 2286592 kB\n")  # 2233 MiB, as CI printed
    peaks = StagePeaks(clear_refs=tmp_path / "clear_refs", status=status)
    _big_then_small(peaks)
    assert peaks.peaks == {"big": None, "small": None}
    assert peaks.not_measured is not None and "2233 to 2233 MiB" in peaks.not_measured


def test_a_reset_refused_is_not_measured(tmp_path: Path) -> None:
    """A clear_refs that cannot be written names the file and the error."""
    peaks = StagePeaks(clear_refs=tmp_path / "missing" / "clear_refs")
    with peaks.stage("any"):
        pass
    assert peaks.peaks == {"any": None}
    assert peaks.not_measured is not None and "clear_refs" in peaks.not_measured


if __name__ == "__main__":  # the stages alone in this process (test_each_stage_reports_its_own_peak_or_says_it_cannot)
    alone = StagePeaks()
    before = _big_then_small(alone)
    print(json.dumps({"before": before, "peaks": alone.peaks, "not_measured": alone.not_measured}))
