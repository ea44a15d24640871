"""Health, metrics and the live stream of results."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse, PlainTextResponse, StreamingResponse

from ...models import ErrorBody, Health, Status, software_version
from ..deps import PartQuery, Services, ServicesDep
from ..metrics import CONTENT_TYPE

router = APIRouter()


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
    summary="Server-sent events: one `result` event per new result",
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
) -> StreamingResponse:
    events = svc.hub.stream(part=part, status=status.value if status else None)
    return StreamingResponse(
        events,
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
