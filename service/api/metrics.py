"""Prometheus metrics in the text exposition format (version 0.0.4), written by hand.

A handful of counters, gauges and one histogram do not justify a dependency;
the format is small and stable. Names follow Prometheus conventions (base
units: seconds, ``_total`` for counters).
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterable

from starlette.types import ASGIApp, Message, Receive, Scope, Send

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

# Seconds; spans a sub-10 ms fit to a slow multi-second upload.
DURATION_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _labels(labels: Iterable[tuple[str, str]]) -> str:
    items = [f'{k}="{_escape(v)}"' for k, v in labels]
    return "{" + ",".join(items) + "}" if items else ""


def _num(x: float) -> str:
    if x == float("inf"):
        return "+Inf"
    return repr(float(x)) if not float(x).is_integer() else str(int(x))


class Metrics:
    """Counters and histograms updated by the API; gauges read at scrape time."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counters: dict[str, dict[tuple[tuple[str, str], ...], float]] = defaultdict(dict)
        self._help: dict[str, tuple[str, str]] = {}
        self._hist: dict[str, dict[tuple[tuple[str, str], ...], list[float]]] = defaultdict(dict)
        self._gauges: list[
            tuple[str, str, Callable[[], Iterable[tuple[dict[str, str], float]]]]
        ] = []

    def inc(self, name: str, help_: str, value: float = 1.0, **labels: str) -> None:
        key = tuple(sorted(labels.items()))
        with self._lock:
            self._help.setdefault(name, ("counter", help_))
            self._counters[name][key] = self._counters[name].get(key, 0.0) + value

    def observe(self, name: str, help_: str, value: float, **labels: str) -> None:
        """Add ``value`` to histogram ``name`` (buckets :data:`DURATION_BUCKETS_S`)."""
        key = tuple(sorted(labels.items()))
        with self._lock:
            self._help.setdefault(name, ("histogram", help_))
            h = self._hist[name].setdefault(key, [0.0] * (len(DURATION_BUCKETS_S) + 2))
            for i, b in enumerate(DURATION_BUCKETS_S):
                if value <= b:
                    h[i] += 1
            h[-2] += 1  # count
            h[-1] += value  # sum

    def gauge(
        self, name: str, help_: str, read: Callable[[], Iterable[tuple[dict[str, str], float]]]
    ) -> None:
        """Register a gauge whose samples ``read()`` returns at each scrape."""
        self._gauges.append((name, help_, read))

    def render(self) -> str:
        lines: list[str] = []
        with self._lock:
            for name in sorted(self._counters):
                kind, help_ = self._help[name]
                lines += [f"# HELP {name} {help_}", f"# TYPE {name} {kind}"]
                for key, v in sorted(self._counters[name].items()):
                    lines.append(f"{name}{_labels(key)} {_num(v)}")
            for name in sorted(self._hist):
                kind, help_ = self._help[name]
                lines += [f"# HELP {name} {help_}", f"# TYPE {name} histogram"]
                for key, h in sorted(self._hist[name].items()):
                    for i, b in enumerate(DURATION_BUCKETS_S):
                        lines.append(
                            f"{name}_bucket{_labels((*key, ('le', _num(b))))} {_num(h[i])}"
                        )
                    lines.append(f"{name}_bucket{_labels((*key, ('le', '+Inf')))} {_num(h[-2])}")
                    lines.append(f"{name}_count{_labels(key)} {_num(h[-2])}")
                    lines.append(f"{name}_sum{_labels(key)} {_num(h[-1])}")
        for name, help_, read in self._gauges:
            lines += [f"# HELP {name} {help_}", f"# TYPE {name} gauge"]
            for labels, v in read():
                lines.append(f"{name}{_labels(sorted(labels.items()))} {_num(v)}")
        return "\n".join(lines) + "\n"


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
