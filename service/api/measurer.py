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
import multiprocessing.connection
import os
import queue
import signal
import threading
import traceback
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
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
from ..store import archived_rows
from .clouds import parse_cloud
from .gate import NICE

log = logging.getLogger(__name__)

PARTS_KEPT = 4
"""Parts a measuring process keeps loaded (the most recently used)."""

CLOSE_S = 30.0
"""How long the uploads being measured are given to finish when the measurer closes, s
(by default)."""

LOWEST_PRIORITY = 19
"""The largest nice value the kernel allows."""


class MeasurerDied(RuntimeError):
    """No measuring process answered the upload: the one measuring it ended first
    (killed, out of memory), none could be started, or the measurer is closing."""


@dataclass(frozen=True, eq=False)
class UploadOutcome:
    """What a measuring process sends back: the result, and the points the archive keeps
    (CAD frame) with their deviations, or None without a fit."""

    result: InspectionResult
    points_cad: np.ndarray | None
    distances: np.ndarray | None


class _Slot:
    """One measuring process and the pipe it takes its uploads on; used by one thread
    at a time (the one that took it from the measurer's free slots), but for the
    measurer's request to stop."""

    def __init__(self) -> None:
        self.process: BaseProcess | None = None
        self.conn: Connection | None = None
        self._sending = threading.Lock()  # an upload and the request to stop, never interleaved

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
        process = ctx.Process(target=_serve, args=(there, logging.getLogger().level),
                              name="upload-measurer", daemon=True)  # fmt: skip
        try:
            process.start()
        except OSError as exc:  # no memory, no process or file slots left
            here.close()
            raise MeasurerDied(f"no measuring process could be started: {exc}") from exc
        finally:
            there.close()
        _lower_priority(process)
        self.process, self.conn = process, here

    def measure(self, job: tuple[Any, ...]) -> UploadOutcome:
        try:
            self.ensure()
            try:
                self._send(job)
            except OSError:  # ended since ensure(), before it had the upload: once more
                self.discard()
                self.ensure()
                self._send(job)
            assert self.conn is not None
            ok, answer = self.conn.recv()
        except (EOFError, OSError) as exc:
            process = self.process
            self.discard()  # waits a moment for it to end
            how = ""
            if process is not None and process.exitcode is not None:
                how = f" (exit code {process.exitcode})"
            raise MeasurerDied(
                f"the process measuring this upload ended before answering{how}"
            ) from exc
        if not ok:
            raise answer
        out: UploadOutcome = answer
        return out

    def _send(self, job: tuple[Any, ...] | None) -> None:
        with self._sending:
            if self.conn is None:
                raise OSError("no measuring process")
            self.conn.send(job)

    def ask_to_stop(self) -> None:
        """Ask the process to end once it has answered the upload it measures, if any."""
        try:
            self._send(None)
        except OSError:
            pass  # ended already, or being replaced

    def discard(self) -> None:
        if self.conn is not None:
            self.conn.close()
        if self.process is not None:
            self.process.join(1.0)
        self.process, self.conn = None, None


def _lower_priority(process: BaseProcess) -> None:
    """Run ``process`` ``NICE`` lower than this thread, from its start (its imports too)."""
    assert process.pid is not None
    try:
        mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        os.setpriority(os.PRIO_PROCESS, process.pid, min(mine + NICE, LOWEST_PRIORITY))
    except (AttributeError, OSError) as exc:  # not Linux, or not allowed
        log.info("API measurements run at the line's priority: %s", exc)


class UploadMeasurer:
    """Measuring processes for API uploads, one upload at a time each.

    Parameters
    ----------
    processes : int
        Measuring processes (uploads measured at once). Uploads beyond that
        wait for a free process; the caller bounds how many may wait
        (:class:`~service.api.gate.MeasureGate`).
    close_s : float
        How long :meth:`close` gives the uploads being measured to finish, s.
    """

    def __init__(self, processes: int, *, close_s: float = CLOSE_S) -> None:
        if processes < 1 or not close_s >= 0.0:
            raise ValueError("processes must be at least 1 and close_s at least 0")
        self.close_s = close_s
        self._slots = [_Slot() for _ in range(processes)]
        self._free: queue.SimpleQueue[_Slot] = queue.SimpleQueue()
        for slot in self._slots:
            self._free.put(slot)
        self._threads = ThreadPoolExecutor(processes, thread_name_prefix="upload-measurer")
        self._closing = threading.Event()

    def start(self) -> None:
        """Start the processes now, in the background: each imports what it measures
        with while the API starts, so that the first upload pays only for its part."""
        self._threads.submit(self._start_all).add_done_callback(_log_failure)

    def _start_all(self) -> None:
        # Through the free slots, as an upload takes them: a slot measuring now is
        # left to the thread that has it.
        for _ in self._slots:
            slot = self._free.get()
            try:
                if not self._closing.is_set():
                    slot.ensure()
            finally:
                self._free.put(slot)

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
            The process ended before answering, or none could be started (the
            measurer closing, the system out of processes or memory).
        """
        if self._closing.is_set():
            raise MeasurerDied("the API is stopping")
        job = (PartBundle.of(part), data, trigger, frame, str(trees_dir), keep_points)
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._threads, self._measure, job)

    def _measure(self, job: tuple[Any, ...]) -> UploadOutcome:
        slot = self._free.get()
        try:
            if self._closing.is_set():
                raise MeasurerDied("the API is stopping")
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
        """End the measuring processes. An upload being measured is given ``close_s``
        to finish; past that its process is killed and the upload answered 503."""
        self._closing.set()
        processes = [s.process for s in self._slots if s.process is not None]
        for slot in self._slots:
            slot.ask_to_stop()
        multiprocessing.connection.wait([p.sentinel for p in processes], self.close_s)
        for process in processes:
            if process.is_alive():
                log.warning("a measuring process did not end in %.0f s: killed", self.close_s)
                process.kill()
        # The threads' waits have all ended now: with an answer, or with the pipe closed.
        self._threads.shutdown(wait=True, cancel_futures=True)
        for slot in self._slots:
            slot.discard()


def _log_failure(future: Future[None]) -> None:
    if (exc := future.exception()) is not None:
        log.error("the measuring processes could not be started: %s", exc)


# --------------------------------------------------------------------------- in the process

_parts: OrderedDict[str, LoadedPart] = OrderedDict()
"""The parts this measuring process has loaded, most recently used last."""


def _serve(conn: Connection, log_level: int) -> None:
    """A measuring process: uploads from ``conn`` one after the other, until None."""
    # The API stops it (None, or the pipe closing): a Ctrl-C that reaches the whole
    # process group must not cut an upload short before the API has answered it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=log_level, format=f"%(asctime)s %(levelname)s %(name)s "
                        f"[measuring process {os.getpid()}]: %(message)s")  # fmt: skip
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
            exc.add_note(f"in measuring process {os.getpid()}:\n{traceback.format_exc()}")
            answer = (False, exc)
        try:
            conn.send(answer)
        except OSError:
            return  # the API went away
        except Exception as exc:  # an answer that does not pickle (it is pickled before sending)
            try:
                conn.send((False, RuntimeError(f"an answer that could not be sent: {exc}"[:2000])))
            except OSError:
                return


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
    if points_cad is not None and distances is not None:
        keep = archived_rows(len(points_cad), keep_points)
        points_cad, distances = points_cad[keep], distances[keep]
    return UploadOutcome(outcome.result, points_cad, distances)
