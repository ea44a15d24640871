"""The SQLite result store: one row per trigger, filters, pagination, trends, migrations."""

from __future__ import annotations

import sqlite3
import threading

import numpy as np
import pytest

from service.models import InspectionResult, PointResult, make_result_id, software_version
from service.store import (
    SCHEMA_VERSION,
    DeviationArchive,
    Filters,
    InvalidCursor,
    ResultStore,
    StoreError,
    encode_cursor,
)

T0 = 1_700_000_000_000_000_000


def res(
    seq: int, *, part="demo-panel", status="pass", devs=(0.1, -0.2), t=None
) -> InspectionResult:
    t = T0 + seq * 1_000_000_000 if t is None else t
    comparison = [
        PointResult(
            name=f"p{i}",
            deviation_mm=d,
            lower_mm=-0.5,
            upper_mm=0.5,
            support=20 if d is not None else 0,
            verdict=("not_measurable" if d is None else "pass" if -0.5 <= d <= 0.5 else "fail"),
        )
        for i, d in enumerate(devs)
    ]
    return InspectionResult(
        id=make_result_id("line1", "st1", seq, t),
        line="line1",
        station="st1",
        part=part,
        serial=f"SN{seq}",
        seq=seq,
        triggered_ns=t,
        status=status,
        comparison=comparison,
        software_version=software_version(),
    )


@pytest.fixture
def store(tmp_path):
    with ResultStore(tmp_path / "results.sqlite") as s:
        yield s


def test_upsert_keeps_one_row_per_id(store):
    store.put(res(1))
    store.put(res(1, status="fail"))
    assert store.count() == 1
    assert store.get(res(1).id).status == "fail"
    assert store.get("nope") is None


def test_wal_mode_and_schema_version(tmp_path, store):
    mode = store._db.execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"
    assert store.schema_version == SCHEMA_VERSION


def test_reopen_keeps_results(tmp_path):
    path = tmp_path / "r.sqlite"
    with ResultStore(path) as s:
        for i in range(5):
            s.put(res(i))
    with ResultStore(path) as s:
        assert s.count() == 5
        assert s.get(res(3).id) == res(3)


def test_newer_schema_is_refused(tmp_path):
    path = tmp_path / "r.sqlite"
    ResultStore(path).close()
    with sqlite3.connect(path) as db:
        db.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION + 1,))
    with pytest.raises(StoreError, match="newer"):
        ResultStore(path)


def test_not_a_database_is_refused(tmp_path):
    path = tmp_path / "r.sqlite"
    path.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(StoreError, match="not a result store"):
        ResultStore(path)


def test_pagination_visits_every_row_once_newest_first(store):
    for i in range(23):
        store.put(res(i, part="a" if i % 2 else "b", status="fail" if i % 3 == 0 else "pass"))
    # Two results at the same instant: the id breaks the tie.
    store.put(res(100, t=T0 + 5 * 1_000_000_000))
    seen, cursor = [], None
    while True:
        items, cursor = store.list(limit=5, cursor=cursor)
        seen += items
        if cursor is None:
            break
    assert len(seen) == 24 == len({r.id for r in seen})
    keys = [(r.triggered_ns, r.id) for r in seen]
    assert keys == sorted(keys, reverse=True)


@pytest.mark.parametrize("part", [None, "a", "b", "c"])
@pytest.mark.parametrize("status", [None, "pass", "fail"])
@pytest.mark.parametrize("since", [None, 10])
def test_filters_match_a_plain_python_filter(store, part, status, since):
    all_ = [
        res(i, part="a" if i % 2 else "b", status="fail" if i % 3 == 0 else "pass")
        for i in range(20)
    ]
    for r in all_:
        store.put(r)
    since_ns = None if since is None else T0 + since * 1_000_000_000
    want = [
        r.id
        for r in sorted(all_, key=lambda r: (r.triggered_ns, r.id), reverse=True)
        if (part is None or r.part == part)
        and (status is None or r.status == status)
        and (since_ns is None or r.triggered_ns >= since_ns)
    ]
    f = Filters(part=part, status=status, since_ns=since_ns)
    assert [r.id for r in store.iter_all(f, page=3)] == want
    assert store.count(f) == len(want)


def test_bad_cursor_and_limit(store):
    with pytest.raises(InvalidCursor):
        store.list(cursor="%%%")
    with pytest.raises(InvalidCursor):
        store.list(cursor=encode_cursor(1, "x")[:-3] + "!!")
    with pytest.raises(ValueError):
        store.list(limit=0)


def test_trend_statistics(store):
    rng = np.random.default_rng(0)
    devs = rng.normal(0.1, 0.05, size=30)
    for i, d in enumerate(devs):
        store.put(res(i, devs=(float(d), None)))
    store.put(res(99, status="error", devs=(5.0, 5.0)))  # errors do not count
    store.put(res(98, part="other", devs=(3.0, 3.0)))
    tr = store.trend("demo-panel", window=20)
    assert tr.parts == 20
    p0, p1 = tr.points
    last = devs[-20:]
    assert p0.n == 20
    assert p0.mean_mm == pytest.approx(last.mean())
    assert p0.sigma_mm == pytest.approx(last.std(ddof=1))
    assert p0.cp == pytest.approx(1.0 / (6 * last.std(ddof=1)))
    assert p0.cpk == pytest.approx((0.5 - last.mean()) / (3 * last.std(ddof=1)))
    assert p1.n == 0 and p1.mean_mm is None and p1.cp is None
    empty = store.trend("nothing")
    assert empty.parts == 0 and empty.points == []


def test_concurrent_writers_and_readers(store):
    errors = []

    def write(base):
        try:
            for i in range(50):
                store.put(res(base + i))
                store.list(limit=10)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=write, args=(k * 1000,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert store.count() == 200


def test_deviation_archive_round_trip(tmp_path):
    arc = DeviationArchive(tmp_path / "dev")
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(100, 3)) * 100
    d = rng.normal(size=100)
    d[3] = np.nan
    arc.save("line1.st1.5.1", pts, d)
    p2, d2 = arc.load("line1.st1.5.1")
    assert p2.dtype == np.float32 and p2.shape == (100, 3)
    np.testing.assert_allclose(d2, d, atol=1e-6, equal_nan=True)
    assert arc.load("other") is None
    with pytest.raises(ValueError):
        arc.path("../etc/passwd")
    with pytest.raises(ValueError):
        arc.save("x", pts, d[:5])


def test_an_older_file_is_migrated_on_open(tmp_path):
    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE schema_version (version INTEGER NOT NULL)")
        db.execute("INSERT INTO schema_version VALUES (0)")
    with ResultStore(path) as s:
        assert s.schema_version == SCHEMA_VERSION
        s.put(res(1))
        assert s.count() == 1
    with sqlite3.connect(path) as db:
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    assert {"schema_version", "results"} <= tables


def test_readers_in_other_processes_see_committed_rows(tmp_path):
    """WAL: a second connection (e.g. `sqlite3` on the shell) reads while the store is open."""
    path = tmp_path / "r.sqlite"
    with ResultStore(path) as s:
        s.put(res(1))
        with sqlite3.connect(path) as db:
            assert db.execute("SELECT COUNT(*) FROM results").fetchone()[0] == 1


def test_the_archive_keeps_at_most_its_points_evenly_spread(tmp_path):
    """A cloud of millions (an upload) is kept as the colour map needs it, not whole."""
    arc = DeviationArchive(tmp_path, max_points=100)
    pts = np.column_stack([np.arange(1000.0), np.zeros(1000), np.zeros(1000)])
    arc.save("big", pts, np.arange(1000.0))
    p, d = arc.load("big")
    assert len(p) == 100 and p[0, 0] == 0 and p[-1, 0] == 999
    np.testing.assert_array_equal(p[:, 0], d)  # each point keeps its own deviation
    assert np.all(np.diff(p[:, 0]) <= 11)
