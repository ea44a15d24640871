"""The worker: FrameSets in, InspectionResults out, exactly one per trigger.

Jobs come from a :class:`JobSource`: :class:`ZenohFrameSource`, a
subscription to the station's frames key. The worker accounts for each of
them and hands what it accepted to an :class:`~service.executor.Executor`,
which measures it: in this process by default
(:class:`~service.executor.InProcessExecutor`, one at a time, in the worker's
thread), or on a Dask cluster (:mod:`service.dask_executor`), several at
once, whose results come back in the order they finish, not in seq order.

What happens to every trigger, and why none is silently lost:

- the zenoh reading thread only copies the payload into a bounded queue
  (:class:`JobQueue`); the worker's thread takes a job from it only when the
  executor has a free slot (:meth:`~service.executor.Executor.slots` jobs in
  flight at most), so that what the executor cannot take yet waits there;
- the accounting (seq, duplicates, journal, statistics, the sinks) happens
  under one lock, whether in the worker's thread or in the thread that hands
  out finished measurements: one result per trigger, whoever finishes first;
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
- a FrameSet naming a part the station does not hold yet (created over the
  API: :mod:`service.station_parts`) waits, with its journal entry, while the
  part is taken from the store off this thread; it is then measured, or
  answered ``error`` when the part is unknown there too, or when it has not
  come within ``part_wait_s`` (the reason names the part and what its load
  was doing). At most the queue's capacity of them wait; beyond that the
  oldest is answered ``missed``. One still waiting when the worker stops
  keeps its journal entry, measured at the next start;
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
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Protocol

import zenoh

from . import bus
from .executor import Executor, InProcessExecutor, Measured
from .history import HistoryQueryable
from .journal import Journal
from .metrics import LATENCY_BUCKETS_S, Metrics, executor_collector, worker_collector
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


class PartSource(Protocol):
    """Where a worker gets a part its pipeline lacks (:mod:`service.station_parts`)."""

    def request(self, name: str, done: Callable[[str | None], None]) -> None:
        """Get part ``name`` into the pipeline's parts (any thread); ``done(None)`` once it
        is there, ``done(reason)`` when it cannot be had."""

    def pending(self, name: str) -> str:
        """What getting part ``name`` is doing now, in a few words; called without waiting
        (under the worker's lock) for a FrameSet that gave up waiting."""


PART_WAIT_S = 120.0
"""How long a FrameSet waits for its part by default, s (``[station] part_wait_s``)."""


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

FIRED_GRACE_S = 5.0
"""How long after the trigger source said a seq fired its FrameSet may still come
(with nothing left in the queue): a FrameSet crosses the bus in milliseconds, so
one that has not come by then was lost, and its trigger is answered ``missed``."""

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

    def fired(self, seq: int, triggered_ns: int) -> SeqCheck:
        """The trigger source says it fired up to ``seq`` (at ``triggered_ns``), and no
        FrameSet of the seqs above the count came: they are missing, ``seq`` included.

        Before any seq was seen, nothing is missing (where counting starts is
        the first FrameSet's, as ever); at or below the count, nothing either.
        A claim beyond the bound is refused, like a FrameSet's jump.
        """
        nxt = self.next
        if nxt is None or seq < nxt:
            return SeqCheck(True)
        if seq > nxt + self.max_jump:
            message = (f"the trigger source says seq {seq} fired, beyond the bound of "
                       f"{self.max_jump} after seq {nxt - 1}: not answered as missed")  # fmt: skip
            return SeqCheck(False, alarm=(AlarmKind.seq_jump, message))
        last_ns = self.last_ns if self.last_ns is not None else triggered_ns
        step = (triggered_ns - last_ns) / (seq - nxt + 1)
        missing = [
            (m, max(0, int(last_ns + k * step)))
            for k, m in enumerate(range(nxt, seq + 1), start=1)
            if m not in self._answered
        ]
        return self._accept(seq, triggered_ns, missing)

    def behind(self, seq: int) -> bool:
        """Whether ``seq`` is below the count (answered, or owed from before a restart)."""
        return self.next is not None and seq < self.next

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


@dataclass(frozen=True, eq=False)
class InFlight:
    """A FrameSet handed to the executor, and the journal entry it leaves once answered."""

    fs: FrameSet
    journal_key: str | None


@dataclass
class JobTimes:
    """Measurements one executor worker made: how many, and their time (s)."""

    jobs: int = 0
    total_s: float = 0.0
    last_s: float = 0.0


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
    lost: int = 0
    by_worker: dict[str, JobTimes] = field(default_factory=dict)


class Worker:
    """Accounts for every job of a source, has the executor measure those it accepts, and
    hands each outcome to the sinks.

    Parameters
    ----------
    pipeline : Pipeline
        What the station measures with; the in-process executor runs it.
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
    executor : Executor, optional
        Where the measurements run; default :class:`~service.executor.InProcessExecutor`
        on ``pipeline``.
    fired_grace_s : float
        See :data:`FIRED_GRACE_S` and :meth:`note_fired`.
    parts : PartSource, optional
        Asked for the part of a FrameSet of this station that ``pipeline``
        does not know; without one such a FrameSet is answered ``error`` at once.
    part_wait_s : float
        How long such a FrameSet waits for its part; then it is answered ``error``.
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
        executor: Executor | None = None,
        fired_grace_s: float = FIRED_GRACE_S,
        parts: PartSource | None = None,
        part_wait_s: float = PART_WAIT_S,
    ) -> None:
        self.pipeline = pipeline
        self.parts = parts
        self.part_wait_s = part_wait_s
        self.executor: Executor = executor if executor is not None else InProcessExecutor(pipeline)
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
        # What the trigger source said it fired, (seq, triggered_ns, when heard),
        # and the seqs answered missed on its word: their FrameSet, should it
        # still come, is not answered again.
        self.fired_grace_s = fired_grace_s
        self._fired_lock = threading.Lock()
        self._fired: tuple[int, int, float] | None = None
        self._fired_heard: int | None = None
        self._given_up: collections.OrderedDict[int, None] = collections.OrderedDict()
        # The accounting's one lock; ``_changed`` wakes whoever waits for a
        # finished measurement or a free slot.
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._in_flight: dict[str, InFlight] = {}
        self._finished: collections.deque[tuple[str, Future[Measured]]] = collections.deque()
        # FrameSets waiting for their part (oldest first) with their deadline (monotonic s),
        # and the answers about parts that came (result id, None or why it cannot be had).
        self._waiting: collections.OrderedDict[str, tuple[InFlight, float]] = (
            collections.OrderedDict()
        )
        self._parts_came: collections.deque[tuple[str, str | None]] = collections.deque()
        self._stop = threading.Event()
        self._stop_s = 60.0  # how long a stop waits for what was accepted to be answered
        self._closed = False
        self._thread: threading.Thread | None = None
        self._results: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name=f"worker-{self.station}", daemon=True)
        self._results = threading.Thread(
            target=self._hand_out, name=f"results-{self.station}", daemon=True
        )
        self._thread.start()
        self._results.start()

    def stop(self, timeout_s: float = 60.0) -> None:
        """Stop after measuring what is already waiting (stop the source first).

        The queue holds at most its capacity and the executor its slots, so
        this ends; a trigger that was accepted is measured, not dropped on the
        floor. One still being measured, or still waiting for its part, after
        ``timeout_s`` stays in the journal, measured again at the next start.
        """
        self._stop_s = timeout_s
        self._stop.set()
        if self._thread is not None:
            # The thread drains for ``timeout_s`` after the stop: a moment more lets it end
            # its last drain before the results thread goes.
            self._thread.join(timeout_s + 1.0)
        with self._changed:
            self._closed = True
            self._changed.notify_all()
        if self._results is not None:
            self._results.join(timeout_s)

    def run(self, drain_s: float | None = None) -> None:
        """Process jobs until :meth:`stop`, then what is still queued, being measured or
        waiting for its part, for at most ``drain_s`` after the stop (default: the stop's
        timeout). Never raises."""
        deadline: float | None = None
        while True:
            stopping = self._stop.is_set()
            if stopping and deadline is None:
                deadline = time.monotonic() + (self._stop_s if drain_s is None else drain_s)
            if deadline is not None and time.monotonic() > deadline:
                break
            try:
                if not self._wait_for_slot(0.2):
                    continue
                item = self.source.get(0.0 if stopping else 0.2)
                if item is None:
                    if stopping:
                        break
                    self._settle_fired()
                    continue
                self.handle(item)
            except Exception:  # the loop must survive anything
                log.exception("worker loop error")
        left = 0.0 if deadline is None else max(0.0, deadline - time.monotonic())
        if not self.drain(left):
            log.warning("stopping with %d FrameSet(s) still being measured and %d waiting for "
                        "their part: they stay in the journal", len(self._in_flight),
                        len(self._waiting))  # fmt: skip

    def _wait_for_slot(self, timeout_s: float) -> bool:
        """Hand out finished measurements, and measure the FrameSets whose part came, until
        the executor has a free slot (or timeout)."""
        with self._changed:
            return self._changed.wait_for(self._slot_free, timeout_s)

    def _slot_free(self) -> bool:
        self._hand_out_finished()
        self._measure_waiting()
        self._give_up_waiting()
        return len(self._in_flight) < self.executor.slots()

    def _hand_out(self) -> None:
        """The results thread: every measurement as it finishes, to the sinks."""
        with self._changed:
            while True:
                self._changed.wait_for(lambda: bool(self._finished) or self._closed)
                if not self._finished and self._closed:
                    return
                try:
                    self._hand_out_finished()
                except Exception:  # the thread must survive anything
                    log.exception("results thread error")

    # ------------------------------------------------------------------ one job

    def handle(self, item: Job | Dropped) -> None:
        """Process one job or drop marker (public so tests and replay can drive it).

        With the in-process executor its result has gone to the sinks when
        this returns; with another one, when the measurement finishes.
        """
        with self._lock:
            submitted = False
            try:
                if isinstance(item, Dropped):
                    self._dropped(item)
                else:
                    submitted = self._job(item)
            finally:
                if not submitted and self.journal is not None:
                    self.journal.remove(item.journal_key)
            self._hand_out_finished()

    def drain(self, timeout_s: float) -> bool:
        """Wait until every measurement handed out, and every FrameSet waiting for its part,
        has gone to the sinks (tests and replay, without :meth:`start`); whether none is left."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                self._hand_out_finished()
                self._measure_waiting(every=True)
                self._give_up_waiting()
                if not self._in_flight and not self._waiting:
                    return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                # Woken by a measurement or a part that came; a waiting FrameSet's
                # deadline passes without either.
                self._changed.wait(min(left, 0.2))

    def note_fired(self, next_seq: int, triggered_ns: int) -> None:
        """The trigger source's word: it has fired every seq below ``next_seq``, the last
        at ``triggered_ns`` (any thread).

        FrameSets usually tell the worker of a trigger whose FrameSet was lost:
        the next one shows the gap. The last triggers before the source stops,
        or those fired while this worker was down, have no next FrameSet; once
        the queue is empty and :attr:`fired_grace_s` has passed, they are
        answered ``missed``.
        """
        seq = next_seq - 1
        if seq < 0:
            return
        with self._fired_lock:
            if self._fired_heard == seq:
                return  # the same word again (it is repeated every second)
            self._fired_heard = seq
            self._fired = (seq, triggered_ns, time.monotonic())

    def _settle_fired(self) -> None:
        """Answer what the trigger source fired and no FrameSet brought (queue empty)."""
        with self._fired_lock:
            fired = self._fired
            if fired is None or time.monotonic() - fired[2] < self.fired_grace_s:
                return
            if self.source.depth() > 0:
                return
            self._fired = None
        seq, t_ns, _ = fired
        with self._lock:
            check = self.seqs.fired(seq, t_ns)
            self._admit(check, seq, t_ns)
            for missing, _t in check.missing:
                self._given_up[missing] = None
            while len(self._given_up) > RECENT_IDS:
                self._given_up.popitem(last=False)
            self._hand_out_finished()

    def _answered_before(
        self, line: str, station: str, seq: int | None, triggered_ns: int, replayed: bool
    ) -> bool:
        """Whether this FrameSet's trigger has its answer already, which raised its alarm.

        A FrameSet of a trigger answered missed on the trigger source's word is
        told as late first: its missed answer may carry the same id (the count
        names the last trigger's time exactly), and "delivered again" would
        misname it.
        """
        if not replayed and self._came_late(line, station, seq, triggered_ns):
            return True
        id_ = make_result_id(line, station, seq or 0, triggered_ns)
        return self._answered(id_, seq, triggered_ns, replayed)

    def _came_late(self, line: str, station: str, seq: int | None, triggered_ns: int) -> bool:
        """Whether this is the FrameSet of a trigger answered missed already, on the
        trigger source's word (it came after the grace): an alarm, no second result."""
        if seq is None or (line, station) != (self.line, self.station):
            return False
        if seq not in self._given_up:
            return False
        self.stats.duplicates += 1
        message = (f"FrameSet seq {seq} came after its trigger was answered missed: "
                   "not answered again")  # fmt: skip
        self._alarm(AlarmKind.seq_repeat, message, triggered_ns, seq)
        return True

    def _dropped(self, item: Dropped) -> None:
        ident = item.identity
        seq = ident.get("seq")
        t_ns = ident.get("triggered_ns", item.received_ns)
        line, station = ident.get("line", self.line), ident.get("station", self.station)
        if self._answered_before(line, station, seq, t_ns, item.replayed):
            return
        fields: dict[str, Any] = dict(
            line=line, station=station, seq=seq if seq is not None else 0, triggered_ns=t_ns,
            part=ident.get("part") or self.missed_part, serial=ident.get("serial"),
            calibration_id=ident.get("calibration_id"),
        )  # fmt: skip
        if (
            seq is not None
            and (line, station) == (self.line, self.station)
            and not self._owed(seq, item.replayed)
        ):
            check = self.seqs.check(seq, t_ns)
            if not self._admit(check, seq, t_ns):
                self._emit(Outcome(error_result(reason=_refusal(check), **fields)), None)
                return
        self._alarm(AlarmKind.queue_overflow, item.reason, t_ns, seq)
        self._emit(Outcome(missed_result(reason=item.reason, **fields)), None, "queue_full")

    def _job(self, item: Job) -> bool:
        """Account for one job; whether it went to the executor (its journal entry stays)."""
        try:
            fs = decode_frameset(item.payload, cameras=self.cameras)
        except ProtocolError as exc:
            ident = peek_identity(item.payload)
            seq = ident.get("seq")
            t_ns = ident.get("triggered_ns", item.received_ns)
            line, station = ident.get("line", self.line), ident.get("station", self.station)
            if self._answered_before(line, station, seq, t_ns, item.replayed):
                return False
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
            return False
        if self._answered_before(fs.line, fs.station, fs.seq, fs.triggered_ns, item.replayed):
            return False
        id_ = make_result_id(fs.line, fs.station, fs.seq, fs.triggered_ns)
        if (fs.line, fs.station) == (self.line, self.station) and not self._owed(
            fs.seq, item.replayed
        ):
            check = self.seqs.check(fs.seq, fs.triggered_ns)
            if not self._admit(check, fs.seq, fs.triggered_ns):
                result = error_result(
                    line=fs.line, station=fs.station, seq=fs.seq, triggered_ns=fs.triggered_ns,
                    part=fs.part, serial=fs.serial, calibration_id=fs.calibration_id or None,
                    reason=_refusal(check),
                )  # fmt: skip
                self._emit(Outcome(result), fs)
                return False
        flight = InFlight(fs, item.journal_key)
        if self.parts is not None and self._lacks_part(fs):
            self._wait_for_part(id_, flight)
            return True
        return self._submit(id_, flight)

    def _submit(self, id_: str, flight: InFlight) -> bool:
        """Hand ``flight`` to the executor (lock held); whether it took it (else answered)."""
        self._in_flight[id_] = flight
        try:
            future = self.executor.submit(flight.fs)
        except Exception as exc:  # an executor that cannot take it: still one result
            del self._in_flight[id_]
            self._emit(self._lost(flight.fs, exc), flight.fs)
            return False
        future.add_done_callback(lambda f: self._on_finished(id_, f))
        return True

    # ------------------------------------------------------------------ parts not held yet

    def _lacks_part(self, fs: FrameSet) -> bool:
        """A FrameSet this station would measure, but of a part its pipeline does not hold."""
        return (
            (fs.line, fs.station) == (self.line, self.station)
            and fs.sensor == self.pipeline.stages.sensor
            and fs.part not in self.pipeline.parts
        )

    def _wait_for_part(self, id_: str, flight: InFlight) -> None:
        """Park ``flight`` until its part comes or :attr:`part_wait_s` passes (lock held);
        the oldest parked one is answered ``missed`` when as many wait as the queue holds."""
        assert self.parts is not None
        if len(self._waiting) >= self.source.capacity:
            _, (oldest, _) = self._waiting.popitem(last=False)
            reason = (f"worker queue full ({self.source.capacity} frame sets waiting for "
                      "their part to load)")  # fmt: skip
            self._alarm(AlarmKind.queue_overflow, reason, oldest.fs.triggered_ns, oldest.fs.seq)
            self._answer_unmeasured(oldest, missed_result, reason, "queue_full")
        log.info("seq %d: part %s is not loaded here; asked for it", flight.fs.seq, flight.fs.part)
        self._waiting[id_] = (flight, time.monotonic() + self.part_wait_s)
        self.parts.request(flight.fs.part, lambda why: self._on_part(id_, why))

    def _on_part(self, id_: str, why: str | None) -> None:
        """The part of waiting FrameSet ``id_`` came (``why`` None) or cannot come (any thread)."""
        with self._changed:
            self._parts_came.append((id_, why))
            self._changed.notify_all()

    def _measure_waiting(self, *, every: bool = False) -> bool:
        """Hand the FrameSets whose part came to the executor while it has free slots
        (``every``: all of them), and answer those whose part cannot come (lock held).

        Returns False, so that it can sit in a wait's condition.
        """
        while self._parts_came and (every or len(self._in_flight) < self.executor.slots()):
            id_, why = self._parts_came.popleft()
            parked = self._waiting.pop(id_, None)
            if parked is None:  # answered meanwhile (missed, or given up)
                continue
            flight = parked[0]
            if why is not None:
                self._answer_unmeasured(flight, error_result, why)
            elif not self._submit(id_, flight) and self.journal is not None:
                self.journal.remove(flight.journal_key)
            self._hand_out_finished()
        return False

    def _give_up_waiting(self) -> None:
        """Answer ``error`` every FrameSet that waited :attr:`part_wait_s` for its part
        (lock held); the part's load goes on, for the FrameSets after it."""
        now = time.monotonic()
        while self._waiting:
            id_, (flight, deadline) = next(iter(self._waiting.items()))
            if deadline > now:
                return  # one wait for all: the oldest expires first
            del self._waiting[id_]
            part = flight.fs.part
            doing = self.parts.pending(part) if self.parts is not None else "not asked for"
            reason = (f"part {part!r} was not loaded within {self.part_wait_s:g} s "
                      f"([station] part_wait_s): {doing}")  # fmt: skip
            log.error("seq %d: %s", flight.fs.seq, reason)
            self._answer_unmeasured(flight, error_result, reason)

    def _answer_unmeasured(
        self,
        flight: InFlight,
        make: Callable[..., InspectionResult],
        reason: str,
        cause: str | None = None,
    ) -> None:
        """Answer a parked FrameSet without measuring it (lock held)."""
        fs = flight.fs
        result = make(
            line=fs.line, station=fs.station, seq=fs.seq, triggered_ns=fs.triggered_ns,
            part=fs.part, serial=fs.serial, calibration_id=fs.calibration_id or None,
            reason=reason,
        )  # fmt: skip
        try:
            self._emit(Outcome(result), fs, cause)
        finally:
            if self.journal is not None:
                self.journal.remove(flight.journal_key)

    def _on_finished(self, id_: str, future: Future[Measured]) -> None:
        """Called by the executor's future, in whatever thread finished it."""
        with self._changed:
            self._finished.append((id_, future))
            self._changed.notify_all()

    def _hand_out_finished(self) -> bool:
        """Give every finished measurement to the sinks, in the order they finished (lock held).

        Returns False, so that it can sit in a wait's condition.
        """
        while self._finished:
            id_, future = self._finished.popleft()
            flight = self._in_flight.pop(id_)
            try:
                measured = future.result()
            except Exception as exc:  # the cluster gave up on it: still one result
                outcome = self._lost(flight.fs, exc)
            else:
                outcome = measured.outcome
                self._count_job(measured)
            try:
                self._emit(outcome, flight.fs)
            finally:
                if self.journal is not None:
                    self.journal.remove(flight.journal_key)
            self._changed.notify_all()
        return False

    def _lost(self, fs: FrameSet, exc: Exception) -> Outcome:
        """The error result of a FrameSet whose measurement never came back."""
        self.stats.lost += 1
        reason = f"the measurement was lost: {type(exc).__name__}: {exc}"
        log.error("seq %d: %s", fs.seq, reason)
        return Outcome(
            error_result(
                line=fs.line, station=fs.station, seq=fs.seq, triggered_ns=fs.triggered_ns,
                part=fs.part, serial=fs.serial, calibration_id=fs.calibration_id or None,
                reason=reason,
            )
        )  # fmt: skip

    def _count_job(self, m: Measured) -> None:
        times = self.stats.by_worker.setdefault(m.where, JobTimes())
        times.jobs += 1
        times.total_s += m.seconds
        times.last_s = m.seconds
        if self.metrics is not None:
            self.metrics.observe(
                "inspection_executor_job_seconds", "Time of a measurement, by who made it.",
                m.seconds, worker=m.where, line=self.line, station=self.station,
            )  # fmt: skip
            self.metrics.observe(
                "inspection_executor_dispatch_seconds",
                "Round trip of a measurement less its own time: sending, queueing, returning.",
                max(0.0, m.round_trip_s - m.seconds), line=self.line, station=self.station,
            )  # fmt: skip

    def _owed(self, seq: int, replayed: bool) -> bool:
        """Whether a journal entry is owed its result from before a stop, below the count.

        Results finish out of seq order: the store's last seq, where counting
        goes on, may be above a trigger that was still being measured at a
        kill. Its journal entry (not in the store, or it would be answered
        already) is answered now, and the count stays where it is.
        """
        if not (replayed and self.seqs.behind(seq)):
            return False
        log.info("journal: seq %d, accepted before the stop, is answered now", seq)
        return True

    def _answered(self, id_: str, seq: int | None, triggered_ns: int, replayed: bool) -> bool:
        """Whether the trigger with this result id was answered already (or is being measured).

        A trigger delivered again is not answered again, and raises an alarm;
        a journal entry answered just before a kill is simply done.
        """
        if (
            id_ not in self._recent
            and id_ not in self._in_flight
            and id_ not in self._waiting
            and not (self.is_stored is not None and self.is_stored(id_))
        ):
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
        # Observed before the sinks, as the counts are: whoever sees a result has its
        # times in the histograms too, and the recording after the publication is not
        # part of the trigger-to-result latency.
        if self.metrics is not None and r.status is not Status.missed:
            self._observe(r)
        for sink in self.sinks:
            try:
                sink(outcome, fs)
            except Exception:
                log.exception("result sink %r failed for %s", sink, r.id)
        self._recent[r.id] = None
        if len(self._recent) > RECENT_IDS:
            self._recent.popitem(last=False)

    def _observe(self, r: InspectionResult) -> None:
        assert self.metrics is not None
        # The worker's own line and station, not the result's: a FrameSet of a foreign
        # station (answered with an error) must not make series of its own.
        line, station = self.line, self.station
        for stage, ms in r.timings_ms.items():
            self.metrics.observe(
                "inspection_stage_seconds", "Time of a measuring stage.", ms / 1e3,
                stage=stage, line=line, station=station,
            )  # fmt: skip
        latency_s = (time.time_ns() - r.triggered_ns) / 1e9
        if 0 <= latency_s < 3600:  # a trigger clock far off says nothing of the latency
            self.metrics.observe(
                "inspection_latency_seconds", "Trigger to answered result.", latency_s,
                buckets=LATENCY_BUCKETS_S, line=line, station=station,
            )  # fmt: skip

    def executor_status(self) -> dict[str, Any]:
        """The executor's own status, with the jobs in flight and the measurements each of
        its workers made (count, mean and last time, s)."""
        # No lock: the heartbeat and a scrape must not wait for an in-process measurement.
        # Snapshots of the dicts suffice; a count one job behind is no harm.
        in_flight = len(self._in_flight)
        waiting = len(self._waiting)
        jobs = {
            where: {"jobs": t.jobs, "mean_s": t.total_s / t.jobs, "last_s": t.last_s}
            for where, t in sorted(dict(self.stats.by_worker).items())
            if t.jobs
        }
        return {
            **self.executor.status(),
            "in_flight": in_flight,
            "waiting_for_part": waiting,
            "jobs": jobs,
        }

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
            "executor": self.executor_status(),
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

    With ``parts``, a FrameSet of a part the pipeline lacks waits for it, at most
    ``part_wait_s`` (see :class:`Worker`). With a ``store`` (the one ``sinks`` write to), the worker
    goes on counting from the station's last stored seq, answers a trigger
    already stored once, and serves the stored results on the station's
    history queryable (:mod:`service.history`). With a ``journal``, what it had accepted before
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
        executor: Executor | None = None,
        alarms: Iterable[AlarmSink] = (),
        fired_grace_s: float = FIRED_GRACE_S,
        parts: PartSource | None = None,
        part_wait_s: float = PART_WAIT_S,
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
            # Stored before published, as results are.
            alarms=[*alarms, zenoh_alarm_sink(session, keys)],
            journal=journal,
            metrics=metrics,
            cameras=[(c["name"], c["width"], c["height"]) for c in cals] or None,
            executor=executor,
            fired_grace_s=fired_grace_s,
            parts=parts,
            part_wait_s=part_wait_s,
        )
        if metrics is not None:
            own = {"line": keys.line, "station": station}
            metrics.collector(
                worker_collector(self.worker.stats, self.source.depth, self.source.capacity, **own)
            )
            metrics.collector(executor_collector(self.worker.executor_status, **own))
        self._state = "ready"
        self.token = session.liveliness().declare_token(keys.worker_token(station, self.id))
        self.heartbeat = bus.Heartbeat(
            session,
            keys.status(station),
            lambda: self.worker.status(self.id, self._state),
            period_s=heartbeat_s,
        )
        self.fired = bus.RingSubscriber(
            session, keys.fired(station), self._on_fired, capacity=4, name="fired-rx"
        )
        self.worker.start()
        self.heartbeat.publish()

    def _on_fired(self, sample: zenoh.Sample) -> None:
        try:
            doc = json.loads(sample.payload.to_bytes())
            next_seq, triggered_ns = doc["next_seq"], doc["triggered_ns"]
            if not all(type(v) is int and v >= 0 for v in (next_seq, triggered_ns)):
                raise ValueError("next_seq and triggered_ns must be whole numbers >= 0")
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("ignored a trigger count on %s: %s", sample.key_expr, exc)
            return
        self.worker.note_fired(next_seq, triggered_ns)

    def close(self) -> None:
        """Stop receiving, finish the job in hand, say goodbye on the status key."""
        self.fired.close()
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
