"""The results history: the same tests on SQLite and on PostgreSQL.

PostgreSQL runs when SLSCAN_TEST_PG_URL names a server (e.g.
postgresql://postgres@127.0.0.1:5432/postgres); each test works in a schema of its own,
dropped afterwards."""

from __future__ import annotations

import csv
import datetime as dt
import importlib.util
import io
import os
import uuid
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import quote

import pytest

from slscan.station.results import (
    LEASE_S,
    PartStart,
    ResultRow,
    ResultsError,
    ResultsStore,
    ValueRecord,
    csv_cell,
    open_results,
    redact,
    write_csv,
)

PG_URL = os.environ.get("SLSCAN_TEST_PG_URL")
T0 = dt.datetime(2026, 11, 23, 8, 0, 0, 123456, tzinfo=dt.UTC)


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ResultsStore]:
    if request.param == "sqlite":
        with open_results(f"sqlite:{tmp_path / 'db' / 'results.sqlite'}") as s:
            yield s
        return
    if not PG_URL:
        pytest.skip("PostgreSQL: set SLSCAN_TEST_PG_URL to a server's URL to run the results tests on it")
    if importlib.util.find_spec("psycopg") is None:
        pytest.skip("psycopg is not installed: the [station-db] extra (pip install -e '.[station-db]') runs this test")
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
    assert ((row.operator, row.station, row.rig, row.calibration_id)
            == ("ana", "bench-1", "sim-bench", "factory-sim-bench"))
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
    _other, a3 = store.begin_part(start("SN-7", 2, program="other-part"))
    assert (a1, a2, a3) == (1, 2, 1)  # attempts count per program and serial
    rows = store.results(program="demo-part", serial="SN-7")
    assert [(r.attempt, r.status) for r in rows] == [(1, "aborted"), (2, "pass")]
    assert store.values([first, second]) == {first: [], second: VALUES[:1]}


def _dead_owner() -> str:
    """The owner string of a process of this host that has exited."""
    import socket
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait(timeout=60)
    return f"{socket.gethostname()}:{child.pid}:1"


def test_only_cycles_whose_owner_is_gone_are_marked_incomplete(store: ResultsStore) -> None:
    """Issue 15 item 10: a second station sharing the config must not mark the first one's
    running cycle incomplete; only cycles of a process that is gone (this host: not running;
    another host: lease expired) are."""
    done, _ = store.begin_part(start("SN-1"))
    store.finish_part(done, "pass", "", VALUES[:1], T0)
    running, _ = store.begin_part(start("SN-2", 1))  # owned by this (live) process
    store.owner = _dead_owner()
    dead, _ = store.begin_part(start("SN-3", 2))
    store.owner = "other-host:4242:99"
    remote, _ = store.begin_part(start("SN-4", 3))  # lease fresh: LEASE_S from now
    elsewhere, _ = store.begin_part(start("SN-5", 4, station="bench-2"))
    assert store.mark_interrupted("bench-1", "station stopped") == [dead]
    assert store.result(dead).status == "incomplete" and store.result(dead).message == "station stopped"
    assert [store.result(i).status for i in (done, running, remote, elsewhere)] == [
        "pass", "in_progress", "in_progress", "in_progress"]
    later = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=2 * LEASE_S)  # the remote lease has run out
    assert store.mark_interrupted("bench-1", "again", now=later) == [remote]
    assert store.result(running).status == "in_progress"


def test_a_held_cycle_has_its_lease_renewed(store: ResultsStore) -> None:
    import threading

    rid, _ = store.begin_part(start("SN-1"))
    first = _lease(store, rid)
    assert first > dt.datetime.now(dt.UTC) + dt.timedelta(seconds=LEASE_S / 2)
    renewed = threading.Event()
    with store.hold(rid, every_s=0.05):
        deadline = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=60)
        while dt.datetime.now(dt.UTC) < deadline and not renewed.is_set():
            if _lease(store, rid) > first:
                renewed.set()
            renewed.wait(0.05)
    assert renewed.is_set()  # within a generous bound, 60 s for a 0.05 s renewal
    store.finish_part(rid, "pass", "", [], T0)
    assert _lease(store, rid) is None and store.renew(rid) is False  # finished: nothing to renew


def _lease(store: ResultsStore, rid: int) -> dt.datetime | None:
    import sqlalchemy as sa

    from slscan.station.results import RESULTS

    with store.engine.connect() as conn:
        return conn.execute(sa.select(RESULTS.c.lease_until).where(RESULTS.c.id == rid)).scalar()


def test_concurrent_writers_never_share_an_attempt_number(store: ResultsStore) -> None:
    """Issue 15 item 11: 6 writers x 20 cycles of one serial, each writer with a store (a
    connection) of its own as two stations have, gave duplicate attempts when MAX(attempt)
    was read outside the insert's transaction."""
    from concurrent.futures import ThreadPoolExecutor

    def writer(k: int) -> list[int]:
        with open_results(store.url) as own:
            return [own.begin_part(start("SN-X", k))[1] for _ in range(20)]

    with ThreadPoolExecutor(6) as pool:
        attempts = sorted(a for batch in pool.map(writer, range(6)) for a in batch)
    assert attempts == list(range(1, 121))
    assert sorted(r.attempt for r in store.results(serial="SN-X")) == list(range(1, 121))


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


@pytest.mark.parametrize("url, secret", [
    ("postgresql://u:s3@cr3t@127.0.0.1:1/x", "s3@cr3t"),  # a password holding '@' (refused: ambiguous)
    ("postgresql://u@127.0.0.1:1/x?password=s3cr3t", "s3cr3t"),  # in the query
    ("postgresql://u:s3cr3t@127.0.0.1:notaport/x", "s3cr3t"),  # echoed by the driver's own message
    ("postgresql://u:s3cr3t@[bad/x", "s3cr3t"),
    ("postgresql://u:p%40ss%2Fw@127.0.0.1:1/x", "p@ss/w"),  # URL-encoded
    ("mysql://u:s3cr3t@h/x", "s3cr3t"),
])
def test_no_message_shows_a_password(url: str, secret: str) -> None:
    """Issue 15 item 12: the password of a database URL never reaches a message."""
    with pytest.raises(ResultsError) as exc:
        open_results(url)
    text = str(exc.value)
    assert "\n" not in text and "***" in text
    for part in [secret] + [piece for piece in secret.split("@") if len(piece) > 2]:
        assert part not in text, text
    assert redact(f"failed for {url}", url).count("***") >= 1


def test_csv_cells_cannot_become_formulas() -> None:
    """Issue 15 item 12: text cells starting with = + - @, tab or CR are escaped; numbers stay numbers."""
    for text in ("=1+1", "+SUM(A1)", "-2+3", "@cmd", "\tx", "\rx"):
        assert csv_cell(text) == "'" + text
    assert csv_cell("ana") == "ana" and csv_cell(-0.5) == -0.5 and csv_cell(None) is None
    rows = [replace_operator(start("=HYPERLINK(\"x\")"), "=1+1")]
    buf = io.StringIO()
    write_csv(buf, rows, {})
    [line] = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert line["operator"] == "'=1+1" and line["serial"] == "'=HYPERLINK(\"x\")"


def replace_operator(s: PartStart, operator: str) -> ResultRow:
    from dataclasses import asdict

    return ResultRow(**{**asdict(s), "operator": operator}, id=1, attempt=1, status="pass")


def test_reading_never_creates_a_database(tmp_path: Path) -> None:
    """Issue 15 item 8: `slscan results --data` on a mistyped folder must not create one."""
    missing = tmp_path / "mistyped" / "results.sqlite"
    with pytest.raises(ResultsError, match="no results database there"):
        open_results(f"sqlite:{missing}", create=False)
    assert not missing.parent.exists()
    with pytest.raises(ResultsError, match="cannot create the results folder"):
        open_results("sqlite:/proc/slscan-test/results.sqlite")  # /proc refuses new folders, even to root
    not_db = tmp_path / "notes.sqlite"
    not_db.write_text("hello")
    with pytest.raises(ResultsError, match="notes.sqlite"):
        open_results(f"sqlite:{not_db}", create=False)


def test_a_version_1_database_is_upgraded_and_its_duplicate_attempts_renumbered(tmp_path: Path) -> None:
    import sqlite3

    path = tmp_path / "v1.sqlite"
    conn = sqlite3.connect(path)
    conn.executescript(V1_SCHEMA)
    row = ("demo-part", "1.0", "abc", "SN-1", "ana", "bench-1", "sim", None, "0.1.0", "inspection", "/p", "pass", "",
           "2026-11-23T08:00:00+00:00", "2026-11-23T08:01:00+00:00", "station")
    for attempt in (1, 1, 2):  # version 1 could give one attempt number twice
        conn.execute("INSERT INTO results (program, program_version, program_fingerprint, serial, operator, station, "
                     "rig, calibration_id, software_version, measurement, part_path, status, message, started_at, "
                     "finished_at, source, attempt) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)", row + (attempt,))
    conn.execute("INSERT INTO slscan_schema (version) VALUES (1)")
    conn.commit()
    conn.close()
    with pytest.raises(ResultsError, match="schema version 1.*a station opening it upgrades it"):
        open_results(f"sqlite:{path}", create=False)
    with open_results(f"sqlite:{path}") as s:
        rows = s.results()
        assert [r.attempt for r in rows] == [1, 2, 3]
        assert rows[0].started_at == dt.datetime(2026, 11, 23, 8, 0, tzinfo=dt.UTC)
        assert s.begin_part(start("SN-1"))[1] == 4 and s.begin_part(start("SN-1", program="other"))[1] == 1


V1_SCHEMA = """
CREATE TABLE slscan_schema (version INTEGER NOT NULL);
CREATE TABLE results (id INTEGER PRIMARY KEY AUTOINCREMENT, program TEXT NOT NULL, program_version TEXT NOT NULL,
    program_fingerprint TEXT NOT NULL, serial TEXT NOT NULL, attempt INTEGER NOT NULL, operator TEXT NOT NULL,
    station TEXT NOT NULL, rig TEXT NOT NULL, calibration_id TEXT, software_version TEXT NOT NULL,
    measurement TEXT NOT NULL, part_path TEXT NOT NULL, status TEXT NOT NULL, message TEXT NOT NULL,
    started_at TEXT NOT NULL, finished_at TEXT, source TEXT NOT NULL);
CREATE TABLE measured (result_id INTEGER NOT NULL REFERENCES results (id) ON DELETE CASCADE,
    position INTEGER NOT NULL, characteristic TEXT NOT NULL, kind TEXT NOT NULL, face TEXT NOT NULL, value_mm REAL,
    tolerance_mm REAL NOT NULL, conforms INTEGER, points INTEGER NOT NULL, note TEXT NOT NULL,
    PRIMARY KEY (result_id, characteristic));
"""


def test_a_version_2_database_is_upgraded_and_its_values_keep_their_plain_decisions(tmp_path: Path) -> None:
    """Schema 3 adds each value's U, detection limit, decision and rule: values stored by a
    version 2 station keep what their plain comparison said (conforms true / false / null),
    under a rule that says so; new values keep all four."""
    import sqlite3

    from slscan.station.results import OLD_RULE

    path = tmp_path / "v2.sqlite"
    conn = sqlite3.connect(path)
    conn.executescript(V1_SCHEMA + "ALTER TABLE results ADD COLUMN owner TEXT;\n"
                       "ALTER TABLE results ADD COLUMN lease_until TEXT;\n"
                       "CREATE UNIQUE INDEX results_attempt ON results (program, serial, attempt);\n"
                       "INSERT INTO slscan_schema (version) VALUES (2);")
    conn.execute("INSERT INTO results (program, program_version, program_fingerprint, serial, operator, station, "
                 "rig, calibration_id, software_version, measurement, part_path, status, message, started_at, "
                 "finished_at, source, attempt) VALUES ('demo-part', '1.0', 'abc', 'SN-1', 'ana', 'bench-1', 'sim', "
                 "NULL, '0.1.0', 'inspection', '/p', 'fail', '', '2026-11-23T08:00:00+00:00', NULL, 'station', 1)")
    for k, (name, conforms) in enumerate((("a", 1), ("b", 0), ("c", None))):
        conn.execute("INSERT INTO measured VALUES (1, ?, ?, 'flatness', '#657', ?, 0.05, ?, 10, '')",
                     (k, name, None if conforms is None else 0.04 + 0.02 * (1 - conforms), conforms))
    conn.commit()
    conn.close()
    with pytest.raises(ResultsError, match="schema version 2.*a station opening it upgrades it"):
        open_results(f"sqlite:{path}", create=False)
    with open_results(f"sqlite:{path}") as s:
        old = s.values([1])[1]
        assert [(v.conforms, v.decision, v.rule, v.u_mm) for v in old] == [
            (True, "conforming", OLD_RULE, None), (False, "non-conforming", OLD_RULE, None),
            (None, "not measured", OLD_RULE, None)]
        rid, _ = s.begin_part(start("SN-2"))
        new = [ValueRecord("a", "flatness", "#657", 0.048, 0.05, None, 10, "", 0.004, 0.007, "uncertain",
                           "guard-banded"),
               ValueRecord("sq", "sq", "#657", None, 0.03, True, 10, "below", None, 0.0046, "conforming",
                           "guard-banded")]
        s.finish_part(rid, "uncertain", "uncertain: a", new, T0)
        assert s.values([rid])[rid] == new and s.result(rid).status == "uncertain"
