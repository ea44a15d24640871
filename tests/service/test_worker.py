"""The worker: every trigger gives exactly one result, whatever arrives (or does not)."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
from linekit import LINE, PART, STATION, client, demo, free_port, peer, pipeline, rig

from service import bus
from service.depthrig import Cloud
from service.models import Status
from service.pipeline import Pipeline
from service.protocol import FrameSet, Keys, encode_frameset
from service.worker import Job, JobQueue, Worker, ZenohWorker, result_from_json


class Collect:
    def __init__(self) -> None:
        self.results = []
        self.framesets = []
        self.event = threading.Condition()

    def __call__(self, outcome, fs) -> None:
        with self.event:
            self.results.append(outcome.result)
            self.framesets.append(fs)
            self.event.notify_all()

    def wait(self, n: int, timeout_s: float = 60.0) -> bool:
        with self.event:
            return self.event.wait_for(lambda: len(self.results) >= n, timeout_s)


@pytest.fixture(scope="module")
def framesets() -> list[FrameSet]:
    r = rig(defect_rate=0.5, seed=7)
    return [r.capture(seq, 1_800_000_000_000_000_000 + seq * 2_000_000_000) for seq in range(6)]


def job(fs_or_bytes) -> Job:
    data = fs_or_bytes if isinstance(fs_or_bytes, bytes) else encode_frameset(fs_or_bytes)
    return Job(data, 0)


def make_worker(p: Pipeline | None = None, sinks=()) -> tuple[Worker, Collect]:
    got = Collect()
    w = Worker(
        p or pipeline(), JobQueue(4), [*sinks, got], line=LINE, station=STATION, missed_part=PART
    )
    return w, got


def test_good_framesets_are_measured(framesets):
    w, got = make_worker()
    for fs in framesets[:2]:
        w.handle(job(fs))
    assert [r.seq for r in got.results] == [0, 1]
    for r, fs in zip(got.results, framesets, strict=False):
        assert r.status in (Status.passed, Status.fail, Status.not_measurable)
        assert r.serial == fs.serial and r.triggered_ns == fs.triggered_ns
        T_cad_rig = np.asarray(r.transform)
        np.testing.assert_allclose(T_cad_rig @ fs.truth.T_rig_part, np.eye(4), atol=1e-2)  # mm, rad
        assert set(r.timings_ms) >= {"reconstruct", "align", "deviations", "total"}
        assert r.cad_hash and r.tree_hash and r.calibration_id and r.software_version


def test_gap_in_seq_becomes_missed_results(framesets):
    w, got = make_worker()
    w.handle(job(framesets[0]))
    w.handle(job(framesets[3]))
    assert [(r.seq, r.status) for r in got.results] == [
        (0, got.results[0].status),
        (1, Status.missed),
        (2, Status.missed),
        (3, got.results[3].status),
    ]
    assert got.results[1].serial == "unknown-1" and got.results[1].part == PART
    t0, t3 = framesets[0].triggered_ns, framesets[3].triggered_ns
    assert t0 < got.results[1].triggered_ns < got.results[2].triggered_ns < t3
    assert len({r.id for r in got.results}) == 4


def test_queue_overflow_drops_oldest_and_records_it_as_missed(framesets):
    q = JobQueue(2)
    for fs in framesets[:4]:
        q.put(job(fs))
    w = Worker(pipeline(), q, [], line=LINE, station=STATION)
    got = Collect()
    w.sinks.append(got)
    while (item := q.get(0)) is not None:
        w.handle(item)
    assert [(r.seq, r.status == Status.missed) for r in got.results] == [
        (0, True),
        (1, True),
        (2, False),
        (3, False),
    ]
    assert got.results[0].serial == framesets[0].serial  # the real serial, read from the header
    assert "queue full" in got.results[0].reason and q.dropped == 2


def bad_payloads(fs: FrameSet) -> dict[str, bytes]:
    good = encode_frameset(fs)
    return {"garbage": b"not a frameset", "truncated": good[: len(good) // 2], "empty": b""}


@pytest.mark.parametrize("kind", ["garbage", "truncated", "empty"])
def test_malformed_frameset_gives_error_and_worker_goes_on(framesets, kind):
    w, got = make_worker()
    w.handle(job(framesets[0]))
    w.handle(job(bad_payloads(framesets[1])[kind]))
    w.handle(job(framesets[2]))
    statuses = [r.status for r in got.results]
    assert Status.error in statuses
    err = next(r for r in got.results if r.status is Status.error)
    assert err.reason.startswith("bad FrameSet")
    if kind == "truncated":  # the header survived: the error keeps the trigger's identity
        assert err.seq == 1 and err.serial == framesets[1].serial
        assert [r.seq for r in got.results] == [0, 1, 2]
    assert got.results[-1].seq == 2 and got.results[-1].status is not Status.error


def test_unknown_part_is_an_error(framesets):
    w, got = make_worker()
    fs = dataclasses.replace(framesets[0], part="no-such-part")
    w.handle(job(fs))
    assert got.results[0].status is Status.error and "unknown part" in got.results[0].reason


@pytest.mark.parametrize(
    "points", [np.full((500, 3), np.nan), np.zeros((0, 3))], ids=["nan", "empty"]
)
def test_nan_and_empty_clouds_are_errors(framesets, points):
    stages, part = demo()
    bad = dataclasses.replace(
        stages, reconstruct=lambda rig, frames: Cloud(points, np.ones(len(points)))
    )
    w, got = make_worker(Pipeline(bad, {PART: part}))
    w.handle(job(framesets[0]))
    assert got.results[0].status is Status.error and "empty cloud" in got.results[0].reason


def test_a_crashing_stage_or_sink_does_not_stop_the_worker(framesets):
    stages, part = demo()

    def boom(*a):
        raise RuntimeError("stage bug")

    def bad_sink(outcome, fs):
        raise OSError("disk full")

    crashing = dataclasses.replace(stages, align=boom)
    w, got = make_worker(Pipeline(crashing, {PART: part}), sinks=[bad_sink])
    w.handle(job(framesets[0]))
    w.handle(job(framesets[1]))
    assert [r.status for r in got.results] == [Status.error, Status.error]
    assert "stage bug" in got.results[0].reason


def test_zenoh_worker_end_to_end(framesets):
    port = free_port()
    keys = Keys(LINE)
    got = Collect()
    with bus.open_session(peer(port)) as wsess, bus.open_session(client(port)) as csess:
        zw = ZenohWorker(
            wsess, keys, STATION, pipeline(), queue_size=4, sinks=[got], missed_part=PART
        )
        try:
            status = csess.declare_subscriber(
                keys.status(STATION), bus.zenoh.handlers.FifoChannel(64)
            )
            seen = Collect()
            sub = bus.RingSubscriber(
                csess,
                keys.results(),
                lambda s: seen(
                    type("O", (), {"result": result_from_json(s.payload.to_bytes())}), None
                ),
                capacity=16,
            )
            pub = bus.frame_publisher(csess, keys.frames(STATION))
            assert bus.wait_for_subscribers(pub, 10)
            for fs in framesets[:3]:
                pub.put(encode_frameset(fs))
            assert got.wait(3) and seen.wait(3)
            tokens = list(csess.liveliness().get(keys.workers(), timeout=5))
            assert any(str(t.ok.key_expr).endswith(zw.id) for t in tokens if t.ok)
            pub.undeclare()
            sub.close()
            beat = status.handler.recv()
            assert b'"station":"st1"' in beat.payload.to_bytes().replace(b" ", b"")
            status.undeclare()
        finally:
            zw.close()
    assert [r.seq for r in got.results] == [0, 1, 2]
    assert [r.model_dump() for r in seen.results] == [r.model_dump() for r in got.results]


def test_stop_measures_what_is_already_queued(framesets):
    q = JobQueue(4)
    got = Collect()
    w = Worker(pipeline(), q, [got], line=LINE, station=STATION)
    for fs in framesets[:3]:
        q.put(job(fs))
    w.start()
    w.stop()
    assert [r.seq for r in got.results] == [0, 1, 2]


def test_bad_input_leaves_earlier_results_intact(tmp_path, framesets):
    from service.line import store_sink
    from service.store import ResultStore

    with ResultStore(tmp_path / "r.sqlite") as store:
        w, got = make_worker(sinks=[store_sink(store)])
        w.handle(job(framesets[0]))
        before = store.get(got.results[0].id)
        for bad in bad_payloads(framesets[1]).values():
            w.handle(job(bad))
        w.handle(job(dataclasses.replace(framesets[2], part="nope")))
        assert store.get(before.id) == before
        assert store.count() == len({r.id for r in got.results})


def test_ingest_spends_seq_numbers_of_triggers_it_could_not_fire():
    from service.ingest import Ingest

    class Slow:
        """A source whose first capture takes three trigger periods."""

        def __init__(self) -> None:
            self.release = threading.Event()
            self.calls = 0

        def capture(self, seq, triggered_ns):
            self.calls += 1
            if self.calls == 1:
                self.release.wait(0.35)  # the capture is slow: the conveyor moves on
            return rig().capture(seq, triggered_ns)

    sent = []
    ing = Ingest(Slow(), sent.append, period_s=0.1)
    ing.run(count=4)
    from service.protocol import decode_frameset

    seqs = [decode_frameset(b).seq for b in sent]
    assert seqs[0] == 0 and seqs[1] >= 3 and seqs == sorted(seqs)
    assert ing.seq == seqs[-1] + 1
