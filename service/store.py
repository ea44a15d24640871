"""The result store: one SQLite file (WAL mode) with a row per accepted trigger.

Every result is upserted by its ``id``, so a trigger published twice (a
retry, a replay into the same store) still has exactly one row. The full
result is kept as JSON beside indexed columns used for filtering; a
``schema_version`` table and the :data:`MIGRATIONS` list take a file from any
earlier layout to the current one when it is opened.

Per-point deviations are too large for a row; :class:`DeviationArchive`
keeps them as one ``.npz`` per inspection next to the database.

Errors::

    StoreError                a file from a newer version, or not a store at all
"""

from __future__ import annotations

import base64
import binascii
import logging
import math
import os
import re
import sqlite3
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .models import InspectionResult, Status, Trend, TrendPoint, Verdict
from .names import ID_PATTERN

log = logging.getLogger(__name__)

MIGRATIONS: list[str] = [
    # 1: results with the columns the API filters and orders by.
    """
    CREATE TABLE results (
        id            TEXT PRIMARY KEY,
        line          TEXT NOT NULL,
        station       TEXT NOT NULL,
        part          TEXT NOT NULL,
        serial        TEXT NOT NULL,
        seq           INTEGER NOT NULL,
        triggered_ns  INTEGER NOT NULL,
        status        TEXT NOT NULL,
        body          TEXT NOT NULL,
        stored_ns     INTEGER NOT NULL
    );
    CREATE INDEX results_time ON results (triggered_ns, id);
    CREATE INDEX results_part_time ON results (part, triggered_ns, id);
    CREATE INDEX results_status_time ON results (status, triggered_ns, id);
    """,
    # 2: a restarted worker asks for its station's last trigger.
    """
    CREATE INDEX results_station_seq ON results (line, station, seq);
    """,
]
"""Schema migrations, in order; the database's version is the number applied."""

SCHEMA_VERSION = len(MIGRATIONS)

MAX_LIMIT = 1000

_ID_RE = re.compile(ID_PATTERN)


class StoreError(Exception):
    """The database cannot be used: newer than this software, or not a result store."""


class InvalidCursor(ValueError):
    """A pagination cursor that this store did not hand out."""


@dataclass(frozen=True)
class Filters:
    """What a listing selects: each field ``None`` means no restriction."""

    part: str | None = None
    status: Status | None = None
    since_ns: int | None = None


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


class ResultStore:
    """Inspection results in one SQLite file.

    Thread-safe: one connection shared behind a lock (the worker thread writes
    while the API's threads read). Open with :meth:`open` or the constructor
    and close with :meth:`close` (or use it as a context manager).

    Parameters
    ----------
    path : str or Path
        The database file (created with its parents) or ``":memory:"``.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        if self.path != ":memory:":
            Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        try:
            self._db = sqlite3.connect(
                self.path, check_same_thread=False, isolation_level=None, timeout=30.0
            )
            self._db.execute("PRAGMA journal_mode=WAL")
            # In WAL mode NORMAL still survives a process crash; only an OS crash
            # can lose the last transactions.
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._migrate()
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{self.path}: not a result store: {exc}") from exc

    @classmethod
    def open(cls, path: str | Path) -> ResultStore:
        return cls(path)

    def __enter__(self) -> ResultStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # ------------------------------------------------------------------ schema

    def _migrate(self) -> None:
        # One write transaction from reading the version to the last step: a
        # worker and an API opening a new file at once must not both migrate it.
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            db.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
            row = db.execute("SELECT version FROM schema_version").fetchone()
            version = 0 if row is None else int(row[0])
            if row is None:
                db.execute("INSERT INTO schema_version (version) VALUES (0)")
            if version > SCHEMA_VERSION:
                raise StoreError(
                    f"{Path(self.path).name}: schema version {version} is newer than this "
                    f"software's ({SCHEMA_VERSION}); upgrade the software"
                )
            for i in range(version, SCHEMA_VERSION):
                log.info("%s: migrating schema %d -> %d", self.path, i, i + 1)
                for stmt in _split_sql(MIGRATIONS[i]):
                    db.execute(stmt)
                db.execute("UPDATE schema_version SET version = ?", (i + 1,))
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise

    @property
    def schema_version(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT version FROM schema_version").fetchone()[0])

    # ------------------------------------------------------------------ writes

    def put(self, result: InspectionResult) -> None:
        """Insert ``result`` or replace the row with the same ``id``."""
        body = result.model_dump_json()
        with self._lock:
            self._db.execute(
                """
                INSERT INTO results
                    (id, line, station, part, serial, seq, triggered_ns, status, body, stored_ns)
                VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)
                ON CONFLICT (id) DO UPDATE SET
                    line = excluded.line, station = excluded.station, part = excluded.part,
                    serial = excluded.serial, seq = excluded.seq,
                    triggered_ns = excluded.triggered_ns, status = excluded.status,
                    body = excluded.body, stored_ns = excluded.stored_ns
                """,
                (
                    result.id,
                    result.line,
                    result.station,
                    result.part,
                    result.serial,
                    result.seq,
                    result.triggered_ns,
                    result.status.value,
                    body,
                    time.time_ns(),
                ),
            )

    def enforce(self, max_bytes: int | None, max_age_s: float | None) -> int:
        """Delete the oldest rows beyond ``max_bytes`` of result JSON or older than
        ``max_age_s`` (by trigger time); returns how many went.

        The pages freed are reused by new rows, so the file stops growing.
        """
        removed = 0
        with self._lock:
            if max_age_s is not None:
                cutoff = time.time_ns() - int(max_age_s * 1e9)
                removed += self._db.execute(
                    "DELETE FROM results WHERE triggered_ns < ?", (cutoff,)
                ).rowcount
            if max_bytes is not None:
                total = self._db.execute("SELECT TOTAL(LENGTH(body)) FROM results").fetchone()[0]
                excess = int(total) - max_bytes
                if excess > 0:
                    # The oldest rows whose bodies add up to the excess, in one pass.
                    row = self._db.execute(
                        """
                        SELECT triggered_ns, id FROM (
                            SELECT triggered_ns, id, SUM(LENGTH(body)) OVER (
                                ORDER BY triggered_ns, id ROWS UNBOUNDED PRECEDING) AS upto
                            FROM results)
                        WHERE upto >= ? ORDER BY triggered_ns, id LIMIT 1
                        """,
                        (excess,),
                    ).fetchone()
                    if row is not None:
                        removed += self._db.execute(
                            "DELETE FROM results WHERE triggered_ns < ? "
                            "OR (triggered_ns = ? AND id <= ?)",
                            (row[0], row[0], row[1]),
                        ).rowcount
        return removed

    def delete_part(self, part: str) -> int:
        """Delete every result of ``part``; returns how many rows went."""
        with self._lock:
            cur = self._db.execute("DELETE FROM results WHERE part = ?", (part,))
            return cur.rowcount

    # ------------------------------------------------------------------ reads

    def get(self, id_: str) -> InspectionResult | None:
        with self._lock:
            row = self._db.execute("SELECT body FROM results WHERE id = ?", (id_,)).fetchone()
        return None if row is None else InspectionResult.model_validate_json(row[0])

    def has(self, id_: str) -> bool:
        """Whether a result with this id is stored."""
        with self._lock:
            row = self._db.execute("SELECT 1 FROM results WHERE id = ?", (id_,)).fetchone()
        return row is not None

    def last_trigger(self, line: str, station: str) -> tuple[int, int] | None:
        """``(seq, triggered_ns)`` of the station's highest stored seq, or None.

        Uploads (seq 0, another station name) never count: they are not triggers.
        """
        with self._lock:
            row = self._db.execute(
                "SELECT seq, triggered_ns FROM results WHERE line = ? AND station = ? "
                "ORDER BY seq DESC LIMIT 1",
                (line, station),
            ).fetchone()
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
        with self._lock:
            rows = self._db.execute(
                "SELECT body FROM results WHERE line = ? AND station = ? AND seq BETWEEN ? AND ? "
                "AND triggered_ns BETWEEN ? AND ? ORDER BY seq, triggered_ns, id LIMIT ?",
                (line, station, seq[0], seq[1], since_ns, until_ns, limit),
            ).fetchall()
        return [InspectionResult.model_validate_json(r[0]) for r in rows]

    def count(self, filters: Filters | None = None) -> int:
        where, params = _where(filters or Filters())
        with self._lock:
            return int(
                self._db.execute(f"SELECT COUNT(*) FROM results {where}", params).fetchone()[0]
            )

    def list(
        self,
        filters: Filters | None = None,
        *,
        limit: int = 50,
        cursor: str | None = None,
    ) -> tuple[list[InspectionResult], str | None]:
        """One page of results, newest trigger first.

        Parameters
        ----------
        filters : Filters, optional
        limit : int
            1..:data:`MAX_LIMIT` results.
        cursor : str, optional
            The ``next`` of the previous page.

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
        if cursor is not None:
            ns, id_ = decode_cursor(cursor)
            # Keyset pagination: stable while new rows arrive at the top.
            where += (
                " AND " if where else "WHERE "
            ) + "(triggered_ns < ? OR (triggered_ns = ? AND id < ?))"
            params += [ns, ns, id_]
        sql = f"SELECT body FROM results {where} ORDER BY triggered_ns DESC, id DESC LIMIT ?"
        with self._lock:
            rows = self._db.execute(sql, [*params, limit + 1]).fetchall()
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
        with self._lock:
            rows = self._db.execute(
                "SELECT status, COUNT(*) FROM results GROUP BY status"
            ).fetchall()
        return {s.value: 0 for s in Status} | {r[0]: int(r[1]) for r in rows}

    def trend(self, part: str, window: int = 50) -> Trend:
        """Process statistics per comparison point over the last ``window`` measured parts.

        Only results with status pass or fail count (a part with an error or a
        missed part has no measurement). Per point, not-measurable entries are
        left out; sigma is the sample standard deviation (n - 1).
        """
        if window < 1:
            raise ValueError(f"window must be at least 1, got {window}")
        with self._lock:
            rows = self._db.execute(
                """
                SELECT body FROM results WHERE part = ? AND status IN (?, ?)
                ORDER BY triggered_ns DESC, id DESC LIMIT ?
                """,
                (part, Status.passed.value, Status.fail.value, window),
            ).fetchall()
        results = [InspectionResult.model_validate_json(r[0]) for r in rows]
        values: dict[str, list[float]] = {}
        limits: dict[str, tuple[float, float]] = {}
        fails: dict[str, int] = {}
        order: list[str] = []
        # Oldest first so the newest limits win when a spec changed in the window.
        for res in reversed(results):
            for c in res.comparison:
                if c.name not in values:
                    values[c.name] = []
                    fails[c.name] = 0
                    order.append(c.name)
                limits[c.name] = (c.lower_mm, c.upper_mm)
                if c.verdict == Verdict.FAIL:
                    fails[c.name] += 1
                if c.deviation_mm is not None and c.verdict != Verdict.NOT_MEASURABLE:
                    values[c.name].append(c.deviation_mm)
        points = [
            _trend_point(
                name, np.asarray(values[name], dtype=np.float64), limits[name], fails[name]
            )
            for name in order
        ]
        return Trend(
            part=part,
            window=window,
            parts=len(results),
            since_ns=results[-1].triggered_ns if results else None,
            until_ns=results[0].triggered_ns if results else None,
            points=points,
        )


def _trend_point(name: str, x: np.ndarray, limits: tuple[float, float], fails: int) -> TrendPoint:
    lower, upper = limits
    n = len(x)
    mean = float(x.mean()) if n else None
    sigma = float(x.std(ddof=1)) if n >= 2 else None
    cp = cpk = None
    if mean is not None and sigma is not None and sigma > 0:
        # Process capability: the tolerance band over six sigma, and its
        # one-sided version from the mean to the nearer limit.
        cp = (upper - lower) / (6.0 * sigma)
        cpk = min(upper - mean, mean - lower) / (3.0 * sigma)
    return TrendPoint(
        name=name,
        n=n,
        mean_mm=_finite(mean),
        sigma_mm=_finite(sigma),
        lower_mm=lower,
        upper_mm=upper,
        cp=_finite(cp),
        cpk=_finite(cpk),
        fails=fails,
    )


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


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
    return ("WHERE " + " AND ".join(clauses) if clauses else ""), params


def _split_sql(script: str) -> list[str]:
    return [s.strip() for s in script.split(";") if s.strip()]


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
        if len(p) > self.max_points:
            keep = np.linspace(0, len(p) - 1, self.max_points).round().astype(np.int64)
            p, d = p[keep], d[keep]
        p, d = p.astype(np.float32), d.astype(np.float32)
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
