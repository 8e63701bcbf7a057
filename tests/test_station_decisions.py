"""The station's ISO 14253-1 decisions (issue 12): every characteristic decided with its U
and detection limit under the program's rule, the part's verdict from them (uncertain is
neither pass nor fail), and what the station stores, writes and shows.

Independent truths: the guard-banded rule written out here (`iso_14253`); on the
simulator, the simulated part's true defect (a closed form of the imposed bow) against part
programs whose tolerance it violates by a known amount, clears by much more than U, or
equals (acceptance: a full-resolution scan and inspection)."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from station_support import DEMO_PROGRAM, face_row, program_copy, station_config

from inspection.tolerances import GUARD_BANDED
from inspection.uncertainty import Estimate, K
from scanner.config import CONFIG_DIR
from scanner.errors import ConfigError
from scanner.session import Session
from sim.parts_demo import PLATE_X, PLATE_Y, STEP_X
from sim.station_parts import TRUTH_FILE
from slscan.station.app import open_station, outcome_lines
from slscan.station.history_report import write_report
from slscan.station.loop import PART_RECORD
from slscan.station.measure import REPORT_FILE, MeasuredValue, MeasurementResult, SimulatorTruth, _pick, view_decisions
from slscan.station.program import Characteristic, PartProgram, load_program, program_tolerances
from slscan.station.quality import judge, running_stats
from slscan.station.station_config import StationConfig

FLAT = Characteristic("high_top_flatness", "#657", "flatness", 0.05, "minimum_zone")


def iso_14253(value: float | None, U: float, tol: float, limit: float | None = None) -> str:
    """ISO 14253-1 for an upper limit, written out: conforming when value + U <= tol,
    non-conforming when value - U > tol, otherwise uncertain; a figure below its detection
    limit conforms when the limit is within the tolerance, else is uncertain."""
    if value is None:
        return "conforming" if limit is not None and limit <= tol else "uncertain"
    return "conforming" if value + U <= tol else "non-conforming" if value - U > tol else "uncertain"


def program_with(tolerances: dict[str, float], rule: str | None = None) -> PartProgram:
    """The demo program with the given characteristics' tolerances (mm) and decision rule."""
    program = load_program(DEMO_PROGRAM)
    chars = tuple(dataclasses.replace(c, tolerance_mm=tolerances.get(c.name, c.tolerance_mm))
                  for c in program.characteristics)
    return dataclasses.replace(program, characteristics=chars, decision_rule=rule or program.decision_rule)


def result(**values: tuple[float | None, float | None, float | None]) -> MeasurementResult:
    """A measurement of every demo characteristic: name=(value, U, limit) mm; the others
    read 0.010 +- 0.002 (far inside every demo tolerance)."""
    out = []
    for c in load_program(DEMO_PROGRAM).characteristics:
        value, U, limit = values.get(c.name, (0.010, 0.002, None))
        out.append(MeasuredValue(c.name, value, 500, u_mm=U, limit_mm=limit))
    return MeasurementResult(True, tuple(out))


@pytest.mark.parametrize("value,U,limit", [(0.030, 0.004, None), (0.047, 0.004, None), (0.053, 0.004, None),
                                          (0.058, 0.004, None), (0.050, 0.0, None), (None, None, 0.008),
                                          (None, None, 0.060)])
def test_each_value_is_decided_by_iso_14253_with_its_U(value: float | None, U: float | None,
                                                       limit: float | None) -> None:
    program = load_program(DEMO_PROGRAM)
    status, records, message = judge(program, result(high_top_flatness=(value, U, limit)))
    [rec] = [r for r in records if r.characteristic == "high_top_flatness"]
    want = iso_14253(value, U or 0.0, 0.05, limit)
    assert (rec.decision, rec.rule, rec.u_mm, rec.limit_mm) == (want, "guard-banded", U, limit)
    assert rec.conforms == {"conforming": True, "non-conforming": False, "uncertain": None}[want]
    assert status == {"conforming": "pass", "non-conforming": "fail", "uncertain": "uncertain"}[want]
    if want == "uncertain":
        assert message == "uncertain (within U of the tolerance; re-measure): high_top_flatness"


def test_the_plain_rule_judges_the_value_alone() -> None:
    status, records, _ = judge(program_with({}, "plain"), result(high_top_flatness=(0.048, 0.004, None)))
    assert status == "pass" and records[0].decision == "conforming" and records[0].rule == "plain"


def test_the_program_names_its_decision_rule(tmp_path: Path) -> None:
    assert load_program(DEMO_PROGRAM).decision_rule == GUARD_BANDED  # the default
    description = 'description = "Bundled demo part: stepped plate with a boss"'
    plain = load_program(program_copy(tmp_path, (description, description + '\ndecision_rule = "plain"')))
    assert plain.decision_rule == "plain" and program_tolerances(plain).decision_rule == "plain"
    with pytest.raises(ConfigError, match="program.decision_rule"):
        load_program(program_copy(tmp_path, (description, description + '\ndecision_rule = "lenient"')))


def test_a_part_fails_on_any_proven_nonconformity_and_is_never_passed_on_a_missing_value() -> None:
    program = load_program(DEMO_PROGRAM)
    both = result(high_top_flatness=(0.048, 0.004, None), high_top_profile=(0.30, 0.002, None))
    assert judge(program, both)[0] == "fail"  # one proven out outweighs one uncertain
    missing = result(high_top_flatness=(0.048, 0.004, None), high_top_sq=(None, None, None))
    assert judge(program, missing)[:3:2] == ("error", "not measured: high_top_sq")


def test_the_adapter_reads_U_and_a_detection_limit_and_keeps_a_below_limit_figure_unnumbered() -> None:
    table = face_row("#657", 900, flatness_mz=Estimate(0.031, 0.0025 / K, 0.007), sq=Estimate(None, 0.002, 0.0046))
    flat = _pick(FLAT, [table])
    assert (flat.value_mm, flat.u_mm, flat.limit_mm) == (0.031, 0.0025, 0.007)
    sq = _pick(Characteristic("high_top_sq", "#657", "sq", 0.03), [table])
    assert (sq.value_mm, sq.u_mm, sq.limit_mm) == (None, None, 0.0046) and "detection limit 4.6 um" in sq.note


def test_a_views_json_names_each_characteristic_with_its_tolerance_and_decision() -> None:
    program = program_with({"high_top_flatness": 0.032})
    table = face_row("#657", 900, flatness_mz=Estimate(0.031, 0.0025 / K), profile=Estimate(0.02, 0.002 / K),
                     sq=Estimate(None, 0.002, 0.0046))
    block = view_decisions(program, table, 1)
    assert (block["name"], block["view"], block["decision_rule"]) == ("demo-part", 1, "guard-banded")
    rows = {r["name"]: r for r in block["characteristics"]}
    assert [r["name"] for r in block["characteristics"]] == [c.name for c in program.characteristics]
    flat = rows["high_top_flatness"]
    assert (flat["face"], flat["face_name"], flat["tolerance_mm"], flat["decision"]) == (
        "#657", "high top", 0.032, iso_14253(0.031, 0.0025, 0.032))  # uncertain
    assert rows["high_top_sq"]["decision"] == "conforming" and rows["high_top_sq"]["value_mm"] is None
    assert rows["low_top_flatness"]["decision"] == "not measured"  # #158 not in this view
    assert rows["low_top_flatness"]["note"] == "face #158 not seen in any view"


class TruthWithU(SimulatorTruth):
    """Test double: the simulated part's true values reported with an expanded uncertainty
    of `U` mm each (what a measurement of that quality could report)."""

    name = "simulator truth with U (test double)"
    U = 0.004

    def measure(self, sessions: Sequence[Session], program: PartProgram) -> MeasurementResult:
        truth = json.loads((sessions[0].root / TRUTH_FILE).read_text())["imposed_mm"]
        return MeasurementResult(True, tuple(MeasuredValue(c.name, truth[c.name], 100, u_mm=self.U)
                                             for c in program.characteristics))


def test_an_uncertain_part_is_stored_shown_and_counted_apart(tmp_path: Path) -> None:
    """Part 2 of the simulated lineup has a 20 um bow (flatness 0.020 mm); against a
    flatness tolerance of 0.022 mm with U = 4 um its decision is uncertain: the part is
    neither passed nor failed, stored as such, and shown as such in its record, the
    terminal lines, the report and the statistics."""
    program_path = program_copy(tmp_path, ("tolerance_mm = 0.05", "tolerance_mm = 0.022"))  # the first: high top
    config = StationConfig.load(station_config(tmp_path))
    with open_station(program_path, config, "ana", TruthWithU()) as run:
        first, second = run.station.run_cycle("SN-0", part=0), run.station.run_cycle("SN-2", part=2)
        assert (first.status, second.status) == ("pass", "uncertain")
        assert second.message == "uncertain (within U of the tolerance; re-measure): high_top_flatness"
        rows = run.store.results()
        assert [r.status for r in rows] == ["pass", "uncertain"]
        stored = {v.characteristic: v for v in run.store.values([rows[1].id])[rows[1].id]}
        flat = stored["high_top_flatness"]
        assert (flat.value_mm, flat.u_mm, flat.decision, flat.rule, flat.conforms) == (
            0.02, 0.004, iso_14253(0.02, 0.004, 0.022), "guard-banded", None)
        record = json.loads((second.part_path / PART_RECORD).read_text())
        assert record["status"] == "uncertain" and record["values"][0]["decision"] == "uncertain"
        assert "0.0200 ± 0.0040 mm  <= 0.022  UNCERTAIN" in "\n".join(outcome_lines(run.program, second))
        stats = running_stats(run.program, rows, run.store.values([r.id for r in rows]))
        assert (stats.parts, stats.passed, stats.uncertain, stats.yield_percent) == (2, 1, 1, 50.0)
        page = write_report(tmp_path / "report", run.program, rows, run.store.values([r.id for r in rows]), "test")
        text = page.read_text()
        assert "1 uncertain (re-measure)" in text and "0.0200 ± 0.0040 UNCERTAIN" in text


# ------------------------------------------------------------------ measured on the simulator

def bow_zone_inside_margin(bow_mm: float, margin_mm: float) -> float:
    """The true minimum-zone flatness of the bowed high top over the part that form
    evaluation keeps (the face less `margin_mm` along its border): the bow is d = b(1 -
    r^2/R^2) from the face's centre, R its half-diagonal (sim.station_parts), so the zone is
    b at the centre less d at the kept region's corners."""
    half = np.array([(STEP_X - PLATE_X[0]) / 2, (PLATE_Y[1] - PLATE_Y[0]) / 2])  # 17.5 x 30 mm
    corner = half - margin_mm
    return bow_mm * float(corner @ corner) / float(half @ half)  # b - d(corner) = b r^2 / R^2


@pytest.mark.acceptance
@pytest.mark.slow
def test_measured_decisions_follow_the_simulated_parts_truth(tmp_path: Path) -> None:
    """One simulated part (the 150 um bow of the high top, part 1) scanned at full
    resolution and inspected by the station; its measured values decided against part
    programs whose tolerances are placed by the truth: the high top's flatness over the
    evaluated face (`bow_zone_inside_margin`, 1 mm edge margin: 0.1385 mm) and its profile
    zone (2 b = 0.300 mm). A tolerance the part violates by 20 um is non-conforming, one it
    clears by 20 um (about 8 U) conforming, and one equal to the true flatness uncertain
    (the measurement lands within its U of it). The per-view JSON says the same."""
    from inspection.form import FormSettings

    assert FormSettings().edge_margin_mm == 1.0  # the margin this truth is for
    config = StationConfig.load(station_config(tmp_path, measurement="inspection",
                                               rig=CONFIG_DIR / "rigs" / "sim_bench.toml"))
    with open_station(DEMO_PROGRAM, config) as run:
        o = run.station.run_cycle("ACC-1", part=1)
        measured = json.loads((o.part_path / PART_RECORD).read_text())["measurement_result"]
    assert o.truth["imposed_mm"]["high_top_flatness"] == 0.15 and o.status == "fail"
    values = MeasurementResult(True, tuple(MeasuredValue(**v) for v in measured["values"]))
    flat_true, profile_true = bow_zone_inside_margin(0.15, 1.0), o.truth["imposed_mm"]["high_top_profile"]
    m = values.value("high_top_flatness")
    print("flatness", m.value_mm, m.u_mm, "true", flat_true, "profile", values.value("high_top_profile"))
    cases = {"non-conforming": {"high_top_flatness": flat_true - 0.02, "high_top_profile": profile_true - 0.02},
             "conforming": {"high_top_flatness": flat_true + 0.02, "high_top_profile": profile_true + 0.02}}
    for want, tolerances in cases.items():
        _, records, _ = judge(program_with(tolerances), values)
        decided = {r.characteristic: r.decision for r in records}
        assert decided["high_top_flatness"] == decided["high_top_profile"] == want, (tolerances, records)
    _, records, _ = judge(program_with({"high_top_flatness": flat_true}), values)
    assert records[0].decision == "uncertain", records[0]
    view = json.loads((o.sessions[0] / "outputs" / REPORT_FILE).read_text())
    rows = {r["name"]: r for r in view["program"]["characteristics"]}
    assert rows["high_top_flatness"]["decision"] == rows["high_top_profile"]["decision"] == "non-conforming"
    assert {r["decision"] for r in rows.values()} <= {"conforming", "non-conforming"}  # nominal faces: clear
