"""The result store: one row per trigger, filters, pagination, trends, migrations.

Each test that takes ``store`` or ``store_target`` runs on SQLite and on a real
PostgreSQL server (see ``conftest.py``): one test body, both backends.
"""

from __future__ import annotations

import contextlib
import socket
import sqlite3
import threading

import numpy as np
import pgserver
import psycopg
import pytest

from service.models import (
    Alarm,
    Baseline,
    ChartLimits,
    InspectionResult,
    PointResult,
    Status,
    make_result_id,
    software_version,
)
from service.store import (
    MIGRATIONS,
    SCHEMA_VERSION,
    CopyConflict,
    DeviationArchive,
    Filters,
    InvalidCursor,
    PartExists,
    ResultStore,
    StoreError,
    copy_store,
    encode_cursor,
    part_key,
)
from service.store_url import is_postgres_url

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


@contextlib.contextmanager
def raw_connection(target):
    """A connection of the database's own driver beside the store's, committing each
    statement: what another program sees, and a way to set up what the store refuses."""
    if is_postgres_url(target):
        with psycopg.connect(target, autocommit=True) as db:
            yield db
    else:
        db = sqlite3.connect(target, isolation_level=None)
        try:
            yield db
        finally:
            db.close()


def index_names(target) -> set[str]:
    with raw_connection(target) as db:
        sql = (
            "SELECT indexname FROM pg_indexes WHERE tablename = 'results'"
            if is_postgres_url(target)
            else "SELECT name FROM sqlite_master WHERE type = 'index' AND tbl_name = 'results'"
        )
        return {r[0] for r in db.execute(sql).fetchall()}


@pytest.fixture
def store(store_target):
    with ResultStore(store_target) as s:
        yield s


def test_upsert_keeps_one_row_per_id(store):
    store.put(res(1))
    store.put(res(1, status="fail"))
    assert store.count() == 1
    assert store.get(res(1).id).status == "fail"
    assert store.get("nope") is None
    assert store.has(res(1).id) and not store.has("nope")


def test_put_many_writes_a_batch_once_however_often_it_comes(store):
    batch = [res(i) for i in range(30)]
    assert store.put_many(batch) == 30
    assert store.put_many([*batch[:10], res(3, status="fail")]) == 11
    assert store.count() == 30
    assert store.get(res(3).id).status == "fail"
    assert store.put_many([]) == 0


def test_a_new_store_is_at_the_current_schema(store):
    assert store.schema_version == SCHEMA_VERSION


def test_the_sqlite_file_is_in_wal_mode(tmp_path):
    path = tmp_path / "r.sqlite"
    ResultStore(path).close()
    with raw_connection(path) as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_reopen_keeps_results(store_target):
    with ResultStore(store_target) as s:
        for i in range(5):
            s.put(res(i))
    with ResultStore(store_target) as s:
        assert s.count() == 5
        assert s.get(res(3).id) == res(3)


def test_newer_schema_is_refused(store_target):
    ResultStore(store_target).close()
    with raw_connection(store_target) as db:
        db.execute(f"UPDATE schema_version SET version = {SCHEMA_VERSION + 1}")
    with pytest.raises(StoreError, match="newer"):
        ResultStore(store_target)


def test_not_a_database_is_refused(tmp_path):
    path = tmp_path / "r.sqlite"
    path.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(StoreError, match="not a result store"):
        ResultStore(path)


@pytest.mark.parametrize("version", range(SCHEMA_VERSION))
def test_an_older_store_is_migrated_on_open_and_keeps_its_rows(store_target, version):
    """A database left at each earlier schema version (with a row where it has the
    table) is brought to the current one when opened."""
    old = res(1)
    with raw_connection(store_target) as db:
        db.execute("CREATE TABLE schema_version (version INTEGER NOT NULL)")
        db.execute(f"INSERT INTO schema_version VALUES ({version})")
        for script in MIGRATIONS[:version]:
            for stmt in script.split(";"):
                if stmt.strip():
                    db.execute(stmt)
        if version >= 1:
            body = old.model_dump_json().replace("'", "''")
            db.execute(
                "INSERT INTO results VALUES ("
                f"'{old.id}', 'line1', 'st1', 'demo-panel', 'SN1', 1, {old.triggered_ns}, "
                f"'pass', '{body}', 0)"
            )
    with ResultStore(store_target) as s:
        assert s.schema_version == SCHEMA_VERSION
        assert s.count() == (1 if version >= 1 else 0)
        assert version < 1 or s.get(old.id) == old
        s.put(res(2))
        assert s.last_trigger("line1", "st1") == (2, res(2).triggered_ns)
    assert "results_station_seq" in index_names(store_target)
    # The parts table of the newest migration takes a part whatever the start.
    with ResultStore(store_target) as s:
        assert s.add_part("p", "{}", CAD).revision == 1


def test_a_new_store_opened_four_times_at_once_is_migrated_once(store_target):
    """A worker and an API starting together: each opens its own connection."""
    barrier = threading.Barrier(4)
    versions, errors = [], []

    def open_it():
        barrier.wait()
        try:
            with ResultStore(store_target) as s:
                versions.append(s.schema_version)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=open_it) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and versions == [SCHEMA_VERSION] * 4
    with raw_connection(store_target) as db:
        assert db.execute("SELECT version FROM schema_version").fetchall() == [(SCHEMA_VERSION,)]


@pytest.mark.parametrize("oldest_first", [False, True])
def test_pagination_visits_every_row_once_in_either_order(store, oldest_first):
    for i in range(23):
        store.put(res(i, part="a" if i % 2 else "b", status="fail" if i % 3 == 0 else "pass"))
    # Two results at the same instant: the id breaks the tie.
    store.put(res(100, t=T0 + 5 * 1_000_000_000))
    seen, cursor = [], None
    while True:
        items, cursor = store.list(limit=5, cursor=cursor, oldest_first=oldest_first)
        seen += items
        if cursor is None:
            break
    assert len(seen) == 24 == len({r.id for r in seen})
    keys = [(r.triggered_ns, r.id) for r in seen]
    assert keys == sorted(keys, reverse=not oldest_first)


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


@pytest.mark.parametrize(
    ("serial", "station", "until"), [("SN4", None, None), (None, "st2", None), (None, "st2", 9),
                                     ("SN3", "st2", 2), (None, None, 5)],
)  # fmt: skip
def test_serial_station_and_until_filters(store, serial, station, until):
    all_ = [res(i).model_copy(update={"station": "st2" if i % 2 else "st1"}) for i in range(12)]
    for r in all_:
        store.put(r)
    until_ns = None if until is None else T0 + until * 1_000_000_000
    want = [
        r.id
        for r in sorted(all_, key=lambda r: (r.triggered_ns, r.id), reverse=True)
        if (serial is None or r.serial == serial)
        and (station is None or r.station == station)
        and (until_ns is None or r.triggered_ns <= until_ns)
    ]
    f = Filters(serial=serial, station=station, until_ns=until_ns)
    assert [r.id for r in store.iter_all(f, page=4)] == want


def test_bad_cursor_and_limit(store):
    with pytest.raises(InvalidCursor):
        store.list(cursor="%%%")
    with pytest.raises(InvalidCursor):
        store.list(cursor=encode_cursor(1, "x")[:-3] + "!!")
    with pytest.raises(ValueError):
        store.list(limit=0)


def test_measured_results_oldest_first(store):
    for i in range(8):
        store.put(res(i, status="fail" if i == 3 else "pass"))
    store.put(res(99, status="error"))  # nothing measured: never on a chart
    store.put(res(98, part="other"))
    newest = store.measured("demo-panel", limit=5)
    assert [r.seq for r in newest] == [3, 4, 5, 6, 7]
    assert [r.seq for r in store.measured("demo-panel", limit=3, oldest=True)] == [0, 1, 2]
    t2 = res(2).triggered_ns
    assert [r.seq for r in store.measured("demo-panel", since_ns=t2, until_ns=t2)] == [2]
    assert store.measured("nothing") == []


def test_alarms_kept_listed_and_acknowledged(store):
    a = Alarm(kind="spc_rule", message="drift", triggered_ns=5, line="l", station="s",
              raised_ns=10, part="demo-panel", feature="p1", rule="nelson1")  # fmt: skip
    b = Alarm(kind="seq_jump", message="jump", triggered_ns=6, line="l", station="s", raised_ns=20)
    store.put_alarm(a)
    store.put_alarm(b)
    assert [x.id for x in store.alarms()] == [b.id, a.id]
    store.put_alarm(a.model_copy(update={"acknowledged_by": "ann", "acknowledged_ns": 30}))
    assert [x.id for x in store.alarms(open_only=True)] == [b.id]
    assert store.alarm(a.id).acknowledged_by == "ann"
    assert store.alarm("nope") is None


def test_baselines_round_trip(store):
    lim = ChartLimits(center=0, sigma=1, lcl=-3, ucl=3, spread_center=1.1, spread_lcl=0,
                      spread_ucl=3.7, subgroup=1, n=20, frozen=True)  # fmt: skip
    b = Baseline(part="demo-panel", since_ns=None, until_ns=5, frozen_ns=7, frozen_by="ann",
                 results=20, limits={"p1": lim})  # fmt: skip
    assert store.baseline("demo-panel") is None
    store.put_baseline(b)
    store.put_baseline(b.model_copy(update={"frozen_ns": 8}))
    assert store.baseline("demo-panel").frozen_ns == 8
    assert store.delete_baseline("demo-panel") and not store.delete_baseline("demo-panel")


CAD = bytes(range(256)) * 40  # every byte value, NUL included: a binary STL's bytes


def test_a_part_is_kept_by_revision_and_a_deleted_one_stays_for_its_results(store):
    spec = '{"name": "bracket", "version": "1", "cad": "cad.stl"}'
    first = store.add_part("bracket", spec, CAD)
    assert (first.revision, first.key, first.retired_ns) == (1, part_key(spec, CAD), None)
    got = store.part("bracket")
    assert (got.revision, got.key, got.spec, got.cad) == (1, first.key, spec, CAD)
    assert store.part_keys() == {"bracket": first.key} and store.part("other") is None
    with pytest.raises(PartExists, match="delete it first"):
        store.add_part("bracket", spec, b"another CAD")

    assert store.retire_part("bracket") and not store.retire_part("bracket")
    assert store.part("bracket") is None and store.part_keys() == {}
    retired = store.part("bracket", 1)
    assert retired.cad == CAD and retired.retired_ns >= first.created_ns

    spec2 = spec.replace('"1"', '"2"')
    second = store.add_part("bracket", spec2, CAD)
    assert second.revision == 2 and second.key != first.key
    assert store.part_keys() == {"bracket": second.key}
    assert store.part_revisions() == [("bracket", 1), ("bracket", 2)]
    # Parts are not results: retention sweeps and result deletions leave them.
    store.enforce(0, 0.0)
    store.delete_part("bracket")
    assert store.part_keys() == {"bracket": second.key}


def test_two_processes_creating_one_part_at_once_make_one_revision(store_target):
    """Two APIs on one database: one creation wins, the other is told the part exists."""
    stores = [ResultStore(store_target) for _ in range(4)]
    barrier = threading.Barrier(len(stores))
    made, refused = [], []

    def create(s, n):
        barrier.wait()
        try:
            made.append(s.add_part("bracket", f'{{"n": {n}}}', CAD))
        except PartExists:
            refused.append(n)

    threads = [threading.Thread(target=create, args=(s, n)) for n, s in enumerate(stores)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    try:
        assert len(made) == 1 and len(refused) == 3
        assert stores[0].part_keys() == {"bracket": made[0].key}
        assert stores[0].part_revisions() == [("bracket", 1)]
    finally:
        for s in stores:
            s.close()


def test_a_creation_repeated_after_a_lost_connection_is_the_same_revision(tmp_path, monkeypatch):
    """The store runs a statement again when the connection was lost under it, whether its
    commit went through or not: a creation that did go through is not refused as a part
    that exists."""
    import service.store as store_module

    attempt = store_module._attempt

    def committed_then_lost(db, work, transaction, schema):
        attempt(db, work, transaction, schema)  # done, but the answer never came back
        return attempt(db, work, transaction, schema)

    with ResultStore(tmp_path / "s.sqlite") as s:
        monkeypatch.setattr(store_module, "_attempt", committed_then_lost)
        made = s.add_part("bracket", "{}", CAD)
        monkeypatch.undo()
        assert made.revision == 1 and s.part_revisions() == [("bracket", 1)]
        with pytest.raises(PartExists):  # another creation is still refused
            s.add_part("bracket", "{}", CAD)


def test_a_copy_never_overwrites_the_target_and_a_second_copy_changes_nothing(
    tmp_path, store_target
):
    """Two stations' stores copied into one plant database: a part revision of the same
    name and number but another CAD is refused before anything is copied; what the plant
    did since a copy (an acknowledgement, a deletion, a part created again) stands when the
    copy runs again, and a deletion in the station since is carried over."""
    st1, st2 = ResultStore(tmp_path / "st1.sqlite"), ResultStore(tmp_path / "st2.sqlite")
    with st1, st2, ResultStore(store_target) as plant:
        a1 = st1.add_part("a", '{"station": 1}', CAD)
        b1 = st1.add_part("b", "{}", CAD)
        st1.put(res(1))
        alarm = Alarm(kind="seq_jump", message="m", triggered_ns=1, line="line1", station="st1",
                      raised_ns=5)  # fmt: skip
        st1.put_alarm(alarm)
        st2.add_part("a", '{"station": 2}', CAD[::-1])
        st2.put(res(2, part="a"))
        copy_store(st1, plant)

        with pytest.raises(CopyConflict, match="part 'a' revision 1 is another spec or CAD"):
            copy_store(st2, plant)
        assert plant.part("a", 1).key == a1.key and plant.count() == 1

        plant.put_alarm(alarm.model_copy(update={"acknowledged_by": "ann", "acknowledged_ns": 9}))
        plant.retire_part("a")
        copy_store(st1, plant)
        assert plant.alarm(alarm.id).acknowledged_by == "ann" and not plant.alarms(open_only=True)
        assert plant.part_keys() == {"b": b1.key}

        again = plant.add_part("a", '{"plant": 1}', CAD)
        copy_store(st1, plant)
        assert again.revision == 2 and plant.part_keys() == {"a": again.key, "b": b1.key}

        st1.retire_part("b")
        copy_store(st1, plant)
        assert plant.part_keys() == {"a": again.key} and plant.part("b", 1).retired_ns

        # The station created "a" again too: its revision 2 is not the plant's.
        st1.retire_part("a")
        st1.add_part("a", '{"station": 1, "again": true}', CAD)
        with pytest.raises(CopyConflict, match="part 'a' revision 2 is another spec or CAD"):
            copy_store(st1, plant)
        assert plant.part("a").key == again.key

    # Control limits frozen at the plant are not replaced by a station's.
    frozen = Baseline(part="c", since_ns=None, until_ns=5, frozen_ns=7, frozen_by="ann",
                      results=20, limits={})  # fmt: skip
    with ResultStore(tmp_path / "st3.sqlite") as st3, ResultStore(store_target) as plant:
        st3.put_baseline(frozen)
        plant.put_baseline(frozen)
        copy_store(st3, plant)
        st3.put_baseline(frozen.model_copy(update={"frozen_ns": 8}))
        with pytest.raises(CopyConflict, match="part 'c' has another frozen baseline"):
            copy_store(st3, plant)


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


def test_other_connections_see_each_put_at_once(store_target):
    """Each put is committed when it returns: the API of another process, or `sqlite3`
    and `psql` on the shell, read it while the store is open (SQLite: WAL)."""
    with ResultStore(store_target) as s:
        s.put(res(1))
        with raw_connection(store_target) as db:
            assert db.execute("SELECT COUNT(*) FROM results").fetchone()[0] == 1


def test_a_station_s_triggers_by_seq_and_time(store):
    for seq in range(10):
        store.put(res(seq, status="fail" if seq == 4 else "pass"))
    store.put(res(7, status="error", t=T0 + 7_500_000_000))  # a repeat of seq 7, refused
    other = res(20).model_copy(
        update={"station": "st2", "id": make_result_id("line1", "st2", 20, T0)}
    )
    store.put(other)
    assert store.last_trigger("line1", "st1") == (9, res(9).triggered_ns)
    assert store.last_trigger("line1", "st2") == (20, other.triggered_ns)
    assert store.last_trigger("line1", "nowhere") is None
    got = store.station_results("line1", "st1", seq=(5, 8))
    assert [(r.seq, r.status) for r in got] == [(5, "pass"), (6, "pass"), (7, "pass"),
                                                (7, "error"), (8, "pass")]  # fmt: skip
    by_time = store.station_results("line1", "st1", since_ns=T0 + 2 * 10**9,
                                    until_ns=T0 + 3 * 10**9)  # fmt: skip
    assert [r.seq for r in by_time] == [2, 3]
    assert [r.seq for r in store.station_results("line1", "st1", limit=3)] == [0, 1, 2]
    counts = {s.value: 0 for s in Status} | {"pass": 10, "fail": 1, "error": 1}
    assert store.status_counts() == counts


def test_deleting_a_part_deletes_its_results_only(store):
    for seq in range(6):
        store.put(res(seq, part="a" if seq % 2 else "b"))
    assert store.delete_part("a") == 3
    assert store.delete_part("a") == 0
    assert sorted(r.seq for r in store.iter_all()) == [0, 2, 4]


# ----------------------------------------------------------------------------- PostgreSQL


def test_a_connection_the_server_dropped_is_replaced_without_losing_a_put(pg_server, caplog):
    """A server restart or a dropped link between two results: the next put reconnects
    and is stored."""
    url = pg_server.new_database()
    with ResultStore(url) as s:
        s.put(res(1))
        with psycopg.connect(url, autocommit=True) as admin:
            (pid,) = admin.execute(
                "SELECT pid FROM pg_stat_activity WHERE application_name = 'inspection' "
                "AND datname = current_database()"
            ).fetchone()
            # With a timeout the call returns once the server process has gone.
            assert admin.execute("SELECT pg_terminate_backend(%s, 10000)", (pid,)).fetchone()[0]
        s.put(res(2))
        assert s.count() == 2
    assert "connection lost" in caplog.text


def test_a_database_that_went_away_is_a_store_error(pg_server):
    url = pg_server.new_database()
    with ResultStore(url) as s:
        s.put(res(1))
        name = url.rsplit("/", 1)[1]
        with psycopg.connect(pg_server.url(), autocommit=True) as admin:
            admin.execute(f"DROP DATABASE {name} WITH (FORCE)")
        with pytest.raises(StoreError, match=f'database "{name}" does not exist'):
            s.put(res(2))


def test_a_server_that_is_not_there_is_a_clear_error_without_the_password(pg_server):
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # bound and not listening: nothing answers there
        with pytest.raises(StoreError, match="cannot connect") as err:
            ResultStore(f"postgresql://postgres:s3cret@127.0.0.1:{port}/results")
    assert "s3cret" not in str(err.value) and "postgres:***@" in str(err.value)
    with pytest.raises(StoreError, match='database "nope" does not exist'):
        ResultStore(pg_server.url("nope"))
    with pytest.raises(StoreError, match="not a valid PostgreSQL URL"):
        ResultStore("postgresql://postgres:s3cret@127.0.0.1/results?sslmod=require")


def test_without_a_server_installed_the_postgresql_variants_say_how_to_get_one(monkeypatch):
    monkeypatch.setattr(pgserver, "find_bindir", lambda: None)
    with pytest.raises(pgserver.ServerUnavailable, match="apt-get install postgresql"):
        pgserver.PgServer.start()


def test_the_archive_keeps_at_most_its_points_evenly_spread(tmp_path):
    """A cloud of millions (an upload) is kept as the colour map needs it, not whole."""
    arc = DeviationArchive(tmp_path, max_points=100)
    pts = np.column_stack([np.arange(1000.0), np.zeros(1000), np.zeros(1000)])
    arc.save("big", pts, np.arange(1000.0))
    p, d = arc.load("big")
    assert len(p) == 100 and p[0, 0] == 0 and p[-1, 0] == 999
    np.testing.assert_array_equal(p[:, 0], d)  # each point keeps its own deviation
    assert np.all(np.diff(p[:, 0]) <= 11)
