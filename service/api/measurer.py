"""Clouds uploaded over the API, measured in processes of their own.

A measurement holds Python's interpreter lock for much of its time (the
sequence's orchestration, numpy operations that keep it), and in
``inspection run`` the API shares its process with the station's worker:
a large upload measured on a thread there delays every part of the line,
however low the thread's CPU priority, since the line's threads then wait
for the lock. So an upload is parsed and measured in a separate process,
at a lower CPU priority (a higher nice value), and only its result and the
few points the deviation archive keeps come back.

A measuring process keeps the parts it has loaded (a tree from the shared
tree cache, built there once otherwise), keyed by the part's spec and CAD:
a part changed under the same name is loaded anew. The processes are
started with the ``spawn`` method (a zenoh session must not be forked) by
:meth:`UploadMeasurer.start`, or else by the first upload. A process that
dies (killed, out of memory) costs the uploads it was measuring an answer
of 503; the pool is made again for the next one.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import threading
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from inspection.cad import CadModel
from inspection.measure import Frame, validate_cloud
from inspection.nurbs import NurbsModel

from ..config import PartSpec, canonical_hash
from ..models import InspectionResult
from ..parts import LoadedPart, part_from_cad
from ..results import Outcome, Trigger, measure_upload
from .clouds import parse_cloud
from .gate import NICE

log = logging.getLogger(__name__)

PARTS_KEPT = 4
"""Parts a measuring process keeps loaded (the most recently used)."""


class MeasurerDied(RuntimeError):
    """The process measuring an upload ended before answering (killed, out of memory)."""


@dataclass(frozen=True, eq=False)
class UploadPart:
    """A part as a measuring process receives it: its spec and CAD, no tree.

    ``key`` changes with the spec or the geometry, so that a part replaced
    under the same name is loaded anew.
    """

    spec: PartSpec
    cad: CadModel
    nurbs: NurbsModel | None
    key: str

    @classmethod
    def of(cls, part: LoadedPart) -> UploadPart:
        key = canonical_hash({"spec": part.spec.model_dump(mode="json"), "cad": part.cad.hash})
        return cls(part.spec, part.cad, part.model.nurbs, key)


@dataclass(frozen=True, eq=False)
class UploadOutcome:
    """What a measuring process sends back: the result, and the points the archive keeps
    (CAD frame) with their deviations, or None without a fit."""

    result: InspectionResult
    points_cad: np.ndarray | None
    distances: np.ndarray | None


class UploadMeasurer:
    """A pool of measuring processes for API uploads.

    Parameters
    ----------
    processes : int
        Measuring processes (uploads measured at once).
    """

    def __init__(self, processes: int) -> None:
        if processes < 1:
            raise ValueError("processes must be at least 1")
        self.processes = processes
        self._lock = threading.Lock()
        self._pool: ProcessPoolExecutor | None = None
        self.restarts = 0

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
        pool = self._running_pool()
        job = (UploadPart.of(part), data, trigger, frame, str(trees_dir), keep_points)
        try:
            return await asyncio.wrap_future(pool.submit(measure_in_process, *job))
        except BrokenProcessPool as exc:
            self._replace(pool)
            raise MeasurerDied("the process measuring this upload ended before answering") from exc

    def start(self) -> None:
        """Start the processes now, in the background: each imports what it measures
        with, so that the first upload pays only for loading its part."""
        pool = self._running_pool()
        for _ in range(self.processes):
            pool.submit(_ready)

    def pids(self) -> list[int]:
        """The process ids of the measuring processes running now."""
        with self._lock:
            pool = self._pool
        if pool is None:
            return []
        # The executor names its processes nowhere public; it keeps them by pid here.
        procs = dict(pool._processes or {})
        return sorted(pid for pid, p in procs.items() if p.is_alive())

    def close(self) -> None:
        """End the measuring processes (those measuring finish first)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def _running_pool(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    self.processes,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_lower_priority,
                )
            return self._pool

    def _replace(self, broken: ProcessPoolExecutor) -> None:
        with self._lock:
            if self._pool is broken:
                self._pool = None
                self.restarts += 1
                log.error("a measuring process died: starting another for the next upload")
        broken.shutdown(wait=False, cancel_futures=True)


# --------------------------------------------------------------------------- in the process

_parts: OrderedDict[str, LoadedPart] = OrderedDict()
"""The parts this measuring process has loaded, most recently used last."""


def _lower_priority() -> None:
    try:
        os.nice(NICE)
    except OSError as exc:  # not allowed: measure at the line's priority
        log.info("API measurements run at the line's priority: %s", exc)


def _ready() -> None:
    """Nothing: a job that makes a new process import this module (and what it imports)."""


def _loaded(part: UploadPart, trees_dir: Path) -> LoadedPart:
    loaded = _parts.get(part.key)
    if loaded is None:
        loaded = part_from_cad(part.spec, part.cad, trees_dir, nurbs=part.nurbs)
        _parts[part.key] = loaded
        while len(_parts) > PARTS_KEPT:
            _parts.popitem(last=False)
    _parts.move_to_end(part.key)
    return loaded


def measure_in_process(
    part: UploadPart, data: bytes, trigger: Trigger, frame: Frame, trees_dir: str,
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
