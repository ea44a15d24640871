"""Measuring on a Dask cluster: the station's worker dispatches, Dask's workers measure.

The station's worker (the dispatcher) keeps every trigger's accounting; a
:class:`DaskExecutor` only sends it FrameSets to measure and hands back what
comes back. On the cluster:

- :class:`StationPlugin`, a Dask worker plugin registered by the
  dispatcher, makes each Dask worker ready before it takes a job: it builds
  the station's measuring stages from their recipe
  (:attr:`service.pipeline.Stages.remake`: the calibrated rig as text, the
  matching mode), loads the station's parts from what the plugin carries
  (each part's spec and CAD model, keyed by a hash of both: nothing is read
  from the dispatcher's disk), takes their trees from the tree cache when
  the dispatcher's is reachable on that host, else builds them once into a
  cache beside the Dask worker's own folder, and measures one FrameSet to
  compile the kernels. A Dask worker that joins later gets the plugin from
  the scheduler and does the same before it takes a job.
- :func:`measure_on_worker` is the task: the station's one
  :meth:`~service.pipeline.Pipeline.run` on the FrameSet it is given. A part
  the plugin did not carry (one created over the API, which the dispatcher
  took from the store) travels with the job, scattered once to the cluster
  under its hash; each Dask worker fetches it with its first job of that
  part and keeps it, and measures each job with the very revision the job
  names (the newest revisions of each name are kept: :data:`KEPT_REVISIONS`).
  Scattered data lives on the workers that hold it: when they die it is
  lost, and the dispatcher, told so by a job cancelled for its lost
  dependency (or by its reference before it sends one), scatters the part
  again and sends that job once more. Scattering blocks on the cluster: it
  happens on a thread of the executor's own, never on the worker's
  accounting thread nor on the thread distributed runs every future's
  callbacks on; the jobs in flight with the lost part share one scatter.
- A Dask worker that dies mid-job has its jobs run again elsewhere by the
  scheduler; a job whose worker died ``distributed.scheduler.allowed-failures``
  times (KilledWorker: it may be what kills them), or that raised
  ``RETRIES + 1`` times, comes back failed, and the dispatcher answers that
  trigger ``error``: one result either way, never sent again.
- Every measurement is logged on the scheduler's event topic
  :data:`EVENT_TOPIC` (its task key, result id, seq, worker and time), so who
  measured what can be read from the cluster itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import CancelledError, Future, InvalidStateError, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from distributed import Client, LocalCluster, WorkerPlugin, get_worker

from .config import DaskAddress, canonical_hash
from .executor import IN_PROCESS, ExecutorError, Measured
from .models import make_result_id
from .parts import LoadedPart, PartBundle
from .pipeline import Outcome, Pipeline, Stages
from .protocol import FrameSet

log = logging.getLogger(__name__)

EVENT_TOPIC = "inspection-measured"
"""The scheduler's event topic every measurement is logged on."""

RETRIES = 2
"""Times Dask runs a job again after it raised (a worker that could not load the station)."""

CLUSTER_VIEW_S = 1.0
"""How often the dispatcher asks the scheduler about the cluster (workers, threads), s."""

KEPT_REVISIONS = 2
"""Revisions of one part that travelled with jobs a Dask worker keeps loaded: the newest,
and the one before it, whose jobs may still come after the newest's first."""


class StationNotLoaded(RuntimeError):
    """A job reached a Dask worker that has not loaded its station."""


# --------------------------------------------------------------------------- on a Dask worker


@dataclass(frozen=True, eq=False)
class Remote:
    """What a job sends back: the outcome, who measured it and how long it took (s)."""

    outcome: Outcome
    where: str
    seconds: float


class StationPlugin(WorkerPlugin):
    """The station on a Dask worker: its stages and parts, loaded once and warmed up.

    Parameters
    ----------
    remake : callable(threads) -> Stages
        The station's :attr:`Stages.remake`.
    calibration_id : str
        What the remade stages must measure with (the dispatcher's).
    line, station : str
    parts : tuple of PartBundle
        The station's parts.
    warm_up : FrameSet or None
        Measured once at set-up, so the first job does not pay for compiling.
    trees_dir : str or None
        The dispatcher's tree cache; used where this host can write to it.
    """

    idempotent = True
    """Registering the same station again (a restarted dispatcher) keeps the loaded one."""

    def __init__(
        self,
        remake: Any,
        calibration_id: str,
        line: str,
        station: str,
        parts: tuple[PartBundle, ...],
        warm_up: FrameSet | None,
        trees_dir: str | None,
    ) -> None:
        self.remake = remake
        self.calibration_id = calibration_id
        self.line = line
        self.station = station
        self.parts = parts
        self.warm_up = warm_up
        self.trees_dir = trees_dir
        self.name = (
            "inspection-station-"
            + canonical_hash(
                {
                    "line": line,
                    "station": station,
                    "calibration_id": calibration_id,
                    "remake": repr(remake),
                    "parts": [b.key for b in parts],
                }
            )[:16]
        )
        self.pipeline: Pipeline | None = None
        self.address = ""

    async def setup(self, worker: Any) -> None:
        # Off the worker's event loop: loading takes seconds and the worker must
        # keep talking to the scheduler meanwhile.
        await asyncio.to_thread(self.load, worker.address, Path(worker.local_directory))

    def load(self, address: str, local_directory: Path) -> None:
        """Build the stages, load the parts, measure the warm-up FrameSet."""
        t0 = time.perf_counter()
        # One core per Dask thread: the cluster's parallelism is its threads.
        stages: Stages = self.remake(1)
        if stages.calibration_id != self.calibration_id:
            raise StationNotLoaded(
                f"the remade stages measure with calibration {stages.calibration_id!r}, "
                f"the station with {self.calibration_id!r}"
            )
        self._trees = self._tree_cache(local_directory)
        self._lock = threading.Lock()
        # Parts that travelled with jobs: name -> bundle key -> (revision, loaded part).
        self._bundled: dict[str, dict[str, tuple[int, LoadedPart]]] = {}
        parts = {b.spec.name: b.load(self._trees) for b in self.parts}
        pipeline = Pipeline(stages, parts, line=self.line, station=self.station)
        if self.warm_up is not None:
            r = pipeline.run(self.warm_up).result
            log.info("station %s warm-up: %s in %.1f s", self.station, r.status.value,
                     r.timings_ms.get("total", 0.0) / 1e3)  # fmt: skip
        self.address = address
        self.pipeline = pipeline
        log.info("station %s/%s ready on %s in %.1f s (parts %s, trees in %s)",
                 self.line, self.station, address, time.perf_counter() - t0, sorted(parts),
                 self._trees)  # fmt: skip

    def _tree_cache(self, local_directory: Path) -> Path:
        if self.trees_dir is not None:
            shared = Path(self.trees_dir)
            if shared.is_dir() and os.access(shared, os.W_OK | os.X_OK):
                return shared
        # Beside the worker's own scratch folder, which goes with the worker: a
        # worker started again on this host finds the trees built before.
        own = local_directory.parent / "inspection-trees"
        own.mkdir(parents=True, exist_ok=True)
        return own

    def measure(self, fs: FrameSet, bundle: PartBundle | None) -> tuple[Outcome, float]:
        """The station's pipeline on ``fs``; ``bundle``: its part, when the plugin lacked it
        (the job is measured with that revision, whatever other jobs bring)."""
        if self.pipeline is None:
            raise StationNotLoaded(f"station {self.station} is not loaded on {self.address}")
        pipeline = self.pipeline
        if bundle is not None:
            part = self._part_of(bundle)
            pipeline = Pipeline(
                pipeline.stages, {**pipeline.parts, bundle.spec.name: part},
                line=self.line, station=self.station, version=pipeline.version,
            )  # fmt: skip
        t0 = time.perf_counter()
        outcome = pipeline.run(fs)
        return outcome, time.perf_counter() - t0

    def _part_of(self, bundle: PartBundle) -> LoadedPart:
        """The loaded part of ``bundle``: one held, else loaded now (its tree from the cache,
        or built once). The :data:`KEPT_REVISIONS` newest revisions of each name are held:
        a job of the revision before, still in flight when the newest came, is measured
        without loading either again."""
        name = bundle.spec.name
        with self._lock:
            held = self._bundled.setdefault(name, {})
            if bundle.key in held:
                return held[bundle.key][1]
            log.info("part %s (revision %s) arrived with a job: loading it", name,
                     bundle.revision)  # fmt: skip
            part = bundle.load(self._trees)
            held[bundle.key] = (bundle.revision or 0, part)
            while len(held) > KEPT_REVISIONS:
                del held[min(held, key=lambda k: held[k][0])]
            return part


def measure_on_worker(plugin: str, fs: FrameSet, bundle: PartBundle | None) -> Remote:
    """The job: measure ``fs`` with the station of plugin ``plugin`` on this Dask worker."""
    worker = get_worker()
    station = worker.plugins.get(plugin)
    if not isinstance(station, StationPlugin):
        raise StationNotLoaded(f"Dask worker {worker.address} has no station plugin {plugin}")
    outcome, seconds = station.measure(fs, bundle)
    r = outcome.result
    worker.log_event(
        EVENT_TOPIC,
        {
            "key": str(worker.get_current_task()),
            "id": r.id,
            "station": r.station,
            "seq": r.seq,
            "status": r.status.value,
            "worker": worker.address,
            "seconds": seconds,
        },
    )
    return Remote(outcome, worker.address, seconds)


# --------------------------------------------------------------------------- the dispatcher's side


class DaskExecutor:
    """Measures a station's FrameSets on a Dask cluster.

    Build it with :meth:`connect`. It registers the station's
    :class:`StationPlugin` (which returns once every Dask worker present has
    loaded it) and then takes jobs.

    Parameters
    ----------
    client : distributed.Client
    pipeline : Pipeline
        The dispatcher's own: its stages' recipe and its parts go to the
        cluster; a FrameSet it refuses (another station, an unknown part) is
        answered here without a round trip.
    warm_up : FrameSet, optional
    trees_dir : Path, optional
        The dispatcher's tree cache.
    cluster : distributed.LocalCluster, optional
        A cluster started for this executor, closed with it.
    """

    kind = "dask"

    def __init__(
        self,
        client: Client,
        pipeline: Pipeline,
        *,
        warm_up: FrameSet | None = None,
        trees_dir: Path | None = None,
        cluster: LocalCluster | None = None,
    ) -> None:
        remake = pipeline.stages.remake
        if remake is None:
            raise ExecutorError(
                f"the {pipeline.stages.name!r} stages cannot be built on a Dask worker"
            )
        if pipeline.line is None or pipeline.station is None:
            raise ExecutorError("a Dask executor measures for one line and station")
        self.client = client
        self.cluster = cluster
        self.pipeline = pipeline
        self.address = str(client.scheduler.address)
        bundles = tuple(PartBundle.of(p) for p in pipeline.parts.values())
        self.plugin = StationPlugin(
            remake, pipeline.stages.calibration_id, pipeline.line, pipeline.station, bundles,
            warm_up, None if trees_dir is None else str(Path(trees_dir).resolve()),
        )  # fmt: skip
        self._carried = {b.key for b in bundles}
        self._lock = threading.Lock()
        self._scattered: dict[str, tuple[str, Any]] = {}  # part name -> (bundle key, data)
        self._running: dict[str, Any] = {}
        # Jobs whose part travels with them are sent from here: scattering blocks.
        self._sender = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dask-send")
        t0 = time.perf_counter()
        try:
            client.register_plugin(self.plugin, name=self.plugin.name)
        except Exception as exc:
            raise ExecutorError(
                f"a Dask worker could not load station {pipeline.station}: "
                f"{type(exc).__name__}: {exc}"
            ) from exc
        log.info("station %s loaded on the Dask workers of %s in %.1f s", pipeline.station,
                 self.address, time.perf_counter() - t0)  # fmt: skip
        # The worker asks for slots under its accounting lock: it reads this view, which
        # a thread of its own keeps, and never waits on the scheduler.
        self._view = self._ask_cluster()
        self._closing = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="dask-view", daemon=True)
        self._watcher.start()

    @classmethod
    def connect(
        cls,
        address: DaskAddress,
        pipeline: Pipeline,
        *,
        warm_up: FrameSet | None = None,
        trees_dir: Path | None = None,
        timeout_s: float = 30.0,
        workers_timeout_s: float = 120.0,
    ) -> DaskExecutor:
        """Connect to the scheduler of ``address`` (or start ``local:N``) and load the station.

        Waits up to ``workers_timeout_s`` for a first Dask worker.

        Raises
        ------
        ExecutorError
            The scheduler cannot be reached, no worker joined, or a worker
            could not load the station.
        """
        cluster: LocalCluster | None = None
        client: Client | None = None
        try:
            if address.local_workers is not None:
                import dask

                # Spawned, not forked: a process with a zenoh session open must not fork.
                # Without the nanny's aggressive malloc trimming, which costs the
                # measurement about 30 % more CPU; its memory is the same every part.
                settings = {
                    "distributed.worker.multiprocessing-method": "spawn",
                    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                }
                with dask.config.set(settings):
                    cluster = LocalCluster(
                        n_workers=address.local_workers, threads_per_worker=1, processes=True,
                        host="127.0.0.1", dashboard_address=None,
                    )  # fmt: skip
                client = Client(cluster, set_as_default=False)
            else:
                client = Client(address.scheduler, timeout=timeout_s, set_as_default=False)
            log.info("Dask scheduler %s: waiting for a worker", client.scheduler.address)
            client.wait_for_workers(1, timeout=workers_timeout_s)
            return cls(client, pipeline, warm_up=warm_up, trees_dir=trees_dir, cluster=cluster)
        except ExecutorError:
            _close(client, cluster)
            raise
        except (OSError, TimeoutError) as exc:
            _close(client, cluster)
            what = (
                f"no Dask worker joined {address} within {workers_timeout_s:.0f} s"
                if client is not None
                else f"the Dask scheduler at {address} cannot be reached"
            )
            raise ExecutorError(f"{what}: {type(exc).__name__}: {exc}") from exc

    # ------------------------------------------------------------------ the interface

    def slots(self) -> int:
        with self._lock:
            return int(self._view["threads"]) + 1

    def submit(self, fs: FrameSet) -> Future[Measured]:
        done: Future[Measured] = Future()
        t0 = time.perf_counter()
        part = self.pipeline.parts.get(fs.part)
        if part is None or self.pipeline.refusal(fs) is not None:
            outcome = self.pipeline.run(fs)
            seconds = time.perf_counter() - t0
            done.set_result(Measured(outcome, IN_PROCESS, seconds, seconds))
            return done
        bundle = PartBundle.of(part)
        if bundle.key in self._carried:
            self._send(fs, bundle, done, t0)
        else:  # its part may have to be scattered first: not on the caller's thread
            self._later(lambda: self._send(fs, bundle, done, t0), done)
        return done

    def _later(self, send: Callable[[], None], done: Future[Measured]) -> None:
        """Run ``send`` on the executor's own thread; ``done`` gets what stops it."""

        def fail(exc: BaseException) -> None:
            with contextlib.suppress(InvalidStateError):
                done.set_exception(exc if isinstance(exc, Exception) else RuntimeError(repr(exc)))

        try:
            sending = self._sender.submit(send)
        except RuntimeError:  # shut down
            fail(ExecutorError("the Dask executor is closed"))
            return

        def check(f: Future[None]) -> None:
            if f.cancelled():
                fail(ExecutorError("the Dask executor closed before the job was sent"))
            elif f.exception() is not None:
                fail(f.exception())  # type: ignore[arg-type]

        sending.add_done_callback(check)

    def _send(
        self, fs: FrameSet, bundle: PartBundle, done: Future[Measured], t0: float,
        lost: Any = None,
    ) -> None:  # fmt: skip
        """Submit the job of ``fs``; its outcome goes to ``done``. ``lost``: the scattered
        part its first sending carried, which the cluster lost: send the part anew too."""
        data = self._bundle(bundle, lost=lost)
        # The result id names the job (the events, the scheduler's view); a
        # suffix keeps a job of a restarted dispatcher, or sent again, apart.
        rid = make_result_id(fs.line, fs.station, fs.seq, fs.triggered_ns)
        key = f"measure-{rid}-{uuid.uuid4().hex[:8]}"
        fut = self.client.submit(
            measure_on_worker, self.plugin.name, fs, data, key=key, pure=False, retries=RETRIES
        )
        with self._lock:
            self._running[key] = fut

        def settle(f: Any) -> None:
            # On distributed's one callback thread of this process: nothing here may block.
            try:
                remote: Remote = f.result()
            except BaseException as exc:  # the trigger is answered either way
                if data is not None and lost is None and _part_lost(exc):
                    log.warning("seq %d: the cluster lost part %s with the workers that held "
                                "it (%s): sending both again", fs.seq, fs.part, exc)  # fmt: skip
                    self._later(lambda: self._send(fs, bundle, done, t0, lost=data), done)
                    return
                done.set_exception(exc if isinstance(exc, Exception) else RuntimeError(repr(exc)))
            else:
                back = time.perf_counter() - t0
                done.set_result(Measured(remote.outcome, remote.where, remote.seconds, back))
            finally:
                with self._lock:
                    self._running.pop(key, None)

        fut.add_done_callback(settle)

    def status(self) -> dict[str, Any]:
        with self._lock:
            view = self._view
            running = len(self._running)
        return {
            "kind": self.kind,
            "scheduler": self.address,
            "workers": len(view["workers"]),
            "threads": view["threads"],
            "slots": view["threads"] + 1,
            "running": running,
            "cluster": view["workers"],
        }

    def close(self) -> None:
        self._closing.set()
        self._watcher.join(10)
        # A scatter under way ends with the client; jobs not sent yet are answered.
        self._sender.shutdown(wait=False, cancel_futures=True)
        _close(self.client, self.cluster)

    # ------------------------------------------------------------------ helpers

    def _bundle(self, bundle: PartBundle, *, lost: Any = None) -> Any:
        """None for a part every worker has (the plugin's); else the bundle on the cluster,
        scattered once, and again when the cluster no longer holds it (the workers that
        held it died; ``lost``: the data a job found gone). A scatter newer than ``lost``
        that the cluster holds is used as it is: the jobs of the part that were in flight
        share it. One revision per part is kept there: the newest."""
        if bundle.key in self._carried:
            return None
        with self._lock:
            held = self._scattered.get(bundle.spec.name)
        if (
            held is not None
            and held[0] == bundle.key
            and (lost is None or held[1].key != lost.key)
            and held[1].status == "finished"
        ):
            return held[1]
        # A name of its own each time: the lost data's key may linger on the scheduler.
        name = f"part-{bundle.key}-{uuid.uuid4().hex[:8]}"
        data = self.client.scatter({name: bundle})[name]
        with self._lock:
            self._scattered[bundle.spec.name] = (bundle.key, data)
        return data

    def _release_gone_parts(self) -> None:
        """Let go of the scattered parts the station measures no more (deleted, or replaced
        by another revision): the cluster frees them once the jobs carrying them are done."""
        with self._lock:
            held = dict(self._scattered)
        for name, (key, _) in held.items():
            part = self.pipeline.parts.get(name)
            if part is not None and PartBundle.of(part).key == key:
                continue
            with self._lock:
                if self._scattered.get(name, (None,))[0] == key:
                    del self._scattered[name]

    def _watch(self) -> None:
        while not self._closing.wait(CLUSTER_VIEW_S):
            view = self._ask_cluster()
            with self._lock:
                self._view = view
            self._release_gone_parts()

    def _ask_cluster(self) -> dict[str, Any]:
        """Workers (address: threads, jobs running) and their threads, from the scheduler."""
        try:
            info: dict[str, Any] = dict(self.client.scheduler_info(n_workers=-1))
        except Exception as exc:  # a scheduler away for a moment: say no workers
            log.warning("Dask scheduler %s: %s", self.address, exc)
            info = {"workers": {}}
        workers = {
            addr: {
                "threads": int(w.get("nthreads", 0)),
                "executing": int(w.get("metrics", {}).get("task_counts", {}).get("executing", 0)),
            }
            for addr, w in sorted(info.get("workers", {}).items())
        }
        return {"workers": workers, "threads": sum(w["threads"] for w in workers.values())}


def _part_lost(exc: BaseException) -> bool:
    """Whether a job failed because the part it carried is gone from the cluster: the
    scheduler cancels a job whose dependency was lost. A job that killed its workers
    (KilledWorker) lost the part too when they held it, but has had its tries: sending it
    again would double them."""
    return isinstance(exc, CancelledError)


def _close(client: Client | None, cluster: LocalCluster | None) -> None:
    if client is not None:
        with contextlib.suppress(Exception):
            client.close()
    if cluster is not None:
        with contextlib.suppress(Exception):
            cluster.close()
