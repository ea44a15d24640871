"""The parts a station measures: its own, and those created over the API, taken from the store.

The station's configured parts (``[station] parts``) are loaded before it
reports ready. A part created over the API reaches it through the result
store (:class:`~service.store.StoredPart`: the spec and the CAD bytes),
whatever host the API runs on, with nothing read from the API's files:

- A FrameSet naming a part the station does not hold makes the worker ask
  for it (:meth:`StationParts.request`). The store is read in a thread of
  this module's own and the part loaded there by the station's
  :class:`~service.parts.PartRegistry` (its copy of the files in the
  station's own folder, the tree from the cache keyed by its hash or built
  once, the alignment model, a warm-up), off the worker's accounting thread.
  The FrameSet waits for it and is then measured, or answered ``error`` when
  the store does not know the part either or it cannot be loaded.
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

import logging
import threading
from collections.abc import Callable, Iterable, MutableMapping
from concurrent.futures import ThreadPoolExecutor

from .parts import LoadedPart, PartError, PartRegistry
from .store import ResultStore, StoredPart, StoreError

log = logging.getLogger(__name__)

PARTS_POLL_S = 2.0
"""How often a station asks the store whether the parts it took from it changed, s."""

PartDone = Callable[[str | None], None]
"""Told, once a part was asked for: None when the station's parts hold it, else why not."""

PartListener = Callable[[str, LoadedPart | None], None]
"""Told each part the station took from the store (None: it left, deleted in the store)."""


class StationParts:
    """Keeps a station's parts in step with the parts created over the API.

    Parameters
    ----------
    parts : mutable mapping of name to LoadedPart
        The station's parts, read by its pipelines; those it holds at the
        start are its own and never replaced from the store.
    store : ResultStore
    registry : PartRegistry
        Loads the store's parts (and, shared with the API in one process,
        hands over those the API loaded already).
    station : str
        For messages.
    poll_s : float
        See :data:`PARTS_POLL_S`.
    listeners : iterable of PartListener
        Told each part taken or dropped (the recorder's scenes, the charts).
    """

    def __init__(
        self,
        parts: MutableMapping[str, LoadedPart],
        store: ResultStore,
        registry: PartRegistry,
        *,
        station: str,
        poll_s: float = PARTS_POLL_S,
        listeners: Iterable[PartListener] = (),
    ) -> None:
        self.parts = parts
        self.store = store
        self.registry = registry
        self.station = station
        self.poll_s = poll_s
        self.listeners = list(listeners)
        self._own = frozenset(parts)
        self._lock = threading.Lock()
        self._taken: dict[str, str] = {}  # name -> key of the revision the station measures
        self._failed: dict[str, tuple[str, str]] = {}  # name -> (key, why it did not load)
        self._asked: dict[str, list[PartDone]] = {}  # parts being fetched, and who waits
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="parts-load")
        self._stop = threading.Event()
        self._poller = threading.Thread(target=self._poll, name="parts-poll", daemon=True)
        self._poller.start()

    def request(self, name: str, done: PartDone) -> None:
        """Have part ``name`` taken from the store (any thread); ``done`` is told once
        :attr:`parts` holds it or it cannot be had (at once when it is there)."""
        if name in self.parts:
            done(None)
            return
        if self._ask(name, done):
            self._pool.submit(self._fetch, name)

    def close(self) -> None:
        """Stop following the store (a load under way finishes first)."""
        self._stop.set()
        self._poller.join(10)
        self._pool.shutdown(wait=True, cancel_futures=True)

    # ------------------------------------------------------------------ loading

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
        for done in waiting:
            done(why)

    def _take(self, name: str) -> str | None:
        key = self.store.part_keys().get(name)
        if key is None:
            own = ", ".join(sorted(self._own)) or "none"
            return (
                f"unknown part {name!r}: neither a part of station {self.station} "
                f"(its parts: {own}) nor one created over the API"
            )
        with self._lock:
            if self._taken.get(name) == key:
                return None
            failed = self._failed.get(name)
        if failed is not None and failed[0] == key:
            return failed[1]  # that revision does not load; a new one is tried again
        stored = self.store.part(name)  # the CAD comes only now: it may weigh megabytes
        if stored is None:
            return f"part {name!r} was deleted meanwhile"
        return self._load(stored)

    def _load(self, stored: StoredPart) -> str | None:
        name = stored.name
        log.info("part %s: revision %d taken from the store (%s)", name, stored.revision,
                 stored.key)  # fmt: skip
        try:
            job = self.registry.adopt(stored)
            if job is not None:
                self.registry.wait(job.id)
            loaded = self.registry.get(name)
        except (PartError, ValueError, OSError) as exc:
            why = f"part {name!r} (revision {stored.revision}) cannot be measured: {exc}"
            log.error("%s", why)
            with self._lock:
                self._failed[name] = (stored.key, why)
            return why
        # One assignment: a pipeline reading the parts sees the old revision or the new one.
        self.parts[name] = loaded
        with self._lock:
            self._taken[name] = stored.key
            self._failed.pop(name, None)
        self._tell(name, loaded)
        return None

    def _drop(self, name: str) -> None:
        log.info("part %s was deleted in the store: the station measures it no more", name)
        self.parts.pop(name, None)
        with self._lock:
            self._taken.pop(name, None)
        self.registry.forget(name)
        self._tell(name, None)

    def _tell(self, name: str, part: LoadedPart | None) -> None:
        for listen in self.listeners:
            try:
                listen(name, part)
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
                self._pool.submit(self._drop, name)
            elif self._ask(name, None):
                self._pool.submit(self._fetch, name)
