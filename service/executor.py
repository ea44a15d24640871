"""Where a station's measurements run: an :class:`Executor`.

The station's worker stays the one accountant of its triggers (seq, journal,
exactly one result each, see :mod:`service.worker`); it hands each FrameSet
it accepted to an executor, which runs the pipeline's one measuring call
(:meth:`service.pipeline.Pipeline.run`, i.e. ``inspection.measure_frames``)
somewhere and hands back a :class:`Measured`:

- :class:`InProcessExecutor` (the default) measures in the calling thread,
  one FrameSet at a time: the future it returns is done when ``submit``
  returns;
- :class:`service.dask_executor.DaskExecutor` measures on the worker
  processes of a Dask cluster, several at once; its futures finish in
  whatever order the cluster finishes them.

An executor bounds nothing itself: :meth:`Executor.slots` says how many jobs
should be in flight at once, and the worker keeps to it, so that FrameSets
beyond it wait in the worker's own queue, where an overflow is answered
``missed``.
"""

from __future__ import annotations

import time
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Protocol

from .pipeline import Outcome, Pipeline
from .protocol import FrameSet

IN_PROCESS = "in-process"
"""The ``where`` of a measurement made in the worker's own process."""


class ExecutorError(Exception):
    """An executor cannot start: its cluster is unreachable, or cannot take the station."""


@dataclass(frozen=True, eq=False)
class Measured:
    """One FrameSet measured.

    Attributes
    ----------
    outcome : Outcome
    where : str
        Who measured it: :data:`IN_PROCESS`, or a Dask worker's address.
    seconds : float
        Time of the measurement where it ran, s.
    round_trip_s : float
        From ``submit`` to the result being back, s; less ``seconds``, the
        cost of dispatching (sending, queueing, returning).
    """

    outcome: Outcome
    where: str
    seconds: float
    round_trip_s: float


class Executor(Protocol):
    """Runs a station's measurements; see the module docstring."""

    kind: str
    """``in-process`` or ``dask``."""

    def slots(self) -> int:
        """Jobs that should be in flight at once (the cluster's threads and one more)."""

    def submit(self, fs: FrameSet) -> Future[Measured]:
        """Start measuring ``fs``; the future holds its :class:`Measured`.

        The future fails only when the measurement was lost (its cluster gave
        up on it); a FrameSet that cannot be measured is an ``error`` result.
        """

    def status(self) -> dict[str, Any]:
        """What runs the measurements now: ``kind``, ``workers``, ``threads``, ``slots``
        and, for a cluster, its address and each worker's threads and running jobs."""

    def close(self) -> None:
        """Release what the executor started (a cluster it started itself)."""


class InProcessExecutor:
    """Measures in the calling thread, with the worker's own pipeline: one at a time.

    Parameters
    ----------
    pipeline : Pipeline
    """

    kind = IN_PROCESS

    def __init__(self, pipeline: Pipeline) -> None:
        self.pipeline = pipeline

    def slots(self) -> int:
        return 1

    def submit(self, fs: FrameSet) -> Future[Measured]:
        t0 = time.perf_counter()
        outcome = self.pipeline.run(fs)
        seconds = time.perf_counter() - t0
        done: Future[Measured] = Future()
        done.set_result(Measured(outcome, IN_PROCESS, seconds, seconds))
        return done

    def status(self) -> dict[str, Any]:
        return {"kind": self.kind, "workers": 1, "threads": 1, "slots": 1}

    def close(self) -> None:
        """Nothing to release."""
