"""The measuring step through its one adapter onto `inspection`.

How the adapter reads the per-face inspection report is tested on report tables; the verdicts
of measured simulated parts are the acceptance of `slscan station --parts 5 --auto`."""

from __future__ import annotations

from pathlib import Path

import pytest
from station_support import DEMO_PROGRAM, face_row, station_config

from inspection.figures import asked_by
from scanner.config import CONFIG_DIR
from slscan.station.app import expected_status, open_station
from slscan.station.measure import ViewReport, _pick
from slscan.station.program import Characteristic, load_program
from slscan.station.results import ValueRecord
from slscan.station.station_config import StationConfig

FLAT = Characteristic("high_top_flatness", "#657", "flatness", 0.05, "minimum_zone")
PROFILE = Characteristic("high_top_profile", "#657", "profile", 0.4)


def test_adapter_takes_each_value_from_the_view_that_sees_the_face_best() -> None:
    views = [face_row("#657", 900, flatness_mz=0.031, flatness_ls=0.035, profile=0.10, raw_deviation_min=-0.08,
                  raw_deviation_max=0.09),
             face_row("#657", 1500, flatness_mz=0.027, flatness_ls=0.030, profile=0.18, raw_deviation_min=-0.13,
                  raw_deviation_max=0.08)]
    flat = _pick(FLAT, views)
    assert (flat.value_mm, flat.points, flat.view) == (0.027, 1500, 1)
    assert _pick(Characteristic("f", "#657", "flatness", 0.05, "least_squares"), views).value_mm == 0.030
    assert _pick(PROFILE, views).value_mm == 0.18  # the form surface's zone, not the raw points' 2 x 0.13


def test_a_face_not_seen_or_not_evaluated_has_no_value_and_says_why() -> None:
    unseen = _pick(FLAT, [face_row("#158", 10), face_row("#657", 0)])
    assert unseen.value_mm is None and unseen.note == "face #657 not seen in any view"
    failed = _pick(FLAT, [face_row("#657", 40, "too few points for a minimum zone", flatness_mz=None)])
    assert failed.value_mm is None and failed.note == "face #657: too few points for a minimum zone"
    nan = _pick(FLAT, [face_row("#657", 40, status="", flatness_mz=float("nan"))])
    assert nan.value_mm is None and "flatness_mz_mm" in nan.note


def _run_demo_parts(tmp_path: Path, parts: list[int]) -> None:
    """Measure simulated demo parts at full resolution through inspection; every verdict must
    be the one its imposed defects call for, so must each characteristic's (nominal faces read
    their ~5-9 um noise floor, far inside the tolerances), and every imposed form defect
    measured near its truth: flatness to 5 um + 10 %; cylindricity, seen on about half the
    boss's side, between 0.52 of its whole-side zone (the least half an arc keeps of 3-lobe
    lobing) and the zone."""
    config = StationConfig.load(station_config(tmp_path, measurement="inspection",
                                               rig=CONFIG_DIR / "rigs" / "sim_bench.toml"))
    program = load_program(DEMO_PROGRAM)
    with open_station(DEMO_PROGRAM, config) as run:
        for k in parts:
            o = run.station.run_cycle(f"ACC-{k}", part=k)
            print(o.truth["name"], o.status, [(v.characteristic, v.value_mm) for v in o.values])
            assert o.status == expected_status(program, o.truth), (o.truth, o.values, o.message)
            for v in o.values:
                truth = o.truth["imposed_mm"][v.characteristic]
                assert v.conforms == program.characteristic(v.characteristic).conforms(truth), v  # each one, too
                if v.characteristic.endswith("flatness") and truth > 0:
                    _agrees_with_truth(v, truth - 0.005 - 0.1 * truth, truth + 0.005 + 0.1 * truth)
                if v.characteristic == "boss_cylindricity" and truth > 0:
                    _agrees_with_truth(v, 0.52 * truth - 0.005, truth + 0.005)


def _agrees_with_truth(v: ValueRecord, low_mm: float, high_mm: float) -> None:
    """A value lies in what its truth allows [low, high] (mm); a value reported below its
    detection limit instead must have a limit the truth's least visible figure does not exceed
    (a form error larger than the limit must be measured, not called undetectable)."""
    if v.value_mm is None:
        assert v.limit_mm is not None and low_mm <= v.limit_mm, v
    else:
        assert low_mm <= v.value_mm <= high_mm, v


@pytest.mark.acceptance
def test_measured_verdict_of_a_bowed_part(tmp_path: Path) -> None:
    _run_demo_parts(tmp_path, [1])  # the 150 um bow: FAIL on the high top's flatness


@pytest.mark.acceptance
def test_five_parts_with_imposed_defects_get_the_right_verdicts(tmp_path: Path) -> None:
    _run_demo_parts(tmp_path, [0, 1, 2, 3, 4])


def test_a_view_whose_pose_is_not_proven_measures_nothing() -> None:
    """A view whose registration is ambiguous gives no values (its faces left out, though its
    table has points on them); with no proven view the part is not measured and its message
    names the ambiguity (`judge`: status "error")."""
    from slscan.station.measure import view_values
    from slscan.station.quality import judge

    program = load_program(DEMO_PROGRAM)
    flat = program.characteristics[0]
    name = asked_by(flat.kind, flat.method).name
    seen = face_row(flat.face, 2000, **{name: 0.5})
    note = "not measured: the pose is ambiguous between the best pose and 1 other pose(s) that explain the scan"
    ambiguous = ViewReport(0.9, 0.01, "not measured", "ambiguous", note)
    ok = ViewReport(0.9, 0.01, "conforming")
    proven = view_values(program, [seen, face_row(flat.face, 300, **{name: 0.02})], [ambiguous, ok], {}, [])
    assert proven.ok and proven.value(flat.name).value_mm == 0.02  # the ambiguous view's 2000 points are not used
    alone = view_values(program, [seen, {}], [ambiguous, ok], {}, [])
    assert alone.value(flat.name).value_mm is None and "view 0: not measured: the pose is ambiguous" in \
        alone.value(flat.name).note
    none = view_values(program, [seen], [ambiguous], {}, [])
    status, records, message = judge(program, none)
    assert not none.ok and status == "error" and not records
    assert message.startswith("not measured: view 0: the pose is ambiguous between the best pose"), message
