"""Measurements asked for over the API, bounded so they cannot starve the line.

An upload is admitted before its body is read: at most ``running`` measure at
once and ``waiting`` more wait for a turn; beyond that the API answers 503
``busy`` with ``Retry-After``, and nothing of the request is parsed. Admitted
measurements run on threads of their own at a lower CPU priority (a higher
nice value, per thread on Linux), so on a loaded machine the station's worker
gets the cores first.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import os
import threading
from collections.abc import Callable
from typing import Any, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")

NICE = 10
"""How much lower than the line an API measurement runs (nice increment)."""


def _lower_priority() -> None:
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), NICE)
    except (AttributeError, OSError) as exc:  # not Linux, or not allowed
        log.info("API measurements run at the line's priority: %s", exc)


class Busy(Exception):
    """No room for another measurement; ``retry_after_s`` is a fair wait."""

    def __init__(self, retry_after_s: int) -> None:
        super().__init__("busy")
        self.retry_after_s = retry_after_s


class MeasureGate:
    """Admission and a low-priority pool for API measurements.

    Parameters
    ----------
    running : int
        Measurements at once (threads of the pool).
    waiting : int
        Admitted requests that may wait for a thread.
    """

    def __init__(self, running: int, waiting: int) -> None:
        if running < 1 or waiting < 0:
            raise ValueError("running must be at least 1 and waiting at least 0")
        self.running = running
        self.capacity = running + waiting
        self._admitted = 0
        self._lock = threading.Lock()
        self._pool = concurrent.futures.ThreadPoolExecutor(
            running, thread_name_prefix="api-measure", initializer=_lower_priority
        )
        self.refused = 0

    def admit(self) -> None:
        """Take a place or raise :class:`Busy`; pair with :meth:`leave`."""
        with self._lock:
            if self._admitted >= self.capacity:
                self.refused += 1
                raise Busy(retry_after_s=5)
            self._admitted += 1

    def leave(self) -> None:
        with self._lock:
            self._admitted -= 1

    @property
    def admitted(self) -> int:
        with self._lock:
            return self._admitted

    async def run(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run ``fn`` on the gate's pool and wait for it without blocking the event loop."""
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._pool, lambda: fn(*args, **kwargs))

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
