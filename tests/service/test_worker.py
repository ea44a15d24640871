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
        overrides={("storage", "data_dir"): str(tmp_path), ("storage", "trees_dir"): str(trees)},
    )
    station = Station.load(cfg, warm_up=False)
    try:
        assert station.registry is not None and station.registry.ready()
        part = station.registry.get(PART)
        assert station.parts[PART] is part
        assert station.pipeline().parts[PART].model.tree is part.model.tree
        assert part.model.alignment is not None
    finally:
        station.close()
