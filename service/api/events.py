"""In-process fan-out of new results to the API's server-sent-event streams.

Whoever produces results (the API's own uploads, the worker in the same
process, a zenoh subscriber in a separate API process) calls
:meth:`ResultHub.publish` from any thread; each open stream has its own
bounded queue on the event loop. A stream that falls behind loses its oldest
events (and is told how many), it never slows the producers down.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import AsyncIterator
from dataclasses import dataclass, field

from ..models import InspectionResult

log = logging.getLogger(__name__)

_CLOSED = object()


@dataclass(eq=False)
class _Subscriber:
    loop: asyncio.AbstractEventLoop
    queue: asyncio.Queue[object]
    dropped: int = 0
    part: str | None = None
    status: str | None = None


@dataclass(eq=False)
class ResultHub:
    """Broadcasts results to the open streams.

    Parameters
    ----------
    queue_size : int
        Events buffered per stream before the oldest are dropped.
    """

    queue_size: int = 256
    _subs: set[_Subscriber] = field(default_factory=set)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _closed: bool = False

    @property
    def subscribers(self) -> int:
        with self._lock:
            return len(self._subs)

    def publish(self, result: InspectionResult) -> None:
        """Queue ``result`` for every open stream (thread-safe, never blocks)."""
        with self._lock:
            subs = list(self._subs)
        for sub in subs:
            if sub.part is not None and result.part != sub.part:
                continue
            if sub.status is not None and result.status.value != sub.status:
                continue
            try:
                sub.loop.call_soon_threadsafe(self._offer, sub, result)
            except RuntimeError:  # the stream's loop is closed
                with self._lock:
                    self._subs.discard(sub)

    @staticmethod
    def _offer(sub: _Subscriber, item: object) -> None:
        if sub.queue.full():
            sub.queue.get_nowait()
            sub.dropped += 1
        sub.queue.put_nowait(item)

    def close(self) -> None:
        """End every stream (at shutdown, so the server can stop)."""
        with self._lock:
            self._closed = True
            subs = list(self._subs)
        for sub in subs:
            try:
                sub.loop.call_soon_threadsafe(self._offer, sub, _CLOSED)
            except RuntimeError:
                pass

    async def stream(
        self, *, part: str | None = None, status: str | None = None, keepalive_s: float = 15.0
    ) -> AsyncIterator[str]:
        """Server-sent events: a ``ready`` event, then one ``result`` event per new result.

        A comment line is sent every ``keepalive_s`` without results so that
        proxies keep the connection open; a ``dropped`` event says how many
        results a slow client missed.
        """
        sub = _Subscriber(
            loop=asyncio.get_running_loop(),
            queue=asyncio.Queue(self.queue_size),
            part=part,
            status=status,
        )
        with self._lock:
            if self._closed:
                return
            self._subs.add(sub)
        try:
            # Tells the client that it is subscribed: what it triggers from
            # now on will be streamed.
            yield "event: ready\ndata: {}\n\n"
            while True:
                try:
                    item = await asyncio.wait_for(sub.queue.get(), keepalive_s)
                except TimeoutError:
                    yield ": keepalive\n\n"
                    continue
                if item is _CLOSED:
                    return
                if sub.dropped:
                    yield f'event: dropped\ndata: {{"count": {sub.dropped}}}\n\n'
                    sub.dropped = 0
                assert isinstance(item, InspectionResult)
                yield f"event: result\nid: {item.id}\ndata: {item.model_dump_json()}\n\n"
        finally:
            with self._lock:
                self._subs.discard(sub)
