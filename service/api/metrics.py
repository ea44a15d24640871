"""Request metrics of the REST API, into the process's :class:`service.metrics.Metrics`."""

from __future__ import annotations

import time

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from ..metrics import CONTENT_TYPE, Metrics

__all__ = ["CONTENT_TYPE", "Metrics", "RequestMetrics"]


class RequestMetrics:
    """ASGI middleware counting requests by method, route template and status code."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        status = 500

        async def tracking_send(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
                # The router has put the matched route into the scope by now.
                route = getattr(scope.get("route"), "path", "unmatched")
                self.metrics.observe(
                    "http_request_duration_seconds", "Time to the response's start.",
                    time.perf_counter() - t0, route=route,
                )  # fmt: skip
            await send(message)

        try:
            await self.app(scope, receive, tracking_send)
        finally:
            route = getattr(scope.get("route"), "path", "unmatched")
            self.metrics.inc(
                "http_requests_total", "HTTP requests answered.",
                method=scope["method"], route=route, code=str(status),
            )  # fmt: skip
