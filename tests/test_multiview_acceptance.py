"""Issue 13's acceptance figures (slow; run on purpose: pytest -m slow tests/test_multiview_acceptance.py -s):
`slscan bench views` on the simulated turntable, demo part, 8 views at 1280 x 1024. Thresholds are
what the method delivers with margin, checked against the simulator's truth; the figures are
printed (and written to viewbench.json in the run's folder)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from slscan import cli

pytestmark = [pytest.mark.slow, pytest.mark.acceptance]


def test_whole_part_acceptance(tmp_path: Path) -> None:
    assert cli.main(["bench", "views", "--out", str(tmp_path), "--views", "8"]) == 0
    f = json.loads((tmp_path / "viewbench.json").read_text())
    for key in ("alignment", "alignment_axis_error"):  # with and without a stage-axis calibration error
        assert f[key]["max_deg"] < 0.02 and f[key]["max_mm"] < 0.05, (key, f[key])
    assert f["alignment_axis_error"]["prior_max_deg"] > 0.5  # the prior was off: the refinement corrected it
    assert f["coverage"]["area_share"] > 0.6  # the base stands on the platter: no view sees it
    assert f["noise"]["merged_rms_mm"] < f["noise"]["single_view_rms_mm"]
    assert f["form"]["faces"]["#17"]["points"] > 10000  # the boss, all round
    for apart in ("45 deg", "90 deg", "135 deg"):
        assert f["pairs"][apart]["ours"]["wrong"] == 0  # found or refused, never silently wrong
    assert f["pairs"]["45 deg"]["ours"]["found"] == 8
