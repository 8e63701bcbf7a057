"""Batch re-inspection of stored parts, serially and on a local Dask cluster started by the
test (2 in-process workers): the same results either way, per-part failures reported
without stopping the batch. The measuring step is the simulator's truth (`measure.SimulatorTruth`)."""

from __future__ import annotations

import importlib.util
import json
import threading
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from station_support import DEMO_PROGRAM, TRUTH_GAUGE, station_config

from scanner.pointcloud import read_ply_points
from scanner.rig import DEFAULT_RIG, RigConfig
from slscan import cli
from slscan.station.app import open_station
from slscan.station.batch import compare, part_sessions, run_batch
from slscan.station.measure import SimulatorTruth
from slscan.station.results import open_results
from slscan.station.station_config import StationConfig


@pytest.fixture(scope="module")
def stored(tmp_path_factory: pytest.TempPathFactory) -> tuple[StationConfig, list[Path]]:
    """Three measured parts (nominal, 150 um bow, 10 um lobing) and one aborted mid-capture."""
    folder = tmp_path_factory.mktemp("batch")
    config = StationConfig.load(station_config(folder))
    with open_station(DEMO_PROGRAM, config, "ana", SimulatorTruth()) as run:
        parts = [run.station.run_cycle(f"SN-{k}", part=k).part_path for k in range(3)]
        cancel = threading.Event()
        aborted = run.station.run_cycle("SN-X", part=3, cancel=cancel,
                                        progress=lambda stage, done, total: cancel.set() if done == 2 else None)
    assert aborted.status == "aborted"
    return config, parts + [aborted.part_path]


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    if importlib.util.find_spec("distributed") is None:
        pytest.skip("Dask is not installed: the [batch] extra (pip install -e '.[batch]') runs this test")
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        yield cluster.scheduler_address


def test_dask_batch_gives_the_serial_results_and_reports_failures_without_stopping(
        stored: tuple[StationConfig, list[Path]], scheduler: str) -> None:
    _config, parts = stored
    serial = run_batch(parts, DEMO_PROGRAM, workers=0, measurement=TRUTH_GAUGE)
    seen: list[tuple[int, int]] = []
    dask = run_batch(parts, DEMO_PROGRAM, scheduler=scheduler, measurement=TRUTH_GAUGE,
                     progress=lambda stage, done, total: seen.append((done, total)))
    assert seen == [(k, 4) for k in range(1, 5)]
    assert dask.where.startswith("dask ") and "(2 workers)" in dask.where and serial.where == "serial, this process"
    assert [i.status for i in serial.items] == ["pass", "fail", "pass", "error"]
    assert [(i.path, i.status, i.serial, i.values) for i in dask.items] == \
           [(i.path, i.status, i.serial, i.values) for i in serial.items]
    assert {i.worker for i in dask.items[:3]} <= {0, 1, "0", "1"} and {i.worker for i in serial.items} == {"local"}
    [failed] = dask.failures
    assert failed.path == str(parts[3]) and failed.serial == "SN-X"
    assert "IncompleteSession" in failed.message and "no manifest.json" in failed.message
    assert dask.items[1].truth["name"] == "bow150"
    assert dask.items[1].message == "out of tolerance: high_top_flatness, high_top_profile"
    assert compare(serial, dask) == ([], 0.0, "")
    nudged = replace(dask.items[1], values=tuple(replace(v, value_mm=v.value_mm + 0.001) for v in dask.items[1].values))
    other = replace(dask, items=[dask.items[0], nudged, replace(dask.items[2], status="fail"), dask.items[3]])
    differ, worst, where = compare(serial, other)
    assert worst == pytest.approx(0.001) and where.startswith(f"{serial.items[1].serial} ")
    assert len(differ) == 1 and differ[0].startswith(f"{parts[2]}: pass")


def test_batch_regenerates_the_outputs_from_the_raw_frames(stored: tuple[StationConfig, list[Path]]) -> None:
    _, parts = stored
    cloud = part_sessions(parts[0])[0] / "outputs" / "cloud.ply"
    cloud.unlink()
    [item] = run_batch(parts[:1], DEMO_PROGRAM, workers=0, measurement=TRUTH_GAUGE).items
    assert item.status == "pass" and cloud.stat().st_size > 0


def test_batch_command_stores_results_and_prints_a_summary(stored: tuple[StationConfig, list[Path]], scheduler: str,
                                                           capsys: pytest.CaptureFixture) -> None:
    config, parts = stored
    code = cli.main(["batch", *map(str, parts), "--program", str(DEMO_PROGRAM), "--scheduler", scheduler, "--store",
                     "--config", str(config.path), "--measurement", TRUTH_GAUGE, "--json"])
    assert code == 1  # one part failed
    summary = json.loads(capsys.readouterr().out)
    assert summary["counts"] == {"pass": 2, "fail": 1, "uncertain": 0, "error": 1} and len(summary["items"]) == 4
    assert summary["status"] == "failed"  # what the exit code says
    with open_results(config.database_url) as store:
        batch = [r for r in store.results() if r.source == "batch"]
        assert [(r.serial, r.status, r.operator) for r in batch] == [
            ("SN-0", "pass", "batch"), ("SN-1", "fail", "batch"), ("SN-2", "pass", "batch"), ("SN-X", "error", "batch")]
        assert [v.value_mm for v in store.values([batch[1].id])[batch[1].id]][:1] == [0.15]


def test_batch_reconstructs_with_the_rig_given_and_its_calibration(stored: tuple[StationConfig, list[Path]],
                                                                   tmp_path: Path) -> None:
    from scanner.calibration_file import write_calibration

    config, parts = stored
    cloud = part_sessions(parts[0])[0] / "outputs" / "cloud.ply"
    captured = read_ply_points(cloud)
    rig = RigConfig.load(config.rig_path)
    moved = rig.nominal_model()
    shifted = moved.cam_from_proj.copy()
    shifted[0, 3] += 2.0  # a calibration that puts the projector 2 mm further right
    write_calibration(tmp_path / "cal.json", replace(moved, cam_from_proj=shifted), {}, "sim-bench")
    recal = tmp_path / "rig.toml"
    calibration = tmp_path / "cal.json"
    recal.write_text(config.rig_path.read_text().replace("[rig]\n", f'[rig]\ncalibration = "{calibration}"\n'))
    [item] = run_batch(parts[:1], DEMO_PROGRAM, workers=0, measurement=TRUTH_GAUGE, rig_path=recal).items
    assert item.status == "pass" and item.calibration_id.startswith("sim-bench@")
    again = read_ply_points(cloud)
    assert len(again) == len(captured) and np.median(again[:, 2] - captured[:, 2]) > 1.0  # a longer baseline
    [item] = run_batch(parts[:1], DEMO_PROGRAM, workers=0, measurement=TRUTH_GAUGE).items
    assert item.calibration_id == "factory-sim-bench" and np.array_equal(read_ply_points(cloud), captured)
    [bad] = run_batch(parts[:1], DEMO_PROGRAM, workers=0, measurement=TRUTH_GAUGE, rig_path=DEFAULT_RIG).items
    assert bad.status == "error" and "captured with a (320, 256) camera" in bad.message
