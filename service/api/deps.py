"""What the routes work with, gathered in one object on ``app.state``."""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

from fastapi import Depends, Path, Query, Request

from ..config import LineConfig
from ..models import InspectionResult
from ..names import NAME_MAX_LEN, NAME_PATTERN, NAME_RULE
from ..parts import PartRegistry
from ..store import DeviationArchive, ResultStore
from .events import ResultHub
from .gate import MeasureGate
from .measurer import UploadMeasurer
from .metrics import Metrics

log = logging.getLogger(__name__)

PartPath = Annotated[
    str,
    Path(pattern=NAME_PATTERN, max_length=NAME_MAX_LEN, description=f"A part name: {NAME_RULE}"),
]
"""A part name in a route's path, checked before any route code sees it."""

PartQuery = Annotated[
    str | None,
    Query(pattern=NAME_PATTERN, max_length=NAME_MAX_LEN, description=f"A part name: {NAME_RULE}"),
]
"""An optional part name in a query string."""

NameQuery = Annotated[
    str | None,
    Query(pattern=NAME_PATTERN, max_length=NAME_MAX_LEN, description=f"A name: {NAME_RULE}"),
]
"""An optional serial or station name in a query string."""

Pipeline = Callable[..., Any]
"""``pipeline(part, points, trigger, *, frame) -> Outcome``, as ``results.measure_upload``."""


@dataclass(eq=False)
class Services:
    """Everything a request may need; built by ``create_app``."""

    settings: LineConfig
    store: ResultStore
    parts: PartRegistry
    pipeline: Pipeline
    hub: ResultHub
    archive: DeviationArchive | None
    metrics: Metrics
    gate: MeasureGate
    measurer: UploadMeasurer | None
    checks: Mapping[str, Callable[[], bool]] = field(default_factory=dict)

    def record(self, result: InspectionResult, points: Any = None, distances: Any = None) -> None:
        """Keep a new result: per-point arrays first, then the row, then tell the streams.

        The arrays go first so that a client reacting to the row or the event
        finds the colour map already there.
        """
        if self.archive is not None and points is not None and distances is not None:
            try:
                self.archive.save(result.id, points, distances)
            except OSError as exc:  # a full disk must not lose the result itself
                log.error("deviations of %s not kept: %s", result.id, exc)
        self.store.put(result)
        self.metrics.inc(
            "inspection_results_total", "Results produced through this API process.",
            status=result.status.value, part=result.part,
        )  # fmt: skip
        total_ms = result.timings_ms.get("total")
        if total_ms is not None:
            self.metrics.observe(
                "inspection_duration_seconds", "Time to inspect one cloud.", total_ms / 1e3
            )
        self.hub.publish(result)


def services(request: Request) -> Services:
    svc: Services = request.app.state.services
    return svc


ServicesDep = Annotated[Services, Depends(services)]
"""Route parameter type giving the :class:`Services`."""
