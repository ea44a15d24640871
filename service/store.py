"""The result store: a row per accepted trigger, in an SQLite file or a PostgreSQL database.

SQLite (one file, WAL mode) is the embedded default; a ``postgresql://`` URL
puts the results of several stations into one database that an API on
another host reads. Both run the same queries and the same :data:`MIGRATIONS`;
a backend class holds only what the two differ in (connecting, placeholders,
taking the write lock).

Every result is upserted by its ``id``, so a trigger published twice (a
retry, a replay into the same store) still has exactly one row. The full
result is kept as JSON beside indexed columns used for filtering; a
``schema_version`` table and the :data:`MIGRATIONS` list take a database from
any earlier layout to the current one when it is opened.

Parts created over the API are kept here too (:class:`StoredPart`: the spec
and the CAD file's bytes), so that a station's worker and its Dask workers
on hosts that share no filesystem with the API measure them. Each creation
is a new *revision* of its name; deleting a part retires its revision but
keeps it, so a result measured with it (its ``spec_version``, ``cad_hash``,
``tree_hash``) can still be traced to the very spec and CAD it was measured
against.

Per-point deviations are too large for a row; :class:`DeviationArchive`
keeps them as one ``.npz`` per inspection in the data directory.

Errors::

    StoreError         a database from a newer version, not a store at all,
     │                 a server that cannot be reached, a statement that failed
     ├── PartExists    creating a part whose name has a current revision
     └── CopyConflict  copying into a store that holds other data under the same keys
"""

from __future__ import annotations

import base64
import binascii
import builtins
import contextlib
import hashlib
import logging
import os
import re
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

import numpy as np

from .models import Alarm, Baseline, InspectionResult, Status
from .names import ID_PATTERN
from .store_url import check_postgres_url, is_postgres_url, redact_url

if TYPE_CHECKING:
    import psycopg

log = logging.getLogger(__name__)

MIGRATIONS: list[str] = [
    # 1: results with the columns the API filters and orders by. BIGINT: nanosecond
    # times pass 2**31 (PostgreSQL's INTEGER); SQLite's integers are 64-bit either way.
    """
    CREATE TABLE results (
        id            TEXT PRIMARY KEY,
        line          TEXT NOT NULL,
        station       TEXT NOT NULL,
        part          TEXT NOT NULL,
        serial        TEXT NOT NULL,
        seq           BIGINT NOT NULL,
        triggered_ns  BIGINT NOT NULL,
        status        TEXT NOT NULL,
        body          TEXT NOT NULL,
        stored_ns     BIGINT NOT NULL
    );
    CREATE INDEX results_time ON results (triggered_ns, id);
    CREATE INDEX results_part_time ON results (part, triggered_ns, id);
    CREATE INDEX results_status_time ON results (status, triggered_ns, id);
    """,
    # 2: a restarted worker asks for its station's last trigger.
    """
    CREATE INDEX results_station_seq ON results (line, station, seq);
    """,
    # 3: alarms (acknowledged by a person, or open) and frozen control-chart baselines;
    # look-ups by serial.
    """
    CREATE TABLE alarms (
        id            TEXT PRIMARY KEY,
        line          TEXT NOT NULL,
        station       TEXT NOT NULL,
        kind          TEXT NOT NULL,
        raised_ns     BIGINT NOT NULL,
        acknowledged  INTEGER NOT NULL,
        body          TEXT NOT NULL
    );
    CREATE INDEX alarms_time ON alarms (raised_ns, id);
    CREATE TABLE baselines (
        part          TEXT PRIMARY KEY,
        frozen_ns     BIGINT NOT NULL,
        body          TEXT NOT NULL
    );
    CREATE INDEX results_serial ON results (serial, triggered_ns, id);
    """,
    # 4: parts created over the API, every revision of each; the current one (not retired)
    # is unique per name. BYTEA: PostgreSQL's bytes; SQLite keeps bytes under any type.
    """
    CREATE TABLE parts (
        name          TEXT NOT NULL,
        revision      BIGINT NOT NULL,
        key           TEXT NOT NULL,
        spec          TEXT NOT NULL,
        cad           BYTEA NOT NULL,
        created_ns    BIGINT NOT NULL,
        retired_ns    BIGINT,
        PRIMARY KEY (name, revision)
    );
    CREATE UNIQUE INDEX parts_current ON parts (name) WHERE retired_ns IS NULL;
    """,
]
"""Schema migrations, in order; the database's version is the number applied.

Each is SQL that SQLite and PostgreSQL both take, statements separated by ``;``.
"""

SCHEMA_VERSION = len(MIGRATIONS)

MAX_LIMIT = 1000

T = TypeVar("T")

_SQLITE_BUSY_S = 30.0  # how long a connection waits for another holding the file

_ID_RE = re.compile(ID_PATTERN)

_UPSERT = """
    INSERT INTO results
        (id, line, station, part, serial, seq, triggered_ns, status, body, stored_ns)
    VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)
    ON CONFLICT (id) DO UPDATE SET
        line = excluded.line, station = excluded.station, part = excluded.part,
        serial = excluded.serial, seq = excluded.seq,
        triggered_ns = excluded.triggered_ns, status = excluded.status,
        body = excluded.body, stored_ns = excluded.stored_ns
"""


# The first acknowledgement stands: a write of an alarm that is acknowledged here already
# (a copy from a store where nobody acknowledged it, a second acknowledgement) changes nothing.
_PUT_ALARM = """
    INSERT INTO alarms (id, line, station, kind, raised_ns, acknowledged, body)
    VALUES (?, ?, ?, ?, ?, ?, ?) ON CONFLICT (id) DO UPDATE SET
        acknowledged = excluded.acknowledged, body = excluded.body
    WHERE alarms.acknowledged = 0
"""


class StoreError(Exception):
    """The store cannot be used: newer than this software, not a result store,
    unreachable, or a statement failed in the database."""


class PartExists(StoreError):
    """A part of that name has a current revision already (retire it first)."""


class CopyConflict(StoreError):
    """The target of a copy holds other data under a key the source uses: a part revision
    of the same name and number with another spec or CAD, another current revision of a
    part, or another frozen baseline of a part."""


class InvalidCursor(ValueError):
    """A pagination cursor that this store did not hand out."""


@dataclass(frozen=True, eq=False)
class StoredPart:
    """One revision of a part created over the API, as the store keeps it.

    Attributes
    ----------
    name : str
    revision : int
        1 for the first creation of ``name``, then one more each time it is created again.
    key : str
        Hash of ``spec`` and ``cad`` (:func:`part_key`): the same content, the same key.
    spec : str
        The part spec as JSON (``service.config.PartSpec``); its ``cad`` names the file
        ``cad`` holds (its suffix says the format).
    cad : bytes
        The CAD file as uploaded.
    created_ns : int
        When it was created, ns since the epoch.
    retired_ns : int or None
        When it was deleted (or created again); None: the current revision.
    """

    name: str
    revision: int
    key: str
    spec: str
    cad: bytes
    created_ns: int
    retired_ns: int | None = None


@dataclass(frozen=True)
class PartRevision:
    """What identifies a part revision the store keeps, without its spec and CAD
    (:meth:`ResultStore.part_index`); the fields are :class:`StoredPart`'s."""

    name: str
    revision: int
    key: str
    retired_ns: int | None


def part_key(spec: str, cad: bytes) -> str:
    """The content hash of a part revision: its spec JSON and its CAD bytes (24 hex digits)."""
    h = hashlib.sha256()
    h.update(hashlib.sha256(spec.encode()).digest())
    h.update(hashlib.sha256(cad).digest())
    return h.hexdigest()[:24]


@dataclass(frozen=True)
class Filters:
    """What a listing selects: each field ``None`` means no restriction."""

    part: str | None = None
    status: Status | None = None
    since_ns: int | None = None
    until_ns: int | None = None
    """Up to and including this trigger time."""
    serial: str | None = None
    station: str | None = None


def encode_cursor(triggered_ns: int, id_: str) -> str:
    """An opaque cursor pointing after the row (``triggered_ns``, ``id``)."""
    return base64.urlsafe_b64encode(f"{triggered_ns}:{id_}".encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[int, str]:
    """Inverse of :func:`encode_cursor`; raises :class:`InvalidCursor`."""
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode()
        ns, id_ = raw.split(":", 1)
        value = int(ns)
    except (binascii.Error, UnicodeDecodeError, ValueError) as exc:
        raise InvalidCursor(f"not a valid cursor: {cursor!r}") from exc
    if not 0 <= value < 2**63 or not id_:
        raise InvalidCursor(f"not a valid cursor: {cursor!r}")
    return value, id_


# --------------------------------------------------------------------------- backends


class _Cursor(Protocol):
    @property
    def rowcount(self) -> int: ...

    def fetchone(self) -> Any: ...

    def fetchall(self) -> list[Any]: ...


class _Backend(Protocol):
    """One connection to one database, and what the two databases differ in.

    Statements are written with ``?`` placeholders. Callers hold the store's
    lock around every use.
    """

    where: str
    """The database, for messages: a file name, or the URL without its password."""
    errors: tuple[type[Exception], ...]
    """The driver's exceptions, which the store reports as :class:`StoreError`."""
    integrity: type[Exception]
    """The driver's exception for a statement that broke a key or a unique index."""

    def execute(self, sql: str, params: Sequence[object] = ()) -> _Cursor: ...

    def executemany(self, sql: str, rows: Sequence[Sequence[object]]) -> None: ...

    def begin(self, *, schema: bool = False) -> None:
        """Open a write transaction; ``schema``: one that also excludes other migrations."""

    def lost(self) -> bool:
        """Whether the connection was lost (the last statement could not reach the database)."""

    def ensure_connected(self) -> None:
        """Reconnect when the connection was lost."""

    def close(self) -> None: ...


class _Sqlite:
    errors: tuple[type[Exception], ...] = (sqlite3.Error,)
    integrity: type[Exception] = sqlite3.IntegrityError

    def __init__(self, path: str) -> None:
        self.where = path
        if path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = sqlite3.connect(
                path, check_same_thread=False, isolation_level=None, timeout=_SQLITE_BUSY_S
            )
            self._wal()
            # In WAL mode NORMAL still survives a process crash; only an OS crash
            # can lose the last transactions.
            self._db.execute("PRAGMA synchronous=NORMAL")
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{path}: not a result store: {exc}") from exc

    def _wal(self) -> None:
        # Turning a new file to WAL takes its lock without waiting on the busy
        # timeout: several processes opening one new store at once see "database
        # is locked" here, so this waits for the others as the timeout would.
        deadline = time.monotonic() + _SQLITE_BUSY_S
        while True:
            try:
                self._db.execute("PRAGMA journal_mode=WAL")
                return
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() > deadline:
                    raise
                time.sleep(0.01)

    def execute(self, sql: str, params: Sequence[object] = ()) -> _Cursor:
        return self._db.execute(sql, params)

    def executemany(self, sql: str, rows: Sequence[Sequence[object]]) -> None:
        self._db.executemany(sql, rows)

    def begin(self, *, schema: bool = False) -> None:
        # IMMEDIATE takes the file's write lock at once: two processes opening a new
        # file cannot both read version 0 and both migrate it.
        self._db.execute("BEGIN IMMEDIATE")

    def lost(self) -> bool:
        return False  # a file does not go away

    def ensure_connected(self) -> None:
        pass

    def close(self) -> None:
        self._db.close()


_SCHEMA_LOCK = 0x696E_7370  # "insp": the advisory lock key migrations take in PostgreSQL


class _Postgres:
    def __init__(self, url: str) -> None:
        # Imported here: an SQLite store does not pay for loading libpq.
        import psycopg
        from psycopg.conninfo import conninfo_to_dict

        self._psycopg = psycopg
        self.errors: tuple[type[Exception], ...] = (psycopg.Error,)
        self.integrity: type[Exception] = psycopg.IntegrityError
        self.url = url
        self.where = redact_url(url)
        try:
            given = conninfo_to_dict(check_postgres_url(url))
        except ValueError as exc:
            raise StoreError(str(exc)) from None
        # A host that drops packets would hold a start-up for minutes; a DBA sees
        # who holds a connection. A URL that says otherwise wins.
        self._defaults: dict[str, Any] = {
            k: v
            for k, v in {"connect_timeout": 10, "application_name": "inspection"}.items()
            if k not in given
        }
        self._db = self._connect()

    def _connect(self) -> psycopg.Connection[Any]:
        try:
            return self._psycopg.connect(self.url, autocommit=True, **self._defaults)
        except self._psycopg.Error as exc:
            raise StoreError(f"{self.where}: cannot connect: {_first_line(exc)}") from exc

    def execute(self, sql: str, params: Sequence[object] = ()) -> _Cursor:
        # Our statements hold no literal "?" or "%": the placeholders are all there is.
        return self._db.execute(sql.replace("?", "%s"), params)

    def executemany(self, sql: str, rows: Sequence[Sequence[object]]) -> None:
        with self._db.cursor() as cur:
            cur.executemany(sql.replace("?", "%s"), rows)

    def begin(self, *, schema: bool = False) -> None:
        self._db.execute("BEGIN")
        if schema:
            # DDL is transactional here, but CREATE TABLE IF NOT EXISTS is not safe
            # against a second process doing the same: one migrator at a time.
            self._db.execute("SELECT pg_advisory_xact_lock(%s)", (_SCHEMA_LOCK,))

    def lost(self) -> bool:
        # A server restart or a dropped link leaves the connection broken.
        return bool(self._db.broken)

    def ensure_connected(self) -> None:
        if self._db.broken:
            self._db = self._connect()

    def close(self) -> None:
        self._db.close()


def _first_line(exc: Exception) -> str:
    return " ".join(str(exc).split("\n", 1)[0].split()) or type(exc).__name__


def _attempt(db: _Backend, work: Callable[[_Backend], T], transaction: bool, schema: bool) -> T:
    db.ensure_connected()
    if not transaction:
        return work(db)
    db.begin(schema=schema)
    try:
        out = work(db)
    except BaseException:
        # A lost connection has rolled back already; its own error is the one to tell.
        with contextlib.suppress(*db.errors):
            db.execute("ROLLBACK")
        raise
    db.execute("COMMIT")
    return out


def _open_backend(target: str | Path) -> _Backend:
    if is_postgres_url(target):
        return _Postgres(str(target))
    return _Sqlite(str(target))


# --------------------------------------------------------------------------- the store


class ResultStore:
    """Inspection results in an SQLite file or a PostgreSQL database.

    Thread-safe: one connection shared behind a lock (the worker thread writes
    while the API's threads read), for either database. One connection per
    process keeps a shared server's connections to one per worker and API,
    whatever the API's thread pool, and serves many times the line's rate of
    results. Open with :meth:`open` or the constructor and close with
    :meth:`close` (or use it as a context manager).

    Parameters
    ----------
    target : str or Path
        A ``postgresql://`` URL (see :mod:`service.store_url`), else the
        SQLite file (created with its parents) or ``":memory:"``.

    Attributes
    ----------
    where : str
        The database, for messages: the file, or the URL without its password.

    Raises
    ------
    StoreError
        Not a result store, a schema newer than this software's, or a server
        that cannot be reached.
    """

    def __init__(self, target: str | Path) -> None:
        self._lock = threading.Lock()
        self._backend = _open_backend(target)
        self.where = self._backend.where
        try:
            self._migrate()
        except BaseException:
            self._backend.close()
            raise

    @classmethod
    def open(cls, target: str | Path) -> ResultStore:
        return cls(target)

    def __enter__(self) -> ResultStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        with self._lock:
            self._backend.close()

    def _run(
        self, work: Callable[[_Backend], T], *, transaction: bool = False, schema: bool = False
    ) -> T:
        """``work(db)`` on the connection, held by this thread alone, in one write
        transaction when ``transaction``; the driver's errors come out as StoreError.

        A connection lost under ``work`` (a server restart, a dropped link) is
        replaced and ``work`` runs once more: every statement of the store may be
        repeated (upserts by id, deletes, reads), so a database server that
        restarted between two results costs none.
        """
        db = self._backend
        with self._lock:
            try:
                return _attempt(db, work, transaction, schema)
            except db.errors as exc:
                if not db.lost():
                    raise StoreError(f"{self.where}: {_first_line(exc)}") from exc
                log.warning("%s: connection lost (%s); reconnecting", self.where, _first_line(exc))
            try:
                return _attempt(db, work, transaction, schema)
            except db.errors as exc:
                raise StoreError(f"{self.where}: {_first_line(exc)}") from exc

    # ------------------------------------------------------------------ schema

    def _migrate(self) -> None:
        # One write transaction from reading the version to the last step: a
        # worker and an API opening a new database at once must not both migrate it.
        def work(db: _Backend) -> None:
            db.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
            row = db.execute("SELECT version FROM schema_version").fetchone()
            version = 0 if row is None else int(row[0])
            if row is None:
                db.execute("INSERT INTO schema_version (version) VALUES (0)")
            if version > SCHEMA_VERSION:
                raise StoreError(
                    f"{self.where}: schema version {version} is newer than this "
                    f"software's ({SCHEMA_VERSION}); upgrade the software"
                )
            for i in range(version, SCHEMA_VERSION):
                log.info("%s: migrating schema %d -> %d", self.where, i, i + 1)
                for stmt in _split_sql(MIGRATIONS[i]):
                    db.execute(stmt)
                db.execute("UPDATE schema_version SET version = ?", (i + 1,))

        self._run(work, transaction=True, schema=True)

    @property
    def schema_version(self) -> int:
        return self._run(
            lambda db: int(db.execute("SELECT version FROM schema_version").fetchone()[0])
        )

    # ------------------------------------------------------------------ writes

    def put(self, result: InspectionResult) -> None:
        """Insert ``result`` or replace the row with the same ``id``."""
        row = _row(result)
        self._run(lambda db: db.execute(_UPSERT, row))

    def put_many(self, results: Iterable[InspectionResult]) -> int:
        """:meth:`put` each of ``results``, all in one transaction; returns how many."""
        rows = [_row(r) for r in results]
        if rows:
            self._run(lambda db: db.executemany(_UPSERT, rows), transaction=True)
        return len(rows)

    def enforce(self, max_bytes: int | None, max_age_s: float | None) -> int:
        """Delete the oldest rows beyond ``max_bytes`` of result JSON or older than
        ``max_age_s`` (by trigger time); returns how many went.

        The budget counts the JSON's characters, the same on either database; the
        space freed is reused by new rows (SQLite's free pages, PostgreSQL's
        vacuum), so the database stops growing. Acknowledged alarms raised before
        the oldest result still kept go with the results; an open alarm stays
        until someone acknowledges it.
        """

        def work(db: _Backend) -> int:
            removed = _results(db)
            if removed:
                oldest = db.execute("SELECT MIN(triggered_ns) FROM results").fetchone()[0]
                db.execute(
                    "DELETE FROM alarms WHERE acknowledged = 1 AND raised_ns < ?",
                    (time.time_ns() if oldest is None else int(oldest),),
                )
            return removed

        def _results(db: _Backend) -> int:
            removed = 0
            if max_age_s is not None:
                cutoff = time.time_ns() - int(max_age_s * 1e9)
                removed += db.execute(
                    "DELETE FROM results WHERE triggered_ns < ?", (cutoff,)
                ).rowcount
            if max_bytes is None:
                return removed
            total = db.execute("SELECT COALESCE(SUM(LENGTH(body)), 0) FROM results").fetchone()
            excess = int(total[0]) - max_bytes
            if excess <= 0:
                return removed
            # The oldest rows whose bodies add up to the excess, in one pass.
            row = db.execute(
                """
                SELECT triggered_ns, id FROM (
                    SELECT triggered_ns, id, SUM(LENGTH(body)) OVER (
                        ORDER BY triggered_ns, id ROWS UNBOUNDED PRECEDING) AS upto
                    FROM results) AS running
                WHERE upto >= ? ORDER BY triggered_ns, id LIMIT 1
                """,
                (excess,),
            ).fetchone()
            if row is not None:
                removed += db.execute(
                    "DELETE FROM results WHERE triggered_ns < ? OR (triggered_ns = ? AND id <= ?)",
                    (row[0], row[0], row[1]),
                ).rowcount
            return removed

        return self._run(work, transaction=True)

    def delete_part(self, part: str) -> int:
        """Delete every result of ``part``; returns how many rows went."""
        return self._run(
            lambda db: db.execute("DELETE FROM results WHERE part = ?", (part,)).rowcount
        )

    # ------------------------------------------------------------------ reads

    def get(self, id_: str) -> InspectionResult | None:
        row = self._run(
            lambda db: db.execute("SELECT body FROM results WHERE id = ?", (id_,)).fetchone()
        )
        return None if row is None else InspectionResult.model_validate_json(row[0])

    def has(self, id_: str) -> bool:
        """Whether a result with this id is stored."""
        row = self._run(
            lambda db: db.execute("SELECT 1 FROM results WHERE id = ?", (id_,)).fetchone()
        )
        return row is not None

    def last_trigger(self, line: str, station: str) -> tuple[int, int] | None:
        """``(seq, triggered_ns)`` of the station's highest stored seq, or None.

        Uploads (seq 0, another station name) never count: they are not triggers.
        """
        row = self._run(
            lambda db: db.execute(
                "SELECT seq, triggered_ns FROM results WHERE line = ? AND station = ? "
                "ORDER BY seq DESC LIMIT 1",
                (line, station),
            ).fetchone()
        )
        return None if row is None else (int(row[0]), int(row[1]))

    def station_results(
        self,
        line: str,
        station: str,
        *,
        seq: tuple[int, int] = (0, 2**63 - 1),
        since_ns: int = 0,
        until_ns: int = 2**63 - 1,
        limit: int = MAX_LIMIT,
    ) -> list[InspectionResult]:
        """A station's results within a seq range (both ends included) and a trigger-time
        range, lowest seq first, at most ``limit``."""
        rows = self._run(
            lambda db: db.execute(
                "SELECT body FROM results WHERE line = ? AND station = ? AND seq BETWEEN ? AND ? "
                "AND triggered_ns BETWEEN ? AND ? ORDER BY seq, triggered_ns, id LIMIT ?",
                (line, station, seq[0], seq[1], since_ns, until_ns, limit),
            ).fetchall()
        )
        return [InspectionResult.model_validate_json(r[0]) for r in rows]

    def count(self, filters: Filters | None = None) -> int:
        where, params = _where(filters or Filters())
        row = self._run(
            lambda db: db.execute(f"SELECT COUNT(*) FROM results {where}", params).fetchone()
        )
        return int(row[0])

    def list(
        self,
        filters: Filters | None = None,
        *,
        limit: int = 50,
        cursor: str | None = None,
        oldest_first: bool = False,
    ) -> tuple[list[InspectionResult], str | None]:
        """One page of results, newest trigger first (or oldest first).

        Parameters
        ----------
        filters : Filters, optional
        limit : int
            1..:data:`MAX_LIMIT` results.
        cursor : str, optional
            The ``next`` of the previous page (listed in the same order).
        oldest_first : bool
            Oldest trigger first: a reader catching up on what it missed.

        Returns
        -------
        items : list of InspectionResult
        next : str or None
            Cursor of the following page; None when this page is the last.

        Raises
        ------
        ValueError
            ``limit`` out of range; :class:`InvalidCursor` for a bad cursor.
        """
        if not 1 <= limit <= MAX_LIMIT:
            raise ValueError(f"limit must be within 1..{MAX_LIMIT}, got {limit}")
        where, params = _where(filters or Filters())
        below, order = (">", "ASC") if oldest_first else ("<", "DESC")
        if cursor is not None:
            ns, id_ = decode_cursor(cursor)
            # Keyset pagination: stable while new rows arrive at the top.
            where += (
                " AND " if where else "WHERE "
            ) + f"(triggered_ns {below} ? OR (triggered_ns = ? AND id {below} ?))"
            params += [ns, ns, id_]
        sql = f"SELECT body FROM results {where} ORDER BY triggered_ns {order}, id {order} LIMIT ?"
        rows = self._run(lambda db: db.execute(sql, [*params, limit + 1]).fetchall())
        items = [InspectionResult.model_validate_json(r[0]) for r in rows[:limit]]
        nxt = encode_cursor(items[-1].triggered_ns, items[-1].id) if len(rows) > limit else None
        return items, nxt

    def iter_all(
        self, filters: Filters | None = None, *, page: int = 500
    ) -> Iterator[InspectionResult]:
        """Every matching result, newest first, fetched a page at a time."""
        cursor = None
        while True:
            items, cursor = self.list(filters, limit=page, cursor=cursor)
            yield from items
            if cursor is None:
                return

    def status_counts(self) -> dict[str, int]:
        """How many results have each status (for metrics)."""
        rows = self._run(
            lambda db: db.execute("SELECT status, COUNT(*) FROM results GROUP BY status").fetchall()
        )
        return {s.value: 0 for s in Status} | {r[0]: int(r[1]) for r in rows}

    def measured(
        self,
        part: str,
        *,
        limit: int = 50,
        oldest: bool = False,
        since_ns: int = 0,
        until_ns: int = 2**63 - 1,
    ) -> builtins.list[InspectionResult]:
        """A part's results with a measurement (status pass or fail), oldest first.

        ``limit`` of them: the newest (default) or the oldest ones within the
        trigger-time range (both ends included). A part with an error or a
        missed part has no measurement, and a not-measurable one none to chart.
        """
        if limit < 1:
            raise ValueError(f"limit must be at least 1, got {limit}")
        order = "ASC" if oldest else "DESC"
        rows = self._run(
            lambda db: db.execute(
                f"""
                SELECT body FROM results WHERE part = ? AND status IN (?, ?)
                AND triggered_ns BETWEEN ? AND ?
                ORDER BY triggered_ns {order}, id {order} LIMIT ?
                """,
                (part, Status.passed.value, Status.fail.value, since_ns, until_ns, limit),
            ).fetchall()
        )
        out = [InspectionResult.model_validate_json(r[0]) for r in rows]
        return out if oldest else out[::-1]

    # ------------------------------------------------------------------ alarms

    def put_alarm(self, alarm: Alarm) -> None:
        """Insert ``alarm``, or replace the one with its id (an acknowledgement) unless that
        one is acknowledged: the first acknowledgement stands."""
        row = (
            alarm.id, alarm.line, alarm.station, alarm.kind.value, alarm.raised_ns,
            int(alarm.acknowledged_ns is not None), alarm.model_dump_json(),
        )  # fmt: skip
        self._run(lambda db: db.execute(_PUT_ALARM, row))

    def put_alarms(self, alarms: Iterable[Alarm]) -> int:
        """:meth:`put_alarm` each of ``alarms``, all in one transaction; returns how many."""
        rows = [
            (a.id, a.line, a.station, a.kind.value, a.raised_ns,
             int(a.acknowledged_ns is not None), a.model_dump_json())
            for a in alarms
        ]  # fmt: skip
        if rows:
            self._run(lambda db: db.executemany(_PUT_ALARM, rows), transaction=True)
        return len(rows)

    def iter_alarms(self, *, page: int = 500) -> Iterator[Alarm]:
        """Every alarm, acknowledged or not, oldest first, fetched a page at a time."""
        after: tuple[int, str] = (-1, "")
        while True:
            params = (after[0], after[0], after[1], page)
            rows = self._run(
                lambda db: db.execute(
                    "SELECT raised_ns, id, body FROM alarms WHERE raised_ns > ? "
                    "OR (raised_ns = ? AND id > ?) ORDER BY raised_ns, id LIMIT ?",
                    params,  # noqa: B023 (run before the loop goes on)
                ).fetchall()
            )
            yield from (Alarm.model_validate_json(r[2]) for r in rows)
            if len(rows) < page:
                return
            after = (int(rows[-1][0]), str(rows[-1][1]))

    def alarm(self, id_: str) -> Alarm | None:
        row = self._run(
            lambda db: db.execute("SELECT body FROM alarms WHERE id = ?", (id_,)).fetchone()
        )
        return None if row is None else Alarm.model_validate_json(row[0])

    def alarms(self, *, open_only: bool = False, limit: int = 50) -> builtins.list[Alarm]:
        """The newest alarms first; ``open_only``: those nobody acknowledged."""
        where = "WHERE acknowledged = 0" if open_only else ""
        rows = self._run(
            lambda db: db.execute(
                f"SELECT body FROM alarms {where} ORDER BY raised_ns DESC, id DESC LIMIT ?",
                (limit,),
            ).fetchall()
        )
        return [Alarm.model_validate_json(r[0]) for r in rows]

    # ------------------------------------------------------------------ baselines

    def put_baseline(self, baseline: Baseline) -> None:
        row = (baseline.part, baseline.frozen_ns, baseline.model_dump_json())
        self._run(
            lambda db: db.execute(
                "INSERT INTO baselines (part, frozen_ns, body) VALUES (?, ?, ?) "
                "ON CONFLICT (part) DO UPDATE SET frozen_ns = excluded.frozen_ns, "
                "body = excluded.body",
                row,
            )
        )

    def baseline(self, part: str) -> Baseline | None:
        row = self._run(
            lambda db: db.execute("SELECT body FROM baselines WHERE part = ?", (part,)).fetchone()
        )
        return None if row is None else Baseline.model_validate_json(row[0])

    def delete_baseline(self, part: str) -> bool:
        n = self._run(
            lambda db: db.execute("DELETE FROM baselines WHERE part = ?", (part,)).rowcount
        )
        return bool(n)

    def baselines(self) -> builtins.list[Baseline]:
        """Every frozen baseline, by part name."""
        rows = self._run(
            lambda db: db.execute("SELECT body FROM baselines ORDER BY part").fetchall()
        )
        return [Baseline.model_validate_json(r[0]) for r in rows]

    # ------------------------------------------------------------------ parts

    def add_part(self, name: str, spec: str, cad: bytes) -> StoredPart:
        """Keep a new revision of part ``name`` as its current one.

        Parameters
        ----------
        name : str
        spec : str
            The part spec as JSON.
        cad : bytes
            The CAD file the spec's ``cad`` names.

        Raises
        ------
        PartExists
            ``name`` has a current revision (another process may just have created it).
        """
        key, now = part_key(spec, cad), time.time_ns()

        def work(db: _Backend) -> int:
            row = db.execute(
                "SELECT revision, key, created_ns FROM parts WHERE name = ? AND retired_ns IS NULL",
                (name,),
            ).fetchone()
            if row is not None and (str(row[1]), int(row[2])) == (key, now):
                # The row this call wrote: its commit went through before the connection was
                # lost, and this is the repetition that follows (see :meth:`_run`).
                return int(row[0])
            if row is not None:
                raise PartExists(f"part {name!r} exists (revision {row[0]}); delete it first")
            last = db.execute("SELECT MAX(revision) FROM parts WHERE name = ?", (name,)).fetchone()
            revision = 1 if last[0] is None else int(last[0]) + 1
            try:
                db.execute(
                    "INSERT INTO parts (name, revision, key, spec, cad, created_ns, retired_ns) "
                    "VALUES (?, ?, ?, ?, ?, ?, NULL)",
                    (name, revision, key, spec, cad, now),
                )
            except db.integrity as exc:  # a process creating the same name at this moment
                raise PartExists(f"part {name!r} was created meanwhile; delete it first") from exc
            return revision

        revision = self._run(work, transaction=True)
        return StoredPart(name, revision, key, spec, cad, now)

    def retire_part(self, name: str, key: str | None = None) -> bool:
        """Retire the current revision of part ``name`` (kept, for the results measured with
        it), only if its key is ``key`` when given; whether one was retired."""
        sql = "UPDATE parts SET retired_ns = ? WHERE name = ? AND retired_ns IS NULL"
        params: tuple[object, ...] = (time.time_ns(), name)
        if key is not None:
            sql, params = sql + " AND key = ?", (*params, key)
        return bool(self._run(lambda db: db.execute(sql, params).rowcount))

    def part(self, name: str, revision: int | None = None) -> StoredPart | None:
        """The current revision of part ``name`` (or revision ``revision``, retired or not),
        or None."""
        which, params = (
            ("retired_ns IS NULL", (name,))
            if revision is None
            else ("revision = ?", (name, revision))
        )
        row = self._run(
            lambda db: db.execute(
                "SELECT name, revision, key, spec, cad, created_ns, retired_ns FROM parts "
                f"WHERE name = ? AND {which}",
                params,
            ).fetchone()
        )
        if row is None:
            return None
        return StoredPart(
            str(row[0]), int(row[1]), str(row[2]), str(row[3]), bytes(row[4]), int(row[5]),
            None if row[6] is None else int(row[6]),
        )  # fmt: skip

    def part_keys(self) -> dict[str, str]:
        """The key of every current part revision, by name: what a station polls to learn
        that a part it measures changed."""
        rows = self._run(
            lambda db: db.execute("SELECT name, key FROM parts WHERE retired_ns IS NULL").fetchall()
        )
        return {str(r[0]): str(r[1]) for r in rows}

    def part_revisions(self) -> builtins.list[tuple[str, int]]:
        """``(name, revision)`` of every part revision kept, retired ones included."""
        rows = self._run(
            lambda db: db.execute("SELECT name, revision FROM parts ORDER BY name, revision")
            .fetchall()
        )  # fmt: skip
        return [(str(r[0]), int(r[1])) for r in rows]

    def part_index(self) -> builtins.list[PartRevision]:
        """Every part revision kept, retired ones included, by name and revision: what
        identifies each, without its spec and CAD."""
        rows = self._run(
            lambda db: db.execute(
                "SELECT name, revision, key, retired_ns FROM parts ORDER BY name, revision"
            ).fetchall()
        )
        return [
            PartRevision(str(r[0]), int(r[1]), str(r[2]), None if r[3] is None else int(r[3]))
            for r in rows
        ]

    def put_part_revision(self, part: StoredPart) -> bool:
        """Copy revision ``part`` from another store, revision number included; whether it
        was written (False: this store holds it already).

        A revision of that name and number held here already is kept as it is: it is
        only retired when ``part`` is (a deletion in the source since an earlier copy),
        never made current again (a deletion here stands).

        Raises
        ------
        CopyConflict
            The revision held here has another key (another spec or CAD), or ``part`` is
            current and so is another revision of its name here.
        """
        row = (
            part.name, part.revision, part.key, part.spec, part.cad, part.created_ns,
            part.retired_ns,
        )  # fmt: skip
        which = f"part {part.name!r} revision {part.revision}"

        def work(db: _Backend) -> bool:
            held = db.execute(
                "SELECT key, retired_ns FROM parts WHERE name = ? AND revision = ?",
                (part.name, part.revision),
            ).fetchone()
            if held is None:
                current = db.execute(
                    "SELECT revision FROM parts WHERE name = ? AND retired_ns IS NULL",
                    (part.name,),
                ).fetchone()
                if part.retired_ns is None and current is not None:
                    raise CopyConflict(
                        f"{which} is current, and so is revision {current[0]} in {self.where}"
                    )
                db.execute(
                    "INSERT INTO parts (name, revision, key, spec, cad, created_ns, retired_ns) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?)",
                    row,
                )
                return True
            if str(held[0]) != part.key:
                raise CopyConflict(f"{which} is another spec or CAD in {self.where}")
            if held[1] is None and part.retired_ns is not None:
                db.execute(
                    "UPDATE parts SET retired_ns = ? WHERE name = ? AND revision = ?",
                    (part.retired_ns, part.name, part.revision),
                )
            return False

        return self._run(work, transaction=True)


@dataclass(frozen=True)
class Copied:
    """What :func:`copy_store` copied: how many of each kind of row."""

    results: int
    alarms: int
    baselines: int
    parts: int
    """Part revisions, retired ones included."""


def copy_store(source: ResultStore, target: ResultStore, *, page: int = 500) -> Copied:
    """Copy everything ``source`` holds into ``target``: results, alarms, frozen
    baselines and every part revision. Each row keeps its key (an id, a part name, a part's
    name and revision), so copying twice copies nothing twice.

    Rows ``target`` holds already are taken as they are there: a result is written
    again (a trigger measured again in the source replaces its row), an alarm keeps
    an acknowledgement made in the target, a part revision keeps its retirement there
    (and is retired when the source retired it). Data of its own under a key the source
    uses as well (another station's store copied in before) is never overwritten:
    results measured with a part revision must keep tracing to its spec and CAD.

    Raises
    ------
    CopyConflict
        ``target`` holds another spec or CAD under a part revision of the source, another
        current revision of a part current in the source, or another frozen baseline of a
        part; checked before anything is copied, and the message names every conflict.
    """
    baselines = source.baselines()
    revisions = source.part_index()
    conflicts = _conflicts(revisions, target.part_index(), baselines, target.baselines())
    if conflicts:
        listed = "; ".join(conflicts[:20]) + (" ..." if len(conflicts) > 20 else "")
        raise CopyConflict(
            f"{target.where} holds other data under keys of {source.where} "
            f"(nothing was copied): {listed}"
        )
    results = copy_results(source, target, page=page)
    alarms = 0
    batch: builtins.list[Alarm] = []
    for alarm in source.iter_alarms(page=page):
        batch.append(alarm)
        if len(batch) == page:
            alarms += target.put_alarms(batch)
            batch = []
    alarms += target.put_alarms(batch)
    for b in baselines:
        target.put_baseline(b)
    # Oldest revision first: a revision the source retired is retired here before the
    # one that replaced it becomes current.
    for r in revisions:  # one at a time: a CAD file may weigh megabytes
        part = source.part(r.name, r.revision)
        if part is not None:
            target.put_part_revision(part)
    return Copied(results, alarms, len(baselines), len(revisions))


def _conflicts(
    source: builtins.list[PartRevision],
    target: builtins.list[PartRevision],
    source_baselines: builtins.list[Baseline],
    target_baselines: builtins.list[Baseline],
) -> builtins.list[str]:
    """What a copy of ``source`` into ``target`` would overwrite: a sentence each."""
    out = []
    held = {(r.name, r.revision): r for r in target}
    for r in source:
        t = held.get((r.name, r.revision))
        if t is not None and t.key != r.key:
            out.append(f"part {r.name!r} revision {r.revision} is another spec or CAD there "
                       f"(key {t.key}, the source's {r.key})")  # fmt: skip
    # After the copy, a part's current revision is the target's one unless the source
    # retires it; a current revision of the source that the target lacks would be a second.
    retired_by_copy = {(r.name, r.revision) for r in source if r.retired_ns is not None}
    current = {
        r.name: r
        for r in target
        if r.retired_ns is None and (r.name, r.revision) not in retired_by_copy
    }
    for r in source:
        t = current.get(r.name)
        if r.retired_ns is None and (r.name, r.revision) not in held and t is not None:
            out.append(f"part {r.name!r}: revision {r.revision} is current in the source, "
                       f"revision {t.revision} there")  # fmt: skip
    theirs = {b.part: b for b in target_baselines}
    for b in source_baselines:
        t_b = theirs.get(b.part)
        if t_b is not None and t_b != b:
            out.append(f"part {b.part!r} has another frozen baseline there "
                       f"(frozen at {t_b.frozen_ns}, the source's at {b.frozen_ns})")  # fmt: skip
    return out


def copy_results(source: ResultStore, target: ResultStore, *, page: int = 500) -> int:
    """Upsert every result of ``source`` into ``target``, a page (one transaction)
    at a time, newest first; returns how many were read."""
    copied, cursor = 0, None
    while True:
        items, cursor = source.list(limit=page, cursor=cursor)
        copied += target.put_many(items)
        if cursor is None:
            return copied


def _where(f: Filters) -> tuple[str, list[object]]:
    clauses: list[str] = []
    params: list[object] = []
    if f.part is not None:
        clauses.append("part = ?")
        params.append(f.part)
    if f.status is not None:
        clauses.append("status = ?")
        params.append(Status(f.status).value)
    if f.since_ns is not None:
        clauses.append("triggered_ns >= ?")
        params.append(int(f.since_ns))
    if f.until_ns is not None:
        clauses.append("triggered_ns <= ?")
        params.append(int(f.until_ns))
    if f.serial is not None:
        clauses.append("serial = ?")
        params.append(f.serial)
    if f.station is not None:
        clauses.append("station = ?")
        params.append(f.station)
    return ("WHERE " + " AND ".join(clauses) if clauses else ""), params


def _row(r: InspectionResult) -> tuple[object, ...]:
    return (
        r.id, r.line, r.station, r.part, r.serial, r.seq, r.triggered_ns, r.status.value,
        r.model_dump_json(), time.time_ns(),
    )  # fmt: skip


def _split_sql(script: str) -> list[str]:
    return [s.strip() for s in script.split(";") if s.strip()]


def archived_rows(n: int, max_points: int) -> slice | np.ndarray:
    """The rows of ``n`` points the deviation archive keeps: all, or ``max_points`` of
    them evenly strided."""
    if n <= max_points:
        return slice(None)
    return np.linspace(0, n - 1, max_points).round().astype(np.int64)


class DeviationArchive:
    """Per-point deviations of each inspection, one compressed ``.npz`` per result id.

    Each file holds ``points`` (N, 3) float32, CAD frame, mm, and
    ``distances`` (N,) float32, signed, mm (NaN for points that were not
    measured, e.g. outliers). float32 keeps a 50k-point cloud near 0.5 MB
    while staying far finer than the 0.01 mm the colour map can show.

    At most ``max_points`` points of a result are kept, evenly spread over
    its cloud: the colour map shows no more, and compressing a whole cloud
    (~400k points from the line, millions in an upload) costs seconds.
    The recording keeps the line's whole clouds.
    """

    def __init__(
        self, directory: str | Path, max_points: int = 50_000, max_bytes: int | None = None
    ) -> None:
        self.directory = Path(directory)
        self.max_points = max_points
        self.max_bytes = max_bytes
        self._total: int | None = None  # bytes in the directory, as last counted and since written
        self._lock = threading.Lock()

    def path(self, id_: str) -> Path:
        if not _ID_RE.fullmatch(id_) or id_.startswith("."):
            raise ValueError(f"not a valid result id: {id_!r}")
        return self.directory / f"{id_}.npz"

    def save(self, id_: str, points_cad: np.ndarray, distances: np.ndarray) -> Path:
        """Write the arrays of result ``id_`` (atomically: a reader never sees half a file)."""
        p, d = np.asarray(points_cad), np.asarray(distances)
        if p.ndim != 2 or p.shape[1] != 3 or d.shape != (len(p),):
            raise ValueError(
                f"points (N, 3) and distances (N,) expected, got {p.shape} and {d.shape}"
            )
        keep = archived_rows(len(p), self.max_points)
        p, d = p[keep].astype(np.float32), d[keep].astype(np.float32)
        self.directory.mkdir(parents=True, exist_ok=True)
        target = self.path(id_)
        tmp = target.with_name(target.name + ".tmp.npz")
        np.savez_compressed(tmp, points=p, distances=d)
        tmp.replace(target)
        if self.max_bytes is not None:
            # The budget holds as each file is written, not only at the next sweep; the
            # directory is counted again only when the running total passes it.
            with self._lock:
                if self._total is not None:
                    self._total += target.stat().st_size
                if self._total is None or self._total > self.max_bytes:
                    self.enforce(self.max_bytes, None)
        return target

    def load(self, id_: str) -> tuple[np.ndarray, np.ndarray] | None:
        """``(points, distances)`` of result ``id_``, or None when none was kept."""
        path = self.path(id_)
        if not path.is_file():
            return None
        with np.load(path) as z:
            return np.asarray(z["points"]), np.asarray(z["distances"])

    def delete(self, id_: str) -> None:
        self.path(id_).unlink(missing_ok=True)

    def enforce(self, max_bytes: int | None, max_age_s: float | None) -> int:
        """Delete the oldest files beyond ``max_bytes`` or older than ``max_age_s``
        (by modification time); returns how many went."""
        try:
            entries = [
                (st.st_mtime, st.st_size, e.path)
                for e in os.scandir(self.directory)
                if e.name.endswith(".npz") and e.is_file()
                for st in (e.stat(),)
            ]
        except FileNotFoundError:
            return 0
        entries.sort()
        now = time.time()
        total = sum(size for _, size, _ in entries)
        removed = 0
        for mtime, size, path in entries:
            old = max_age_s is not None and now - mtime > max_age_s
            over = max_bytes is not None and total > max_bytes
            if not (old or over):
                break
            Path(path).unlink(missing_ok=True)
            total -= size
            removed += 1
        self._total = total
        return removed
