"""`slscan station --auto` and `slscan results` (query, CSV, HTML report) as the operator's
shell sees them, including a station killed (SIGKILL) or interrupted (SIGINT) in the
middle of a scan. The station
config measures with the simulator's truth (`measure.SimulatorTruth`) (see test_station_support.py)."""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_station_support import DEMO_PROGRAM, station_config

from scanner.errors import IncompleteSession
from scanner.session import ERROR, Session
from slscan.station.results import open_results
from slscan.station.station_config import StationConfig

TESTS = Path(__file__).resolve().parent


def slscan(*args: str, **kw: object) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-m", "slscan.cli", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)  # type: ignore[call-overload]


def wait_for_frames(folder: Path, serial_suffix: str, n: int, proc: subprocess.Popen, timeout_s: float = 60) -> Path:
    """The view0 session of the part whose serial ends in `serial_suffix`, once it holds `n` frames."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        assert proc.poll() is None, proc.communicate()
        for view in folder.glob(f"*{serial_suffix}-*/view0"):
            if len(list((view / "frames").glob("frame_*.png"))) >= n:
                return view
        time.sleep(0.005)
    raise AssertionError(f"no session of part {serial_suffix} reached {n} frames")


def test_killed_mid_scan_loses_no_result_and_leaves_the_session_incomplete(tmp_path: Path) -> None:
    cfg = station_config(tmp_path)
    config = StationConfig.load(cfg)
    proc = slscan("station", str(DEMO_PROGRAM), "--config", str(cfg), "--parts", "5", "--auto", "--operator", "ana")
    view = wait_for_frames(config.sessions_dir / "demo-part", "-003", 3, proc)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)
    with open_results(config.database_url) as store:
        rows = store.results()
        assert [(r.serial[-3:], r.status) for r in rows] == [("001", "pass"), ("002", "fail"), ("003", "in_progress")]
        assert all(store.values([r.id])[r.id] for r in rows[:2])
    with pytest.raises(IncompleteSession, match="no error recorded"):  # killed: no chance to write error.json
        Session.open(view)
    for r in rows[:2]:
        assert Session.open(Path(r.part_path) / "view0").id  # the stored parts' sessions are complete

    out, err = slscan("station", str(DEMO_PROGRAM), "--config", str(cfg), "--parts", "1", "--auto").communicate(
        timeout=120)
    assert f"recovered    results [{rows[2].id}]" in out, err
    assert "part 1/1" in out and "verdicts agreeing with the imposed defects: 1/1" in out
    with open_results(config.database_url) as store:
        after = store.results()
        assert [r.status for r in after] == ["pass", "fail", "incomplete", "pass"]
        assert after[2].message.startswith("the station stopped during this cycle")

    out, err = slscan("results", "--config", str(cfg), "--csv", "-").communicate(timeout=60)
    lines = list(csv.DictReader(io.StringIO(out)))
    assert [x["status"] for x in lines if x["characteristic"] in ("", "high_top_flatness")] == [
        "pass", "fail", "incomplete", "pass"]
    assert {x["operator"] for x in lines} == {"ana", ""}
    out, err = slscan("results", "--config", str(cfg), "--status", "fail").communicate(timeout=60)
    assert "high_top_flatness=0.1500" in out and "1 results in" in err
    report = tmp_path / "report"
    out, err = slscan("results", "--config", str(cfg), "--program", str(DEMO_PROGRAM), "--report",
                      str(report)).communicate(timeout=60)
    assert f"report {report / 'report.html'}" in err
    html = (report / "report.html").read_text()
    assert html.count("<img src='charts/") == 5 and "3 parts (last cycle per serial): 2 pass, 1 fail" in html


def test_interrupted_mid_scan_stores_the_cycle_as_aborted(tmp_path: Path) -> None:
    cfg = station_config(tmp_path)
    config = StationConfig.load(cfg)
    proc = slscan("station", str(DEMO_PROGRAM), "--config", str(cfg), "--parts", "3", "--auto")
    view = wait_for_frames(config.sessions_dir / "demo-part", "-001", 3, proc)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and "interrupted" in err
    with open_results(config.database_url) as store:
        [row] = store.results()
        assert row.status == "aborted" and row.message.startswith("interrupted (Ctrl-C)")
    assert json.loads((view / ERROR).read_text())["error"] == "KeyboardInterrupt"
    with pytest.raises(IncompleteSession):
        Session.open(view)
