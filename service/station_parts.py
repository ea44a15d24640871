"""The parts a station measures: its own, and those created over the API, taken from the store.

The station's configured parts (``[station] parts``) are loaded before it
reports ready. A part created over the API reaches it through the result
store (:class:`~service.store.StoredPart`: the spec and the CAD bytes),
whatever host the API runs on, with nothing read from the API's files:

- A FrameSet naming a part the station does not hold makes the worker ask
  for it (:meth:`StationParts.request`). The store is read in a thread of
  this module's own, through a connection of its own (a CAD may weigh
  megabytes: the worker's sinks must not wait behind it), and the part
  loaded there by the station's :class:`~service.parts.PartRegistry` (its
  copy of the files in the station's own folder, the tree from the cache
  keyed by its hash or built once, the alignment model, a warm-up), off the
  worker's accounting thread. The FrameSet waits for it, at most
  ``[station] part_wait_s`` (the worker's deadline; the load is waited for
  as long), and is then measured, or answered ``error`` when the store does
  not know the part either or it cannot be loaded.
- A revision whose load failed on the part itself (its CAD or spec does not
  load, a configured part or an upload of the station has its name, the
  station's path cannot judge it) is not tried again; a new revision is,
  even of the same files. A load that failed on something that passes (a
  full disk, an unwritable tree cache, the store out of reach) is tried
  again :data:`RETRY_S` later; FrameSets meanwhile are answered with it.
- A thread compares the store's part keys with those the station took,
  every :data:`PARTS_POLL_S`: a part created again (another revision) is
  loaded anew and replaces the old one once it is ready, so a FrameSet is
  measured with whole revisions, never half of each; a part deleted leaves
  the station's parts, and its later FrameSets are answered ``error``.

The station's parts are one dict that every pipeline of the station reads
(:attr:`service.line.Station.parts`); this module is the only writer once
the station runs, and replaces an entry in one assignment.
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable, MutableMapping
from dataclasses import dataclass

from .parts import (
    LoadedPart,
    PartBroken,
    PartConflict,
    PartError,
    PartRegistry,
    PathConflict,
)
from .store import PartRevision, ResultStore, StoredPart, StoreError
from .worker import PART_WAIT_S

log = logging.getLogger(__name__)

PARTS_POLL_S = 2.0
"""How often a station asks the store whether the parts it took from it changed, s."""

RETRY_S = 10.0
"""How long after a load failed on something that passes it is tried again, s."""

PartDone = Callable[[str | None], None]
"""Told, once a part was asked for: None when the station's parts hold it, else why not."""

PartListener = Callable[[str, LoadedPart | None, StoredPart | None], None]
"""Told each part the station took from the store, with the revision it was loaded from
(None, None: it left, deleted in the store)."""


@dataclass(frozen=True)
class _Failure:
    """A revision that did not load: why, whether it fails again (``lasting``), when."""

    key: str
    revision: int
    why: str
    lasting: bool
    at: float
    """time.monotonic() of the failure."""


class StationParts:
    """Keeps a station's parts in step with the parts created over the API.

    Parameters
    ----------
    parts : mutable mapping of name to LoadedPart
        The station's parts, read by its pipelines; those it holds at the
        start are its own and never replaced from the store.
    store : ResultStore
        Read through by this object alone: pass a connection of its own, not
        the one the worker's sinks write through (see ``close_store``).
    registry : PartRegistry
        Loads the store's parts (and, shared with the API in one process,
        hands over those the API loaded already).
    station : str
        For messages.
    wait_s : float
        How long one load is waited for before the FrameSets asking for it are
        told it is still loading (the build goes on; the next request waits for
        it again). See :data:`PART_WAIT_S`.
    poll_s : float
        See :data:`PARTS_POLL_S`.
    retry_s : float
        See :data:`RETRY_S`.
    listeners : iterable of PartListener
        Told each part taken or dropped (the recorder, the charts).
    close_store : bool
        Close ``store`` with this object.
    """

    def __init__(
        self,
        parts: MutableMapping[str, LoadedPart],
        store: ResultStore,
        registry: PartRegistry,
        *,
        station: str,
        wait_s: float = PART_WAIT_S,
        poll_s: float = PARTS_POLL_S,
        retry_s: float = RETRY_S,
        listeners: Iterable[PartListener] = (),
        close_store: bool = False,
    ) -> None:
        self.parts = parts
        self.store = store
        self.registry = registry
        self.station = station
        self.wait_s = wait_s
        self.poll_s = poll_s
        self.retry_s = retry_s
        self.listeners = list(listeners)
        self._close_store = close_store
        self._own = frozenset(parts)
        self._lock = threading.Lock()
        self._taken: dict[str, str] = {}  # name -> key of the revision the station measures
        self._failed: dict[str, _Failure] = {}
        self._asked: dict[str, list[PartDone]] = {}  # parts being fetched, and who waits
        self._doing: dict[str, tuple[str, str | None]] = {}  # name -> (what, registry job)
        self._stop = threading.Event()
        # A daemon thread, not a pool: a tree build under way must not hold a stopping
        # process (a pool's threads are joined at the interpreter's exit).
        self._tasks: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._loader = threading.Thread(target=self._load_tasks, name="parts-load", daemon=True)
        self._loader.start()
        self._poller = threading.Thread(target=self._poll, name="parts-poll", daemon=True)
        self._poller.start()

    def request(self, name: str, done: PartDone) -> None:
        """Have part ``name`` taken from the store (any thread); ``done`` is told once
        :attr:`parts` holds it or it cannot be had (at once when it is there)."""
        if name in self.parts:
            done(None)
            return
        if self._stop.is_set():
            done(f"part {name!r}: station {self.station} is stopping")
            return
        if self._ask(name, done):
            self._tasks.put(functools.partial(self._fetch, name))

    def pending(self, name: str) -> str:
        """What getting part ``name`` is doing now (any thread, without waiting): for a
        FrameSet that gave up waiting for it."""
        with self._lock:
            doing = self._doing.get(name)
            asked = name in self._asked
        if doing is None:
            return "queued behind other parts' loads" if asked else "not being loaded"
        what, job_id = doing
        if job_id is not None:
            try:
                job = self.registry.job(job_id)
            except PartError:
                return what
            return f"{what}: {job.message} ({job.progress:.0%})"
        return what

    def close(self) -> None:
        """Stop following the store. A load under way is not waited for: it ends on its own
        and changes nothing any more."""
        self._stop.set()
        self._tasks.put(None)
        self._poller.join(10)
        if self._close_store:
            self.store.close()

    # ------------------------------------------------------------------ loading

    def _load_tasks(self) -> None:
        while True:
            task = self._tasks.get()
            if task is None:
                return
            try:
                task()
            except Exception:  # the thread must survive anything
                log.exception("parts: a load failed")

    def _ask(self, name: str, done: PartDone | None) -> bool:
        """Note who waits for ``name``; whether a fetch must start (none under way)."""
        with self._lock:
            first = name not in self._asked
            waiting = self._asked.setdefault(name, [])
            if done is not None:
                waiting.append(done)
            return first

    def _fetch(self, name: str) -> None:
        """Take the store's current revision of ``name``, then tell who waits."""
        why: str | None
        try:
            why = self._take(name)
        except StoreError as exc:
            why = f"part {name!r} could not be read from the store: {exc}"
            log.error("%s", why)
        except Exception as exc:  # the waiting FrameSets are answered whatever went wrong
            log.exception("part %s: taking it from the store failed", name)
            why = f"part {name!r} could not be taken from the store: {type(exc).__name__}: {exc}"
        with self._lock:
            waiting = self._asked.pop(name, [])
            self._doing.pop(name, None)
        for done in waiting:
            done(why)

    def _doing_now(self, name: str, what: str, job_id: str | None = None) -> None:
        with self._lock:
            self._doing[name] = (what, job_id)

    def _take(self, name: str) -> str | None:
        self._doing_now(name, "reading it from the store")
        current = self._current(name)
        if current is None:
            own = ", ".join(sorted(self._own)) or "none"
            return (
                f"unknown part {name!r}: neither a part of station {self.station} "
                f"(its parts: {own}) nor one created over the API"
            )
        with self._lock:
            if self._taken.get(name) == current.key:
                return None
            failed = self._failed.get(name)
        if (
            failed is not None
            and (failed.key, failed.revision) == (current.key, current.revision)
            and (failed.lasting or time.monotonic() - failed.at < self.retry_s)
        ):
            return failed.why  # a new revision is tried again, and this one after a while
        stored = self.store.part(name)  # the CAD comes only now: it may weigh megabytes
        if stored is None:
            return f"part {name!r} was deleted meanwhile"
        return self._load(stored)

    def _current(self, name: str) -> PartRevision | None:
        return next(
            (r for r in self.store.part_index() if r.name == name and r.retired_ns is None),
            None,
        )

    def _load(self, stored: StoredPart) -> str | None:
        name = stored.name
        log.info("part %s: revision %d taken from the store (%s)", name, stored.revision,
                 stored.key)  # fmt: skip
        which = f"part {name!r} (revision {stored.revision})"
        self._doing_now(name, f"{which}: writing its files")
        try:
            job = self.registry.adopt(stored)
            if job is not None:
                self._doing_now(name, f"{which}: loading", job.id)
                self.registry.wait(job.id, timeout_s=self.wait_s)
            loaded = self.registry.get(name)
        except TimeoutError:
            # Not a failure: the build goes on, and the next FrameSet waits for it again.
            return f"{which} is still loading after {self.wait_s:g} s: {self.pending(name)}"
        except (PartBroken, PartConflict, PathConflict, ValueError) as exc:
            return self._failure(stored, f"{which} cannot be measured: {exc}", lasting=True)
        except (PartError, OSError) as exc:
            why = f"{which} could not be loaded (tried again after {self.retry_s:g} s): {exc}"
            return self._failure(stored, why, lasting=False)
        # One assignment: a pipeline reading the parts sees the old revision or the new one.
        self.parts[name] = loaded
        with self._lock:
            self._taken[name] = stored.key
            self._failed.pop(name, None)
        self._tell(name, loaded, stored)
        return None

    def _failure(self, stored: StoredPart, why: str, *, lasting: bool) -> str:
        log.error("%s", why)
        with self._lock:
            self._failed[stored.name] = _Failure(
                stored.key, stored.revision, why, lasting, time.monotonic()
            )
        return why

    def _drop(self, name: str) -> None:
        log.info("part %s was deleted in the store: the station measures it no more", name)
        self.parts.pop(name, None)
        with self._lock:
            self._taken.pop(name, None)
        self.registry.forget(name)
        self._tell(name, None, None)

    def _tell(self, name: str, part: LoadedPart | None, stored: StoredPart | None) -> None:
        for listen in self.listeners:
            try:
                listen(name, part, stored)
            except Exception:
                log.exception("part listener %r failed for %s", listen, name)

    # ------------------------------------------------------------------ following the store

    def _poll(self) -> None:
        while not self._stop.wait(self.poll_s):
            self.check()

    def check(self) -> None:
        """Compare the parts taken from the store with the store's now (any thread): a
        part created again is loaded anew, one deleted is dropped (in the loading thread)."""
        with self._lock:
            taken = dict(self._taken)
        if not taken:
            return
        try:
            keys = self.store.part_keys()
        except StoreError as exc:  # the next round asks again
            log.warning("parts: the store cannot be read: %s", exc)
            return
        for name, key in taken.items():
            now = keys.get(name)
            if now == key:
                continue
            if now is None:
                self._tasks.put(functools.partial(self._drop, name))
            elif self._ask(name, None):
                self._tasks.put(functools.partial(self._fetch, name))
