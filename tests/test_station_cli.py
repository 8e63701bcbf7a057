"""`slscan station --auto` and `slscan results` (query, CSV, HTML report) as the operator's
shell sees them, including a station killed (SIGKILL) or interrupted (SIGINT) in the
middle of a scan. The station
config measures with the simulator's truth (`measure.SimulatorTruth`) (see station_support.py)."""

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
from station_support import DEMO_PROGRAM, program_copy, station_config

from scanner.errors import IncompleteSession
from scanner.session import ERROR, Session
from slscan.station.results import open_results
from slscan.station.station_config import StationConfig

TESTS = Path(__file__).resolve().parent


def _ctrl_c_delivered() -> None:
    """In the child before it runs: SIGINT at its default, as for a job in the foreground of a
    terminal. A test run started in the background by a script inherits SIGINT ignored (POSIX:
    `cmd &` without job control), and Python then keeps ignoring it, rightly."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def slscan(*args: str, **kw: object) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-m", "slscan.cli", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_ctrl_c_delivered,
                            **kw)  # type: ignore[call-overload]


def wait_for_frames(folder: Path, serial_suffix: str, n: int, proc: subprocess.Popen, timeout_s: float = 600) -> Path:
    """The view0 session of the part whose serial ends in `serial_suffix`, once it holds `n` frames.
    The bound is a liveness bound, not a speed claim: on a loaded 2-core machine the parts
    before it (scan, inspection, charts) took over 60 s."""
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
    # liveness: storing the aborted cycle and its charts took 10-30 s at load 20-40
    _out, err = proc.communicate(timeout=300)
    assert proc.returncode == 130 and "interrupted" in err, err[-3000:]
    with open_results(config.database_url) as store:
        [row] = store.results()
        assert row.status == "aborted" and row.message.startswith("interrupted (Ctrl-C)")
    assert json.loads((view / ERROR).read_text())["error"] == "KeyboardInterrupt"
    with pytest.raises(IncompleteSession):
        Session.open(view)


def _one_line_error(capsys: pytest.CaptureFixture[str], *args: str) -> str:
    """Run `slscan args` in this process; it must end with exit 2 and a one-line error."""
    from slscan import cli

    assert cli.main(list(args)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_unwritable_or_missing_places_are_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 15 item 8: a data folder that cannot be written (/proc refuses new folders even
    to root; a file standing where a folder must be), an impossible --db, and `results` on a
    mistyped folder: one line each, and nothing created."""
    cfg = str(station_config(tmp_path))
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    station = ("station", str(DEMO_PROGRAM), "--config", cfg, "--auto", "--parts", "1")
    assert "cannot create the results folder" in _one_line_error(capsys, *station, "--out", "/proc/slscan-test")
    assert "a_file" in _one_line_error(capsys, *station, "--out", str(a_file / "data"))
    err = _one_line_error(capsys, *station, "--out", "/proc/slscan-test", "--db", f"sqlite:{tmp_path / 'r.sqlite'}")
    assert "/proc/slscan-test" in err and "must be writable" in err
    assert "no results database there" in _one_line_error(capsys, "results", "--config", cfg, "--db",
                                                          "sqlite:/proc/x/y.sqlite")
    mistyped = tmp_path / "mistyped"
    assert "no results database there" in _one_line_error(capsys, "results", "--config", cfg, "--data", str(mistyped))
    assert not mistyped.exists()


def test_results_refuses_a_negative_limit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from slscan import cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["results", "--config", str(station_config(tmp_path)), "--limit", "-1"])
    assert exc.value.code == 2 and "must be >= 0, got -1" in capsys.readouterr().err


def test_names_from_programs_never_write_outside_their_folder(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 15 item 9: a program named '../../evil' and a characteristic named
    '../../../escaped_chart' made `results --report` write outside the report folder."""
    import datetime as dt

    from slscan import cli
    from slscan.station.program import load_program
    from slscan.station.results import PartStart, ValueRecord

    program_path = program_copy(tmp_path, ('name = "high_top_flatness"', 'name = "../../../escaped_chart"'),
                                name='"../../evil"')
    program = load_program(program_path)
    (tmp_path / "station").mkdir()
    cfg = station_config(tmp_path / "station")
    config = StationConfig.load(cfg)
    t0 = dt.datetime(2026, 11, 23, tzinfo=dt.UTC)
    with open_results(config.database_url) as store:
        for k in range(3):
            rid, _ = store.begin_part(PartStart(program.name, "1", "x", f"SN-{k}", "ana", "b", "r", None, "0", "m",
                                                "/p", t0 + dt.timedelta(minutes=k)))
            store.finish_part(rid, "pass", "", [ValueRecord(c.name, c.kind, c.face, 0.01 + 0.001 * k, c.tolerance_mm,
                                                            True, 10) for c in program.characteristics], t0)
    before = set(tmp_path.rglob("*"))
    report = tmp_path / "deep" / "er" / "report"
    assert cli.main(["results", "--config", str(cfg), "--program", str(program_path), "--report", str(report)]) == 0
    new = set(tmp_path.rglob("*")) - before
    outside = [p for p in new if p != report and report not in p.parents and p not in report.parents
               and not p.name.endswith(("-wal", "-shm"))]  # SQLite's side files of a WAL database being read
    assert new and not outside, outside
    charts = sorted(p.name for p in (report / "charts").iterdir())
    assert len(charts) == len(program.characteristics) and any("escaped_chart-" in n for n in charts)
    assert not list(tmp_path.rglob("escaped_chart.png"))

    from slscan.station.paths import safe_name

    assert [safe_name(n).split("-")[0] for n in ("..", ".", "../x")] == ["_", "_", "_x"]
    assert safe_name("SN-0042") == "SN-0042" and safe_name("a/b") != safe_name("a_b")
