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
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field

from ..models import Alarm, InspectionResult

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

    def publish(self, result: InspectionResult | Alarm) -> None:
        """Queue a result or an alarm for every open stream (thread-safe, never blocks).

        Alarms go to every stream, whatever it filters results by.
        """
        with self._lock:
            subs = list(self._subs)
        for sub in subs:
            if isinstance(result, InspectionResult):
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
        self,
        *,
        part: str | None = None,
        status: str | None = None,
        keepalive_s: float = 15.0,
        backlog: Callable[[], Iterator[list[InspectionResult]]] | None = None,
    ) -> AsyncIterator[str]:
        """Server-sent events: a ``ready`` event, then one ``result`` event per new result
        and one ``alarm`` event per alarm.

        ``backlog`` (called once subscribed, so nothing falls between) gives the
        results a resuming client missed, oldest first, in pages: they are sent
        first, and any of them also arriving live is sent once. A result event's ``id`` is
        the result's: a browser's EventSource sends the last one back as
        ``Last-Event-ID`` when it reconnects. A comment line is sent every
        ``keepalive_s`` without events so that proxies keep the connection
        open; a ``dropped`` event says how many a slow client missed.
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
            sent: set[str] = set()
            if backlog is not None:
                pages = backlog()
                while (page := await asyncio.to_thread(next, pages, None)) is not None:
                    for r in page:
                        sent.add(r.id)
                        yield _result_event(r)
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
                if isinstance(item, Alarm):
                    yield f"event: alarm\ndata: {item.model_dump_json()}\n\n"
                    continue
                assert isinstance(item, InspectionResult)
                if item.id in sent:
                    sent.discard(item.id)
                    continue
                yield _result_event(item)
        finally:
            with self._lock:
                self._subs.discard(sub)


def _result_event(r: InspectionResult) -> str:
    return f"event: result\nid: {r.id}\ndata: {r.model_dump_json()}\n\n"
