"""The worker: FrameSets in, InspectionResults out, one trigger at a time.

Jobs come from a :class:`JobSource`. Today that is :class:`ZenohFrameSource`,
a subscription to the station's frames key; a dispatcher shared by several
workers can replace it later without touching :class:`Worker`.

What happens to every trigger, and why none is silently lost:

- the zenoh reading thread only copies the payload into a bounded queue
  (:class:`JobQueue`); the pipeline runs on the worker's own thread;
- when the queue is full the *oldest* waiting FrameSet is dropped, and a
  marker keeps its place: it becomes a ``missed`` result carrying the serial
  and seq read from its header;
- anything lost before our queue (zenoh's ring buffer, the network, a dead
  ingest) shows as a gap in the per-station ``seq``; each missing number
  becomes a ``missed`` result with the serial ``unknown-<seq>``;
- a FrameSet that cannot be decoded becomes an ``error`` result with the
  reason; a failure in a sink (publishing, storing, recording) is logged and
  the other sinks still run. Nothing a FrameSet contains stops the worker.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

import zenoh

from . import bus
from .models import InspectionResult, Status
from .pipeline import Outcome, Pipeline, error_result, missed_result
from .protocol import FrameSet, Keys, ProtocolError, decode_frameset, peek_identity

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Job:
    """FrameSet bytes as received, with the local receive time (ns since the epoch)."""

    payload: bytes
    received_ns: int


@dataclass(frozen=True)
class Dropped:
    """A FrameSet dropped before it was processed: what could be read of it, and why."""

    identity: dict[str, Any]
    received_ns: int
    reason: str


class JobSource(Protocol):
    """Where a worker's jobs come from: a bounded queue of them."""

    capacity: int
    """Jobs that may wait."""

    def get(self, timeout_s: float) -> Job | Dropped | None:
        """The next job, a drop marker, or None when nothing came within ``timeout_s``."""

    def depth(self) -> int:
        """Jobs waiting now."""

    def close(self) -> None:
        """Stop receiving."""


class JobQueue:
    """A bounded FIFO of jobs that turns overflow into :class:`Dropped` markers.

    Parameters
    ----------
    capacity : int
        Jobs (FrameSets) that may wait. Markers are small and do not count.
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError("queue capacity must be at least 1")
        self.capacity = capacity
        self._items: collections.deque[Job | Dropped] = collections.deque()
        self._jobs = 0
        self._cond = threading.Condition()
        self.dropped = 0

    def put(self, job: Job) -> None:
        with self._cond:
            if self._jobs >= self.capacity:
                # Drop the oldest waiting FrameSet: the newest part on the
                # conveyor is the one still worth measuring.
                for i, item in enumerate(self._items):
                    if isinstance(item, Job):
                        self._items[i] = Dropped(
                            peek_identity(item.payload),
                            item.received_ns,
                            f"worker queue full ({self.capacity} frame sets waiting)",
                        )
                        self._jobs -= 1
                        self.dropped += 1
                        break
            self._items.append(job)
            self._jobs += 1
            self._cond.notify()

    def get(self, timeout_s: float) -> Job | Dropped | None:
        with self._cond:
            if not self._items and not self._cond.wait_for(lambda: bool(self._items), timeout_s):
                return None
            item = self._items.popleft()
            if isinstance(item, Job):
                self._jobs -= 1
            return item

    def depth(self) -> int:
        with self._cond:
            return self._jobs

    def close(self) -> None:
        """Nothing to release: the queue is fed by whoever holds it."""


class ZenohFrameSource:
    """Jobs from a subscription to ``<prefix>/<line>/<station>/frames``.

    Parameters
    ----------
    session : zenoh.Session
    key : str
    capacity : int
        Frame sets waiting in our queue (zenoh's own ring holds as many again).
    """

    def __init__(self, session: zenoh.Session, key: str, capacity: int) -> None:
        self.queue = JobQueue(capacity)
        self.capacity = capacity
        self._sub = bus.RingSubscriber(
            session, key, self._on_sample, capacity=capacity, name="frames-rx"
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.queue.put(Job(sample.payload.to_bytes(), time.time_ns()))

    def get(self, timeout_s: float) -> Job | Dropped | None:
        return self.queue.get(timeout_s)

    def depth(self) -> int:
        return self.queue.depth()

    def close(self) -> None:
        self._sub.close()


ResultSink = Callable[[Outcome, FrameSet | None], object]
"""Called with each outcome (and its FrameSet when one was decoded)."""


@dataclass
class WorkerStats:
    processed: int = 0
    missed: int = 0
    errors: int = 0
    last_seq: int | None = None
    by_status: dict[str, int] = field(default_factory=dict)


class Worker:
    """Runs the pipeline on every job of a source and hands each outcome to the sinks.

    Parameters
    ----------
    pipeline : Pipeline
    source : JobSource
    sinks : iterable of ResultSink
        Called in order for each outcome; a failing sink is logged and skipped.
    line, station : str
        For results that have no readable FrameSet.
    missed_part : str
        Part name for missed triggers whose FrameSet never arrived (the
        station's part when it has one, else ``unknown``).
    """

    def __init__(
        self,
        pipeline: Pipeline,
        source: JobSource,
        sinks: Iterable[ResultSink],
        *,
        line: str,
        station: str,
        missed_part: str = "unknown",
    ) -> None:
        self.pipeline = pipeline
        self.source = source
        self.sinks = list(sinks)
        self.line = line
        self.station = station
        self.missed_part = missed_part
        self.stats = WorkerStats()
        self._next_seq: int | None = None
        self._last_ns: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name=f"worker-{self.station}", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 60.0) -> None:
        """Stop after measuring what is already waiting (stop the source first).

        The queue holds at most its capacity, so this ends; a trigger that was
        accepted is measured, not dropped on the floor.
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def run(self) -> None:
        """Process jobs until :meth:`stop`, then what is still queued. Never raises."""
        while True:
            stopping = self._stop.is_set()
            try:
                item = self.source.get(0.0 if stopping else 0.2)
                if item is None:
                    if stopping:
                        return
                    continue
                self.handle(item)
            except Exception:  # the loop must survive anything
                log.exception("worker loop error")

    # ------------------------------------------------------------------ one job

    def handle(self, item: Job | Dropped) -> None:
        """Process one job or drop marker (public so tests and replay can drive it)."""
        if isinstance(item, Dropped):
            ident = item.identity
            seq = ident.get("seq")
            if seq is not None:
                self._gap_until(seq, ident.get("triggered_ns", item.received_ns))
            self._emit(
                Outcome(
                    missed_result(
                        line=ident.get("line", self.line),
                        station=ident.get("station", self.station),
                        seq=seq if seq is not None else 0,
                        triggered_ns=ident.get("triggered_ns", item.received_ns),
                        part=ident.get("part") or self.missed_part,
                        serial=ident.get("serial"),
                        calibration_id=ident.get("calibration_id"),
                        reason=item.reason,
                    )
                ),
                None,
            )
            return
        try:
            fs = decode_frameset(item.payload)
        except ProtocolError as exc:
            ident = peek_identity(item.payload)
            seq = ident.get("seq")
            if seq is not None:
                self._gap_until(seq, ident.get("triggered_ns", item.received_ns))
            log.warning("bad FrameSet (seq %s): %s", seq, exc)
            self._emit(
                Outcome(
                    error_result(
                        line=ident.get("line", self.line),
                        station=ident.get("station", self.station),
                        # Without a readable seq the receive time keeps the id unique.
                        seq=seq if seq is not None else 0,
                        triggered_ns=ident.get("triggered_ns", item.received_ns),
                        part=ident.get("part"),
                        serial=ident.get("serial"),
                        calibration_id=ident.get("calibration_id"),
                        reason=f"bad FrameSet: {exc}",
                    )
                ),
                None,
            )
            return
        self._gap_until(fs.seq, fs.triggered_ns)
        outcome = self.pipeline.run(fs)
        self._emit(outcome, fs)

    def _gap_until(self, seq: int, triggered_ns: int) -> None:
        """Record every seq between the last one seen and ``seq`` as missed."""
        expected = self._next_seq
        if expected is not None and seq > expected:
            # Spread the unknown trigger times evenly between the neighbours.
            last_ns = self._last_ns if self._last_ns is not None else triggered_ns
            step = (triggered_ns - last_ns) / (seq - expected + 1)
            for k, missing in enumerate(range(expected, seq), start=1):
                self._emit(
                    Outcome(
                        missed_result(
                            line=self.line,
                            station=self.station,
                            seq=missing,
                            triggered_ns=max(0, int(last_ns + k * step)),
                            part=self.missed_part,
                            reason=f"FrameSet seq {missing} never arrived",
                        )
                    ),
                    None,
                )
        elif expected is not None and seq < expected:
            log.warning(
                "seq went back from %d to %d: the ingest restarted; counting anew",
                expected - 1,
                seq,
            )
        self._next_seq = seq + 1
        self._last_ns = triggered_ns

    def _emit(self, outcome: Outcome, fs: FrameSet | None) -> None:
        r = outcome.result
        self.stats.processed += 1
        self.stats.last_seq = r.seq
        self.stats.by_status[r.status.value] = self.stats.by_status.get(r.status.value, 0) + 1
        if r.status is Status.missed:
            self.stats.missed += 1
            # Said out loud: a line that cannot keep up with its trigger must show it.
            log.warning(
                "missed %s seq %d (%d missed of %d): %s",
                r.serial, r.seq, self.stats.missed, self.stats.processed, r.reason,
            )  # fmt: skip
        elif r.status is Status.error:
            self.stats.errors += 1
        for sink in self.sinks:
            try:
                sink(outcome, fs)
            except Exception:
                log.exception("result sink %r failed for %s", sink, r.id)

    def status(self, worker_id: str, state: str) -> dict[str, Any]:
        return {
            "worker": worker_id,
            "station": self.station,
            "state": state,
            "ready": state == "ready",
            "queue_depth": self.source.depth(),
            "queue_capacity": self.source.capacity,
            "processed": self.stats.processed,
            "missed": self.stats.missed,
            "errors": self.stats.errors,
            "last_seq": self.stats.last_seq,
        }


def zenoh_result_sink(session: zenoh.Session, keys: Keys) -> ResultSink:
    """Publish each result as JSON on ``<prefix>/<line>/<station>/result/<part>/<serial>``."""

    def sink(outcome: Outcome, fs: FrameSet | None) -> None:
        r = outcome.result
        bus.put_json(session, keys.result(r.station, r.part, r.serial), r.model_dump_json())

    return sink


class ZenohWorker:
    """A :class:`Worker` on the bus: subscription, results, liveliness token, heartbeat.

    The liveliness token is declared only once the worker can measure (its
    parts are prepared before this object is built), so a token means ready.

    ``sinks`` run before the result is published, ``after_publish`` after it.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        station: str,
        pipeline: Pipeline,
        *,
        queue_size: int,
        sinks: Iterable[ResultSink] = (),
        after_publish: Iterable[ResultSink] = (),
        missed_part: str = "unknown",
        heartbeat_s: float = 1.0,
    ) -> None:
        self.id = bus.worker_id(station)
        self.session = session
        self.source = ZenohFrameSource(session, keys.frames(station), queue_size)
        self.worker = Worker(
            pipeline,
            self.source,
            # Store first: whoever sees the result on zenoh can then fetch it
            # over REST. Sinks nobody waits for (the recording) come after the
            # publication, so they do not add to the trigger-to-result latency.
            [*sinks, zenoh_result_sink(session, keys), *after_publish],
            line=keys.line,
            station=station,
            missed_part=missed_part,
        )
        self._state = "ready"
        self.token = session.liveliness().declare_token(keys.worker_token(station, self.id))
        self.heartbeat = bus.Heartbeat(
            session,
            keys.status(station),
            lambda: self.worker.status(self.id, self._state),
            period_s=heartbeat_s,
        )
        self.worker.start()
        self.heartbeat.publish()

    def close(self) -> None:
        """Stop receiving, finish the job in hand, say goodbye on the status key."""
        self.source.close()
        self.worker.stop()
        self._state = "stopping"
        self.heartbeat.publish()
        self.heartbeat.close()
        try:
            self.token.undeclare()
        except zenoh.ZError:
            pass


def result_from_json(payload: bytes) -> InspectionResult:
    """Parse a result published by a worker."""
    return InspectionResult.model_validate(json.loads(payload))
