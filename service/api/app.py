"""The REST API's app factory.

Nothing is created at import time: ``main`` builds the settings, the store
and the part registry, and passes them to :func:`create_app`. Routes live in
:mod:`service.api.routes`; errors are translated in :mod:`service.api.errors`.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable, Mapping
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from pydantic.json_schema import models_json_schema
from starlette.middleware.cors import CORSMiddleware

from .. import web
from ..config import AuthScope, LineConfig
from ..models import PartCreate, software_version
from ..parts import PartRegistry
from ..results import measure_upload
from ..store import DeviationArchive, ResultStore
from .access import OPEN_PATHS, WRITE_METHODS, Access, is_loopback, load_keys
from .deps import Pipeline, Services
from .errors import install_error_handlers
from .events import ResultHub
from .gate import MeasureGate
from .limits import BodySizeLimit
from .measurer import UploadMeasurer
from .methods import MethodRouting
from .metrics import Metrics, RequestMetrics
from .routes import inspections as inspection_routes
from .routes import parts as part_routes
from .routes import quality as quality_routes
from .routes import system as system_routes

log = logging.getLogger(__name__)


def create_app(
    settings: LineConfig,
    *,
    store: ResultStore,
    parts: PartRegistry,
    pipeline: Pipeline | None = None,
    measurer: UploadMeasurer | None = None,
    bus: ResultHub | None = None,
    archive: DeviationArchive | None = None,
    checks: Mapping[str, Callable[[], bool]] | None = None,
    metrics: Metrics | None = None,
) -> FastAPI:
    """Build the API.

    Parameters
    ----------
    settings : LineConfig
    store : ResultStore
        Where results are kept and read (the caller opens and closes it).
    parts : PartRegistry
        The parts and their trees (the caller preloads and closes it).
    pipeline : callable, optional
        ``pipeline(part, points, trigger, *, frame) -> Outcome``, run on a thread of
        this process; default: :func:`service.results.measure_upload` in measuring
        processes of their own (``measurer``).
    measurer : UploadMeasurer, optional
        The measuring processes of the uploads (the caller closes one it passes);
        default: ``[http] max_measurements`` of them, started and ended with the
        app. Not used with a ``pipeline``.
    bus : ResultHub, optional
        Fan-out of new results to ``/v1/stream``. Pass the one the worker or
        a zenoh subscriber publishes into; default: a new one, fed by the
        API's own uploads. Call its ``close()`` *before* stopping the server:
        uvicorn waits for open responses (event streams never end by
        themselves) before it runs the app's shutdown.
    archive : DeviationArchive, optional
        Per-point deviations (for colour maps); default: under the data dir.
    checks : mapping of name to callable() -> bool, optional
        Extra readiness checks (e.g. ``{"zenoh": bus_connected}``); the
        part registry's readiness is always checked.
    metrics : Metrics, optional
        The process's metrics, served on ``/metrics`` (a worker in the same
        process adds its own to them); default: a new set.
    """
    hub = bus if bus is not None else ResultHub()
    if archive is None:
        archive = DeviationArchive(
            settings.storage.deviations_path(), max_bytes=settings.deviations_max_bytes()
        )
    own_measurer = None
    if pipeline is not None:
        measurer = None
    elif measurer is None:
        measurer = own_measurer = UploadMeasurer(settings.http.max_measurements)
    if metrics is None:
        metrics = Metrics()
    http = settings.http
    keys = load_keys(settings.api_keys_path())
    loopback = is_loopback(http.host)
    if not keys and http.auth is not AuthScope.none:
        log.warning("no API key configured: writes are %s",
                    "open to this machine only" if loopback else "refused")  # fmt: skip
    gate = MeasureGate(http.max_measurements, http.max_waiting_measurements)
    svc = Services(
        settings=settings,
        store=store,
        parts=parts,
        pipeline=pipeline or measure_upload,
        measurer=measurer,
        hub=hub,
        archive=archive,
        metrics=metrics,
        gate=gate,
        checks=dict(checks or {}),
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if own_measurer is not None:
            own_measurer.start()
        yield
        hub.close()  # ends open event streams so the server can stop
        gate.close()
        if own_measurer is not None:
            own_measurer.close()

    app = FastAPI(
        title="Inspection",
        summary="In-line shape inspection: parts, results, trends, live stream.",
        version=software_version(),
        lifespan=lifespan,
        # Served by service.web from the package's own copies: no CDN.
        docs_url=None,
        redoc_url=None,
    )
    app.state.services = svc
    install_error_handlers(app)
    app.include_router(system_routes.router)
    app.include_router(part_routes.router)
    app.include_router(inspection_routes.router)
    app.include_router(quality_routes.router)
    web.install(app)
    _register_gauges(svc)

    # Innermost: answers OPTIONS and 405 for a whole path, from the methods of every
    # router's routes (FastAPI keeps included routers apart: list each one here).
    app.add_middleware(
        MethodRouting,
        routers=[
            app.router,
            system_routes.router,
            part_routes.router,
            inspection_routes.router,
            quality_routes.router,
            web.router,
        ],  # fmt: skip
    )
    # A plain ASGI middleware (not BaseHTTPMiddleware): it does not buffer
    # streamed responses such as /v1/stream.
    app.add_middleware(RequestMetrics, metrics=svc.metrics)
    # Refuses oversized bodies before any parser reads them.
    app.add_middleware(BodySizeLimit, max_bytes=int(settings.http.max_upload_mb * 1e6))
    if http.allowed_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(http.allowed_origins),
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["Authorization", "X-API-Key", "Content-Type"],
        )
    # Outermost: who may ask is settled before anything else reads the request.
    app.add_middleware(
        Access, keys=keys, auth=AuthScope(http.auth).value, loopback=loopback,
        allowed_origins=list(http.allowed_origins), max_drain_bytes=int(http.max_upload_mb * 1e6),
    )  # fmt: skip
    _document_access(app, AuthScope(http.auth), keys_needed=bool(keys) or not loopback)
    svc.metrics.gauge(
        "inspection_api_measurements_admitted",
        "Uploads measuring or waiting for a turn.",
        lambda: [({}, float(gate.admitted))],
    )
    return app


def _document_access(app: FastAPI, auth: AuthScope, *, keys_needed: bool) -> None:
    """State in the OpenAPI schema what :class:`~service.api.access.Access` answers: the
    key it asks for (only where it does ask: a loopback server without keys does not),
    403 on writes, and 503 where uploads queue."""
    make_schema = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = make_schema()
        # The spec travels as a JSON text inside a multipart form, which OpenAPI cannot
        # reference: listed here, a client generator still makes a type of it.
        _, defs = models_json_schema(
            [(PartCreate, "validation")], ref_template="#/components/schemas/{model}"
        )
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        for name, model_schema in defs["$defs"].items():
            components.setdefault(name, model_schema)
        error = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}}
        if keys_needed and auth is not AuthScope.none:
            schema.setdefault("components", {})["securitySchemes"] = {
                "bearer": {"type": "http", "scheme": "bearer"},
                "apiKey": {"type": "apiKey", "in": "header", "name": "X-API-Key"},
            }
        for path, ops in schema.get("paths", {}).items():
            for method, op in ops.items():
                write = method.upper() in WRITE_METHODS
                responses = op.setdefault("responses", {})
                if write:
                    responses.setdefault("403", {
                        "description": "A write from a page of another origin, or writes "
                        "without any key configured on a server beyond loopback",
                        "content": error,
                    })  # fmt: skip
                guarded = auth is AuthScope.all or (auth is AuthScope.writes and write)
                if keys_needed and guarded and path not in OPEN_PATHS:
                    op["security"] = [{"bearer": []}, {"apiKey": []}]
                    responses.setdefault(
                        "401", {"description": "No API key, or not a valid one", "content": error}
                    )
                if path == "/v1/inspections" and method == "post":
                    responses.setdefault(
                        "503", {"description": "As many uploads as the API measures at once "
                                "are measuring or waiting (busy), or the process measuring "
                                "this one died (measurer_died): retry after Retry-After",
                                "content": error},
                    )  # fmt: skip
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def _register_gauges(svc: Services) -> None:
    m = svc.metrics

    def stored() -> list[tuple[dict[str, str], float]]:
        return [({"status": s}, float(n)) for s, n in svc.store.status_counts().items()]

    def parts_state() -> list[tuple[dict[str, str], float]]:
        states = svc.parts.states()
        return [({"part": p, "state": s}, 1.0) for p, s in states.items()]

    m.gauge("inspection_results_stored", "Results in the store, by status.", stored)
    m.gauge("inspection_parts", "Known parts and their tree state (1 per part).", parts_state)
    m.gauge("inspection_ready", "1 when the service is ready.", lambda: [({}, float(_ready(svc)))])
    m.gauge(
        "inspection_stream_clients",
        "Open /v1/stream connections.",
        lambda: [({}, float(svc.hub.subscribers))],
    )


def _ready(svc: Services) -> bool:
    if not svc.parts.ready():
        return False
    for check in svc.checks.values():
        try:
            if not check():
                return False
        except Exception:
            return False
    return True
