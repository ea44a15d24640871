"""A station measured on a Dask cluster, as real processes on loopback, through kills.

``inspection router``, a ``dask scheduler`` and three ``dask worker``
processes (the distributed package's own commands, one thread each), the
station's worker dispatching to them (``inspection worker --dask``), the API
and the ingest: the topology of docs/line.md, "Beyond one machine", on one
host, with a data directory per process and the store on the session's
PostgreSQL server, so that the API, the dispatcher and the ingest share
nothing but the store and the bus. A part is created over the API once the
line runs, and the ingest sends it among the station's own: its spec and CAD
reach the dispatcher through the store and the Dask workers through Dask.

One Dask worker is killed with SIGKILL in the middle of a job (seen so on the
scheduler, by a client asking what runs where), the dispatcher once. The
ingest fires until the cluster has measured a shift of :data:`SHIFT` parts,
however slow the machine: every seq it fired has exactly one result in the
store and on zenoh, the killed worker's job was measured by another, and the
part created over the API was measured on the Dask workers.

Small frames (a quarter of the line's pixels, one matching pass): the test is
about what survives a kill, not about accuracy.
"""

from __future__ import annotations

import json
import logging
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
import uuid
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest
from linekit import ROOT, STATION, client, demo, free_port
from test_faults import KEYS, Frames, Line, Stream
from test_line import ENV, get_json

from inspection.panel import PanelSpec, sheet_metal_panel
from service import bus
from service.dask_executor import EVENT_TOPIC
from service.history import fetch_results

log = logging.getLogger(__name__)

PERIOD_S = 1.0
"""Near what three single-threaded Dask workers on two busy cores measure: fewer triggers
answered missed for a full queue, the same shift."""
SHIFT = 30
"""Parts the cluster measures at least before the ingest stops."""

DASK_WORKERS = ("w0", "w1", "w2")

NEW = "bracket"
"""The part created over the API while the line runs."""


@pytest.fixture
def storage(request, tmp_path) -> str:
    """``[storage]`` lines of every process: a database of the session's PostgreSQL server,
    the plant-wide store of docs/line.md. Where no such server can run here, an SQLite file
    outside every data directory, which the processes then share (said in a warning)."""
    try:
        server = request.getfixturevalue("pg_server")
    except pytest.skip.Exception as exc:
        message = (f"test_scale runs on SQLite, not PostgreSQL ({exc}): the processes share "
                   "its file, not the store of a database server")  # fmt: skip
        warnings.warn(message, stacklevel=1)
        log.warning("%s", message)
        return f'database = "{tmp_path / "shared.sqlite"}"\n'
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
    """Every result seen on the bus, and waits for given ones."""

    def wait_ids(self, ids: set[str], timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: ids <= {r.id for r in self.got}, timeout_s)

    def wait_measured(self, n: int, part: str, timeout_s: float) -> bool:
        """Wait for ``n`` measured results (a measurement ran, whatever its verdict), some of
        them of ``part``."""

        def enough() -> bool:
            done = [r for r in self.got if "reconstruct" in r.timings_ms]
            return len(done) >= n and sum(r.part == part for r in done) >= 3

        with self._cond:
            return self._cond.wait_for(enough, timeout_s)


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


class ScaleLine(Line):
    """The line with a data directory of its own for the API, the dispatcher and the ingest,
    and a tree cache of its own for the API: what they share is the store and the bus (the
    dispatcher and its Dask workers, on one host here, share its tree cache)."""

    def __init__(self, tmp_path: Path, trees: Path, storage: str) -> None:
        super().__init__(tmp_path, trees, period_s=PERIOD_S)
        config = Path(self.common[1])
        own = 'database = "results.sqlite"\n'
        text = config.read_text().replace(own, storage if "database" in storage else own + storage)
        assert storage in text, "the line's config has no [storage] database"
        self.dirs = {name: tmp_path / name for name in ("api", "worker", "ingest")}
        self.data = self.dirs["ingest"]  # where the ingest numbers its triggers
        api_trees = self.dirs["api"] / "trees"
        shutil.copytree(trees, api_trees)  # a cache: the demo panel's tree is not built again
        simulated = f'[simulator]\nparts = ["demo-panel", "{NEW}"]\n'
        self.configs = {
            "worker": text,
            "api": text.replace(f'trees_dir = "{trees}"', f'trees_dir = "{api_trees}"'),
            "ingest": text.replace("[simulator]", simulated, 1),
        }
        assert len(set(self.configs.values())) == 3
        for name, body in self.configs.items():
            (tmp_path / f"{name}.toml").write_text(body)

    def start(self, name: str, *extra: str) -> None:
        if name == "router":
            super().start(name)
            return
        own = ("--config", str(self.dirs[name].parent / f"{name}.toml"),
               "--data-dir", str(self.dirs[name]))  # fmt: skip
        super().start(name, *own, *extra)  # the last --config and --data-dir win


def create_part(http_port: int, tmp_path: Path) -> dict:
    """Create part :data:`NEW` over the API (a panel of other proportions than the demo's,
    its tree coarser so that it builds fast); its public view."""
    stl = tmp_path / "bracket.stl"
    sheet_metal_panel(PanelSpec().scaled(300.0, 200.0)).to_trimesh().export(stl)
    spec = {"name": NEW, "version": "1", "tree": {"spacing_mm": 2.0}}
    boundary = uuid.uuid4().hex
    body = (
        (
            f'--{boundary}\r\nContent-Disposition: form-data; name="spec"\r\n'
            f"Content-Type: application/json\r\n\r\n{json.dumps(spec)}\r\n"
            f'--{boundary}\r\nContent-Disposition: form-data; name="cad"; filename="b.stl"\r\n'
            "Content-Type: model/stl\r\n\r\n"
        ).encode()
        + stl.read_bytes()
        + f"\r\n--{boundary}--\r\n".encode()
    )
    req = urllib.request.Request(
        f"http://127.0.0.1:{http_port}/v1/parts", data=body, method="POST",
        headers={"Content-Type": f"multipart/form-data; boundary={boundary}"},
    )  # fmt: skip
    with urllib.request.urlopen(req, timeout=60) as resp:
        assert resp.status == 202
        return json.loads(resp.read())


def wait_part_ready(http_port: int, timeout_s: float = 300) -> dict:
    deadline = time.monotonic() + timeout_s
    pause = threading.Event()
    while time.monotonic() < deadline:
        code, part = get_json(f"http://127.0.0.1:{http_port}/v1/parts/{NEW}")
        assert code == 200 and part["state"] != "failed", part
        if part["state"] == "ready":
            return part
        pause.wait(0.5)
    pytest.fail(f"the API did not build part {NEW}")


def test_a_station_on_dask_answers_every_trigger_once_through_kills(
    tmp_path, trees, cluster, storage
):
    demo(trees)  # the demo panel's tree in the cache: no process of the line builds it
    line = ScaleLine(tmp_path, trees, storage)
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
                created = create_part(line.http_port, tmp_path)
                assert created["state"] in ("building", "ready"), created
                line.start("ingest")  # it reads the new part from the store

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
                # The shift goes on until the cluster has measured SHIFT parts, and a few of
                # the part created over the API; what came while the dispatcher was down is
                # answered when the next FrameSet shows the gap.
                assert stream.wait_measured(SHIFT, NEW, 600), why(line, beats)
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
                api_part = wait_part_ready(line.http_port)
            finally:
                sub.close()
                seen.close()
                heard.close()
        events = cluster.events()
        for name in ("api", "router"):
            line.stop(name)
    finally:
        line.close()

    counts = {s: sum(r["status"] == s for r in stored) for s in {r["status"] for r in stored}}
    print(f"fired {last + 1}, measured {sum('reconstruct' in r['timings_ms'] for r in stored)} "
          f"({sum(r['part'] == NEW and 'reconstruct' in r['timings_ms'] for r in stored)} of "
          f"{NEW}), by status {counts}")  # fmt: skip
    ids = [r["id"] for r in stored]
    assert len(ids) == len(set(ids))
    assert sorted(r["seq"] for r in stored) == list(range(last + 1)), (
        "every seq fired has exactly one result"
    )
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
    assert len(measured) >= SHIFT, f"a shift of {len(measured)} parts measured"
    for id_ in cut:
        assert id_ in measured, status[id_]
        assert by_id[id_] and killed not in by_id[id_], by_id.get(id_)
    # Nothing refused or lost: every error is a measurement's (a fit that failed on these
    # small frames), every missed a trigger that came while the dispatcher was down, or
    # while its queue was full (a part's first FrameSets waiting for it among them).
    unmeasured = [s for i, s in status.items() if i not in measured and s[0] != "missed"]
    assert not unmeasured, unmeasured
    assert {s for s, _ in status.values()} - {"missed", "error"}, status
    # The part created over the API: measured on the Dask workers with the API's CAD, which
    # reached the dispatcher through the store (its own copy, in its own data directory).
    new = [r for r in stored if r["part"] == NEW and r["id"] in measured]
    assert new, "no FrameSet of the part created over the API was measured"
    assert {r["cad_hash"] for r in new} == {api_part["cad_hash"]}
    assert all(by_id.get(r["id"]) for r in new), "measured elsewhere than on the cluster"
    copy = line.dirs["worker"] / "state" / "line1" / STATION / "parts" / NEW / "cad.stl"
    assert copy.read_bytes() == (tmp_path / "bracket.stl").read_bytes()
    assert (
        not (line.dirs["worker"] / "parts").exists()
        and not (line.dirs["ingest"] / "parts").exists()
    )
