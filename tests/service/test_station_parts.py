"""Parts created over the API reach a station's worker through the store, and no trigger
is answered twice or lost on the way.

An API's part registry and a station's (each with its own folder: they share
the store alone) on the worker's quick stages, with FrameSets naming the
station's part, a part created over the API, and a part nobody knows; then
the part created again (a new revision) and deleted while the station runs.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import pytest
from linekit import LINE, PART, STATION, rig
from test_worker import QUICK, Collect, job

from inspection.panel import PanelSpec, sheet_metal_panel
from service.journal import Journal
from service.models import Job as BuildJob
from service.models import JobState, PartCreate, Status
from service.parts import PartBroken, PartRegistry
from service.pipeline import Pipeline
from service.protocol import FrameSet
from service.station_parts import StationParts
from service.store import ResultStore
from service.worker import Job, JobQueue, Worker

NEW = "bracket"


@pytest.fixture(scope="module")
def framesets(quick_part) -> list[FrameSet]:
    r = rig(QUICK, quick_part, seed=7)
    return [r.capture(seq, 1_800_000_000_000_000_000 + seq * 2_000_000_000) for seq in range(6)]


class Told:
    """What a StationParts tells its listeners, and a wait for it."""

    def __init__(self) -> None:
        self.seen: list[tuple[str, str | None]] = []
        self._cond = threading.Condition()

    def __call__(self, name, part, stored) -> None:
        with self._cond:
            self.seen.append((name, None if part is None else part.spec.version))
            self._cond.notify_all()

    def wait(self, what: tuple[str, str | None], timeout_s: float = 60) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: what in self.seen, timeout_s)


@pytest.fixture
def stl(tmp_path) -> bytes:
    path = tmp_path / "bracket.stl"
    sheet_metal_panel(PanelSpec().scaled(100.0, 70.0)).to_trimesh().export(path)
    return path.read_bytes()


def spec(version: str = "1") -> PartCreate:
    return PartCreate(name=NEW, version=version, tree={"spacing_mm": 2.0})


def test_a_part_created_over_the_api_is_measured_by_a_station_that_shares_only_the_store(
    tmp_path, store_target, stl, quick_part, framesets
):
    store = ResultStore(store_target)
    api = PartRegistry(tmp_path / "api-trees", tmp_path / "api", alignment=False, store=store)
    own = PartRegistry(tmp_path / "station-trees", tmp_path / "station", alignment=False)
    parts = {PART: quick_part}
    told = Told()
    # Polled by the test (``check``), between two changes of the store.
    station = StationParts(parts, store, own, station=STATION, poll_s=3600, listeners=[told])
    q, journal, got = JobQueue(4), Journal(tmp_path / "journal"), Collect()
    p = Pipeline(QUICK, parts, line=LINE, station=STATION)
    w = Worker(p, q, [got], line=LINE, station=STATION, journal=journal, parts=station)

    def send(seq: int, part: str) -> None:
        fs = dataclasses.replace(framesets[seq], part=part)
        payload = job(fs).payload
        q.put(Job(payload, 0, journal.add(payload, fs.triggered_ns)))

    try:
        api.wait(api.create(spec(), stl, "b.stl").id)
        created = api.public(NEW)
        w.start()
        send(0, PART)
        send(1, NEW)
        send(2, "nowhere")
        send(3, NEW)
        assert got.wait(4)
        by_seq = {r.seq: r for r in got.results}
        assert sorted(by_seq) == [0, 1, 2, 3] and len(got.results) == 4
        for seq in (1, 3):
            r = by_seq[seq]
            assert r.status is Status.passed and r.part == NEW, r.reason
            assert (r.cad_hash, r.tree_hash, r.spec_version) == (
                created.cad_hash, created.tree_hash, "1"
            )  # fmt: skip
        unknown = by_seq[2]
        assert unknown.status is Status.error and "unknown part 'nowhere'" in unknown.reason
        assert f"station {STATION}" in unknown.reason and "created over the API" in unknown.reason
        # The station's copy is its own: the API's folder is not where it read the part.
        assert (tmp_path / "station" / NEW / "cad.stl").read_bytes() == stl

        # Created again while the station runs: the new revision replaces the old one.
        api.delete(NEW)
        api.wait(api.create(spec("2"), stl, "b.stl").id)
        station.check()
        assert told.wait((NEW, "2"))
        send(4, NEW)
        assert got.wait(5)
        assert got.results[-1].spec_version == "2" and got.results[-1].status is Status.passed

        # Deleted: the station measures it no more; its FrameSets are answered, once each.
        api.delete(NEW)
        station.check()
        assert told.wait((NEW, None))
        send(5, NEW)
        assert got.wait(6)
        gone = got.results[-1]
        assert gone.status is Status.error and f"unknown part '{NEW}'" in gone.reason
    finally:
        w.stop()
        station.close()
        own.close()
        api.close()
        store.close()
    assert [r.seq for r in sorted(got.results, key=lambda r: r.seq)] == list(range(6))
    assert len(journal) == 0 and w.executor_status()["waiting_for_part"] == 0


class Slow:
    """A part source that answers when the test says."""

    def __init__(self, parts: dict, part) -> None:
        self.parts, self.part = parts, part
        self.asked: list[tuple[str, object]] = []

        self.asked_once = threading.Event()

    def request(self, name, done) -> None:
        self.asked.append((name, done))
        self.asked_once.set()

    def pending(self, name) -> str:
        return "building tree (40%)"

    def answer(self) -> None:
        for name, done in self.asked:
            self.parts[name] = self.part
            done(None)


def test_frame_sets_waiting_for_their_part_are_bounded_and_answered_once(quick_part, framesets):
    """As many FrameSets wait for a part as the queue holds; beyond, the oldest is answered
    missed. A trigger delivered again while it waits is answered once. The others go on."""
    parts = {PART: quick_part}
    slow = Slow(parts, quick_part)
    p = Pipeline(QUICK, parts, line=LINE, station=STATION)
    got = Collect()
    w = Worker(p, JobQueue(2), [got], line=LINE, station=STATION, parts=slow)
    waiting = [dataclasses.replace(fs, part=NEW) for fs in framesets[:3]]
    for fs in waiting:
        w.handle(job(fs))
    w.handle(job(waiting[2]))  # delivered again
    w.handle(job(framesets[3]))  # a part the station holds is measured meanwhile
    assert [(r.seq, r.status) for r in got.results] == [(0, Status.missed), (3, Status.passed)]
    assert "waiting for their part" in got.results[0].reason
    assert w.stats.duplicates == 1 and w.executor_status()["waiting_for_part"] == 2
    slow.answer()
    assert w.drain(30)
    assert [(r.seq, r.status) for r in got.results[2:]] == [(1, Status.passed), (2, Status.passed)]
    assert w.stats.missed_by_cause == {"queue_full": 1}


def test_a_frame_set_waits_for_its_part_at_most_part_wait_s_and_is_answered_once(
    quick_part, framesets
):
    """The part never comes in time: the FrameSet is answered error, naming the part and
    what its load was doing; the part coming later answers nothing twice."""
    parts = {PART: quick_part}
    slow = Slow(parts, quick_part)
    p = Pipeline(QUICK, parts, line=LINE, station=STATION)
    got = Collect()
    w = Worker(p, JobQueue(4), [got], line=LINE, station=STATION, parts=slow, part_wait_s=0.2)
    w.handle(job(dataclasses.replace(framesets[0], part=NEW)))
    assert got.results == [] and w.executor_status()["waiting_for_part"] == 1
    assert w.drain(10)
    [late] = got.results
    assert late.status is Status.error and late.part == NEW
    assert late.reason == (f"part '{NEW}' was not loaded within 0.2 s ([station] part_wait_s): "
                           "building tree (40%)")  # fmt: skip
    slow.answer()
    assert w.drain(1) and len(got.results) == 1


def test_a_frame_set_waiting_when_the_worker_stops_is_measured_once_at_the_next_start(
    tmp_path, quick_part, framesets
):
    """Its journal entry stays while it waits: a worker stopped (or killed) meanwhile leaves
    it to the next one, which measures it, once."""
    journal = Journal(tmp_path / "journal")
    fs = dataclasses.replace(framesets[0], part=NEW)
    payload = job(fs).payload
    q, got = JobQueue(4), Collect()
    parts = {PART: quick_part}
    slow = Slow(parts, quick_part)
    w = Worker(Pipeline(QUICK, parts, line=LINE, station=STATION), q, [got], line=LINE,
               station=STATION, journal=journal, parts=slow)  # fmt: skip
    q.put(Job(payload, 0, journal.add(payload, fs.triggered_ns)))
    w.start()
    assert slow.asked_once.wait(30)
    w.stop(timeout_s=0.2)  # the part never comes to this one
    assert got.results == [] and len(journal) == 1

    again = Journal(tmp_path / "journal")
    q2, got2 = JobQueue(4), Collect()
    w2 = Worker(Pipeline(QUICK, {PART: quick_part, NEW: quick_part}, line=LINE, station=STATION),
                q2, [got2], line=LINE, station=STATION, journal=again, parts=slow)  # fmt: skip
    for entry in again.pending():
        w2.handle(Job(entry.payload, entry.received_ns, entry.key, replayed=True))
    assert w2.drain(30)
    assert [(r.seq, r.part, r.status) for r in got2.results] == [(0, NEW, Status.passed)]
    assert got.results == [] and len(again) == 0


class Registry:
    """A part registry whose loads fail as told, in order, then load ``part``; or, with
    ``hold``, whose build never ends until the test sets it."""

    def __init__(self, part, fail=(), hold: threading.Event | None = None) -> None:
        self.part, self.fail, self.hold = part, list(fail), hold
        self.adopted: list[int] = []

    def adopt(self, stored):
        self.adopted.append(stored.revision)
        if self.fail:
            raise self.fail.pop(0)
        if self.hold is None:
            return None
        return BuildJob(id="j", part=stored.name, state=JobState.running, progress=0.4,
                        message="building tree", created_ns=0)  # fmt: skip

    def wait(self, job_id, timeout_s=None):
        if not self.hold.wait(timeout_s):
            raise TimeoutError
        return self.job(job_id)

    def job(self, job_id):
        return BuildJob(id=job_id, part=NEW, state=JobState.running, progress=0.4,
                        message="building tree", created_ns=0)  # fmt: skip

    def get(self, name):
        return self.part

    def forget(self, name) -> None:
        pass


def ask(station: StationParts, name: str) -> str | None:
    came = []
    done = threading.Event()
    station.request(name, lambda why: (came.append(why), done.set()))
    assert done.wait(30)
    return came[0]


def test_a_load_that_failed_is_tried_again_unless_it_failed_on_the_part_itself(
    tmp_path, quick_part
):
    """A full disk passes: the load is tried again after a while. A part that does not load
    fails again: not tried again, until the part is created again, be it with the same
    files (a new revision)."""
    store = ResultStore(tmp_path / "s.sqlite")
    spec_json = spec().model_dump_json()
    store.add_part(NEW, spec_json, b"CAD")
    registry = Registry(
        quick_part, [OSError(28, "No space left on device"), PartBroken("bad CAD file")]
    )
    station = StationParts({}, store, registry, station=STATION, poll_s=3600, retry_s=3600,
                           close_store=True)  # fmt: skip
    try:
        full = ask(station, NEW)
        assert "No space left on device" in full and "tried again after 3600 s" in full
        assert ask(station, NEW) == full and registry.adopted == [1]  # not yet
        station.retry_s = 0.0
        broken = ask(station, NEW)
        assert f"part '{NEW}' (revision 1) cannot be measured: bad CAD file" == broken
        assert ask(station, NEW) == broken and registry.adopted == [1, 1]
        store.retire_part(NEW)
        store.add_part(NEW, spec_json, b"CAD")
        assert ask(station, NEW) is None and registry.adopted == [1, 1, 2]
        assert station.parts[NEW] is quick_part
    finally:
        station.close()


def test_a_load_is_waited_for_at_most_wait_s_and_a_stop_does_not_wait_for_it(tmp_path, quick_part):
    store = ResultStore(tmp_path / "s.sqlite")
    store.add_part(NEW, spec().model_dump_json(), b"CAD")
    hold = threading.Event()
    registry = Registry(quick_part, hold=hold)
    station = StationParts({}, store, registry, station=STATION, wait_s=0.1, poll_s=3600,
                           retry_s=0.0, close_store=True)  # fmt: skip
    try:
        why = ask(station, NEW)
        assert why == (f"part '{NEW}' (revision 1) is still loading after 0.1 s: "
                       f"part '{NEW}' (revision 1): loading: building tree (40%)")  # fmt: skip
        # Not a failure: the next FrameSet waits for the same build, which may end meanwhile.
        done = threading.Event()
        station.request(NEW, lambda why: done.set())
        t0 = time.monotonic()
        station.close()
        assert time.monotonic() - t0 < 5 and not done.is_set()
    finally:
        hold.set()
