"""Issue 32: stations that stop, crash and share. Run as the bench runs them (separate
processes, a 320 x 256 simulated rig, the simulator's truth as the measuring step):

- two stations on one data folder and one database at once: every cycle stored once with a
  final status, its part.json agreeing with its row, the control charts holding every part
  of both (whichever station closed last);
- a station killed at a random moment and restarted: no row left `in_progress`, the killed
  cycle `incomplete` with a message that says what its part folder really holds (checked
  here against the folder), every other row final with its part.json;
- a station stopped by SIGTERM: its cycle `aborted`, the session kept, exit code 130.

Slow (each runs the station for tens of seconds): `pytest -m slow tests/test_hostile_station.py`."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hostile import campaign_seed
from session_support import small_rig_toml
from store_opener import open_store

from scanner.config import CONFIG_DIR

REPO = Path(__file__).resolve().parents[1]
PROGRAM = str(CONFIG_DIR / "parts" / "demo_part.toml")


@pytest.fixture
def bench(tmp_path: Path) -> Path:
    """A station config on a 320 x 256 simulated bench rig, measuring by the simulator's truth."""
    station = (CONFIG_DIR / "station" / "sim_bench.toml").read_text().replace(
        'rig = "../rigs/sim_bench.toml"', f'rig = "{small_rig_toml(tmp_path)}"').replace(
        'measurement = "inspection"', 'measurement = "simulator-truth"')
    (tmp_path / "station.toml").write_text(station)
    return tmp_path / "station.toml"


def start(config: Path, data: Path, parts: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "slscan", "station", PROGRAM, "--auto", "--parts", str(parts),
                             "--config", str(config), "--out", str(data)], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(REPO)})


def rows(data: Path) -> list[dict]:
    if not (data / "results.sqlite").exists():
        return []  # killed before the station opened its database
    with sqlite3.connect(data / "results.sqlite") as db:
        db.row_factory = sqlite3.Row
        return [dict(r) for r in db.execute("select * from results order by id")]


def folder_state(part: Path) -> str:
    """What a part folder holds, judged here from its files (not by the code under test):
    "complete" (manifest), "all frames" (every frame logged, no manifest), "frames n/12",
    "none" (no session)."""
    views = sorted(p for p in part.iterdir() if p.is_dir()) if part.is_dir() else []
    if not views:
        return "none"
    view = views[0]
    if (view / "manifest.json").exists():
        return "complete"
    log = view / "frames.jsonl"
    n = sum(1 for line in log.read_text().splitlines() if line.endswith("}")) if log.exists() else 0
    return "all frames" if n == 12 else f"frames {n}/12"


def check_consistent(data: Path) -> list[dict]:
    """No row in progress; a final row's part.json agrees with it; an incomplete row's message
    says what its folder holds."""
    stored = rows(data)
    for r in stored:
        assert r["status"] != "in_progress", r
        part = Path(r["part_path"])
        if r["status"] == "incomplete":
            state = folder_state(part)
            expect = ({"complete": "complete", "all frames": "decode --recover", "none": "no session was started",
                       "frames 0/12": "no frame stored"}.get(state)
                      or f"{state[7:].split('/')[0]} of 12 frames, no manifest")
            assert expect in r["message"], (state, r["message"])
            assert not (part / "part.json").exists()
        else:
            record = json.loads((part / "part.json").read_text())
            assert record["result_id"] == r["id"] and record["status"] == r["status"], (record, r)
    return stored


@pytest.mark.slow
def test_two_stations_share_a_folder_and_a_database(bench: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    procs = [start(bench, data, 2) for _ in range(2)]
    outcomes = [(p.wait(600), p.stderr.read()) for p in procs]  # type: ignore[union-attr]
    for code, err in outcomes:
        assert code in (0, 1) and "Traceback" not in err, err
    stored = check_consistent(data)
    assert len(stored) == 4 and len({(r["serial"], r["attempt"]) for r in stored}) == 4
    assert all(r["status"] in ("pass", "fail", "uncertain") for r in stored)
    from scanner.recording_reader import read_summary

    charts = read_summary(data / "reports" / "demo-part" / "control_charts.rrd").entities
    per_part = max(e.rows for name, e in charts.items() if name.endswith("value_mm"))
    assert per_part == 4, {k: v.rows for k, v in charts.items()}  # every part of both stations
    assert not list((data / "reports" / "demo-part").glob("control_charts.*.rrd"))  # the own files merged


@pytest.mark.slow
def test_a_station_killed_at_random_moments_and_restarted(bench: Path, tmp_path: Path, capsys) -> None:
    rng = np.random.default_rng(seed := campaign_seed())
    data = tmp_path / "data"
    seen = []
    for after in rng.uniform(3.0, 30.0, 4):
        p = start(bench, data, 1)
        try:
            p.wait(float(after))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(30)
        stored = rows(data)
        seen.append(f"{after:.1f} s: {stored[-1]['status'] if stored else 'no row'}")
    last = start(bench, data, 1)  # the restart: marks what the kills left, measures one more part
    assert last.wait(600) in (0, 1), last.stderr.read()  # type: ignore[union-attr]
    stored = check_consistent(data)
    with capsys.disabled():
        print(f"\nstation killed at (seed {seed}): {'; '.join(seen)}; after the restart: "
              f"{[(r['id'], r['status']) for r in stored]}")


@pytest.mark.slow
def test_sigterm_marks_the_cycle_aborted_and_keeps_the_session(bench: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    p = start(bench, data, 1)
    deadline = time.monotonic() + 120
    while not list(data.glob("sessions/*/*/view0/frames/frame_003.png")):
        assert time.monotonic() < deadline and p.poll() is None
        time.sleep(0.05)
    p.send_signal(signal.SIGTERM)
    code = p.wait(60)
    err = p.stderr.read()  # type: ignore[union-attr]
    assert code == 130 and "Traceback" not in err, err
    (row,) = rows(data)
    assert row["status"] == "aborted" and row["message"].startswith("terminated (SIGTERM)")
    frames = list(Path(row["part_path"]).glob("view0/frames/frame_*.png"))
    assert len(frames) >= 4 and json.loads((Path(row["part_path"]) / "part.json").read_text())["status"] == "aborted"


@pytest.mark.slow
def test_a_station_on_a_full_disk_stops_with_one_line(bench: Path, tmp_path: Path) -> None:
    """Sessions on a 3 MB tmpfs, the database beside it: the cycle is stored as an error
    naming the full disk, the station stops at once with one line and exit 2, the frames
    captured are kept whole."""
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(disk)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({mounted.stderr.decode().strip()})")
    try:
        p = subprocess.Popen([sys.executable, "-m", "slscan", "station", PROGRAM, "--auto", "--parts", "3", "--config",
                              str(bench), "--out", str(disk / "data"), "--db", f"sqlite:{tmp_path / 'results.sqlite'}"],
                             cwd=REPO, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             env={**os.environ, "PYTHONPATH": str(REPO)})
        code = p.wait(300)
        err = p.stderr.read()  # type: ignore[union-attr]
        errors = [ln for ln in err.splitlines() if "error" in ln.lower()]
        assert code == 2 and len(errors) == 1 and "No space left on device" in errors[0], err
        with sqlite3.connect(tmp_path / "results.sqlite") as db:
            statuses = [r[0] for r in db.execute("select status from results")]
        assert statuses and statuses[-1] == "error" and "in_progress" not in statuses
        from scanner.session import sha256

        for log in disk.glob("data/sessions/*/*/view0/frames.jsonl"):
            for line in log.read_text().splitlines():
                entry = json.loads(line)
                assert sha256((log.parent / entry["file"]).read_bytes()) == entry["sha256"]
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_stations_opening_one_new_database_at_once_make_one_schema(tmp_path: Path) -> None:
    """Four processes open one new SQLite results database at the same moment, five times:
    every one opens it, and it holds one schema version (they had both found it empty and
    written two, or failed with 'table measured already exists')."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    for trial in range(5):
        path = tmp_path / f"r{trial}.sqlite"
        results = ctx.Queue()
        procs = [ctx.Process(target=open_store, args=(str(path), results)) for _ in range(4)]
        for p in procs:
            p.start()
        for p in procs:
            p.join(120)
        said = [results.get(timeout=10) for _ in procs]
        with sqlite3.connect(path) as db:
            versions = db.execute("select count(*) from slscan_schema").fetchone()[0]
        assert said == ["ok"] * 4 and versions == 1, (said, versions)
