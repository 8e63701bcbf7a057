"""The results history: one row per scan cycle of a part, one per measured characteristic.

The same code runs on SQLite (a file in the station's data folder, `sqlite:PATH`) and on
PostgreSQL (`postgresql://...`, through psycopg 3: the `station-db` extra), written with
SQLAlchemy Core: the tables are declared once, statements are built with bound
parameters, and SQLAlchemy speaks each database's dialect (placeholders, identity
columns, types), so this module holds no SQL text of its own per database.

Every write is committed before the station moves on, so a station killed at any moment
loses no stored result. A cycle is stored when it starts (status `in_progress`) and
updated when it ends. The process running it owns it: `owner` is host, process id and
process start time, and `lease_until` is renewed while the cycle runs (`ResultsStore.hold`).
At start-up a station marks `incomplete` only the cycles whose owner is gone (a process of
this host that no longer runs; on another host, a lease that ran out), so a second station
sharing the config never touches the first one's running cycle. Attempt numbers are assigned by the
insert itself (one statement), and a unique (program, serial, attempt) index refuses a
duplicate, which is retried: concurrent writers never share a number.

Tables (lengths in mm, times as UTC timestamps):

    results   id, program, program_version, program_fingerprint, serial, attempt, operator,
              station, rig, calibration_id, software_version, measurement, part_path,
              status (in_progress | pass | fail | uncertain | error | aborted | incomplete), message,
              started_at, finished_at, source (station | batch), owner, lease_until
    measured  result_id, position (the program's order), characteristic, kind, face, value_mm (NULL: not
              measured or below its detection limit), tolerance_mm, conforms (TRUE: conforming, FALSE:
              non-conforming, NULL: uncertain or not measured), points, note, u_mm (expanded uncertainty,
              k = 2), limit_mm (detection limit), decision (conforming | non-conforming | uncertain |
              not measured, ISO 14253-1), rule (the decision rule: guard-banded | plain)
    exclusions  result_id, reason, excluded_by, excluded_at: a result the user left out of the
              statistics (`slscan results --exclude ID=REASON`), applied to every later report and
              export until lifted (`--include ID`); the table is made by the first writer that
              opens the database, and a database without it has no exclusions (the schema
              version stays: an older slscan reading the database ignores the table)

Schema version 2 added `owner`, `lease_until` and the unique attempt index; version 3 the
values' `u_mm`, `limit_mm`, `decision` and `rule`. An older database is upgraded when a
station opens it (duplicate attempts left by version 1 are renumbered in id order; values
stored before version 3 keep their plain comparison as their decision, rule
"plain (before schema 3)").
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import os
import random
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, TextIO
from urllib.parse import unquote

import sqlalchemy as sa
from sqlalchemy.engine import Engine

from scanner.csv_cells import csv_cell
from slscan.station import StationError

SCHEMA_VERSION = 3
STATUSES = ("in_progress", "pass", "fail", "uncertain", "error", "aborted", "incomplete")
VERDICTS = ("pass", "fail", "uncertain", "error")  # the statuses of a cycle that ended with a verdict
OLD_RULE = "plain (before schema 3)"  # the rule of values stored by a schema 1 or 2 station
LEASE_S = 60.0  # a running cycle's lease; renewed every LEASE_S / 4
SCHEMA_LOCK_KEY = 0x736C7363616E  # "slscan": PostgreSQL's advisory lock taken while the schema is made
ATTEMPT_RETRIES = 50  # inserts retried (after a random pause) when a concurrent writer took the same number


class ResultsError(StationError):
    """The results database cannot be opened, is of another schema version, or a query failed."""


class UtcTime(sa.TypeDecorator):
    """A timezone-aware UTC time: TIMESTAMPTZ on PostgreSQL, ISO 8601 text on SQLite (which
    has no time type; the text sorts in time order)."""

    impl = sa.DateTime(timezone=True)
    cache_ok = True

    def load_dialect_impl(self, dialect: sa.Dialect) -> sa.types.TypeEngine[Any]:
        return dialect.type_descriptor(sa.Text() if dialect.name == "sqlite" else sa.DateTime(timezone=True))

    def process_bind_param(self, value: dt.datetime | None, dialect: sa.Dialect) -> Any:
        if value is None:
            return None
        value = value.astimezone(dt.UTC)
        return value.isoformat(timespec="microseconds") if dialect.name == "sqlite" else value

    def process_result_value(self, value: Any, dialect: sa.Dialect) -> dt.datetime | None:
        if value is None:
            return None
        t = dt.datetime.fromisoformat(value) if isinstance(value, str) else value
        return t.replace(tzinfo=dt.UTC) if t.tzinfo is None else t.astimezone(dt.UTC)


_META = sa.MetaData()
_SCHEMA = sa.Table("slscan_schema", _META, sa.Column("version", sa.Integer, nullable=False))
RESULTS = sa.Table(
    "results", _META,
    sa.Column("id", sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True, autoincrement=True),
    *(sa.Column(name, sa.Text, nullable=False) for name in ("program", "program_version", "program_fingerprint",
                                                             "serial")),
    sa.Column("attempt", sa.Integer, nullable=False),
    *(sa.Column(name, sa.Text, nullable=False) for name in ("operator", "station", "rig")),
    sa.Column("calibration_id", sa.Text),
    *(sa.Column(name, sa.Text, nullable=False) for name in ("software_version", "measurement", "part_path", "status",
                                                             "message")),
    sa.Column("started_at", UtcTime, nullable=False), sa.Column("finished_at", UtcTime),
    sa.Column("source", sa.Text, nullable=False),
    sa.Column("owner", sa.Text), sa.Column("lease_until", UtcTime),
    sa.Index("results_program", "program", "started_at"), sa.Index("results_serial", "program", "serial"),
    sa.Index("results_attempt", "program", "serial", "attempt", unique=True),
    sqlite_autoincrement=True)  # ids are never reused
MEASURED = sa.Table(
    "measured", _META,
    sa.Column("result_id", sa.BigInteger().with_variant(sa.Integer, "sqlite"),
              sa.ForeignKey("results.id", ondelete="CASCADE"), primary_key=True),
    sa.Column("position", sa.Integer, nullable=False),
    sa.Column("characteristic", sa.Text, primary_key=True),
    sa.Column("kind", sa.Text, nullable=False), sa.Column("face", sa.Text, nullable=False),
    sa.Column("value_mm", sa.Float), sa.Column("tolerance_mm", sa.Float, nullable=False),
    sa.Column("conforms", sa.Boolean), sa.Column("points", sa.Integer, nullable=False),
    sa.Column("note", sa.Text, nullable=False),
    sa.Column("u_mm", sa.Float), sa.Column("limit_mm", sa.Float), sa.Column("decision", sa.Text),
    sa.Column("rule", sa.Text))
_V3_VALUE_COLUMNS = ("u_mm", "limit_mm", "decision", "rule")
EXCLUSIONS = sa.Table(
    "exclusions", _META,
    sa.Column("result_id", sa.BigInteger().with_variant(sa.Integer, "sqlite"),
              sa.ForeignKey("results.id", ondelete="CASCADE"), primary_key=True),
    sa.Column("reason", sa.Text, nullable=False), sa.Column("excluded_by", sa.Text, nullable=False),
    sa.Column("excluded_at", UtcTime, nullable=False))


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
    """One characteristic's stored outcome: its value (None: not measured, `note` says why,
    or below its detection limit `limit_mm`), its expanded uncertainty `u_mm` (k = 2; None:
    not known), the ISO 14253-1 `decision` under `rule`, and `conforms` as a yes/no where
    the decision is one (None: uncertain or not measured)."""

    characteristic: str
    kind: str
    face: str
    value_mm: float | None
    tolerance_mm: float
    conforms: bool | None
    points: int
    note: str = ""
    u_mm: float | None = None
    limit_mm: float | None = None
    decision: str = ""
    rule: str = ""

    def shown(self) -> str:
        """The value as people read it (mm): "0.0312 ± 0.0025", "< 0.0085" below its
        detection limit, "not measured"."""
        if self.value_mm is None:
            return "not measured" if self.limit_mm is None else f"< {self.limit_mm:.4f}"
        return f"{self.value_mm:.4f}" + ("" if self.u_mm is None else f" ± {self.u_mm:.4f}")


@dataclass(frozen=True)
class ResultRow(PartStart):
    """A stored cycle, with its outcome."""

    id: int = 0
    attempt: int = 0
    status: str = ""
    message: str = ""
    finished_at: dt.datetime | None = None


@dataclass(frozen=True)
class Exclusion:
    """A result left out of the statistics by a user: why, who, when (UTC)."""

    result_id: int
    reason: str
    excluded_by: str
    excluded_at: dt.datetime

    def shown(self) -> str:
        """The reason with who and when, as the report and the listing show it."""
        return f"{self.reason} ({self.excluded_by}, {self.excluded_at:%Y-%m-%d %H:%M} UTC)"


_START_COLUMNS = [f.name for f in fields(PartStart)]
_RESULT_COLUMNS = _START_COLUMNS + ["id", "attempt", "status", "message", "finished_at"]
_VALUE_COLUMNS = [f.name for f in fields(ValueRecord)]


# ------------------------------------------------------------------------------ secrets


def secrets_in(url: str) -> list[str]:
    """The secrets a database URL carries: the password of `scheme://user:password@host`
    (which may itself hold '@') and any `password=` query parameter, as written and decoded."""
    found = []
    netloc = re.match(r"^[A-Za-z][\w+.-]*://([^/?#]*)", url)
    if netloc and "@" in netloc.group(1):
        creds = netloc.group(1).rsplit("@", 1)[0]
        if ":" in creds:
            found.append(creds.split(":", 1)[1])
    found += re.findall(r"(?i)(?:password|passwd)=([^&\s]*)", url)
    return sorted({s for raw in found if raw for s in (raw, unquote(raw))}, key=len, reverse=True)


def redact(text: str, url: str) -> str:
    """`text` with every secret of `url` replaced by ***."""
    for secret in secrets_in(url):
        text = text.replace(secret, "***")
    return text


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


# ------------------------------------------------------------------------------ ownership


def _process_start(pid: int) -> str:
    """A token that differs between two processes that had the same id: the start time in
    clock ticks after boot (Linux /proc), else empty (then the id alone is compared)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return ""
    return stat.rsplit(")", 1)[1].split()[19]  # field 22 of stat, counted after the command name


def this_owner() -> str:
    """This process as the owner of the cycles it runs: host:pid:start."""
    pid = os.getpid()
    return f"{socket.gethostname()}:{pid}:{_process_start(pid)}"


def owner_gone(owner: str | None, lease_until: dt.datetime | None, now: dt.datetime) -> bool:
    """Whether the process owning a running cycle is gone: a process of this host is asked
    directly (is its id running, with the same start time); one of another host by its
    lease (not renewed since `lease_until`). A cycle without owner predates owners: gone."""
    if not owner:
        return True
    host, _, rest = owner.partition(":")
    pid_text, _, start = rest.partition(":")
    if host != socket.gethostname() or not pid_text.isdigit():
        return lease_until is None or lease_until < now
    pid = int(pid_text)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        pass  # it runs, as another user
    return bool(start) and _process_start(pid) not in ("", start)


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


# ------------------------------------------------------------------------------ opening


def open_results(url: str, create: bool = True) -> ResultsStore:
    """The store at `url`: `sqlite:PATH` or `postgresql://...`. With `create` the SQLite
    folder and the tables are made when missing (a station); without, the database must
    already exist and is only read (`slscan results`: a mistyped folder is an error, not a
    new empty database)."""
    where = redact(url, url)
    if url.startswith("sqlite:"):
        path = Path(url[len("sqlite:"):])
        where = str(path)
        if create:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise ResultsError(f"{path}: cannot create the results folder {path.parent}: "
                                   f"{exc.strerror or exc}") from None
        elif not path.is_file():
            raise ResultsError(f"{path}: no results database there (is the data folder or --db right?)")
        target: str | sa.URL = f"sqlite:///{path}" if create else f"sqlite:///file:{path}?mode=ro&uri=true"
        engine = sa.create_engine(target, connect_args={"timeout": 30.0})
        sa.event.listen(engine, "connect", _sqlite_pragmas(create))
    elif url.startswith(("postgresql://", "postgres://")):
        if re.match(r"^[^:]+://[^/?#]*@[^/?#]*@", url):
            raise ResultsError(f"{where}: the URL's user or password holds '@': write it URL-encoded (%40)")
        try:
            target = sa.make_url(url).set(drivername="postgresql+psycopg")
            engine = sa.create_engine(target, connect_args={"connect_timeout": 10}, pool_pre_ping=True)
        except ModuleNotFoundError:
            raise ResultsError(f"{where}: PostgreSQL needs psycopg: pip install 'slscan[station-db]'") from None
        except (sa.exc.ArgumentError, ValueError) as exc:
            raise ResultsError(f"{where}: not a usable database URL: {_one_line(redact(str(exc), url))}") from None
    else:
        raise ResultsError(f"{where!r}: not a results database URL; use sqlite:PATH or postgresql://...")
    try:
        return ResultsStore(engine, where, url, create)
    except BaseException:
        engine.dispose()
        raise


def _sqlite_pragmas(writable: bool) -> Any:
    def on_connect(dbapi_conn: Any, _record: Any) -> None:
        cur = dbapi_conn.cursor()
        if writable:
            cur.execute("PRAGMA journal_mode=WAL")  # readers (slscan results) never block the station
        cur.execute("PRAGMA foreign_keys=ON")
        cur.close()
    return on_connect


class ResultsStore:
    """A connection pool to the results database; the schema is made or upgraded on open
    (`create`), else only checked."""

    def __init__(self, engine: Engine, where: str, url: str, create: bool = True) -> None:
        self.engine = engine
        self.where = where
        self.url = url  # as given, secrets included: for connecting, never for messages
        self.owner = this_owner()
        try:
            engine.connect().close()
        except sa.exc.SQLAlchemyError as exc:
            how = "open" if engine.dialect.name == "sqlite" else "connect to"
            cause = getattr(exc, "orig", None) or exc
            raise ResultsError(f"{where}: cannot {how} the results database: "
                               f"{_one_line(redact(str(cause), url))}") from None
        self._schema(create)

    def _schema(self, create: bool) -> None:
        """Make (with `create`) or upgrade the tables and check the schema version, in one
        transaction that holds the database's write lock from its start (two stations opening
        one new database would otherwise both find it empty and both write its version)."""
        with self._tx() as conn:
            if create and conn.dialect.name == "sqlite":
                conn.exec_driver_sql("BEGIN IMMEDIATE")  # the driver has not begun yet: take the write lock now
            elif create and conn.dialect.name == "postgresql":
                conn.execute(sa.text("SELECT pg_advisory_xact_lock(:key)"), {"key": SCHEMA_LOCK_KEY})
            if create:
                _META.create_all(conn)
            version = self._version(conn)
            if version is None and create:
                conn.execute(sa.insert(_SCHEMA).values(version=SCHEMA_VERSION))
            elif version in (1, 2) and create:
                if version == 1:
                    _upgrade_from_1(conn)
                _upgrade_from_2(conn)
            elif version != SCHEMA_VERSION:
                raise ResultsError(f"{self.where}: results schema version {version}, this slscan uses "
                                   f"{SCHEMA_VERSION}" + (" (a station opening it upgrades it)" if version in (1, 2)
                                                          else ""))

    def _version(self, conn: sa.Connection) -> int | None:
        if not sa.inspect(conn).has_table("slscan_schema"):
            raise ResultsError(f"{self.where}: not a results database (no slscan_schema table)")
        return conn.execute(sa.select(_SCHEMA.c.version)).scalar()

    def __enter__(self) -> ResultsStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.engine.dispose()

    def _error(self, exc: Exception) -> ResultsError:
        """The database's complaint as one line, without secrets."""
        cause = getattr(exc, "orig", None) or exc
        return ResultsError(f"{self.where}: {type(cause).__name__}: {_one_line(redact(str(cause), self.url))}")

    @contextmanager
    def _tx(self) -> Iterator[sa.Connection]:
        """A connection inside one committed transaction (rolled back on error)."""
        try:
            with self.engine.begin() as conn:
                yield conn
        except ResultsError:
            raise
        except sa.exc.SQLAlchemyError as exc:
            raise self._error(exc) from None

    # -- writing

    def begin_part(self, start: PartStart) -> tuple[int, int]:
        """Store a cycle as `in_progress`, owned by this process under a fresh lease; returns
        (result id, attempt number for this program and serial)."""
        values = {**asdict(start), "status": "in_progress", "message": "", "owner": self.owner,
                  "lease_until": utcnow() + dt.timedelta(seconds=LEASE_S)}
        c = RESULTS.c
        names = list(values)
        next_attempt = sa.func.coalesce(sa.func.max(c.attempt), 0) + 1
        chosen = sa.select(*(sa.literal(values[n], c[n].type) for n in names), next_attempt).where(
            c.program == start.program, c.serial == start.serial)
        stmt = sa.insert(RESULTS).from_select(names + ["attempt"], chosen).returning(c.id, c.attempt)
        for retry in range(ATTEMPT_RETRIES):
            try:
                with self.engine.begin() as conn:
                    rid, attempt = conn.execute(stmt).one()
                return int(rid), int(attempt)
            except sa.exc.IntegrityError as exc:  # another writer took this attempt number first
                if retry == ATTEMPT_RETRIES - 1:
                    raise self._error(exc) from None
                time.sleep(random.uniform(0.0, 0.001 * 2 ** min(retry, 7)))  # writers in step would collide again
            except sa.exc.SQLAlchemyError as exc:
                raise self._error(exc) from None
        raise AssertionError("unreachable")

    def renew(self, result_id: int) -> bool:
        """Extend this process's lease on a running cycle; False when it is not (any more)
        this process's running cycle."""
        with self._tx() as conn:
            done = conn.execute(sa.update(RESULTS).where(
                RESULTS.c.id == result_id, RESULTS.c.owner == self.owner, RESULTS.c.status == "in_progress").values(
                lease_until=utcnow() + dt.timedelta(seconds=LEASE_S)))
            return done.rowcount == 1

    @contextmanager
    def hold(self, result_id: int, every_s: float = LEASE_S / 4) -> Iterator[None]:
        """Renew the lease on `result_id` every `every_s` s while the block runs."""
        stop = threading.Event()

        def renew() -> None:
            while not stop.wait(every_s):
                with suppress(ResultsError):  # the database is away for now; the next renewal tries again
                    self.renew(result_id)
        thread = threading.Thread(target=renew, name=f"lease-{result_id}", daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()

    def finish_part(self, result_id: int, status: str, message: str, values: Sequence[ValueRecord],
                    finished_at: dt.datetime, part_path: str | None = None) -> None:
        """Store a cycle's outcome and its measured values, in one transaction."""
        if status not in STATUSES or status == "in_progress":
            raise ValueError(f"not a final status: {status!r}")
        c = RESULTS.c
        with self._tx() as conn:
            done = conn.execute(sa.update(RESULTS).where(c.id == result_id).values(
                status=status, message=message, finished_at=finished_at, lease_until=None,
                part_path=sa.func.coalesce(sa.literal(part_path, sa.Text), c.part_path)))
            if done.rowcount != 1:
                raise ResultsError(f"{self.where}: no result {result_id} to finish")
            conn.execute(sa.delete(MEASURED).where(MEASURED.c.result_id == result_id))
            if values:
                conn.execute(sa.insert(MEASURED), [{"result_id": result_id, "position": k, **asdict(v)}
                                                   for k, v in enumerate(values)])

    def mark_interrupted(self, station: str, message: str | Callable[[str | None], str],
                         now: dt.datetime | None = None) -> list[int]:
        """Cycles of this station left `in_progress` by a process that is gone (see the
        module docstring) become `incomplete` with `message` (or `message(part_path)`); a
        cycle whose owner still runs is left alone."""
        now = now or utcnow()
        c = RESULTS.c
        say = message if callable(message) else (lambda _: message)
        with self._tx() as conn:
            rows = conn.execute(sa.select(c.id, c.owner, c.lease_until, c.part_path).where(
                c.station == station, c.status == "in_progress").order_by(c.id)).all()
            stale = [r for r in rows if owner_gone(r.owner, r.lease_until, now)]
            for r in stale:
                conn.execute(sa.update(RESULTS).where(c.id == r.id, c.status == "in_progress").values(
                    status="incomplete", message=_one_line(say(r.part_path)), lease_until=None))
        return [int(r.id) for r in stale]

    # -- reading

    def results(self, program: str | None = None, serial: str | None = None, status: str | None = None,
                since: dt.datetime | None = None, limit: int | None = None) -> list[ResultRow]:
        """Stored cycles, oldest first (the newest `limit` when given)."""
        if limit is not None and limit < 0:
            raise ValueError(f"limit must be >= 0, got {limit}")
        c = RESULTS.c
        q = sa.select(*(c[n] for n in _RESULT_COLUMNS))
        for col, val in (("program", program), ("serial", serial), ("status", status)):
            if val is not None:
                q = q.where(c[col] == val)
        if since is not None:
            q = q.where(c.started_at >= since)
        q = q.order_by(c.id.desc()).limit(limit)
        with self._tx() as conn:
            rows = conn.execute(q).all()
        return [ResultRow(**r._asdict()) for r in reversed(rows)]

    def result(self, result_id: int) -> ResultRow:
        with self._tx() as conn:
            row = conn.execute(sa.select(*(RESULTS.c[n] for n in _RESULT_COLUMNS)).where(
                RESULTS.c.id == result_id)).one_or_none()
        if row is None:
            raise ResultsError(f"{self.where}: no result {result_id}")
        return ResultRow(**row._asdict())

    def values(self, result_ids: Sequence[int]) -> dict[int, list[ValueRecord]]:
        """Measured values per result id, in stored order."""
        out: dict[int, list[ValueRecord]] = {int(i): [] for i in result_ids}
        if not out:
            return out
        m = MEASURED.c
        with self._tx() as conn:
            rows = conn.execute(sa.select(m.result_id, *(m[n] for n in _VALUE_COLUMNS)).where(
                m.result_id.in_(list(out))).order_by(m.result_id, m.position)).all()
        for r in rows:
            rec = r._asdict()
            out[int(rec.pop("result_id"))].append(ValueRecord(**rec))
        return out


    def exclude(self, result_id: int, reason: str, by: str, at: dt.datetime | None = None) -> Exclusion:
        """Record that result `result_id` is left out of the statistics, `by` whom and why
        (an earlier exclusion of it is replaced); ResultsError when there is no such result."""
        self.result(result_id)
        done = Exclusion(result_id, reason, by, at or utcnow())
        with self._tx() as conn:
            conn.execute(sa.delete(EXCLUSIONS).where(EXCLUSIONS.c.result_id == result_id))
            conn.execute(sa.insert(EXCLUSIONS).values(**asdict(done)))
        return done

    def include(self, result_id: int) -> bool:
        """Lift the exclusion of `result_id`; whether there was one."""
        with self._tx() as conn:
            return conn.execute(sa.delete(EXCLUSIONS).where(EXCLUSIONS.c.result_id == result_id)).rowcount > 0

    def exclusions(self) -> dict[int, Exclusion]:
        """Every recorded exclusion by result id (none in a database that has no table yet)."""
        with self._tx() as conn:
            if not sa.inspect(conn).has_table(EXCLUSIONS.name):
                return {}
            rows = conn.execute(sa.select(EXCLUSIONS).order_by(EXCLUSIONS.c.result_id)).all()
        return {int(r.result_id): Exclusion(**r._asdict()) for r in rows}


def _upgrade_from_1(conn: sa.Connection) -> None:
    """Schema 1 -> 2: the owner and lease columns and the unique attempt index (attempt
    numbers that version 1 gave twice are renumbered in id order first)."""
    for column in (RESULTS.c.owner, RESULTS.c.lease_until):
        kind = column.type.compile(dialect=conn.dialect)
        conn.execute(sa.text(f"ALTER TABLE results ADD COLUMN {column.name} {kind}"))
    c = RESULTS.c
    seen: dict[tuple[str, str], int] = {}
    for rid, program, serial, attempt in conn.execute(sa.select(c.id, c.program, c.serial, c.attempt).order_by(c.id)):
        want = seen.get((program, serial), 0) + 1
        seen[(program, serial)] = want
        if attempt != want:
            conn.execute(sa.update(RESULTS).where(c.id == rid).values(attempt=want))
    next(i for i in RESULTS.indexes if i.name == "results_attempt").create(conn)
    conn.execute(sa.update(_SCHEMA).values(version=2))


def _upgrade_from_2(conn: sa.Connection) -> None:
    """Schema 2 -> 3: the values' U, detection limit, decision and rule; a stored value's
    decision is what its plain comparison said (`OLD_RULE`)."""
    for name in _V3_VALUE_COLUMNS:
        kind = MEASURED.c[name].type.compile(dialect=conn.dialect)
        conn.execute(sa.text(f"ALTER TABLE measured ADD COLUMN {name} {kind}"))
    m = MEASURED.c
    conn.execute(sa.update(MEASURED).values(rule=OLD_RULE, decision=sa.case(
        (m.conforms.is_(True), "conforming"), (m.conforms.is_(False), "non-conforming"), else_="not measured")))
    conn.execute(sa.update(_SCHEMA).values(version=SCHEMA_VERSION))


# ------------------------------------------------------------------------------ export

_CSV_RESULT_COLUMNS = ["id"] + [c for c in _RESULT_COLUMNS if c != "id"]
def write_csv(out: TextIO, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]]) -> int:
    """One CSV line per measured characteristic (a cycle without values: one line with
    empty value columns); times in ISO 8601 UTC; text cells escaped (`csv_cell`). Returns
    the number of lines written."""
    w = csv.writer(out)
    w.writerow(["result_id"] + _CSV_RESULT_COLUMNS[1:] + _VALUE_COLUMNS)
    n = 0
    for r in rows:
        head = [csv_cell(getattr(r, c)) for c in _CSV_RESULT_COLUMNS]
        cycle: list[ValueRecord | None] = [*values.get(r.id, [])] or [None]  # None: one line without values
        for v in cycle:
            w.writerow(head + ([csv_cell(getattr(v, c)) for c in _VALUE_COLUMNS] if v else [""] * len(_VALUE_COLUMNS)))
            n += 1
    return n


def csv_text(rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]]) -> tuple[str, int]:
    """The CSV export as text (written to a file atomically by the caller) and its line count."""
    buf = io.StringIO(newline="")
    n = write_csv(buf, rows, values)
    return buf.getvalue(), n
