"""Prometheus metrics of every process of the line, with ``prometheus-client``.

One :class:`Metrics` per process holds a registry of its own (several apps in
one test process must not share the library's global one). The REST API
serves it on ``/metrics``; a process without an HTTP server (a worker on its
own) serves it on a port of its own (:meth:`Metrics.serve`). Names follow
Prometheus conventions: base units (seconds), ``_total`` for counters.

What a worker exposes (:func:`worker_collector` and :func:`executor_collector`,
read at each scrape, and the histograms it observes as it answers), every
series labelled with the worker's ``line`` and ``station``:

==============================================  =======================================
``inspection_worker_results_total``             results answered, by ``status``
``inspection_worker_missed_total``              missed triggers, by ``cause``
                                                (``queue_full``, ``never_arrived``)
``inspection_worker_alarms_total``              alarms raised, by ``kind``
``inspection_worker_duplicates_total``          triggers delivered again, answered once
``inspection_worker_lost_total``                measurements the executor never returned
``inspection_worker_queue_depth``               FrameSets waiting (gauge), and ``_capacity``
``inspection_stage_seconds``                    time of each measuring stage, by ``stage``
``inspection_latency_seconds``                  trigger to answered result
``inspection_executor_info``                    1, with the executor's ``kind``
``inspection_executor_workers``                 who measures (gauge): Dask workers, or 1
                                                in-process; ``_threads``, ``_slots`` and
                                                ``_in_flight`` beside it
``inspection_executor_cluster_threads``         each Dask worker's threads, by
                                                ``dask_worker`` (its address)
``inspection_executor_cluster_executing``       jobs each Dask worker runs now
``inspection_executor_job_seconds``             time of each measurement where it ran, by
                                                ``worker`` (a Dask worker's address, or
                                                ``in-process``); its ``_count`` is the jobs
``inspection_executor_dispatch_seconds``        a measurement's round trip less its own time
==============================================  =======================================

The API process adds its own (``inspection_results_stored``,
``inspection_ready``, ``http_requests_total``, ...); a line in one process
serves both on the API's ``/metrics``. docs/grafana-dashboard.json charts them.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
    start_http_server,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

log = logging.getLogger(__name__)

CONTENT_TYPE = CONTENT_TYPE_LATEST

DURATION_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
"""Seconds; spans a sub-10 ms fit to a slow multi-second upload."""

LATENCY_BUCKETS_S = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0, 30.0)
"""Seconds from trigger to result: the line's goal is a median of 1 s."""

Samples = Callable[[], Iterable[tuple[dict[str, str], float]]]


class _Read(Collector):
    """A collector whose samples a function returns at each scrape."""

    def __init__(self, collect: Callable[[], Iterable[Metric]]) -> None:
        self._collect = collect

    def collect(self) -> Iterator[Metric]:
        try:
            yield from self._collect()
        except Exception:  # a scrape must not fail because one source did
            log.exception("metrics collector failed")


class Metrics:
    """One process's metrics: counters and histograms made on first use, gauges read
    at scrape time."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self._lock = threading.Lock()
        self._counters: dict[str, Counter] = {}
        self._hists: dict[str, Histogram] = {}

    def inc(self, name: str, help_: str, value: float = 1.0, **labels: str) -> None:
        """Add ``value`` to counter ``name`` (its label names fixed by the first call)."""
        with self._lock:
            c = self._counters.get(name)
            if c is None:
                c = Counter(name, help_, sorted(labels), registry=self.registry)
                self._counters[name] = c
        (c.labels(**labels) if labels else c).inc(value)

    def observe(
        self,
        name: str,
        help_: str,
        value: float,
        *,
        buckets: tuple[float, ...] = DURATION_BUCKETS_S,
        **labels: str,
    ) -> None:
        """Add ``value`` to histogram ``name``."""
        with self._lock:
            h = self._hists.get(name)
            if h is None:
                h = Histogram(name, help_, sorted(labels), buckets=buckets, registry=self.registry)
                self._hists[name] = h
        (h.labels(**labels) if labels else h).observe(value)

    def gauge(self, name: str, help_: str, read: Samples) -> None:
        """Register a gauge whose samples ``read()`` returns at each scrape."""

        def collect() -> Iterator[Metric]:
            samples = list(read())
            names = sorted(samples[0][0]) if samples else []
            g = GaugeMetricFamily(name, help_, labels=names)
            for labels, v in samples:
                g.add_metric([labels[k] for k in names], v)
            yield g

        self.registry.register(_Read(collect))

    def collector(self, collect: Callable[[], Iterable[Metric]]) -> None:
        """Register a function returning whole metric families at each scrape."""
        self.registry.register(_Read(collect))

    def render(self) -> bytes:
        """Everything, in the Prometheus text exposition format."""
        return generate_latest(self.registry)

    def serve(self, host: str, port: int) -> Any | None:
        """Serve ``/metrics`` on ``host:port`` from a thread (0: any free port).

        Returns the server (its ``server_port`` is the port), or None when the
        port could not be bound: the process goes on without metrics, said in
        the log, rather than stop measuring.
        """
        try:
            server, _ = start_http_server(port, addr=host, registry=self.registry)
        except OSError as exc:
            log.error("metrics not served on %s:%d: %s", host, port, exc)
            return None
        log.info("metrics on http://%s:%d/metrics", host, server.server_port)
        return server


STATION_LABELS = ("line", "station")
"""The labels of every series of a station's worker: one Prometheus can tell stations apart."""


def worker_collector(
    stats: Any, depth: Callable[[], int], capacity: int, *, line: str, station: str
) -> Callable[[], Any]:
    """The metric families of a worker's :class:`~service.worker.WorkerStats`."""
    own = [line, station]

    def counts(name: str, help_: str, label: str, by: dict[str, int]) -> CounterMetricFamily:
        family = CounterMetricFamily(name, help_, labels=[*STATION_LABELS, label])
        for key, n in sorted(by.items()):
            family.add_metric([*own, key], n)
        return family

    def one(family: CounterMetricFamily | GaugeMetricFamily, value: float) -> Metric:
        family.add_metric(own, value)
        return family

    def collect() -> Iterator[Metric]:
        yield counts(
            "inspection_worker_results", "Results answered by the worker.", "status",
            stats.by_status,
        )  # fmt: skip
        yield counts(
            "inspection_worker_missed", "Triggers answered missed, by cause.", "cause",
            stats.missed_by_cause,
        )  # fmt: skip
        yield counts(
            "inspection_worker_alarms", "Alarms raised, by kind.", "kind", stats.alarms_by_kind
        )
        yield one(
            CounterMetricFamily(
                "inspection_worker_duplicates", "Triggers delivered again and answered once.",
                labels=STATION_LABELS,
            ),
            stats.duplicates,
        )  # fmt: skip
        yield one(
            CounterMetricFamily(
                "inspection_worker_lost",
                "Measurements the executor never returned (answered as errors).",
                labels=STATION_LABELS,
            ),
            stats.lost,
        )
        yield one(
            GaugeMetricFamily(
                "inspection_worker_queue_depth", "FrameSets waiting for the worker.",
                labels=STATION_LABELS,
            ),
            depth(),
        )  # fmt: skip
        yield one(
            GaugeMetricFamily(
                "inspection_worker_queue_capacity", "FrameSets that may wait.",
                labels=STATION_LABELS,
            ),
            capacity,
        )  # fmt: skip

    return collect


def executor_collector(
    status: Callable[[], dict[str, Any]], *, line: str, station: str
) -> Callable[[], Any]:
    """The gauges of a worker's executor (``status``: its
    :meth:`~service.worker.Worker.executor_status`); a Dask cluster's workers one by one."""
    own = [line, station]

    def collect() -> Iterator[Metric]:
        st = status()
        info = GaugeMetricFamily(
            "inspection_executor_info", "What measures: 1, labelled with the executor's kind.",
            labels=[*STATION_LABELS, "kind"],
        )  # fmt: skip
        info.add_metric([*own, str(st.get("kind", "unknown"))], 1)
        yield info
        for key, help_ in (
            ("workers", "Who measures: Dask workers (1 in-process)."),
            ("threads", "Measurements the executor's workers run at once."),
            ("slots", "Measurements the worker keeps in flight at most."),
            ("in_flight", "Measurements handed out and not yet answered."),
            ("waiting_for_part", "FrameSets waiting for their part to be taken from the store."),
        ):
            g = GaugeMetricFamily(f"inspection_executor_{key}", help_, labels=STATION_LABELS)
            g.add_metric(own, st.get(key, 0))
            yield g
        # Always yielded, empty in-process: the series' names do not depend on the executor.
        labels = [*STATION_LABELS, "dask_worker"]
        threads = GaugeMetricFamily(
            "inspection_executor_cluster_threads", "Threads of each Dask worker.", labels=labels
        )
        executing = GaugeMetricFamily(
            "inspection_executor_cluster_executing", "Jobs each Dask worker runs now.",
            labels=labels,
        )  # fmt: skip
        for address, w in sorted(st.get("cluster", {}).items()):
            threads.add_metric([*own, address], w.get("threads", 0))
            executing.add_metric([*own, address], w.get("executing", 0))
        yield threads
        yield executing

    return collect
