"""Clouds uploaded over the API, measured in processes of their own.

A measurement holds Python's interpreter lock for much of its time (the
sequence's orchestration, numpy operations that keep it), and in
``inspection run`` the API shares its process with the station's worker:
a large upload measured on a thread there delays every part of the line,
however low the thread's CPU priority, since the line's threads then wait
for the lock. So an upload is parsed and measured in a separate process,
at a lower CPU priority (a higher nice value), and only its result and the
few points the deviation archive keeps come back.

Each measuring process measures one upload at a time and keeps the parts it
has loaded (a tree from the shared tree cache, built there once otherwise),
keyed by the part's spec and CAD: a part changed under the same name is
loaded anew. The processes are started with the ``spawn`` method (a zenoh
session must not be forked) by :meth:`UploadMeasurer.start`, or else as
uploads come. A process that dies (killed, out of memory) while it measures
costs that upload an answer of 503; one found dead when an upload comes is
started again for it, at no cost but the time.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import queue
import signal
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import numpy as np

from inspection.measure import Frame, validate_cloud

from ..models import InspectionResult
from ..parts import LoadedPart, PartBundle
from ..results import Outcome, Trigger, measure_upload
from .clouds import parse_cloud
from .gate import NICE

log = logging.getLogger(__name__)

PARTS_KEPT = 4
"""Parts a measuring process keeps loaded (the most recently used)."""

STOP_S = 10.0
"""How long a measuring process is given to end by itself when the measurer closes, s."""


class MeasurerDied(RuntimeError):
    """The process measuring an upload ended before answering (killed, out of memory)."""


@dataclass(frozen=True, eq=False)
class UploadOutcome:
    """What a measuring process sends back: the result, and the points the archive keeps
    (CAD frame) with their deviations, or None without a fit."""

    result: InspectionResult
    points_cad: np.ndarray | None
    distances: np.ndarray | None


class _Slot:
    """One measuring process and the pipe it takes its uploads on."""

    def __init__(self) -> None:
        self.process: BaseProcess | None = None
        self.conn: Connection | None = None

    def alive(self) -> bool:
        return self.process is not None and self.process.is_alive()

    def ensure(self) -> None:
        """A running process: the one there was, or a new one."""
        if self.alive():
            return
        if self.process is not None:
            log.error("a measuring process ended (exit code %s): starting another",
                      self.process.exitcode)  # fmt: skip
            self.discard()
        ctx = multiprocessing.get_context("spawn")
        here, there = ctx.Pipe()
        self.process = ctx.Process(target=_serve, args=(there,), name="upload-measurer",
                                   daemon=True)  # fmt: skip
        self.process.start()
        there.close()
        self.conn = here

    def measure(self, job: tuple[Any, ...]) -> UploadOutcome:
        self.ensure()
        assert self.conn is not None and self.process is not None
        try:
            self.conn.send(job)
            ok, answer = self.conn.recv()
        except (EOFError, OSError) as exc:
            process = self.process
            self.discard()  # waits a moment for it to end
            how = f" (exit code {process.exitcode})" if process.exitcode is not None else ""
            raise MeasurerDied(
                f"the process measuring this upload ended before answering{how}"
            ) from exc
        if not ok:
            raise answer
        out: UploadOutcome = answer
        return out

    def discard(self) -> None:
        if self.conn is not None:
            self.conn.close()
        if self.process is not None:
            self.process.join(1.0)
        self.process, self.conn = None, None

    def stop(self) -> None:
        if self.conn is not None and self.alive():
            try:
                self.conn.send(None)
            except OSError:
                pass
        if self.process is not None:
            self.process.join(STOP_S)
            if self.process.is_alive():
                self.process.kill()
                self.process.join(STOP_S)
        self.discard()


class UploadMeasurer:
    """Measuring processes for API uploads, one upload at a time each.

    Parameters
    ----------
    processes : int
        Measuring processes (uploads measured at once). The caller admits no
        more uploads at once than that (:class:`~service.api.gate.MeasureGate`);
        more wait for a process.
    """

    def __init__(self, processes: int) -> None:
        if processes < 1:
            raise ValueError("processes must be at least 1")
        self.processes = processes
        self._slots = [_Slot() for _ in range(processes)]
        self._free: queue.SimpleQueue[_Slot] = queue.SimpleQueue()
        for slot in self._slots:
            self._free.put(slot)
        self._threads = ThreadPoolExecutor(processes, thread_name_prefix="upload-measurer")
        self._lock = threading.Lock()

    def start(self) -> None:
        """Start the processes now, in the background: each imports what it measures
        with while the API starts, so that the first upload pays only for its part."""
        self._threads.submit(self._start_all)

    def _start_all(self) -> None:
        with self._lock:
            for slot in self._slots:
                slot.ensure()

    async def measure(
        self,
        part: LoadedPart,
        data: bytes,
        trigger: Trigger,
        *,
        frame: Frame,
        trees_dir: Path,
        keep_points: int,
    ) -> UploadOutcome:
        """Parse ``data`` (NPY or PLY) and measure it as ``part``, in a measuring process.

        ``trees_dir``: the tree cache the part's tree is loaded from (built there
        once otherwise); at most ``keep_points`` points of the result come back,
        evenly strided as the deviation archive keeps them.

        Raises
        ------
        UnsupportedCloudFormat, inspection.InvalidInput
            As :func:`service.api.clouds.parse_cloud` and
            :func:`inspection.measure.validate_cloud` raise them.
        MeasurerDied
            The process ended before answering.
        """
        job = (PartBundle.of(part), data, trigger, frame, str(trees_dir), keep_points)
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._threads, self._measure, job)

    def _measure(self, job: tuple[Any, ...]) -> UploadOutcome:
        slot = self._free.get()
        try:
            with self._lock:
                slot.ensure()
            return slot.measure(job)
        finally:
            self._free.put(slot)

    def pids(self) -> list[int]:
        """The process ids of the measuring processes running now."""
        return sorted(
            s.process.pid for s in self._slots
            if s.process is not None and s.process.pid is not None and s.alive()
        )  # fmt: skip

    def close(self) -> None:
        """End the measuring processes (an upload being measured is waited for)."""
        self._threads.shutdown(wait=True, cancel_futures=True)
        for slot in self._slots:
            slot.stop()


# --------------------------------------------------------------------------- in the process

_parts: OrderedDict[str, LoadedPart] = OrderedDict()
"""The parts this measuring process has loaded, most recently used last."""


def _serve(conn: Connection) -> None:
    """A measuring process: uploads from ``conn`` one after the other, until None."""
    # The API stops it (None, or the pipe closing): a Ctrl-C that reaches the whole
    # process group must not cut an upload short before the API has answered it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        os.nice(NICE)
    except OSError as exc:  # not allowed: measure at the line's priority
        log.info("API measurements run at the line's priority: %s", exc)
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return  # the API went away
        if job is None:
            return
        try:
            answer: tuple[bool, Any] = (True, measure_in_process(*job))
        except Exception as exc:  # every failure goes back as the upload's answer
            answer = (False, exc)
        try:
            conn.send(answer)
        except Exception:  # an exception that does not pickle: its words go instead
            conn.send((False, RuntimeError(f"{type(answer[1]).__name__}: {answer[1]}"[:2000])))


def _loaded(part: PartBundle, trees_dir: Path) -> LoadedPart:
    loaded = _parts.get(part.key)
    if loaded is None:
        loaded = part.load(trees_dir)
        _parts[part.key] = loaded
        while len(_parts) > PARTS_KEPT:
            _parts.popitem(last=False)
    _parts.move_to_end(part.key)
    return loaded


def measure_in_process(
    part: PartBundle, data: bytes, trigger: Trigger, frame: Frame, trees_dir: str,
    keep_points: int,
) -> UploadOutcome:  # fmt: skip
    """One upload, in a measuring process: parsed, measured, and what comes back thinned
    to what the deviation archive keeps."""
    points = validate_cloud(parse_cloud(data))
    outcome: Outcome = measure_upload(_loaded(part, Path(trees_dir)), points, trigger, frame=frame)
    points_cad, distances = outcome.points_cad(), outcome.distances
    if points_cad is not None and distances is not None and len(points_cad) > keep_points:
        keep = np.linspace(0, len(points_cad) - 1, keep_points).round().astype(np.int64)
        points_cad, distances = points_cad[keep], distances[keep]
    return UploadOutcome(outcome.result, points_cad, distances)
