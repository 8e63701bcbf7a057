"""The operator loop on a small simulated bench: cycles, verdicts, storage, abort, re-scan,
refusal, the control charts and the report. The measuring step is the simulator's truth (`measure.SimulatorTruth`)
double (it reports the imposed defects), so these tests check the station, not a
measurement; measured verdicts are tested through the inspection adapter."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest
from station_support import DEMO_PROGRAM, program_copy, station_config

from scanner.errors import IncompleteSession
from scanner.recording_reader import read_component, read_summary
from scanner.session import ERROR, Session
from sim.station_parts import TRUTH_FILE, lineup
from slscan.station.app import StationRun, expected_status, open_station
from slscan.station.charts import control_metric
from slscan.station.loop import PART_RECORD, Refused
from slscan.station.measure import MeasurementResult, SimulatorTruth
from slscan.station.program import PartProgram
from slscan.station.station_config import StationConfig
from slscan.station.tui import StationTUI


@pytest.fixture
def config(tmp_path: Path) -> StationConfig:
    return StationConfig.load(station_config(tmp_path))


@pytest.fixture
def run(config: StationConfig) -> Iterator[StationRun]:
    with open_station(DEMO_PROGRAM, config, "ana", SimulatorTruth()) as r:
        yield r


def test_cycles_give_the_verdicts_of_the_imposed_defects_and_store_everything(run: StationRun) -> None:
    station = run.station
    assert station.refusals() == []
    outcomes = [station.run_cycle(f"SN-{k}", part=k) for k in range(3)]
    parts = lineup()
    assert [o.truth["name"] for o in outcomes] == [p.name for p in parts[:3]]  # nominal, bow150, bow20-lobe10
    assert [o.status for o in outcomes] == ["pass", "fail", "pass"]
    assert [o.status for o in outcomes] == [expected_status(run.program, o.truth) for o in outcomes]
    assert outcomes[1].message == "out of tolerance: high_top_flatness, high_top_profile"
    rows = run.store.results(program="demo-part")
    assert [(r.serial, r.status, r.attempt, r.operator) for r in rows] == [
        ("SN-0", "pass", 1, "ana"), ("SN-1", "fail", 1, "ana"), ("SN-2", "pass", 1, "ana")]
    assert {r.calibration_id for r in rows} == {"factory-sim-bench"}
    assert {r.measurement for r in rows} == {SimulatorTruth.name}
    values = run.store.values([r.id for r in rows])
    assert [(v.characteristic, v.value_mm, v.conforms) for v in values[rows[1].id]][:1] == [
        ("high_top_flatness", 0.15, False)]
    for o, r in zip(outcomes, rows):
        assert Path(r.part_path) == o.part_path and o.sessions == (o.part_path / "view0",)
        session = Session.open(o.sessions[0])  # complete: manifest written
        assert json.loads((session.root / TRUTH_FILE).read_text())["name"] == o.truth["name"]
        record = json.loads((o.part_path / PART_RECORD).read_text())
        assert (record["result_id"], record["status"], record["serial"]) == (r.id, r.status, r.serial)
        assert record["measurement_result"]["ok"] and record["calibration_id"] == "factory-sim-bench"
    s = station.stats()
    assert (s.parts, s.passed, s.failed, s.yield_percent) == (3, 2, 1, pytest.approx(200 / 3))
    flat = s.characteristics[0]
    assert flat.n == 3 and flat.max_mm == 0.15 and flat.mean_mm == pytest.approx(0.17 / 3)
    report = (run.report_dir / "report.html").read_text()
    assert "charts/high_top_flatness.png" in report and "SN-1" in report and "FAIL" in report
    assert (run.report_dir / "charts" / "low_top_flatness.png").stat().st_size > 1000
    run.close()
    chart = run.report_dir / "control_charts.rrd"
    entity = f"metrics/{control_metric('high_top_flatness', 'value_mm')}"
    assert "scan" in read_summary(chart).entities[entity].timelines
    series = read_component(chart, entity, "Scalars:scalars")
    assert [(t, float(v[0])) for t, v in series] == [(r.id, v) for r, v in zip(rows, (0.0, 0.15, 0.02))]


def test_abort_keeps_the_frames_stores_the_cycle_and_a_rescan_is_a_new_attempt(run: StationRun) -> None:
    cancel = threading.Event()

    def progress(stage: str, done: int, total: int) -> None:
        if stage == "capture" and done == 4:
            cancel.set()  # the operator presses abort during the capture

    aborted = run.station.run_cycle("SN-9", part=1, cancel=cancel, progress=progress)
    assert aborted.status == "aborted" and "aborted by the operator during capture" in aborted.message
    view = aborted.sessions[0]
    with pytest.raises(IncompleteSession, match="5 raw frame"):  # the abort takes effect at the next frame
        Session.open(view)
    assert json.loads((view / ERROR).read_text())["error"] == "OperatorAbort"
    again = run.station.run_cycle("SN-9", part=1)
    assert (again.status, again.attempt) == ("fail", 2)
    rows = run.store.results(serial="SN-9")
    assert [(r.attempt, r.status) for r in rows] == [(1, "aborted"), (2, "fail")]
    assert run.store.values([rows[0].id]) == {rows[0].id: []}
    assert run.station.stats().parts == 1  # statistics count the part once, by its last cycle


def test_mismatched_calibration_is_refused_before_anything_is_scanned(tmp_path: Path, config: StationConfig) -> None:
    program = program_copy(tmp_path, ('id = "factory-sim-bench"', 'id = "cal-2026-10-01"'))
    with open_station(program, config, "ana", SimulatorTruth()) as r:
        with pytest.raises(Refused, match="calibration mismatch: program.toml expects calibration.id 'cal-2026-10-01'"):
            r.station.run_cycle("SN-1")
        assert r.store.results() == [] and not config.sessions_dir.exists()


class Unmeasurable(SimulatorTruth):
    """Test double: the part cannot be registered."""

    name = "unmeasurable (test double)"

    def measure(self, sessions: Sequence[Session], program: PartProgram) -> MeasurementResult:
        return MeasurementResult(False, message="registration failed: fitness 0.12 below 0.5")


class Unavailable(SimulatorTruth):
    name = "missing (test double)"

    def unavailable(self) -> str | None:
        return "inspection.report has no function inspect_session() yet"


def test_a_part_that_cannot_be_measured_is_stored_as_error_never_as_a_number(config: StationConfig) -> None:
    with open_station(DEMO_PROGRAM, config, "ana", Unmeasurable()) as r:
        o = r.station.run_cycle("SN-1")
        assert o.status == "error" and o.values == ()
        assert o.message == "not measured: registration failed: fitness 0.12 below 0.5"
        record = json.loads((o.part_path / PART_RECORD).read_text())["measurement_result"]
        assert record == {"ok": False, "message": "registration failed: fitness 0.12 below 0.5", "details": {},
                          "values": [], "report_paths": []}
        assert r.store.results()[0].status == "error"


def test_an_unavailable_measuring_step_refuses_to_measure(config: StationConfig) -> None:
    with (open_station(DEMO_PROGRAM, config, "ana", Unavailable()) as r,
          pytest.raises(Refused, match=r"measuring step \(missing \(test double\)\) unavailable")):
        r.station.run_cycle("SN-1")


def test_foot_switch_on_the_trigger_box_input_starts_one_scan_per_press(run: StationRun) -> None:
    """The foot switch on the simulated trigger box's input starts a scan in the operator
    loop when it is READY; a press while a scan runs starts nothing afterwards."""
    tui = StationTUI(run, max_parts=1)
    tui.state.serial = "SN-7"
    assert not tui.tick(-1) and tui.worker is None  # nothing pressed: nothing scanned
    stored = run.station.on_stored
    run.station.on_stored = lambda o: (run.bench.switch.press(), stored(o))  # pressed again during the scan
    run.bench.switch.press()
    assert not tui.tick(-1) and tui.busy()
    tui.worker.join()
    assert tui.tick(-1) and tui.worker is not None and not tui.busy()  # one part measured: the run is over
    rows = run.store.results()
    assert [(r.serial, r.attempt, r.status) for r in rows] == [("SN-7", 1, "pass")]
    run.station.on_stored = stored
    run.bench.switch.press()  # the next press: the same serial again, a new attempt
    tui.tick(-1)
    tui.worker.join()
    assert [(r.serial, r.attempt) for r in run.store.results()] == [("SN-7", 1), ("SN-7", 2)]


def test_a_program_with_two_views_scans_the_part_twice_turned(tmp_path: Path, config: StationConfig) -> None:
    program = program_copy(tmp_path, ("views = 1", "views = 2"))
    steps: list[str] = []
    with open_station(program, config, "ana", SimulatorTruth()) as r:
        o = r.station.run_cycle("SN-1", part=1, progress=lambda stage, done, total: steps.append(stage))
    assert o.status == "fail" and o.sessions == (o.part_path / "view0", o.part_path / "view1")
    truths = [json.loads((Session.open(s).root / TRUTH_FILE).read_text()) for s in o.sessions]
    assert [(t["name"], t["view"]) for t in truths] == [("bow150", 0), ("bow150", 1)]
    assert "capture (view 1/2)" in steps and "capture (view 2/2)" in steps


def test_a_second_station_on_the_same_config_leaves_the_running_cycle_alone(tmp_path: Path) -> None:
    """Issue 15 item 10: starting a second station that shares the station config, while
    the first is in the middle of a cycle, marked that cycle incomplete."""
    config = StationConfig.load(station_config(tmp_path))
    seen: dict[str, object] = {}

    def start_second(stage: str, done: int, total: int) -> None:
        if stage == "capture" and done == 2 and "second" not in seen:
            with open_station(DEMO_PROGRAM, config, "ben", SimulatorTruth()) as second:
                seen["second"] = second.recovered
                seen["status"] = [r.status for r in second.store.results()]

    with open_station(DEMO_PROGRAM, config, "ana", SimulatorTruth()) as first:
        outcome = first.station.run_cycle("SN-1", progress=start_second)
        rows = first.store.results()
    assert seen == {"second": [], "status": ["in_progress"]}
    assert outcome.status == "pass" and [(r.serial, r.status) for r in rows] == [("SN-1", "pass")]
