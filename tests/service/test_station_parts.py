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

import pytest
from linekit import LINE, PART, PARTS_DIR, STATION, rig
from test_worker import QUICK, Collect, job

from inspection.measure import PartModel
from inspection.panel import PanelSpec, sheet_metal_panel
from service.config import load_part_spec
from service.journal import Journal
from service.models import PartCreate, Status
from service.parts import LoadedPart, PartRegistry, measure_params
from service.pipeline import Pipeline
from service.protocol import FrameSet
from service.station_parts import StationParts
from service.store import ResultStore
from service.worker import Job, JobQueue, Worker

NEW = "bracket"


@pytest.fixture(scope="module")
def quick_part() -> LoadedPart:
    spec = load_part_spec(PARTS_DIR / f"{PART}.toml")
    model = PartModel.build(sheet_metal_panel(name=PART), spacing_mm=5.0, alignment=False)
    return LoadedPart(spec, model, "quick-tree", measure_params(spec))


@pytest.fixture(scope="module")
def framesets(quick_part) -> list[FrameSet]:
    r = rig(QUICK, quick_part, seed=7)
    return [r.capture(seq, 1_800_000_000_000_000_000 + seq * 2_000_000_000) for seq in range(6)]


class Told:
    """What a StationParts tells its listeners, and a wait for it."""

    def __init__(self) -> None:
        self.seen: list[tuple[str, str | None]] = []
        self._cond = threading.Condition()

    def __call__(self, name, part) -> None:
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

    def request(self, name, done) -> None:
        self.asked.append((name, done))

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
