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
- every FrameSet received is first written to the :class:`~service.journal.Journal`
  and leaves it once answered, so a killed worker measures again, at its next
  start, what it had accepted; it then learns the station's last seq from the
  store and answers the triggers that came while it was down;
- anything lost before our queue (zenoh's ring buffer, the network, a dead
  ingest or worker) shows as a gap in the per-station ``seq``; each missing
  number becomes a ``missed`` result with the serial ``unknown-<seq>``;
- a seq is checked, not trusted (:class:`SeqTracker`): a jump beyond
  ``max_seq_jump``, a seq already answered, and the seq of a FrameSet that
  cannot be decoded are answered with an ``error`` result and an
  :class:`~service.models.Alarm`, never expanded into missed records;
- a trigger delivered twice (same id) is answered once;
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
from .history import HistoryQueryable
from .journal import Journal
from .metrics import LATENCY_BUCKETS_S, Metrics, worker_collector
from .models import Alarm, AlarmKind, InspectionResult, Status, make_result_id
from .pipeline import Outcome, Pipeline, error_result, missed_result
from .protocol import FrameSet, Keys, ProtocolError, decode_frameset, peek_identity
from .store import ResultStore

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Job:
    """FrameSet bytes as received, with the local receive time (ns since the epoch)
    and its journal entry (None: not journaled); ``replayed``: taken from the
    journal at a start, so it may have been answered just before a kill."""

    payload: bytes
    received_ns: int
    journal_key: str | None = None
    replayed: bool = False


@dataclass(frozen=True)
class Dropped:
    """A FrameSet dropped before it was processed: what could be read of it, and why."""

    identity: dict[str, Any]
    received_ns: int
    reason: str
    journal_key: str | None = None
    replayed: bool = False


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

    def put(self, job: Job, *, force: bool = False) -> None:
        """Queue ``job``; when full, the oldest waiting job becomes a drop marker.

        ``force``: queue it beyond the capacity (the journal's entries at a
        start, each of which was accepted once already).
        """
        with self._cond:
            if self._jobs >= self.capacity and not force:
                # Drop the oldest waiting FrameSet: the newest part on the
                # conveyor is the one still worth measuring.
                for i, item in enumerate(self._items):
                    if isinstance(item, Job):
                        self._items[i] = Dropped(
                            peek_identity(item.payload),
                            item.received_ns,
                            f"worker queue full ({self.capacity} frame sets waiting)",
                            item.journal_key,
                            item.replayed,
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


RX_RING_MIN = 32
"""Samples zenoh's ring holds for the receiving thread at least: a burst of small
FrameSets must reach our queue, where an overflow is answered, not lost."""


class ZenohFrameSource:
    """Jobs from a subscription to ``<prefix>/<line>/<station>/frames``.

    Parameters
    ----------
    session : zenoh.Session
    key : str
    capacity : int
        Frame sets waiting in our queue.
    journal : Journal, optional
        Every FrameSet is journaled as it is received; what the journal holds
        from before (a killed worker) is queued first.
    """

    def __init__(
        self, session: zenoh.Session, key: str, capacity: int, journal: Journal | None = None
    ) -> None:
        self.queue = JobQueue(capacity)
        self.capacity = capacity
        self.journal = journal
        if journal is not None:
            pending = journal.pending()
            if pending:
                log.warning("journal: %d FrameSet(s) accepted before a stop are measured "
                            "first", len(pending))  # fmt: skip
            for entry in pending:
                self.queue.put(Job(entry.payload, entry.received_ns, entry.key, True), force=True)
        self._sub = bus.RingSubscriber(
            session, key, self._on_sample, capacity=max(RX_RING_MIN, 4 * capacity),
            name="frames-rx",
        )  # fmt: skip

    def _on_sample(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        now = time.time_ns()
        key = self.journal.add(payload, now) if self.journal is not None else None
        self.queue.put(Job(payload, now, key))

    def get(self, timeout_s: float) -> Job | Dropped | None:
        return self.queue.get(timeout_s)

    def depth(self) -> int:
        return self.queue.depth()

    def close(self) -> None:
        self._sub.close()


ResultSink = Callable[[Outcome, FrameSet | None], object]
"""Called with each outcome (and its FrameSet when one was decoded)."""

AlarmSink = Callable[[Alarm], object]
"""Called with each alarm the worker raises."""

DEFAULT_MAX_SEQ_JUMP = 300
"""Triggers a seq may skip before the jump is refused instead of answered as missed."""

RECENT_IDS = 4096
"""Result ids remembered to answer a trigger delivered twice once, store or not."""


@dataclass(frozen=True)
class SeqCheck:
    """What :meth:`SeqTracker.check` made of a seq.

    Attributes
    ----------
    accepted : bool
        Measure the FrameSet (False: answer it with an error).
    missing : list of (seq, triggered_ns)
        Triggers skipped before it, to be answered ``missed`` (their times
        spread between the neighbours').
    alarm : (AlarmKind, str) or None
    """

    accepted: bool
    missing: list[tuple[int, int]] = field(default_factory=list)
    alarm: tuple[AlarmKind, str] | None = None


class SeqTracker:
    """A station's seq, checked against what came before.

    - The next seq, or one up to ``max_jump`` beyond it, is accepted; the
      ones skipped are missing (answered ``missed``), except those already
      answered as undecodable FrameSets.
    - A seq below the next one (a repeat) or beyond the bound (a jump) is
      refused with an alarm, and the count stays where it was: one corrupt or
      forged seq costs one error result, never a flood of missed records.
    - A seq right after a refused one means the trigger source really counts
      anew (a restarted ingest without its state): it is accepted, with an
      alarm, and counting goes on from there.

    Parameters
    ----------
    max_jump : int
    resume : (seq, triggered_ns), optional
        The station's last answered trigger (from the store, at a restart).
    """

    def __init__(self, max_jump: int, resume: tuple[int, int] | None = None) -> None:
        if max_jump < 1:
            raise ValueError("max_jump must be at least 1")
        self.max_jump = max_jump
        self.next: int | None = None if resume is None else resume[0] + 1
        self.last_ns: int | None = None if resume is None else resume[1]
        self._refused: int | None = None
        self._answered: set[int] = set()

    def check(self, seq: int, triggered_ns: int) -> SeqCheck:
        nxt = self.next
        if nxt is None:
            return self._accept(seq, triggered_ns, [])
        if nxt <= seq <= nxt + self.max_jump:
            last_ns = self.last_ns if self.last_ns is not None else triggered_ns
            step = (triggered_ns - last_ns) / (seq - nxt + 1)
            missing = [
                (m, max(0, int(last_ns + k * step)))
                for k, m in enumerate(range(nxt, seq), start=1)
                if m not in self._answered
            ]
            return self._accept(seq, triggered_ns, missing)
        if self._refused is not None and seq == self._refused + 1:
            return self._accept(
                seq, triggered_ns, [],
                (AlarmKind.seq_rebased,
                 f"seq counts anew from {seq - 1} (expected {nxt}): the trigger source restarted"),
            )  # fmt: skip
        self._refused = seq
        if seq < nxt:
            return SeqCheck(False, alarm=(AlarmKind.seq_repeat,
                            f"seq {seq} repeated: seq {nxt - 1} was answered already"))  # fmt: skip
        return SeqCheck(False, alarm=(AlarmKind.seq_jump,
                        f"seq jumped from {nxt - 1} to {seq}, beyond the bound of "
                        f"{self.max_jump}: refused, not answered as missed"))  # fmt: skip

    def note_unreadable(self, seq: int | None) -> None:
        """An undecodable FrameSet claimed ``seq``: answered already, never missing.

        The count does not move: the claim may be as broken as the frame.
        """
        if (
            seq is not None
            and self.next is not None
            and self.next <= seq <= self.next + self.max_jump
        ):
            self._answered.add(seq)

    def _accept(
        self,
        seq: int,
        triggered_ns: int,
        missing: list[tuple[int, int]],
        alarm: tuple[AlarmKind, str] | None = None,
    ) -> SeqCheck:
        self.next = seq + 1
        self.last_ns = triggered_ns
        self._refused = None
        self._answered = {a for a in self._answered if a > seq}
        return SeqCheck(True, missing, alarm)


@dataclass
class WorkerStats:
    processed: int = 0
    missed: int = 0
    errors: int = 0
    alarms: int = 0
    duplicates: int = 0
    last_seq: int | None = None
    by_status: dict[str, int] = field(default_factory=dict)
    missed_by_cause: dict[str, int] = field(default_factory=dict)
    alarms_by_kind: dict[str, int] = field(default_factory=dict)


class Worker:
    """Runs the pipeline on every job of a source and hands each outcome to the sinks.

    Parameters
    ----------
    pipeline : Pipeline
    source : JobSource
    sinks : iterable of ResultSink
        Called in order for each outcome; a failing sink is logged and skipped.
    line, station : str
        For results that have no readable FrameSet; FrameSets of this line
        and station have their seq checked.
    missed_part : str
        Part name for missed triggers whose FrameSet never arrived (the
        station's part when it has one, else ``unknown``).
    max_seq_jump : int
        See :class:`SeqTracker`.
    resume : (seq, triggered_ns), optional
        The station's last stored trigger: where counting goes on after a restart.
    is_stored : callable(id) -> bool, optional
        Whether a result is stored already (the store's ``has``): a trigger
        delivered again, or journaled and answered just before a kill, is
        not answered twice.
    alarms : iterable of AlarmSink
    journal : Journal, optional
        Entries of answered jobs are removed from it.
    metrics : Metrics, optional
        Stage times and trigger-to-result latency are observed into it.
    cameras : list of (name, width, height), optional
        The station's cameras: a FrameSet announcing other images is refused
        before its images are decoded.
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
        max_seq_jump: int = DEFAULT_MAX_SEQ_JUMP,
        resume: tuple[int, int] | None = None,
        is_stored: Callable[[str], bool] | None = None,
        alarms: Iterable[AlarmSink] = (),
        journal: Journal | None = None,
        metrics: Metrics | None = None,
        cameras: list[tuple[str, int, int]] | None = None,
    ) -> None:
        self.pipeline = pipeline
        self.metrics = metrics
        self.cameras = cameras
        self.source = source
        self.sinks = list(sinks)
        self.line = line
        self.station = station
        self.missed_part = missed_part
        self.seqs = SeqTracker(max_seq_jump, resume)
        self.is_stored = is_stored
        self.alarms = list(alarms)
        self.journal = journal
        self.stats = WorkerStats()
        self._recent: collections.OrderedDict[str, None] = collections.OrderedDict()
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
        try:
            if isinstance(item, Dropped):
                self._dropped(item)
            else:
                self._job(item)
        finally:
            if self.journal is not None:
                self.journal.remove(item.journal_key)

    def _dropped(self, item: Dropped) -> None:
        ident = item.identity
        seq = ident.get("seq")
        t_ns = ident.get("triggered_ns", item.received_ns)
        line, station = ident.get("line", self.line), ident.get("station", self.station)
        if self._answered(make_result_id(line, station, seq or 0, t_ns), seq, t_ns, item.replayed):
            return
        fields: dict[str, Any] = dict(
            line=line, station=station, seq=seq if seq is not None else 0, triggered_ns=t_ns,
            part=ident.get("part") or self.missed_part, serial=ident.get("serial"),
            calibration_id=ident.get("calibration_id"),
        )  # fmt: skip
        if seq is not None and (line, station) == (self.line, self.station):
            check = self.seqs.check(seq, t_ns)
            if not self._admit(check, seq, t_ns):
                self._emit(Outcome(error_result(reason=_refusal(check), **fields)), None)
                return
        self._alarm(AlarmKind.queue_overflow, item.reason, t_ns, seq)
        self._emit(Outcome(missed_result(reason=item.reason, **fields)), None, "queue_full")

    def _job(self, item: Job) -> None:
        try:
            fs = decode_frameset(item.payload, cameras=self.cameras)
        except ProtocolError as exc:
            ident = peek_identity(item.payload)
            seq = ident.get("seq")
            t_ns = ident.get("triggered_ns", item.received_ns)
            line, station = ident.get("line", self.line), ident.get("station", self.station)
            if self._answered(
                make_result_id(line, station, seq or 0, t_ns), seq, t_ns, item.replayed
            ):
                return
            if (line, station) == (self.line, self.station):
                self.seqs.note_unreadable(seq)
            log.warning("bad FrameSet (seq %s): %s", seq, exc)
            self._alarm(AlarmKind.bad_frameset, f"bad FrameSet (seq {seq}): {exc}", t_ns, seq)
            self._emit(
                Outcome(
                    error_result(
                        line=line,
                        station=station,
                        # Without a readable seq the receive time keeps the id unique.
                        seq=seq if seq is not None else 0,
                        triggered_ns=t_ns,
                        part=ident.get("part"),
                        serial=ident.get("serial"),
                        calibration_id=ident.get("calibration_id"),
                        reason=f"bad FrameSet: {exc}",
                    )
                ),
                None,
            )
            return
        id_ = make_result_id(fs.line, fs.station, fs.seq, fs.triggered_ns)
        if self._answered(id_, fs.seq, fs.triggered_ns, item.replayed):
            return
        if (fs.line, fs.station) == (self.line, self.station):
            check = self.seqs.check(fs.seq, fs.triggered_ns)
            if not self._admit(check, fs.seq, fs.triggered_ns):
                result = error_result(
                    line=fs.line, station=fs.station, seq=fs.seq, triggered_ns=fs.triggered_ns,
                    part=fs.part, serial=fs.serial, calibration_id=fs.calibration_id or None,
                    reason=_refusal(check),
                )  # fmt: skip
                self._emit(Outcome(result), fs)
                return
        self._emit(self.pipeline.run(fs), fs)

    def _answered(self, id_: str, seq: int | None, triggered_ns: int, replayed: bool) -> bool:
        """Whether the trigger with this result id was answered already.

        A trigger delivered again is not answered again, and raises an alarm;
        a journal entry answered just before a kill is simply done.
        """
        if id_ not in self._recent and not (self.is_stored is not None and self.is_stored(id_)):
            return False
        self.stats.duplicates += 1
        if replayed:
            log.info("journal: trigger %s was answered before the stop", id_)
        else:
            message = f"trigger {id_} delivered again: answered once"
            self._alarm(AlarmKind.seq_repeat, message, triggered_ns, seq)
        return True

    def _admit(self, check: SeqCheck, seq: int, triggered_ns: int) -> bool:
        """Answer what ``check`` found missing and raise its alarm; whether to go on."""
        if check.alarm is not None:
            self._alarm(check.alarm[0], check.alarm[1], triggered_ns, seq)
        for missing, t_ns in check.missing:
            self._emit(
                Outcome(
                    missed_result(
                        line=self.line,
                        station=self.station,
                        seq=missing,
                        triggered_ns=t_ns,
                        part=self.missed_part,
                        reason=f"FrameSet seq {missing} never arrived",
                    )
                ),
                None,
                "never_arrived",
            )
        return check.accepted

    def _alarm(self, kind: AlarmKind, message: str, triggered_ns: int, seq: int | None) -> None:
        alarm = Alarm(
            kind=kind, message=message[:2000], triggered_ns=triggered_ns, line=self.line,
            station=self.station, seq=seq, raised_ns=time.time_ns(),
        )  # fmt: skip
        self.stats.alarms += 1
        self.stats.alarms_by_kind[kind.value] = self.stats.alarms_by_kind.get(kind.value, 0) + 1
        log.warning("alarm %s: %s", kind.value, message)
        for sink in self.alarms:
            try:
                sink(alarm)
            except Exception:
                log.exception("alarm sink %r failed", sink)

    def _emit(self, outcome: Outcome, fs: FrameSet | None, cause: str | None = None) -> None:
        r = outcome.result
        self.stats.processed += 1
        self.stats.last_seq = r.seq
        self.stats.by_status[r.status.value] = self.stats.by_status.get(r.status.value, 0) + 1
        if r.status is Status.missed:
            self.stats.missed += 1
            cause = cause or "other"
            self.stats.missed_by_cause[cause] = self.stats.missed_by_cause.get(cause, 0) + 1
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
        self._recent[r.id] = None
        if len(self._recent) > RECENT_IDS:
            self._recent.popitem(last=False)
        if self.metrics is not None and r.status not in (Status.missed,):
            self._observe(r)

    def _observe(self, r: InspectionResult) -> None:
        assert self.metrics is not None
        for stage, ms in r.timings_ms.items():
            self.metrics.observe(
                "inspection_stage_seconds", "Time of a measuring stage.", ms / 1e3, stage=stage
            )
        latency_s = (time.time_ns() - r.triggered_ns) / 1e9
        if 0 <= latency_s < 3600:  # a trigger clock far off says nothing of the latency
            self.metrics.observe(
                "inspection_latency_seconds", "Trigger to answered result.", latency_s,
                buckets=LATENCY_BUCKETS_S,
            )  # fmt: skip

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
            "alarms": self.stats.alarms,
            "duplicates": self.stats.duplicates,
            "last_seq": self.stats.last_seq,
        }


def _refusal(check: SeqCheck) -> str:
    return check.alarm[1] if check.alarm is not None else "seq refused"


def zenoh_result_sink(session: zenoh.Session, keys: Keys) -> ResultSink:
    """Publish each result as JSON on ``<prefix>/<line>/<station>/result/<part>/<serial>``."""

    def sink(outcome: Outcome, fs: FrameSet | None) -> None:
        r = outcome.result
        bus.put_json(session, keys.result(r.station, r.part, r.serial), r.model_dump_json())

    return sink


def zenoh_alarm_sink(session: zenoh.Session, keys: Keys) -> AlarmSink:
    """Publish each alarm as JSON on ``<prefix>/<line>/<station>/alarm``."""

    def sink(alarm: Alarm) -> None:
        bus.put_json(session, keys.alarm(alarm.station), alarm.model_dump_json())

    return sink


class ZenohWorker:
    """A :class:`Worker` on the bus: subscription, results, liveliness token, heartbeat.

    The liveliness token is declared only once the worker can measure (its
    parts are prepared before this object is built), so a token means ready.

    ``sinks`` run before the result is published, ``after_publish`` after it.

    With a ``store`` (the one ``sinks`` write to), the worker goes on counting
    from the station's last stored seq, answers a trigger already stored
    once, and serves the stored results on the station's history queryable
    (:mod:`service.history`). With a ``journal``, what it had accepted before
    a kill is measured first. Alarms go to ``<prefix>/<line>/<station>/alarm``, then
    to ``alarms`` (the store, the streams, the recording).
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
        store: ResultStore | None = None,
        journal: Journal | None = None,
        max_seq_jump: int = DEFAULT_MAX_SEQ_JUMP,
        metrics: Metrics | None = None,
        alarms: Iterable[AlarmSink] = (),
    ) -> None:
        self.id = bus.worker_id(station)
        self.session = session
        resume = store.last_trigger(keys.line, station) if store is not None else None
        if resume is not None:
            log.info("station %s: going on after seq %d", station, resume[0])
        self.history = (
            HistoryQueryable(session, keys, station, store) if store is not None else None
        )
        self.source = ZenohFrameSource(session, keys.frames(station), queue_size, journal)
        cals = pipeline.stages.calibrations()
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
            max_seq_jump=max_seq_jump,
            resume=resume,
            is_stored=store.has if store is not None else None,
            alarms=[zenoh_alarm_sink(session, keys), *alarms],
            journal=journal,
            metrics=metrics,
            cameras=[(c["name"], c["width"], c["height"]) for c in cals] or None,
        )
        if metrics is not None:
            metrics.collector(
                worker_collector(self.worker.stats, self.source.depth, self.source.capacity)
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
        if self.history is not None:
            self.history.close()
        try:
            self.token.undeclare()
        except zenoh.ZError:
            pass


def result_from_json(payload: bytes) -> InspectionResult:
    """Parse a result published by a worker."""
    return InspectionResult.model_validate(json.loads(payload))
