"""Executors: the in-process one and a Dask cluster measure alike; the worker accounts the same.

One test body runs over both executors on the line's flash stages (frames of a
quarter of the line's pixels, one matching pass) and a real ``local:2`` Dask
cluster: the same statuses and deviations, to the bit, whoever measures. The
worker's side (slots, finishing order, duplicates in flight, a lost
measurement) runs on an executor of this file whose futures the test
finishes by hand.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import threading
from concurrent.futures import Future

import numpy as np
import pytest
from linekit import LINE, PART, PARTS_DIR, STATION, demo, free_port, rig
from test_line import cli
from test_worker import QUICK, Collect, job, pipeline

from inspection.measure import PartModel
from inspection.panel import sheet_metal_panel
from inspection.rig import Rig
from service.config import load_part_spec, parse_dask_address
from service.dask_executor import Remote
from service.executor import IN_PROCESS, ExecutorError, InProcessExecutor, Measured
from service.journal import Journal
from service.models import Status
from service.parts import LoadedPart, measure_params
from service.pipeline import Pipeline, flash_stages
from service.protocol import FrameSet, encode_frameset
from service.worker import Job, JobQueue, Worker

SIZE = (640, 512)


@pytest.fixture(scope="module")
def small(trees):
    """The flash stages on small frames, the demo panel, and four FrameSets of it."""
    _, part = demo(trees)
    stages = flash_stages(
        Rig.default().with_image_size(*SIZE), guided=False, truth=Rig.nominal(*SIZE)
    )
    r = rig(stages, part, defect_rate=0.5, seed=3)
    sets = [r.capture(seq, 1_800_000_000_000_000_000 + seq * 10**9) for seq in range(4)]
    return stages, part, sets


@pytest.fixture(scope="module")
def reference(small):
    """What the in-process pipeline gives for each FrameSet."""
    stages, part, sets = small
    p = Pipeline(stages, {PART: part}, line=LINE, station=STATION)
    return [p.run(fs).result for fs in sets]


@pytest.fixture(scope="module")
def cluster(small, trees):
    """A ``local:2`` Dask cluster with the station loaded; its pipeline's parts can grow."""
    from service.dask_executor import DaskExecutor

    stages, part, sets = small
    p = Pipeline(stages, {PART: part}, line=LINE, station=STATION)
    ex = DaskExecutor.connect(parse_dask_address("local:2"), p, warm_up=sets[0], trees_dir=trees)
    try:
        yield ex
    finally:
        ex.close()


def same_measurement(a, b) -> None:
    assert (a.id, a.status, a.reason) == (b.id, b.status, b.reason)
    assert (a.cad_hash, a.tree_hash, a.calibration_id) == (
        b.cad_hash,
        b.tree_hash,
        b.calibration_id,
    )
    got = [c.deviation_mm for c in a.comparison]
    want = [c.deviation_mm for c in b.comparison]
    assert [d is None for d in got] == [d is None for d in want]
    np.testing.assert_allclose(
        [d for d in got if d is not None], [d for d in want if d is not None], rtol=0, atol=1e-6
    )
    np.testing.assert_allclose(a.transform, b.transform, rtol=0, atol=1e-9)


@pytest.mark.parametrize("kind", ["in-process", "dask"])
def test_every_executor_measures_alike(kind, small, reference, request):
    stages, part, sets = small
    ex = (
        InProcessExecutor(Pipeline(stages, {PART: part}, line=LINE, station=STATION))
        if kind == "in-process"
        else request.getfixturevalue("cluster")
    )
    status = ex.status()
    assert status["kind"] == kind and status["slots"] == status["threads"] + (kind == "dask")
    futures = [ex.submit(fs) for fs in sets]  # all at once: the cluster takes them in parallel
    measured = [f.result(timeout=300) for f in futures]
    for m, want in zip(measured, reference, strict=True):
        assert isinstance(m, Measured) and m.seconds > 0 and m.round_trip_s >= m.seconds
        same_measurement(m.outcome.result, want)
        assert m.outcome.points is not None and len(m.outcome.points) > 1000
    where = {m.where for m in measured}
    if kind == "in-process":
        assert where == {IN_PROCESS}
    else:
        assert where <= set(status["cluster"]) and status["workers"] == 2
        assert {m.outcome.result.software_version for m in measured} == {
            reference[0].software_version
        }


def test_a_part_the_workers_lack_travels_with_its_first_job(small, reference, cluster):
    """The dispatcher learns a part after the cluster loaded the station: its spec and CAD
    go with the job (no file is read on the worker), and it is measured as in-process."""
    stages, part, sets = small
    other = "demo-panel-copy"
    copy = LoadedPart(part.spec.model_copy(update={"name": other}), part.model, part.tree_hash,
                      part.params)  # fmt: skip
    cluster.pipeline.parts[other] = copy
    try:
        fs = dataclasses.replace(sets[1], part=other)
        local = Pipeline(stages, {other: copy}, line=LINE, station=STATION).run(fs).result
        remote = cluster.submit(fs).result(timeout=300)
        assert remote.where != IN_PROCESS and remote.outcome.result.part == other
        same_measurement(remote.outcome.result, local)
        assert remote.outcome.result.status is not Status.error, remote.outcome.result.reason
    finally:
        del cluster.pipeline.parts[other]
    # A FrameSet the station refuses is answered by the dispatcher, without a round trip.
    refused = cluster.submit(dataclasses.replace(sets[1], part="no-such-part")).result()
    assert refused.where == IN_PROCESS and refused.outcome.result.status is Status.error
    assert "unknown part" in refused.outcome.result.reason


def test_a_worker_on_dask_answers_every_trigger_once(tmp_path, small, reference, cluster):
    """The worker dispatches to the cluster: one result per FrameSet, each journal entry
    removed once answered, the cluster's workers and their job times in its status and in
    its metrics."""
    from prometheus_client.parser import text_string_to_metric_families

    from service.metrics import Metrics, executor_collector

    _, _, sets = small
    q = JobQueue(8)
    journal = Journal(tmp_path / "journal")
    got = Collect()
    metrics = Metrics()
    w = Worker(cluster.pipeline, q, [got], line=LINE, station=STATION, missed_part=PART,
               journal=journal, executor=cluster, metrics=metrics)  # fmt: skip
    metrics.collector(executor_collector(w.executor_status, line=LINE, station=STATION))
    for fs in sets:
        payload = encode_frameset(fs)
        q.put(Job(payload, 0, journal.add(payload, fs.triggered_ns)))
    w.start()
    try:
        assert got.wait(len(sets), 300)
    finally:
        w.stop()
    by_seq = {r.seq: r for r in got.results}
    assert sorted(by_seq) == [0, 1, 2, 3] and len(got.results) == 4
    for want in reference:
        same_measurement(by_seq[want.seq], want)
    assert len(journal) == 0
    status = w.status("w", "ready")["executor"]
    assert status["kind"] == "dask" and status["in_flight"] == 0
    assert sum(j["jobs"] for j in status["jobs"].values()) == 4
    assert set(status["jobs"]) <= set(status["cluster"])
    families = {f.name: f for f in text_string_to_metric_families(metrics.render().decode())}
    own = {"line": LINE, "station": STATION}
    [info] = families["inspection_executor_info"].samples
    assert info.labels == {**own, "kind": "dask"} and info.value == 1
    threads = {s.labels["dask_worker"]: s.value
               for s in families["inspection_executor_cluster_threads"].samples}  # fmt: skip
    assert set(threads) == set(status["cluster"]) and all(n >= 1 for n in threads.values())
    jobs = {s.labels["worker"]: s.value
            for s in families["inspection_executor_job_seconds"].samples
            if s.name.endswith("_count")}  # fmt: skip
    assert sum(jobs.values()) == 4 and set(jobs) <= set(threads)


def test_every_measurement_is_logged_on_the_cluster(cluster):
    from service.dask_executor import EVENT_TOPIC

    events = [msg for _, msg in cluster.client.get_events(EVENT_TOPIC)]
    assert events, "the jobs above left no event"
    assert all(e["key"].startswith(f"measure-{e['id']}-") for e in events)
    assert {e["worker"] for e in events} <= set(cluster.status()["cluster"])


def test_stages_that_cannot_travel_and_unreachable_schedulers_are_refused(cluster, small):
    from service.dask_executor import DaskExecutor

    spec = load_part_spec(PARTS_DIR / f"{PART}.toml")
    model = PartModel.build(sheet_metal_panel(name=PART), spacing_mm=5.0, alignment=False)
    quick = Pipeline(QUICK, {PART: LoadedPart(spec, model, "t", measure_params(spec))},
                     line=LINE, station=STATION)  # fmt: skip
    with pytest.raises(ExecutorError, match="cannot be built on a Dask worker"):
        DaskExecutor(cluster.client, quick)
    nobody = parse_dask_address(f"tcp://127.0.0.1:{free_port()}")
    with pytest.raises(ExecutorError, match="cannot be reached"):
        DaskExecutor.connect(nobody, cluster.pipeline, timeout_s=2)


def test_a_part_lost_with_the_workers_that_held_it_is_sent_again(small, cluster):
    """A part the plugin did not carry lives on the Dask workers that hold it: SIGKILL them
    all, and the next jobs of that part are still measured, on the workers the nannies
    start again. The dispatcher sends the part anew, and a job sent before it knew of the
    loss (it failed on the lost part) once more. Last of the cluster's tests: it restarts
    its workers."""
    stages, part, sets = small
    other = "demo-panel-lost"
    copy = LoadedPart(part.spec.model_copy(update={"name": other}), part.model, part.tree_hash,
                      part.params)  # fmt: skip
    cluster.pipeline.parts[other] = copy
    try:
        first = cluster.submit(dataclasses.replace(sets[1], part=other)).result(timeout=300)
        assert first.where != IN_PROCESS and first.outcome.result.status is not Status.error
        _, data = cluster._scattered[other]
        holders = cluster.client.who_has([data])[data.key]
        pids = cluster.client.run(os.getpid)
        assert holders and set(holders) <= set(pids)
        for address in holders:
            os.kill(pids[address], signal.SIGKILL)
        # At once: the scheduler may not know yet, and the jobs go out with the lost part.
        again = [dataclasses.replace(fs, part=other) for fs in sets[2:4]]
        futures = [cluster.submit(fs) for fs in again]
        local = Pipeline(stages, {other: copy}, line=LINE, station=STATION)
        for fs, f in zip(again, futures, strict=True):
            m = f.result(timeout=300)
            assert m.where != IN_PROCESS and m.where not in holders
            same_measurement(m.outcome.result, local.run(fs).result)
        assert cluster._scattered[other][1].key != data.key, "the part was not sent anew"
    finally:
        del cluster.pipeline.parts[other]


@pytest.mark.parametrize("bad", ["local:0", "local:65", "tcp://host", "http://host:8786", "x"])
def test_a_bad_dask_address_on_the_command_line_exits_2(bad):
    p = cli("worker", "--zenoh-connect", "tcp/127.0.0.1:1", "--dask", bad)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 2, err
    assert "is not a Dask address" in err and "Traceback" not in err


# --------------------------------------------------------------------------- the worker's side


class Gated:
    """An executor whose measurements finish when the test says (by seq), in any order."""

    kind = "gated"

    def __init__(self, p: Pipeline, slots: int, lose: frozenset[int] = frozenset()) -> None:
        self.p = p
        self.n = slots
        self.lose = lose
        self.pending: dict[int, tuple[FrameSet, Future[Measured]]] = {}
        self.submitted = 0
        self._cond = threading.Condition()

    def slots(self) -> int:
        return self.n

    def submit(self, fs: FrameSet) -> Future[Measured]:
        f: Future[Measured] = Future()
        with self._cond:
            self.pending[fs.seq] = (fs, f)
            self.submitted += 1
            self._cond.notify_all()
        return f

    def wait_submitted(self, n: int) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: self.submitted >= n, 30)

    def finish(self, seq: int) -> None:
        with self._cond:
            fs, f = self.pending.pop(seq)
        if seq in self.lose:
            f.set_exception(RuntimeError("worker died 3 times"))
        else:
            f.set_result(Measured(self.p.run(fs), f"gate-{seq % 2}", 0.01, 0.02))

    def status(self) -> dict:
        return {"kind": self.kind, "workers": 2, "threads": self.n - 1, "slots": self.n}

    def close(self) -> None:
        pass


@pytest.fixture(scope="module")
def quick_sets(quick_part) -> list[FrameSet]:
    r = rig(QUICK, quick_part, seed=5)
    return [r.capture(seq, 1_800_000_000_000_000_000 + seq * 10**9) for seq in range(5)]


def test_the_worker_keeps_to_the_slots_and_answers_as_measurements_finish(
    tmp_path, quick_part, quick_sets
):
    p = pipeline(quick_part)
    gate = Gated(p, slots=2, lose=frozenset({3}))
    q = JobQueue(8)
    journal = Journal(tmp_path / "journal")
    got = Collect()
    w = Worker(p, q, [got], line=LINE, station=STATION, journal=journal, executor=gate)
    for fs in quick_sets:
        payload = encode_frameset(fs)
        q.put(Job(payload, 0, journal.add(payload, fs.triggered_ns)))
    w.start()
    try:
        assert gate.wait_submitted(2)
        # Two in flight: the other three wait in the worker's queue, where an overflow
        # is answered.
        assert q.depth() == 3 and w.executor_status()["in_flight"] == 2
        gate.finish(1)  # the later trigger finishes first, and is answered first
        assert got.wait(1) and gate.wait_submitted(3)
        assert q.depth() == 2 and len(journal) == 4
        gate.finish(0)
        assert gate.wait_submitted(4)
        gate.finish(2)
        assert gate.wait_submitted(5)
        gate.finish(3)
        gate.finish(4)
        assert got.wait(5)
    finally:
        w.stop()
    assert [r.seq for r in got.results] == [1, 0, 2, 3, 4]
    lost = got.results[3]
    assert lost.status is Status.error and "measurement was lost" in lost.reason
    assert lost.serial == quick_sets[3].serial and w.stats.lost == 1
    assert len(journal) == 0
    assert w.executor_status()["jobs"] == {
        "gate-0": {"jobs": 3, "mean_s": 0.01, "last_s": 0.01},
        "gate-1": {"jobs": 1, "mean_s": 0.01, "last_s": 0.01},
    }


def test_a_trigger_delivered_again_while_measured_is_answered_once(quick_part, quick_sets):
    p = pipeline(quick_part)
    gate = Gated(p, slots=4)
    got = Collect()
    w = Worker(p, JobQueue(4), [got], line=LINE, station=STATION, executor=gate)
    w.handle(job(quick_sets[0]))
    w.handle(job(quick_sets[0]))  # still being measured: not measured again, nor refused
    assert gate.submitted == 1 and w.stats.duplicates == 1 and got.results == []
    gate.finish(0)
    assert w.drain(30)
    assert [r.seq for r in got.results] == [0] and got.results[0].status is not Status.error


def test_an_executor_that_refuses_a_job_still_gives_it_a_result(quick_part, quick_sets):
    class Refusing(InProcessExecutor):
        def submit(self, fs):
            raise ConnectionError("scheduler gone")

    p = pipeline(quick_part)
    got = Collect()
    w = Worker(p, JobQueue(4), [got], line=LINE, station=STATION, executor=Refusing(p))
    w.handle(job(quick_sets[0]))
    w.handle(job(quick_sets[1]))
    assert [(r.seq, r.status) for r in got.results] == [(0, Status.error), (1, Status.error)]
    assert "scheduler gone" in got.results[0].reason


def test_the_in_process_executor_answers_before_handle_returns(quick_part, quick_sets):
    got = Collect()
    w = Worker(pipeline(quick_part), JobQueue(4), [got], line=LINE, station=STATION)
    w.handle(job(quick_sets[0]))
    assert [r.seq for r in got.results] == [0]
    assert w.executor_status()["kind"] == IN_PROCESS and w.executor_status()["in_flight"] == 0


def test_the_metrics_show_who_measured_and_what_is_in_flight(quick_part, quick_sets):
    from service.metrics import Metrics, executor_collector

    p = pipeline(quick_part)
    gate = Gated(p, slots=3)
    metrics = Metrics()
    w = Worker(p, JobQueue(4), [], line=LINE, station=STATION, executor=gate, metrics=metrics)
    metrics.collector(executor_collector(w.executor_status, line=LINE, station=STATION))
    for fs in quick_sets[:3]:
        w.handle(job(fs))
    gate.finish(0)
    gate.finish(1)
    assert w.drain(0.0) is False  # seq 2 is still being measured
    text = metrics.render().decode()
    own = f'line="{LINE}",station="{STATION}"'
    assert f"inspection_executor_in_flight{{{own}}} 1.0" in text
    assert f"inspection_executor_slots{{{own}}} 3.0" in text
    assert f"inspection_executor_workers{{{own}}} 2.0" in text
    assert f'inspection_executor_job_seconds_count{{{own},worker="gate-0"}} 1.0' in text
    assert f'inspection_executor_job_seconds_count{{{own},worker="gate-1"}} 1.0' in text
    assert f"inspection_executor_dispatch_seconds_count{{{own}}} 2.0" in text
    gate.finish(2)
    assert w.drain(30)


# --------------------------------------------------------------------------- sending on Dask


class Scattered:
    """What a fake client's scatter hands back: a key and a status, as a Dask future."""

    def __init__(self, key: str) -> None:
        self.key, self.status = key, "finished"


class FakeClient:
    """The calls a DaskExecutor makes of distributed's Client; the test settles each job."""

    def __init__(self) -> None:
        self.scheduler = type("Scheduler", (), {"address": "tcp://fake:8786"})()
        self.scattered_on: list[str] = []  # the thread each scatter ran on
        self.jobs: list[tuple[FrameSet, object, Future]] = []
        self._cond = threading.Condition()

    def register_plugin(self, plugin, name) -> None:
        pass

    def scheduler_info(self, n_workers=-1) -> dict:
        return {"workers": {"tcp://w1": {"nthreads": 1}}}

    def scatter(self, data: dict) -> dict:
        self.scattered_on.append(threading.current_thread().name)
        return {name: Scattered(name) for name in data}

    def submit(self, fn, plugin, fs, data, *, key, pure, retries) -> Future:
        f: Future = Future()
        with self._cond:
            self.jobs.append((fs, data, f))
            self._cond.notify_all()
        return f

    def wait_jobs(self, n: int) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: len(self.jobs) >= n, 30)

    def close(self) -> None:
        pass


@pytest.fixture
def fake_dask(quick_part):
    """A DaskExecutor on a fake client, with a part the plugin does not carry."""
    from service.dask_executor import DaskExecutor

    stages = dataclasses.replace(QUICK, remake=lambda threads: QUICK)
    p = Pipeline(stages, {PART: quick_part}, line=LINE, station=STATION)
    client = FakeClient()
    ex = DaskExecutor(client, p)  # type: ignore[arg-type]
    p.parts["other"] = dataclasses.replace(
        quick_part, spec=quick_part.spec.model_copy(update={"name": "other"}), revision=1
    )
    try:
        yield ex, client, p
    finally:
        ex.close()


def test_a_part_lost_by_the_cluster_is_scattered_once_off_the_callback_thread(
    fake_dask, quick_sets
):
    """Three jobs of a travelling part in flight when its workers die: each is cancelled,
    the part is scattered once more, on the executor's own thread (never on the thread
    that submits nor on the one distributed runs the callbacks on), and each job is sent
    again with it, once."""
    from distributed.client import FutureCancelledError

    ex, client, p = fake_dask
    sets = [dataclasses.replace(fs, part="other") for fs in quick_sets[:3]]
    futures = [ex.submit(fs) for fs in sets]
    assert client.wait_jobs(3)
    first = client.jobs[0][1]
    assert all(data is first for _, data, _ in client.jobs)
    first.status = "lost"
    for _, _, f in client.jobs[:3]:
        f.set_exception(FutureCancelledError("k", "lost dependencies"))
    assert client.wait_jobs(6)
    again = client.jobs[3:]
    assert [fs.seq for fs, _, _ in again] == [0, 1, 2]
    assert len({id(data) for _, data, _ in again}) == 1 and again[0][1] is not first
    me = threading.current_thread().name
    assert len(client.scattered_on) == 2 and me not in client.scattered_on
    assert all(name.startswith("dask-send") for name in client.scattered_on)
    for fs, _, f in again:
        f.set_result(Remote(p.run(fs), "tcp://w1", 0.01))
    assert [f.result(5).outcome.result.seq for f in futures] == [0, 1, 2]


def test_a_job_that_killed_its_workers_is_not_sent_again(fake_dask, quick_sets):
    """KilledWorker: the job may be what kills them, and it has had its tries."""
    from distributed.scheduler import KilledWorker

    ex, client, _ = fake_dask
    future = ex.submit(dataclasses.replace(quick_sets[0], part="other"))
    assert client.wait_jobs(1)
    client.jobs[0][1].status = "lost"  # it died with the worker that held the part
    client.jobs[0][2].set_exception(KilledWorker("measure-x", "tcp://w1", 3))
    with pytest.raises(KilledWorker):
        future.result(5)
    assert len(client.jobs) == 1 and len(client.scattered_on) == 1


def test_a_part_the_station_dropped_is_let_go_on_the_cluster(fake_dask, quick_sets):
    ex, client, p = fake_dask
    ex.submit(dataclasses.replace(quick_sets[0], part="other"))
    assert client.wait_jobs(1) and "other" in ex._scattered
    ex._release_gone_parts()
    assert "other" in ex._scattered
    del p.parts["other"]
    ex._release_gone_parts()
    assert "other" not in ex._scattered


def test_a_dask_worker_keeps_the_newest_revisions_of_a_travelling_part(tmp_path, quick_part):
    """Jobs of revisions 1 and 2 interleaved (those of 1 still in flight when 2 came) load
    each once; revision 3 then replaces the oldest, and a straggler of 1 is loaded for its
    own job without displacing the newer ones."""
    from service.dask_executor import StationPlugin
    from service.parts import PartBundle

    loads: list[int] = []

    class Counted(PartBundle):
        def load(self, trees_dir):
            loads.append(self.revision)
            return dataclasses.replace(quick_part, revision=self.revision)

    plugin = StationPlugin(None, "c", LINE, STATION, (), None, None)
    plugin._lock, plugin._bundled, plugin._trees = threading.Lock(), {}, tmp_path
    revisions = {r: Counted(quick_part.spec, quick_part.cad, f"key{r}", None, r) for r in (1, 2, 3)}
    for r in (1, 2, 1, 2, 1):
        assert plugin._part_of(revisions[r]).revision == r
    assert loads == [1, 2]
    for r in (3, 1, 2, 3):
        assert plugin._part_of(revisions[r]).revision == r
    assert loads == [1, 2, 3, 1]
