"""The results history: the same tests on SQLite and on PostgreSQL.

PostgreSQL runs when SLSCAN_TEST_PG_URL names a server (e.g.
postgresql://postgres@127.0.0.1:5432/postgres); each test works in a schema of its own,
dropped afterwards."""

from __future__ import annotations

import csv
import datetime as dt
import io
import os
import uuid
from pathlib import Path
from typing import Iterator
from urllib.parse import quote

import pytest

from slscan.station.results import PartStart, ResultsError, ResultsStore, ValueRecord, open_results, write_csv

PG_URL = os.environ.get("SLSCAN_TEST_PG_URL")
T0 = dt.datetime(2026, 11, 23, 8, 0, 0, 123456, tzinfo=dt.timezone.utc)


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ResultsStore]:
    if request.param == "sqlite":
        with open_results(f"sqlite:{tmp_path / 'db' / 'results.sqlite'}") as s:
            yield s
        return
    if not PG_URL:
        pytest.skip("PostgreSQL: set SLSCAN_TEST_PG_URL to a server's URL to run the results tests on it")
    yield from _pg_store()


def _pg_store() -> Iterator[ResultsStore]:
    import psycopg

    schema = f"slscan_test_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(PG_URL, autocommit=True) as admin:
        admin.execute(f"CREATE SCHEMA {schema}")
        sep = "&" if "?" in PG_URL else "?"
        try:
            with open_results(f"{PG_URL}{sep}options={quote(f'-csearch_path={schema}')}") as s:
                yield s
        finally:
            admin.execute(f"DROP SCHEMA {schema} CASCADE")


def start(serial: str, minutes: int = 0, program: str = "demo-part", station: str = "bench-1") -> PartStart:
    return PartStart(program=program, program_version="1.0", program_fingerprint="abcdef012345", serial=serial,
                     operator="ana", station=station, rig="sim-bench", calibration_id="factory-sim-bench",
                     software_version="0.1.0", measurement="inspection", part_path=f"/data/{serial}",
                     started_at=T0 + dt.timedelta(minutes=minutes))


VALUES = [ValueRecord("high_top_flatness", "flatness", "F2", 0.0213, 0.05, True, 51234),
          ValueRecord("boss_cylindricity", "cylindricity", "F3", 0.1502, 0.05, False, 8123, ""),
          ValueRecord("high_top_sq", "sq", "F2", None, 0.03, None, 0, "face F2: too few points")]


def test_round_trip_keeps_every_field(store: ResultsStore) -> None:
    rid, attempt = store.begin_part(start("SN-1"))
    assert attempt == 1
    row = store.result(rid)
    assert row.status == "in_progress" and row.finished_at is None and row.started_at == T0
    store.finish_part(rid, "fail", "out of tolerance: boss_cylindricity", VALUES, T0 + dt.timedelta(seconds=9.5))
    [row] = store.results()
    assert row == store.result(rid)
    assert (row.id, row.serial, row.attempt, row.status) == (rid, "SN-1", 1, "fail")
    assert (row.program, row.program_version, row.program_fingerprint) == ("demo-part", "1.0", "abcdef012345")
    assert (row.operator, row.station, row.rig, row.calibration_id) == ("ana", "bench-1", "sim-bench", "factory-sim-bench")
    assert (row.software_version, row.measurement, row.part_path, row.source) == ("0.1.0", "inspection", "/data/SN-1",
                                                                                  "station")
    assert row.started_at == T0 and row.finished_at == T0 + dt.timedelta(seconds=9.5)
    assert row.started_at.tzinfo is not None
    assert store.values([rid]) == {rid: VALUES}


def test_rescans_are_new_attempts_and_lose_nothing(store: ResultsStore) -> None:
    first, a1 = store.begin_part(start("SN-7"))
    store.finish_part(first, "aborted", "aborted by the operator during capture", [], T0)
    second, a2 = store.begin_part(start("SN-7", 1))
    store.finish_part(second, "pass", "", VALUES[:1], T0)
    other, a3 = store.begin_part(start("SN-7", 2, program="other-part"))
    assert (a1, a2, a3) == (1, 2, 1)  # attempts count per program and serial
    rows = store.results(program="demo-part", serial="SN-7")
    assert [(r.attempt, r.status) for r in rows] == [(1, "aborted"), (2, "pass")]
    assert store.values([first, second]) == {first: [], second: VALUES[:1]}


def test_cycles_left_in_progress_are_marked_incomplete_for_their_station_only(store: ResultsStore) -> None:
    done, _ = store.begin_part(start("SN-1"))
    store.finish_part(done, "pass", "", VALUES[:1], T0)
    dead, _ = store.begin_part(start("SN-2", 1))
    elsewhere, _ = store.begin_part(start("SN-3", 2, station="bench-2"))
    assert store.mark_interrupted("bench-1", "station stopped") == [dead]
    assert store.result(dead).status == "incomplete" and store.result(dead).message == "station stopped"
    assert store.result(done).status == "pass" and store.result(elsewhere).status == "in_progress"
    assert store.mark_interrupted("bench-1", "again") == []


def test_filters_and_newest_limit(store: ResultsStore) -> None:
    ids = []
    for k in range(5):
        rid, _ = store.begin_part(start(f"SN-{k}", 10 * k))
        store.finish_part(rid, "pass" if k % 2 == 0 else "fail", "", [], T0 + dt.timedelta(minutes=10 * k + 1))
        ids.append(rid)
    assert [r.id for r in store.results(status="fail")] == [ids[1], ids[3]]
    assert [r.id for r in store.results(since=T0 + dt.timedelta(minutes=25))] == ids[3:]
    assert [r.id for r in store.results(limit=2)] == ids[3:]  # the newest two, oldest first
    assert store.results(program="nothing") == []


def test_csv_export_has_one_line_per_value_and_every_result(store: ResultsStore) -> None:
    a, _ = store.begin_part(start("SN-1"))
    store.finish_part(a, "fail", "out of tolerance", VALUES, T0)
    b, _ = store.begin_part(start("SN-2", 1))
    store.finish_part(b, "error", "not measured: registration failed", [], T0)
    rows = store.results()
    buf = io.StringIO()
    assert write_csv(buf, rows, store.values([r.id for r in rows])) == 4
    lines = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert [(x["result_id"], x["characteristic"]) for x in lines] == [
        (str(a), "high_top_flatness"), (str(a), "boss_cylindricity"), (str(a), "high_top_sq"), (str(b), "")]
    assert lines[1]["value_mm"] == "0.1502" and lines[1]["conforms"] == "False" and lines[2]["value_mm"] == ""
    assert lines[0]["started_at"] == "2026-11-23T08:00:00.123456+00:00"
    assert lines[3]["status"] == "error" and lines[3]["message"] == "not measured: registration failed"


def test_finishing_an_unknown_result_or_with_a_bad_status_fails(store: ResultsStore) -> None:
    with pytest.raises(ResultsError, match="no result 999"):
        store.finish_part(999, "pass", "", [], T0)
    rid, _ = store.begin_part(start("SN-1"))
    with pytest.raises(ValueError):
        store.finish_part(rid, "in_progress", "", [], T0)


def test_schema_persists_across_connections_and_results_survive(tmp_path: Path) -> None:
    url = f"sqlite:{tmp_path / 'r.sqlite'}"
    with open_results(url) as s:
        rid, _ = s.begin_part(start("SN-1"))
        s.finish_part(rid, "pass", "", VALUES[:1], T0)
    with open_results(url) as s:
        assert [r.status for r in s.results()] == ["pass"] and s.values([rid])[rid] == VALUES[:1]


def test_unreachable_database_is_a_clear_error() -> None:
    with pytest.raises(ResultsError, match=r"postgresql://slscan:\*\*\*@127.0.0.1:1/x: cannot connect"):
        open_results("postgresql://slscan:secret@127.0.0.1:1/x")
    with pytest.raises(ResultsError, match="not a results database URL"):
        open_results("mysql://x")
