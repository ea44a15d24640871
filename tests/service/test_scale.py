"""A station measured on a Dask cluster, as real processes on loopback, through kills.

``inspection router``, a ``dask scheduler`` and three ``dask worker``
processes (the distributed package's own commands, one thread each), the
station's worker dispatching to them (``inspection worker --dask``), the API
and the ingest: the topology of docs/line.md, "Beyond one machine", on one
host. One Dask worker is killed with SIGKILL in the middle of a job (seen so
on the scheduler, by a client asking what runs where), the dispatcher once.
Every seq the ingest fired has exactly one result in the store and on zenoh,
and the killed worker's job was measured by another.

Small frames (a quarter of the line's pixels, one matching pass): the test is
about what survives a kill, not about accuracy.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from linekit import ROOT, STATION, client, free_port
from test_faults import KEYS, Frames, Line, Stream
from test_line import ENV, get_json

from service import bus
from service.dask_executor import EVENT_TOPIC
from service.history import fetch_results

PERIOD_S = 0.7
SHIFT = 34
"""Triggers fired at least."""

DASK_WORKERS = ("w0", "w1", "w2")


@pytest.fixture
def storage(request) -> str:
    """``[storage]`` lines the dispatcher and the API share: a database of the session's
    PostgreSQL server, the plant-wide store of docs/line.md; where no such server can
    run here, the embedded SQLite store of the data directory (the checks read the
    store through the API, whatever its backend)."""
    try:
        server = request.getfixturevalue("pg_server")
    except pytest.skip.Exception:
        return ""
    return f'url = "{server.new_database()}"\n'


class Cluster:
    """A Dask scheduler and its workers, each a process of the distributed package's own
    command, and a client of the test's own that watches the scheduler."""

    def __init__(self, tmp_path: Path) -> None:
        self.address = f"tcp://127.0.0.1:{free_port()}"
        self.scratch = tmp_path / "dask"
        self.procs: dict[str, subprocess.Popen] = {}
        self.observer = None
        self.names: dict[str, str] = {}
        """Worker address -> name."""

    def _dask(self, name: str, *args: str) -> None:
        dask = Path(sys.executable).with_name("dask")
        env = {**ENV, "PYTHONPATH": str(ROOT)}  # the workers unpickle the station's code
        self.procs[name] = subprocess.Popen(
            [str(dask), *args], env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE, text=True,
        )  # fmt: skip

    def start(self) -> None:
        port = self.address.rsplit(":", 1)[1]
        self._dask("scheduler", "scheduler", "--host", "127.0.0.1", "--port", port,
                   "--no-dashboard")  # fmt: skip
        for name in DASK_WORKERS:
            self._dask(name, "worker", self.address, "--nthreads", "1", "--no-nanny",
                       "--name", name, "--host", "127.0.0.1", "--no-dashboard",
                       "--local-directory", str(self.scratch))  # fmt: skip
        from distributed import Client

        self.observer = Client(self.address, timeout=60, set_as_default=False)
        self.observer.wait_for_workers(len(DASK_WORKERS), timeout=120)
        workers = self.observer.scheduler_info()["workers"]
        self.names = {address: w["name"] for address, w in workers.items()}

    def kill_mid_job(self, timeout_s: float = 120) -> tuple[str, set[str]]:
        """SIGKILL a Dask worker while it runs a measurement; its address and the jobs the
        scheduler had given it (the one it was running, and any waiting there)."""
        deadline = time.monotonic() + timeout_s
        pause = threading.Event()
        while time.monotonic() < deadline:
            processing = self.observer.processing()
            for address, keys in processing.items():
                jobs = {str(k) for k in keys if str(k).startswith("measure-")}
                running = self.observer.call_stack(keys=list(jobs)) if jobs else {}
                if running.get(address):
                    self.procs[self.names[address]].send_signal(signal.SIGKILL)
                    self.procs.pop(self.names[address]).wait(30)
                    return address, jobs
            pause.wait(0.02)
        pytest.fail("no Dask worker was seen measuring")

    def events(self) -> list[dict]:
        return [msg for _, msg in self.observer.get_events(EVENT_TOPIC)]

    def close(self) -> None:
        if self.observer is not None:
            self.observer.close()
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
                p.wait(30)


@pytest.fixture
def cluster(tmp_path) -> Iterator[Cluster]:
    c = Cluster(tmp_path)
    try:
        c.start()
        yield c
    finally:
        c.close()


class Results(Stream):
    """Every result seen on the bus, and a wait for given ones."""

    def wait_ids(self, ids: set[str], timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: ids <= {r.id for r in self.got}, timeout_s)


class Beats:
    """The dispatcher's last status heartbeat."""

    def __init__(self) -> None:
        self.last = ""

    def __call__(self, sample) -> None:
        self.last = sample.payload.to_bytes().decode()


def why(line: Line, beats: Beats) -> str:
    """What the dispatcher says, for a failed wait: its last status and, stopped, its log."""
    p = line.procs.get("worker")
    said = "(not running)"
    if p is not None:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            p.wait(60)
        said = p.stderr.read()[-4000:]
    return f"last status: {beats.last}\nlog: {said}"


def stored_results(http_port: int) -> list[dict]:
    """Every result of the station in the store, read page by page through the API."""
    out, cursor = [], None
    while True:
        url = f"http://127.0.0.1:{http_port}/v1/inspections?limit=1000"
        code, page = get_json(url + (f"&cursor={cursor}" if cursor else ""))
        assert code == 200, page
        out += [r for r in page["items"] if r["station"] == STATION]
        cursor = page["next"]
        if not cursor:
            return out


def test_a_station_on_dask_answers_every_trigger_once_through_kills(
    tmp_path, trees, cluster, storage
):
    line = Line(tmp_path, trees, period_s=PERIOD_S)
    if storage:
        config = Path(line.common[1])
        config.write_text(config.read_text().replace("[storage]\n", f"[storage]\n{storage}"))
        assert storage in config.read_text(), "the line's config has no [storage] table"
    stream, frames = Results(), Frames()
    dispatcher = ("--dask", cluster.address)
    try:
        line.start("router")
        with bus.open_session(client(line.port)) as session:
            sub = bus.RingSubscriber(session, KEYS.results(), stream, capacity=256)
            seen = bus.RingSubscriber(session, KEYS.frames(STATION), frames, capacity=64)
            beats = Beats()
            heard = bus.RingSubscriber(session, KEYS.status(STATION), beats, capacity=8)
            try:
                line.start("worker", *dispatcher)
                line.start("api")
                line.wait_ready(session)
                line.wait_api()
                line.start("ingest")

                def measured(n: int) -> None:
                    target = stream.last_seq() + n
                    assert stream.wait_seq(target, 120), why(line, beats)

                measured(4)
                killed, jobs = cluster.kill_mid_job()
                measured(6)
                line.kill("worker")  # the dispatcher, with jobs in flight and journaled
                assert frames.wait_seq(frames.seq + 2, 60)  # two triggers while it is down
                line.start("worker", *dispatcher)
                line.wait_ready(session)
                # Triggers it sees, too: what came while it was down is answered when the
                # next FrameSet shows the gap (on a loaded machine the shift may have passed
                # SHIFT meanwhile).
                assert frames.wait_seq(max(SHIFT - 1, frames.seq + 2), 300), line._stderr("ingest")
                ingest = line.procs["ingest"]
                line.stop("ingest")
                last = line.fired() - 1
                if not stream.wait_seq(last, 120):
                    seen_seqs = {r.seq for r in stream.got}
                    unanswered = sorted(set(range(last + 1)) - seen_seqs)
                    pytest.fail(
                        f"seqs fired but not answered: {unanswered} (last fired {last}, "
                        f"last FrameSet seen {frames.seq})\n{why(line, beats)}\n"
                        f"ingest log: {ingest.stderr.read()[-3000:]}"
                    )
                fetched = fetch_results(session, KEYS, STATION)
                # Results finish out of seq order: some may still be in flight. Stopped,
                # the dispatcher answers them before it exits.
                line.stop("worker")
                stored = stored_results(line.http_port)
                late = {r["id"] for r in stored} - {r.id for r in fetched}
                assert stream.wait_ids(late, 60), late - {r.id for r in stream.got}
            finally:
                sub.close()
                seen.close()
                heard.close()
        events = cluster.events()
        for name in ("api", "router"):
            line.stop(name)
    finally:
        line.close()

    ids = [r["id"] for r in stored]
    assert len(ids) == len(set(ids))
    assert sorted(r["seq"] for r in stored) == list(range(last + 1)), (
        "every seq fired has exactly one result"
    )
    assert last + 1 >= SHIFT
    streamed = [r.id for r in stream.got]
    assert len(streamed) == len(set(streamed)), "a result was published twice"
    assert set(streamed) <= set(ids)
    assert set(streamed) | {r.id for r in fetched} == set(ids)
    # The killed worker's jobs: measured by another worker, stored once. (Its running job
    # could finish in the instant before the kill; a job it held then is the one cut short.)
    status = {r["id"]: (r["status"], r["reason"] or "") for r in stored}
    by_id: dict[str, list[str]] = {}
    for e in events:
        by_id.setdefault(e["id"], []).append(e["worker"])
    cut = {k.removeprefix("measure-").rsplit("-", 1)[0] for k in jobs}
    cut = {i for i in cut if killed not in by_id.get(i, [])}
    assert cut, f"every job of {killed} finished before the kill: {jobs}"
    measured = {r["id"] for r in stored if "reconstruct" in r["timings_ms"]}
    for id_ in cut:
        assert id_ in measured, status[id_]
        assert by_id[id_] and killed not in by_id[id_], by_id.get(id_)
    # Nothing refused or lost: every error is a measurement's (a fit that failed on these
    # small frames), every missed a trigger that came while the dispatcher was down, or
    # while its queue was full.
    unmeasured = [s for i, s in status.items() if i not in measured and s[0] != "missed"]
    assert not unmeasured, unmeasured
    assert {s for s, _ in status.values()} - {"missed", "error"}, status
