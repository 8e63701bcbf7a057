"""The results history: one row per scan cycle of a part, one per measured characteristic.

The same code runs on SQLite (a file in the station's data folder, `sqlite:PATH`) and on
PostgreSQL (`postgresql://...`, through psycopg 3), with plain DB-API calls; a `Dialect`
holds the few differences (placeholder, identity column, timestamp and boolean types).
Every write is committed before the station moves on, so a station killed at any moment
loses no stored result. A cycle is stored when it starts (status `in_progress`) and
updated when it ends; rows left `in_progress` by a station that died are marked
`incomplete` by `mark_interrupted` the next time that station starts.

Tables (lengths in mm, times as UTC timestamps):

    results   id, program, program_version, program_fingerprint, serial, attempt, operator,
              station, rig, calibration_id, software_version, measurement, part_path,
              status (in_progress | pass | fail | error | aborted | incomplete), message,
              started_at, finished_at, source (station | batch)
    measured  result_id, position (the program's order), characteristic, kind, face, value_mm (NULL: not measured),
              tolerance_mm, conforms (NULL: not measured), points, note
"""

from __future__ import annotations

import csv
import datetime as dt
import sqlite3
import threading
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Iterator, Sequence, TextIO

from slscan.station import StationError

SCHEMA_VERSION = 1
STATUSES = ("in_progress", "pass", "fail", "error", "aborted", "incomplete")

_DDL = [
    "CREATE TABLE IF NOT EXISTS slscan_schema (version INTEGER NOT NULL)",
    """CREATE TABLE IF NOT EXISTS results (
        id {id_column},
        program TEXT NOT NULL, program_version TEXT NOT NULL, program_fingerprint TEXT NOT NULL,
        serial TEXT NOT NULL, attempt INTEGER NOT NULL, operator TEXT NOT NULL, station TEXT NOT NULL,
        rig TEXT NOT NULL, calibration_id TEXT, software_version TEXT NOT NULL, measurement TEXT NOT NULL,
        part_path TEXT NOT NULL, status TEXT NOT NULL, message TEXT NOT NULL,
        started_at {timestamp} NOT NULL, finished_at {timestamp}, source TEXT NOT NULL)""",
    "CREATE INDEX IF NOT EXISTS results_program ON results (program, started_at)",
    "CREATE INDEX IF NOT EXISTS results_serial ON results (program, serial)",
    """CREATE TABLE IF NOT EXISTS measured (
        result_id INTEGER NOT NULL REFERENCES results (id) ON DELETE CASCADE, position INTEGER NOT NULL,
        characteristic TEXT NOT NULL, kind TEXT NOT NULL, face TEXT NOT NULL, value_mm {double},
        tolerance_mm {double} NOT NULL, conforms {boolean}, points INTEGER NOT NULL, note TEXT NOT NULL,
        PRIMARY KEY (result_id, characteristic))""",
]


class ResultsError(StationError):
    """The results database cannot be opened, is of another schema version, or a query failed."""


@dataclass(frozen=True)
class Dialect:
    """What differs between the databases, nothing more."""

    name: str
    placeholder: str
    types: dict[str, str]

    def sql(self, text: str) -> str:
        """`text` written with `?` placeholders, in this dialect."""
        return text.replace("?", self.placeholder)

    def ddl(self, text: str) -> str:
        return text.format(**self.types)

    def to_db_time(self, t: dt.datetime | None) -> Any:
        if t is None:
            return None
        t = t.astimezone(dt.timezone.utc)
        return t.isoformat() if self.name == "sqlite" else t

    def from_db_time(self, value: Any) -> dt.datetime | None:
        if value is None:
            return None
        t = dt.datetime.fromisoformat(value) if isinstance(value, str) else value
        return t.astimezone(dt.timezone.utc)


SQLITE = Dialect("sqlite", "?", {"id_column": "INTEGER PRIMARY KEY AUTOINCREMENT", "timestamp": "TEXT",
                                 "double": "REAL", "boolean": "INTEGER"})
POSTGRES = Dialect("postgresql", "%s", {"id_column": "BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY",
                                        "timestamp": "TIMESTAMPTZ", "double": "DOUBLE PRECISION",
                                        "boolean": "BOOLEAN"})


@dataclass(frozen=True)
class PartStart:
    """What is known when a part's cycle starts."""

    program: str
    program_version: str
    program_fingerprint: str
    serial: str
    operator: str
    station: str
    rig: str
    calibration_id: str | None
    software_version: str
    measurement: str
    part_path: str
    started_at: dt.datetime
    source: str = "station"


@dataclass(frozen=True)
class ValueRecord:
    """One characteristic's stored outcome (value None: not measured, `note` says why)."""

    characteristic: str
    kind: str
    face: str
    value_mm: float | None
    tolerance_mm: float
    conforms: bool | None
    points: int
    note: str = ""


@dataclass(frozen=True)
class ResultRow(PartStart):
    """A stored cycle, with its outcome."""

    id: int = 0
    attempt: int = 0
    status: str = ""
    message: str = ""
    finished_at: dt.datetime | None = None


_START_COLUMNS = [f.name for f in fields(PartStart)]
_RESULT_COLUMNS = _START_COLUMNS + ["id", "attempt", "status", "message", "finished_at"]
_VALUE_COLUMNS = [f.name for f in fields(ValueRecord)]


def open_results(url: str) -> ResultsStore:
    """The store at `url`: `sqlite:PATH` (the folder is created) or `postgresql://...`."""
    if url.startswith("sqlite:"):
        path = Path(url[len("sqlite:"):])
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            conn = sqlite3.connect(path, timeout=30.0, check_same_thread=False)  # calls serialised by the store
            conn.execute("PRAGMA journal_mode=WAL")  # readers (slscan results) never block the station
            conn.execute("PRAGMA foreign_keys=ON")
        except sqlite3.Error as exc:
            raise ResultsError(f"{path}: cannot open the results database: {exc}") from None
        return _store(conn, SQLITE, str(path), sqlite3.Error)
    if url.startswith(("postgresql://", "postgres://")):
        import psycopg

        try:
            conn = psycopg.connect(url, autocommit=True, connect_timeout=10)
        except psycopg.Error as exc:
            raise ResultsError(f"{_redact(url)}: cannot connect to the results database: {exc}") from None
        return _store(conn, POSTGRES, _redact(url), psycopg.Error)
    raise ResultsError(f"{url!r}: not a results database URL; use sqlite:PATH or postgresql://...")


def _store(conn: Any, dialect: Dialect, where: str, error: type[Exception]) -> ResultsStore:
    try:
        return ResultsStore(conn, dialect, where, error)
    except BaseException:
        conn.close()
        raise


def _redact(url: str) -> str:
    """The URL without its password, for messages."""
    head, sep, tail = url.partition("@")
    if not sep or ":" not in head.split("//", 1)[-1]:
        return url
    scheme, _, cred = head.partition("//")
    return f"{scheme}//{cred.split(':')[0]}:***@{tail}"


class ResultsStore:
    """A connection to the results database, schema created on first use."""

    def __init__(self, conn: Any, dialect: Dialect, where: str, error: type[Exception]) -> None:
        self.conn = conn
        self.dialect = dialect
        self.where = where
        self._error = error  # the driver's base exception
        self._lock = threading.RLock()  # one statement at a time on the connection, from any thread
        with self._tx() as cur:
            for stmt in _DDL:
                cur.execute(dialect.ddl(stmt))
            cur.execute("SELECT version FROM slscan_schema")
            row = cur.fetchone()
            if row is None:
                cur.execute(dialect.sql("INSERT INTO slscan_schema (version) VALUES (?)"), (SCHEMA_VERSION,))
            elif row[0] != SCHEMA_VERSION:
                raise ResultsError(f"{where}: results schema version {row[0]}, this slscan uses {SCHEMA_VERSION}")

    def __enter__(self) -> ResultsStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.conn.close()

    @contextmanager
    def _tx(self) -> Iterator[Any]:
        """A cursor inside one committed transaction (rolled back on error)."""
        try:
            with self._lock:
                if self.dialect is SQLITE:
                    with self.conn:
                        yield self.conn.cursor()
                else:
                    with self.conn.transaction(), self.conn.cursor() as cur:
                        yield cur
        except self._error as exc:
            raise ResultsError(f"{self.where}: {type(exc).__name__}: {exc}") from None

    def _query(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        try:
            with self._lock:
                cur = self.conn.cursor()
                cur.execute(self.dialect.sql(sql), tuple(params))
                rows = cur.fetchall()
                cur.close()
                return rows
        except self._error as exc:
            raise ResultsError(f"{self.where}: {type(exc).__name__}: {exc}") from None

    # -- writing

    def begin_part(self, start: PartStart) -> tuple[int, int]:
        """Store a cycle as `in_progress`; returns (result id, attempt number for this serial)."""
        d = self.dialect
        values = asdict(start)
        values["started_at"] = d.to_db_time(start.started_at)
        with self._tx() as cur:
            cur.execute(d.sql("SELECT COALESCE(MAX(attempt), 0) + 1 FROM results WHERE program = ? AND serial = ?"),
                        (start.program, start.serial))
            attempt = int(cur.fetchone()[0])
            cols = _START_COLUMNS + ["attempt", "status", "message"]
            cur.execute(d.sql(f"INSERT INTO results ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))}) "
                              f"RETURNING id"), [values[c] for c in _START_COLUMNS] + [attempt, "in_progress", ""])
            return int(cur.fetchone()[0]), attempt

    def finish_part(self, result_id: int, status: str, message: str, values: Sequence[ValueRecord],
                    finished_at: dt.datetime, part_path: str | None = None) -> None:
        """Store a cycle's outcome and its measured values, in one transaction."""
        if status not in STATUSES or status == "in_progress":
            raise ValueError(f"not a final status: {status!r}")
        d = self.dialect
        with self._tx() as cur:
            cur.execute(d.sql("UPDATE results SET status = ?, message = ?, finished_at = ?, "
                              "part_path = COALESCE(?, part_path) WHERE id = ?"),
                        (status, message, d.to_db_time(finished_at), part_path, result_id))
            if cur.rowcount != 1:
                raise ResultsError(f"{self.where}: no result {result_id} to finish")
            cur.execute(d.sql("DELETE FROM measured WHERE result_id = ?"), (result_id,))
            for k, v in enumerate(values):
                cur.execute(d.sql(f"INSERT INTO measured (result_id, position, {', '.join(_VALUE_COLUMNS)}) "
                                  f"VALUES (?, ?, {', '.join('?' * len(_VALUE_COLUMNS))})"),
                            [result_id, k] + [getattr(v, c) for c in _VALUE_COLUMNS])

    def mark_interrupted(self, station: str, message: str) -> list[int]:
        """Cycles this station left `in_progress` (it died during them) become `incomplete`."""
        d = self.dialect
        with self._tx() as cur:
            cur.execute(d.sql("SELECT id FROM results WHERE station = ? AND status = 'in_progress' ORDER BY id"),
                        (station,))
            ids = [int(r[0]) for r in cur.fetchall()]
            for i in ids:
                cur.execute(d.sql("UPDATE results SET status = 'incomplete', message = ? WHERE id = ?"), (message, i))
        return ids

    # -- reading

    def results(self, program: str | None = None, serial: str | None = None, status: str | None = None,
                since: dt.datetime | None = None, limit: int | None = None) -> list[ResultRow]:
        """Stored cycles, oldest first (the newest `limit` when given)."""
        where, params = [], []
        for col, val in (("program", program), ("serial", serial), ("status", status)):
            if val is not None:
                where.append(f"{col} = ?")
                params.append(val)
        if since is not None:
            where.append("started_at >= ?")
            params.append(self.dialect.to_db_time(since))
        sql = f"SELECT {', '.join(_RESULT_COLUMNS)} FROM results"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY id DESC"
        if limit is not None:
            sql += f" LIMIT {int(limit)}"
        return [self._row(r) for r in reversed(self._query(sql, params))]

    def result(self, result_id: int) -> ResultRow:
        rows = self._query(f"SELECT {', '.join(_RESULT_COLUMNS)} FROM results WHERE id = ?", (result_id,))
        if not rows:
            raise ResultsError(f"{self.where}: no result {result_id}")
        return self._row(rows[0])

    def _row(self, values: Sequence[Any]) -> ResultRow:
        r = dict(zip(_RESULT_COLUMNS, values))
        r["started_at"] = self.dialect.from_db_time(r["started_at"])
        r["finished_at"] = self.dialect.from_db_time(r["finished_at"])
        return ResultRow(**r)

    def values(self, result_ids: Sequence[int]) -> dict[int, list[ValueRecord]]:
        """Measured values per result id, in stored order."""
        out: dict[int, list[ValueRecord]] = {int(i): [] for i in result_ids}
        if not out:
            return out
        marks = ", ".join("?" * len(out))
        rows = self._query(f"SELECT result_id, {', '.join(_VALUE_COLUMNS)} FROM measured "
                           f"WHERE result_id IN ({marks}) ORDER BY result_id, position", list(out))
        for r in rows:
            rec = dict(zip(_VALUE_COLUMNS, r[1:]))
            rec["conforms"] = None if rec["conforms"] is None else bool(rec["conforms"])
            out[int(r[0])].append(ValueRecord(**rec))
        return out


_CSV_RESULT_COLUMNS = ["id"] + [c for c in _RESULT_COLUMNS if c != "id"]


def write_csv(out: TextIO, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]]) -> int:
    """One CSV line per measured characteristic (a cycle without values: one line with
    empty value columns); times in ISO 8601 UTC. Returns the number of lines written."""
    w = csv.writer(out)
    w.writerow(["result_id"] + _CSV_RESULT_COLUMNS[1:] + _VALUE_COLUMNS)
    n = 0
    for r in rows:
        head = [getattr(r, c) for c in _CSV_RESULT_COLUMNS]
        head = [v.isoformat() if isinstance(v, dt.datetime) else v for v in head]
        for v in values.get(r.id) or [None]:
            w.writerow(head + ([getattr(v, c) for c in _VALUE_COLUMNS] if v else [""] * len(_VALUE_COLUMNS)))
            n += 1
    return n
