"""`slscan demo` end to end (acceptance: pytest -m acceptance -s tests/test_inspection_demo.py; the
default run's test_inspection_sim.py inspects the same scene):
the bundled part scanned on the simulated rig, inspected against config/parts/demo_part.step
with its part program config/parts/demo_part.toml, the per-face table printed, the report files in the
session's outputs and the inspection in the session's own recording."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from scanner.recording_reader import read_summary
from slscan import cli
from slscan.exit_codes import Exit

pytestmark = pytest.mark.acceptance


def test_demo_scans_and_inspects(tmp_path: Path, capsys) -> None:
    out = tmp_path / "demo"
    # the nominal part fails none of its tolerances; the boss's cylindricity is not measured: no decision
    assert cli.main(["demo", "--out", str(out)]) == Exit.NO_DECISION == 4
    text = capsys.readouterr().out
    assert "high top #657" in text and "flatness 50 conforming" in text
    assert "verdict not measured" in text  # the boss's side is grazing from above: its cylindricity is not measured
    data = json.loads((out / "outputs" / "inspection.json").read_text())
    rows = {r["label"]: r for r in data["faces"]}
    assert data["verdict"] == "not measured" and data["status"] == "no decision" and data["fitness"] > 0.95
    assert {r["label"] for r in data["faces"] if r.get("verdict_flatness") == "conforming"} == {"#657", "#158"}
    profile = rows["#657"]["profile_mm"] or rows["#657"]["profile_limit_mm"]  # nominal: usually below its limit
    assert rows["#657"]["deviation_source"] == "form surface" and profile < 0.03
    assert {"inspection.csv", "inspection.html"} <= {p.name for p in (out / "outputs").iterdir()}
    rec = read_summary(out / "recording.rrd")
    assert {"world/inspection/cad", "world/inspection/deviation", "world/inspection/faces",
            "inspection/deviation_map", "inspection/report"} <= set(rec.entity_paths)
