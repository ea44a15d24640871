"""The worker: every trigger gives exactly one result, whatever arrives (or does not).

The worker's mechanics (gaps, overflow, malformed frames, crashing stages and
sinks, zenoh, stopping) run on small stages defined here, which answer at
once; measuring real FrameSets runs the line's flash stages.
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
from linekit import LINE, PART, PARTS_DIR, ROOT, STATION, client, demo, free_port, peer, rig

from inspection.deviations import Verdict
from inspection.measure import Measurement, PartModel
from inspection.panel import sheet_metal_panel
from service import bus
from service.config import load_line_config, load_part_spec
from service.line import stages_for
from service.models import Status
from service.parts import LoadedPart, measure_params
from service.pipeline import Pipeline, Stages
from service.protocol import FrameSet, Keys, encode_frameset
from service.worker import Job, JobQueue, Worker, ZenohWorker, result_from_json


def quick_measure(part: LoadedPart, frames: list[np.ndarray]) -> Measurement:
    """A measurement at once: a flat patch, fitted exactly, that passes."""
    patch = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2)
    points = np.column_stack([patch, np.full(len(patch), 47.0)])
    return Measurement(
        verdict=Verdict.PASS,
        reason=None,
        frame="rig",
        transform=np.eye(4),
        points=points,
        timings_ms={"reconstruct": 0.0, "total": 0.0},
    )


QUICK = Stages(
    name="quick",
    rig=None,
    calibration_id="quick-rig",
    measure=quick_measure,
    render=lambda rig, mesh, T, seed: [np.full((16, 16), i, np.uint8) for i in range(4)],
)


@pytest.fixture(scope="module")
def quick_part() -> LoadedPart:
    spec = load_part_spec(PARTS_DIR / f"{PART}.toml")
    model = PartModel.build(sheet_metal_panel(name=PART), spacing_mm=5.0, alignment=False)
    return LoadedPart(spec, model, "quick-tree", measure_params(spec))


def pipeline(part: LoadedPart, stages: Stages = QUICK) -> Pipeline:
    return Pipeline(stages, {PART: part}, line=LINE, station=STATION)


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
def framesets(quick_part) -> list[FrameSet]:
    r = rig(QUICK, quick_part, defect_rate=0.5, seed=7)
    return [r.capture(seq, 1_800_000_000_000_000_000 + seq * 2_000_000_000) for seq in range(6)]


@pytest.fixture(scope="module")
def flash(trees):
    """The line's stages and the demo panel, with two real FrameSets (one dented)."""
    stages, part = demo(trees)
    r = rig(stages, part, defect_rate=0.5, seed=7)
    sets = [r.capture(seq, 1_800_000_000_000_000_000 + seq * 2_000_000_000) for seq in range(2)]
    return stages, part, sets


def job(fs_or_bytes) -> Job:
    data = fs_or_bytes if isinstance(fs_or_bytes, bytes) else encode_frameset(fs_or_bytes)
    return Job(data, 0)


def make_worker(p: Pipeline, sinks=()) -> tuple[Worker, Collect]:
    got = Collect()
    w = Worker(p, JobQueue(4), [*sinks, got], line=LINE, station=STATION, missed_part=PART)
    return w, got


def test_good_framesets_are_measured_with_the_flash_rig(flash):
    stages, part, framesets = flash
    w, got = make_worker(pipeline(part, stages))
    for fs in framesets:
        w.handle(job(fs))
    assert [r.seq for r in got.results] == [0, 1]
    for r, fs in zip(got.results, framesets, strict=True):
        assert r.status in (Status.passed, Status.fail, Status.not_measurable), r.reason
        assert r.serial == fs.serial and r.triggered_ns == fs.triggered_ns
        # The calibrated rig is not the nominal one the frames were rendered with:
        # the pose comes back within a fraction of a millimetre and a milliradian.
        err = np.asarray(r.transform) @ fs.truth.T_rig_part
        np.testing.assert_allclose(err[:3, :3], np.eye(3), atol=2e-3)
        np.testing.assert_allclose(err[:3, 3], 0.0, atol=1.0)
        assert set(r.timings_ms) >= {"reconstruct", "guide", "align", "deviations", "total"}
        # The fit's own diagnostics travel with the result.
        assert r.converged is True and r.stop_reason == "converged" and r.iterations > 0
        assert 0 < r.observability <= 1 and r.weak_directions == []
        assert r.ambiguous is False
        assert r.cad_hash == part.cad.hash and r.tree_hash == part.tree_hash
        assert r.calibration_id == stages.calibration_id and r.software_version
    dented = [r for r, fs in zip(got.results, framesets, strict=True) if fs.truth.defects]
    assert all(r.field.min_mm < -0.5 for r in dented)


def test_gap_in_seq_becomes_missed_results(framesets, quick_part):
    w, got = make_worker(pipeline(quick_part))
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


def test_the_status_reports_the_queue_of_any_job_source(framesets, quick_part):
    q = JobQueue(3)
    w = Worker(pipeline(quick_part), q, [], line=LINE, station=STATION)
    q.put(job(framesets[0]))
    status = w.status("w1", "ready")
    assert (status["queue_depth"], status["queue_capacity"], status["ready"]) == (1, 3, True)


def test_queue_overflow_drops_oldest_and_records_it_as_missed(framesets, quick_part):
    q = JobQueue(2)
    for fs in framesets[:4]:
        q.put(job(fs))
    w = Worker(pipeline(quick_part), q, [], line=LINE, station=STATION)
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
    assert w.stats.missed_by_cause == {"queue_full": 2}
    assert w.stats.alarms_by_kind == {"queue_overflow": 2}


def bad_payloads(fs: FrameSet) -> dict[str, bytes]:
    good = encode_frameset(fs)
    return {"garbage": b"not a frameset", "truncated": good[: len(good) // 2], "empty": b""}


@pytest.mark.parametrize("kind", ["garbage", "truncated", "empty"])
def test_malformed_frameset_gives_error_and_worker_goes_on(framesets, kind, quick_part):
    w, got = make_worker(pipeline(quick_part))
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


def test_unknown_part_is_an_error(framesets, quick_part):
    w, got = make_worker(pipeline(quick_part))
    fs = dataclasses.replace(framesets[0], part="no-such-part")
    w.handle(job(fs))
    assert got.results[0].status is Status.error and "unknown part" in got.results[0].reason


def test_an_unmeasured_part_is_an_error_with_the_reason(framesets, quick_part):
    def nothing_seen(part, frames):
        return Measurement(verdict=None, reason="empty cloud: no surface seen", frame="rig")

    w, got = make_worker(pipeline(quick_part, dataclasses.replace(QUICK, measure=nothing_seen)))
    w.handle(job(framesets[0]))
    r = got.results[0]
    assert r.status is Status.error and r.reason == "empty cloud: no surface seen"
    assert r.transform is None and r.serial == framesets[0].serial


def test_guided_matching_follows_the_station_setting() -> None:
    line = ROOT / "configs" / "line.toml"
    assert stages_for(load_line_config(line)).guided is True
    off = load_line_config(line, overrides={("station", "guided_matching"): False})
    assert stages_for(off).guided is False


def test_a_crashing_stage_or_sink_does_not_stop_the_worker(framesets, quick_part):
    def boom(*a):
        raise RuntimeError("stage bug")

    def bad_sink(outcome, fs):
        raise OSError("disk full")

    crashing = dataclasses.replace(QUICK, measure=boom)
    w, got = make_worker(pipeline(quick_part, crashing), sinks=[bad_sink])
    w.handle(job(framesets[0]))
    w.handle(job(framesets[1]))
    assert [r.status for r in got.results] == [Status.error, Status.error]
    assert "stage bug" in got.results[0].reason


def test_zenoh_worker_end_to_end(framesets, quick_part):
    port = free_port()
    keys = Keys(LINE)
    got = Collect()
    with bus.open_session(peer(port)) as wsess, bus.open_session(client(port)) as csess:
        zw = ZenohWorker(
            wsess, keys, STATION, pipeline(quick_part), queue_size=4, sinks=[got], missed_part=PART
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


def test_stop_measures_what_is_already_queued(framesets, quick_part):
    q = JobQueue(4)
    got = Collect()
    w = Worker(pipeline(quick_part), q, [got], line=LINE, station=STATION)
    for fs in framesets[:3]:
        q.put(job(fs))
    w.start()
    w.stop()
    assert [r.seq for r in got.results] == [0, 1, 2]


def test_bad_input_leaves_earlier_results_intact(tmp_path, framesets, quick_part):
    from service.line import store_sink
    from service.store import ResultStore

    with ResultStore(tmp_path / "r.sqlite") as store:
        w, got = make_worker(pipeline(quick_part), sinks=[store_sink(store)])
        w.handle(job(framesets[0]))
        before = store.get(got.results[0].id)
        for bad in bad_payloads(framesets[1]).values():
            w.handle(job(bad))
        w.handle(job(dataclasses.replace(framesets[2], part="nope")))
        assert store.get(before.id) == before
        assert store.count() == len({r.id for r in got.results})


def test_ingest_spends_seq_numbers_of_triggers_it_could_not_fire(quick_part):
    from service.ingest import Ingest

    source = rig(QUICK, quick_part)

    class Slow:
        """A source whose first capture takes three trigger periods."""

        def __init__(self) -> None:
            self.release = threading.Event()
            self.calls = 0

        def capture(self, seq, triggered_ns):
            self.calls += 1
            if self.calls == 1:
                self.release.wait(0.35)  # the capture is slow: the conveyor moves on
            return source.capture(seq, triggered_ns)

    sent = []
    ing = Ingest(Slow(), sent.append, period_s=0.1)
    ing.run(count=4)
    from service.protocol import decode_frameset

    seqs = [decode_frameset(b).seq for b in sent]
    assert seqs[0] == 0 and seqs[1] >= 3 and seqs == sorted(seqs)
    assert ing.seq == seqs[-1] + 1


def test_worker_and_api_measure_with_the_same_loaded_part(tmp_path, trees):
    """One tree per part: the station's pipeline holds the registry's own objects."""
    from linekit import ROOT

    from service.config import load_line_config
    from service.line import Station

    demo(trees)  # the tree is in the session's cache
    cfg = load_line_config(
        ROOT / "configs" / "line.toml",
        overrides={("storage", "data_dir"): str(tmp_path), ("storage", "trees_dir"): str(trees),
                   ("station", "parts"): [PART]},
    )  # fmt: skip
    station = Station.load(cfg, warm_up=False)
    try:
        assert station.registry is not None and station.registry.ready()
        part = station.registry.get(PART)
        assert station.parts[PART] is part
        assert station.pipeline().parts[PART].model.tree is part.model.tree
        assert part.model.alignment is not None
    finally:
        station.close()


def test_simulator_parts_never_stop_a_worker_that_does_not_simulate(tmp_path, trees):
    """``[simulator] parts`` names what the ingest sends: a part nobody created yet stops
    the ingest (and ``inspection run``, which simulates), not ``inspection worker``."""
    from linekit import ROOT

    from service.config import ConfigError, load_line_config
    from service.line import Station

    demo(trees)  # the tree is in the session's cache
    cfg = load_line_config(
        ROOT / "configs" / "line.toml",
        overrides={("storage", "data_dir"): str(tmp_path), ("storage", "trees_dir"): str(trees),
                   ("station", "parts"): [PART], ("simulator", "parts"): [PART, "bracket"]},
    )  # fmt: skip
    with pytest.raises(ConfigError, match="'bracket' is neither a part of station"):
        Station.load(cfg, build_trees=False, warm_up=False)
    station = Station.load(cfg, warm_up=False, simulate=False)
    try:
        assert list(station.parts) == [PART] and list(station.cads) == [PART]
    finally:
        station.close()


# --------------------------------------------------------------------------- seq checked


class Alarms:
    def __init__(self) -> None:
        self.got = []

    def __call__(self, alarm) -> None:
        self.got.append(alarm)

    def kinds(self) -> list[str]:
        return [a.kind.value for a in self.got]


def checked_worker(p: Pipeline, **kw) -> tuple[Worker, Collect, Alarms]:
    got, alarms = Collect(), Alarms()
    w = Worker(p, JobQueue(4), [got], line=LINE, station=STATION, missed_part=PART,
               alarms=[alarms], **kw)  # fmt: skip
    return w, got, alarms


def at(fs: FrameSet, seq: int, dt_ns: int = 0) -> FrameSet:
    """``fs`` as if triggered with another seq (and later by ``dt_ns``)."""
    return dataclasses.replace(fs, seq=seq, triggered_ns=fs.triggered_ns + dt_ns)


def test_a_seq_jump_beyond_the_bound_is_refused_not_expanded(framesets, quick_part):
    """A seq 10^12 ahead: one error result and an alarm, no missed records, and the
    next part is measured as if the jump had not come."""
    w, got, alarms = checked_worker(pipeline(quick_part), max_seq_jump=300)
    w.handle(job(framesets[0]))
    w.handle(job(at(framesets[1], 10**12)))
    w.handle(job(framesets[1]))
    assert [(r.seq, r.status) for r in got.results] == [
        (0, got.results[0].status), (10**12, Status.error), (1, got.results[2].status)
    ]  # fmt: skip
    assert got.results[2].status in (Status.passed, Status.fail)
    assert "jumped from 0 to 1000000000000" in got.results[1].reason
    assert alarms.kinds() == ["seq_jump"] and alarms.got[0].seq == 10**12


def test_a_jump_within_the_bound_is_answered_as_missed(framesets, quick_part):
    w, got, alarms = checked_worker(pipeline(quick_part), max_seq_jump=3)
    w.handle(job(framesets[0]))
    w.handle(job(framesets[4]))  # 3 skipped: within the bound
    w.handle(job(at(framesets[5], 9)))  # 4 skipped: beyond it
    assert [(r.seq, r.status) for r in got.results][1:4] == [(s, Status.missed) for s in (1, 2, 3)]
    assert got.results[-1].seq == 9 and got.results[-1].status is Status.error
    assert alarms.kinds() == ["seq_jump"]
    assert w.stats.missed_by_cause == {"never_arrived": 3}
    assert w.stats.alarms_by_kind == {"seq_jump": 1}


def test_a_repeated_seq_is_refused_and_the_next_part_measured(framesets, quick_part):
    w, got, alarms = checked_worker(pipeline(quick_part))
    for fs in framesets[:2]:
        w.handle(job(fs))
    w.handle(job(at(framesets[1], 1, dt_ns=1_000)))  # seq 1 again, another trigger
    w.handle(job(framesets[2]))
    assert [(r.seq, r.status is Status.error) for r in got.results] == [
        (0, False), (1, False), (1, True), (2, False)
    ]  # fmt: skip
    assert "seq 1 repeated" in got.results[2].reason
    assert len({r.id for r in got.results}) == 4  # the refusal does not overwrite seq 1's result
    assert alarms.kinds() == ["seq_repeat"]


def test_a_trigger_delivered_twice_is_answered_once(tmp_path, framesets, quick_part):
    """The same FrameSet twice: one result, one alarm; and a worker with a store does not
    answer again a trigger that is stored already (a restart, another delivery)."""
    from service.line import store_sink
    from service.store import ResultStore

    w, got, alarms = checked_worker(pipeline(quick_part))
    w.handle(job(framesets[0]))
    w.handle(job(framesets[0]))
    assert len(got.results) == 1 and alarms.kinds() == ["seq_repeat"]
    with ResultStore(tmp_path / "r.sqlite") as store:
        store_sink(store)(type("O", (), {"result": got.results[0]})(), None)
        w2, got2, alarms2 = checked_worker(pipeline(quick_part), is_stored=store.has)
        w2.handle(job(framesets[0]))
        w2.handle(job(framesets[1]))
        assert [r.seq for r in got2.results] == [1] and alarms2.kinds() == ["seq_repeat"]


def test_the_seq_of_an_undecodable_frameset_is_not_trusted(framesets, quick_part):
    """Bytes that do not decode but claim seq 19: an error result and an alarm, no
    missed records for 1..18, and parts 1..3 are measured when they come."""
    w, got, alarms = checked_worker(pipeline(quick_part))
    w.handle(job(framesets[0]))
    broken = encode_frameset(at(framesets[1], 19))
    w.handle(job(broken[: len(broken) // 2]))
    for fs in framesets[1:4]:
        w.handle(job(fs))
    assert [(r.seq, r.status) for r in got.results][1] == (19, Status.error)
    assert [r.seq for r in got.results] == [0, 19, 1, 2, 3]
    assert all(r.status is not Status.missed for r in got.results)
    assert alarms.kinds() == ["bad_frameset"]


def test_a_source_that_counts_anew_is_followed_after_one_refusal(framesets, quick_part):
    """A trigger source restarted without its state: its first seq is refused, the
    next one (consecutive to it) is accepted with an alarm, and counting goes on."""
    w, got, alarms = checked_worker(pipeline(quick_part))
    for fs in framesets[:4]:
        w.handle(job(fs))
    later = 10**10
    for seq in (0, 1, 2):
        w.handle(job(at(framesets[seq], seq, dt_ns=later)))
    assert [(r.seq, r.status is Status.error) for r in got.results][4:] == [
        (0, True), (1, False), (2, False)
    ]  # fmt: skip
    assert alarms.kinds() == ["seq_repeat", "seq_rebased"]


def test_a_restarted_worker_goes_on_from_the_stored_seq(framesets, quick_part):
    w, got, _ = checked_worker(pipeline(quick_part), resume=(1, framesets[1].triggered_ns))
    w.handle(job(framesets[4]))
    assert [(r.seq, r.status is Status.missed) for r in got.results] == [
        (2, True), (3, True), (4, False)
    ]  # fmt: skip


# --------------------------------------------------------------------------- journal


def test_the_journal_keeps_frames_until_answered(tmp_path):
    from service.journal import Journal

    j = Journal(tmp_path / "j")
    k1 = j.add(b"one", 5)
    k2 = j.add(b"two", 7)
    (tmp_path / "j" / "00000000000000000009-000009.tmp").write_bytes(b"torn")
    j.remove(k1)
    again = Journal(tmp_path / "j")  # a restart: the torn write is discarded
    pending = again.pending()
    assert [(e.key, e.payload, e.received_ns) for e in pending] == [(k2, b"two", 7)]
    assert not list((tmp_path / "j").glob("*.tmp"))
    assert Journal(tmp_path / "small", max_entry_bytes=2).add(b"abc", 1) is None


def test_a_killed_worker_measures_its_journal_first(tmp_path, framesets, quick_part):
    """Frames accepted before a kill are measured at the next start, before new ones; one
    whose result was stored just before the kill is not answered again; the gap to the
    first live frame is answered from the store's last seq."""
    from service.journal import Journal
    from service.line import store_sink
    from service.store import ResultStore

    journal = Journal(tmp_path / "journal")
    with ResultStore(tmp_path / "r.sqlite") as store:
        first = Worker(pipeline(quick_part), JobQueue(4), [store_sink(store)],
                       line=LINE, station=STATION)  # fmt: skip
        first.handle(job(framesets[0]))
        for fs in framesets[:3]:  # 0 was answered; the kill came before its entry went
            journal.add(encode_frameset(fs), fs.triggered_ns)
        port = free_port()
        got = Collect()
        with bus.open_session(peer(port)) as wsess, bus.open_session(client(port)) as csess:
            zw = ZenohWorker(wsess, Keys(LINE), STATION, pipeline(quick_part), queue_size=2,
                             sinks=[store_sink(store), got], missed_part=PART, store=store,
                             journal=journal)  # fmt: skip
            try:
                assert got.wait(2, 30)
                pub = bus.frame_publisher(csess, Keys(LINE).frames(STATION))
                assert bus.wait_for_subscribers(pub, 10)
                pub.put(encode_frameset(framesets[5]))
                assert got.wait(5, 30)
                pub.undeclare()
            finally:
                zw.close()
        assert [(r.seq, r.status is Status.missed) for r in got.results] == [
            (1, False), (2, False), (3, True), (4, True), (5, False)
        ]  # fmt: skip
        assert zw.worker.stats.duplicates == 1 and zw.worker.stats.alarms == 0
        assert len(journal) == 0
        assert sorted(r.seq for r in store.station_results(LINE, STATION)) == [0, 1, 2, 3, 4, 5]


def test_the_ingest_never_uses_a_seq_twice_across_restarts(tmp_path, quick_part):
    from service.ingest import Ingest, SeqState
    from service.protocol import decode_frameset

    state = SeqState(tmp_path / "state" / "ingest-seq")
    sent: list[bytes] = []
    for n in (3, 2):  # two runs of the ingest, the second a restart
        ingest = Ingest(rig(QUICK, quick_part), sent.append, period_s=1.0, seq_state=state)
        for _ in range(n):
            ingest.trigger()
    assert [decode_frameset(b).seq for b in sent] == [0, 1, 2, 3, 4]
    state.path.write_text("garbage")
    with pytest.raises(ValueError, match="not a seq number"):
        Ingest(rig(QUICK, quick_part), sent.append, period_s=0.01, seq_state=state)


class NotingSession:
    """A worker's real session that notes the key of each put before making it."""

    def __init__(self, session, log: list[tuple[str, str]]) -> None:
        self._session, self._log = session, log

    def put(self, key, *args, **kwargs):
        self._log.append(("published", str(key)))
        return self._session.put(key, *args, **kwargs)

    def __getattr__(self, name: str):
        return getattr(self._session, name)


def test_alarms_are_published_on_the_station_alarm_key_once_stored(tmp_path, framesets, quick_part):
    """Whoever sees an alarm on zenoh can find it in the store: it is stored before it is
    published, and a subscriber that looks it up the moment it arrives finds it."""
    from service.models import Alarm
    from service.store import ResultStore

    port = free_port()
    keys = Keys(LINE)
    got = Collect()
    log: list[tuple[str, str]] = []
    found: list[Alarm | None] = []
    looked = threading.Event()

    def put(alarm: Alarm) -> None:
        store.put_alarm(alarm)
        log.append(("stored", keys.alarm(alarm.station)))

    def on_alarm(sample) -> None:
        found.append(store.alarm(Alarm.model_validate_json(sample.payload.to_bytes()).id))
        looked.set()

    with (
        ResultStore(tmp_path / "results.sqlite") as store,
        bus.open_session(peer(port)) as wsess,
        bus.open_session(client(port)) as csess,
    ):
        alarms = csess.declare_subscriber(keys.alarms(), bus.zenoh.handlers.FifoChannel(16))
        seen = csess.declare_subscriber(keys.alarms(), on_alarm)
        zw = ZenohWorker(NotingSession(wsess, log), keys, STATION, pipeline(quick_part),
                         queue_size=4, sinks=[got], alarms=[put])  # fmt: skip
        try:
            pub = bus.frame_publisher(csess, keys.frames(STATION))
            assert bus.wait_for_subscribers(pub, 10)
            pub.put(encode_frameset(framesets[0]))
            pub.put(encode_frameset(at(framesets[1], 10**12)))
            assert got.wait(2, 30)
            sample = alarms.handler.recv()
            assert looked.wait(10)
            pub.undeclare()
        finally:
            zw.close()
            alarms.undeclare()
            seen.undeclare()
    assert str(sample.key_expr) == keys.alarm(STATION)
    alarm = Alarm.model_validate_json(sample.payload.to_bytes())
    assert alarm.kind.value == "seq_jump" and alarm.seq == 10**12 and alarm.station == STATION
    assert alarm.triggered_ns == framesets[1].triggered_ns
    assert [what for what, key in log if key == keys.alarm(STATION)] == ["stored", "published"]
    assert found and found[0] is not None and found[0].id == alarm.id


def bomb_png(side: int) -> bytes:
    """A valid black PNG of ``side`` x ``side`` px, made row by row (about 1 MB for 16384)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    z = zlib.compressobj(9)
    row = bytes(side + 1)  # filter byte and one byte a pixel
    idat = b"".join(z.compress(row) for _ in range(side)) + z.flush()
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def test_a_decompression_bomb_is_refused_before_decoding(framesets, quick_part):
    """Four 16384 x 16384 PNGs (4 MB on the wire, 1 GB decoded) announced for a rig of
    16 x 16 px cameras: refused from the header, with the trigger's identity."""
    import json
    import struct

    from service.protocol import MAGIC, PREAMBLE, VERSION

    png = bomb_png(16384)
    fs = framesets[1]
    header = {
        "line": fs.line, "station": fs.station, "part": fs.part, "serial": fs.serial,
        "seq": fs.seq, "triggered_ns": fs.triggered_ns, "calibration_id": fs.calibration_id,
        "images": [{"camera": f"cam{i}", "width": 16384, "height": 16384,
                    "pixel_format": "mono8", "encoding": "png", "length": len(png)}
                   for i in range(4)],
    }  # fmt: skip
    head = json.dumps(header).encode()
    bomb = PREAMBLE.pack(MAGIC, VERSION, 0, len(head)) + head + png * 4
    assert struct.unpack(">II", png[16:24]) == (16384, 16384)
    cams = [(f"cam{i}", 16, 16) for i in range(4)]
    got, alarms = Collect(), Alarms()
    w = Worker(pipeline(quick_part), JobQueue(4), [got], line=LINE, station=STATION,
               alarms=[alarms], cameras=cams)  # fmt: skip
    w.handle(job(framesets[0]))
    w.handle(job(bomb))
    w.handle(job(framesets[2]))
    err = got.results[1]
    assert err.status is Status.error and err.seq == 1 and err.serial == fs.serial
    assert "image 0 is 16384 x 16384 px; camera cam0 takes 16 x 16 px" in err.reason
    assert got.results[2].seq == 2 and got.results[2].status is not Status.error
    assert alarms.kinds() == ["bad_frameset"]


def test_a_burst_of_garbage_gets_a_result_each(framesets, quick_part):
    """Thirty undecodable payloads at once, then a good FrameSet: thirty-one results."""
    port = free_port()
    keys = Keys(LINE)
    got = Collect()
    with bus.open_session(peer(port)) as wsess, bus.open_session(client(port)) as csess:
        zw = ZenohWorker(wsess, keys, STATION, pipeline(quick_part), queue_size=4, sinks=[got])
        try:
            pub = bus.frame_publisher(csess, keys.frames(STATION))
            assert bus.wait_for_subscribers(pub, 10)
            for i in range(30):
                pub.put(b"garbage %d" % i)
            pub.put(encode_frameset(framesets[0]))
            assert got.wait(31, 60), len(got.results)
            pub.undeclare()
        finally:
            zw.close()
    assert len(got.results) == 31
    assert sum(r.status in (Status.error, Status.missed) for r in got.results) == 30
    assert got.results[-1].seq == 0 and got.results[-1].status is not Status.error


def test_a_journal_entry_below_the_stores_last_seq_is_answered_not_refused(
    tmp_path, framesets, quick_part
):
    """Results finish out of seq order on a cluster: at a kill, seq 1 may still be measured
    while seq 2 is stored. The restarted worker goes on after seq 2 and answers seq 1 from
    its journal; a live FrameSet repeating seq 1 is still refused."""
    from service.line import store_sink
    from service.store import ResultStore

    p = pipeline(quick_part)
    with ResultStore(tmp_path / "r.sqlite") as store:
        for fs in (framesets[0], framesets[2]):
            store.put(p.run(fs).result)
        w, got, alarms = checked_worker(
            p, resume=store.last_trigger(LINE, STATION), is_stored=store.has
        )
        w.sinks.insert(0, store_sink(store))
        w.handle(Job(encode_frameset(framesets[1]), 0, None, replayed=True))
        w.handle(Job(encode_frameset(framesets[2]), 0, None, replayed=True))  # stored: done
        w.handle(job(framesets[3]))
        w.handle(job(at(framesets[1], 1, dt_ns=1_000)))  # another trigger claiming seq 1
        assert [(r.seq, r.status is Status.error) for r in got.results] == [
            (1, False), (3, False), (1, True)
        ]  # fmt: skip
        assert alarms.kinds() == ["seq_repeat"] and w.stats.duplicates == 1
        measured = [r.seq for r in store.station_results(LINE, STATION) if r.status != "error"]
        assert sorted(measured) == [0, 1, 2, 3]


def test_the_trigger_sources_count_answers_what_no_later_frameset_shows():
    from service.worker import SeqTracker

    t = SeqTracker(max_jump=5)
    assert t.fired(3, 300).missing == []  # nothing seen yet: counting starts with a FrameSet
    assert t.check(0, 0).accepted
    assert [m for m, _ in t.fired(3, 300).missing] == [1, 2, 3]
    assert t.fired(3, 300).missing == [] and t.fired(2, 200).missing == []
    refused = t.fired(10, 1000)  # 7 beyond the count: not expanded
    assert not refused.accepted and refused.alarm[0].value == "seq_jump"
    assert t.check(4, 400).missing == []  # the count went on from the word


def test_frames_lost_after_the_last_one_are_answered_on_the_ingests_count(quick_part):
    """The ingest's last two FrameSets never reach the bus: no later FrameSet shows the
    gap, the ``fired`` count does. One of them coming late is not answered twice."""
    from service.ingest import Ingest
    from service.line import FiredCount

    port = free_port()
    keys = Keys(LINE)
    got = Collect()
    with bus.open_session(peer(port)) as wsess, bus.open_session(client(port)) as csess:
        alarms = csess.declare_subscriber(keys.alarms(), bus.zenoh.handlers.FifoChannel(16))
        zw = ZenohWorker(wsess, keys, STATION, pipeline(quick_part), queue_size=4, sinks=[got],
                         missed_part=PART, fired_grace_s=0.5)  # fmt: skip
        try:
            pub = bus.frame_publisher(csess, keys.frames(STATION))
            assert bus.wait_for_subscribers(pub, 10)
            lost: list[bytes] = []
            ingest = Ingest(
                rig(QUICK, quick_part),
                lambda b: pub.put(b) if ingest.seq < 3 else lost.append(b),
                period_s=1.0,
            )
            fired = FiredCount(csess, keys.fired(STATION), ingest, period_s=0.2)
            # A count no ingest could send is ignored, and the worker goes on.
            bus.put_json(csess, keys.fired(STATION), '{"next_seq": -4, "triggered_ns": 1}')
            for _ in range(5):
                ingest.trigger()
            fired.close()
            assert got.wait(5, 30), [r.seq for r in got.results]
            pub.put(lost[-1])  # seq 4, long after its grace
            sample = alarms.handler.recv()
            pub.undeclare()
        finally:
            zw.close()
            alarms.undeclare()
    assert [r.seq for r in got.results] == [0, 1, 2, 3, 4]
    assert [r.status for r in got.results[3:]] == [Status.missed, Status.missed]
    assert all("never arrived" in r.reason for r in got.results[3:])
    assert got.results[2].triggered_ns < got.results[3].triggered_ns < got.results[4].triggered_ns
    assert str(sample.key_expr) == keys.alarm(STATION)
    assert b"came after its trigger was answered missed" in sample.payload.to_bytes()
    assert zw.worker.stats.duplicates == 1
