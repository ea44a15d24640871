"""Health, metrics and the live stream of results."""

from __future__ import annotations

from collections.abc import Iterator

from fastapi import APIRouter, Depends, Header
from fastapi.responses import JSONResponse, PlainTextResponse, StreamingResponse

from ...models import MAX_ID_LEN, ErrorBody, Health, InspectionResult, Status, software_version
from ...store import Filters, encode_cursor
from ..deps import PartQuery, Services, ServicesDep
from ..metrics import CONTENT_TYPE
from ..params import known_parameters

router = APIRouter(dependencies=[Depends(known_parameters)])

BACKLOG_PAGE = 200
"""Results a resuming stream reads from the store at a time."""


def _health(svc: Services) -> Health:
    checks = {"parts": svc.parts.ready()}
    for name, check in svc.checks.items():
        try:
            checks[name] = bool(check())
        except Exception:  # a failing probe means "not ready", not a 500
            checks[name] = False
    return Health(ready=all(checks.values()), checks=checks, version=software_version())


@router.get(
    "/v1/health",
    response_model=Health,
    summary="Readiness: 200 when every check passes (trees loaded, zenoh connected), else 503",
    responses={503: {"model": Health, "description": "Alive but not ready"}},
)
def health(svc: ServicesDep) -> JSONResponse:
    h = _health(svc)
    return JSONResponse(h.model_dump(), status_code=200 if h.ready else 503)


@router.get(
    "/v1/health/live", response_model=Health, summary="Liveness: 200 while the process answers"
)
def live(svc: ServicesDep) -> Health:
    return _health(svc)


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics")
def metrics(svc: ServicesDep) -> PlainTextResponse:
    return PlainTextResponse(svc.metrics.render(), media_type=CONTENT_TYPE)


@router.get(
    "/v1/stream",
    summary="Server-sent events: one `result` event per new result, one `alarm` per alarm; "
    "resumes after `Last-Event-ID`",
    response_class=StreamingResponse,
    responses={
        200: {"content": {"text/event-stream": {}}},
        422: {"model": ErrorBody, "description": "Invalid request"},
    },
)
async def stream(
    svc: ServicesDep,
    part: PartQuery = None,
    status: Status | None = None,
    last_event_id: str | None = Header(
        None,
        max_length=MAX_ID_LEN,
        description="The id of the last result received: every result stored after it "
        "comes first, oldest first",
    ),
) -> StreamingResponse:
    backlog = None
    if last_event_id is not None:
        last = svc.store.get(last_event_id)
        if last is not None:
            filters = Filters(part=part, status=status, since_ns=last.triggered_ns)

            def backlog() -> Iterator[list[InspectionResult]]:
                # A page at a time, so that a client back after a long outage costs a page
                # of memory. The last one received and those stored with it before it
                # are left out.
                cursor: str | None = encode_cursor(last.triggered_ns, last.id)
                while cursor is not None:
                    items, cursor = svc.store.list(
                        filters, limit=BACKLOG_PAGE, cursor=cursor, oldest_first=True
                    )
                    yield items

    events = svc.hub.stream(part=part, status=status.value if status else None, backlog=backlog)
    return StreamingResponse(
        events,
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
