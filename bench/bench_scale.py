"""Scale-out: parts per second in process, and on one and two single-threaded Dask workers.

The line's station as ``configs/line.toml`` sets it up (the flash rig's full
frames, guided matching, the demo panel alone as the line bench holds it,
loaded by ``Station.load``),
measuring the same pre-rendered FrameSets through each executor the
station's worker can use, with the worker's own bound on jobs in flight
(the executor's slots: 1 in process, the cluster's threads + 1 on Dask):

- ``in-process``: in this process, one at a time (what ``make run`` does);
- ``dask local:1`` and ``dask local:2``: a ``LocalCluster`` of one and of two
  single-threaded worker processes on this host, the station loaded on each
  by the worker plugin before timing starts (its time is printed apart).

Per executor: parts per second (wall), CPU seconds per part (this process
and the cluster's worker processes, every thread) and the cores they kept
busy (CPU over wall time: what the machine gave, with whatever else runs on
it), the median time of a measurement where it ran, and the dispatch
overhead per job: the median of
(round trip - measuring time), one job in flight at a time so that nothing
queues. Every executor's statuses and comparison-point deviations are
checked against the in-process ones (to 1e-6 mm). Last, the 2-worker /
1-worker ratio: on this 2-core machine 2 is the limit, less whatever else
runs (the load average is printed).

Environment: BENCH_SMOKE=1 (4 parts instead of 12), BENCH_SCALE_PARTS,
BENCH_SCALE_OVERHEAD_JOBS (default 5), BENCH_SCALE_GUIDED (default: the
line's setting).

Run: ``python -m bench.bench_scale`` (or ``make bench BENCH=scale``).
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

TOLERANCE_MM = 1e-6


@dataclass
class Run:
    """What one executor did."""

    name: str
    wall_s: float = 0.0
    cpu_s: float = 0.0
    setup_s: float = 0.0
    results: list[Any] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    overhead_s: list[float] = field(default_factory=list)

    @property
    def parts_per_s(self) -> float:
        return len(self.results) / self.wall_s


def _cluster_cpu(client: Any) -> float:
    """CPU seconds of a Dask cluster's worker processes so far (0 without one)."""
    if client is None:
        return 0.0
    return float(sum(client.run(time.process_time).values()))


def measure(
    executor: Any, sets: list[Any], run: Run, overhead_jobs: int, client: Any = None
) -> None:
    """Every FrameSet through ``executor`` with its slots in flight, then the overhead;
    ``client``: the Dask cluster's, whose workers' CPU time counts too."""
    cpu0, cluster0 = time.process_time(), _cluster_cpu(client)
    t0 = time.perf_counter()
    by_seq: dict[int, Any] = {}
    pending: dict[Future[Any], int] = {}
    todo = iter(sets)
    more = True
    while more or pending:
        while more and len(pending) < executor.slots():
            fs = next(todo, None)
            if fs is None:
                more = False
                break
            pending[executor.submit(fs)] = fs.seq
        done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
        for f in done:
            m = f.result()
            by_seq[pending.pop(f)] = m
            run.seconds.append(m.seconds)
    run.wall_s = time.perf_counter() - t0
    run.cpu_s = time.process_time() - cpu0 + _cluster_cpu(client) - cluster0
    run.results = [by_seq[fs.seq].outcome.result for fs in sets]
    for fs in sets[:overhead_jobs]:  # one at a time: the round trip, no queue
        t = time.perf_counter()
        m = executor.submit(fs).result()
        run.overhead_s.append(time.perf_counter() - t - m.seconds)


def differences(a: Any, b: Any) -> list[str]:
    """How result ``a`` differs from ``b``: status, or a deviation beyond the tolerance."""
    out = []
    if a.status != b.status:
        out.append(f"seq {a.seq}: status {a.status.value} vs {b.status.value}")
    for pa, pb in zip(a.comparison, b.comparison, strict=True):
        da, db = pa.deviation_mm, pb.deviation_mm
        if (da is None) != (db is None) or (
            da is not None and db is not None and abs(da - db) > TOLERANCE_MM
        ):
            out.append(f"seq {a.seq}: {pa.name} {da} vs {db} mm")
    return out


def main() -> int:
    from bench.bench_line import line_config
    from service.config import load_line_config, parse_dask_address
    from service.dask_executor import DaskExecutor
    from service.executor import InProcessExecutor
    from service.line import Station

    smoke = os.environ.get("BENCH_SMOKE") == "1"
    n_parts = int(os.environ.get("BENCH_SCALE_PARTS", "4" if smoke else "12"))
    overhead_jobs = min(n_parts, int(os.environ.get("BENCH_SCALE_OVERHEAD_JOBS", "5")))
    guided = os.environ.get("BENCH_SCALE_GUIDED")

    with tempfile.TemporaryDirectory() as tmp:
        overrides: dict[tuple[str, str], Any] = {("storage", "data_dir"): tmp}
        if guided is not None:
            overrides[("station", "guided_matching")] = guided == "1"
        cfg = load_line_config(line_config(Path(tmp), Path(tmp) / "trees"), overrides=overrides)
        station = Station.load(cfg)
        try:
            pipeline = station.pipeline()
            sim = station.simulated_rig()
            t_ns = 1_800_000_000_000_000_000
            sets = [sim.capture(seq, t_ns + seq * 10**9) for seq in range(n_parts)]
            warm = sim.capture(n_parts, t_ns + n_parts * 10**9)
            cam = station.stages.calibrations()[0]
            print(
                f"{n_parts} parts of {next(iter(station.parts))}, 4 x {cam['width']} x "
                f"{cam['height']} px, guided matching {station.stages.guided}; load average "
                f"(1 min) {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores",
                flush=True,
            )
            runs = []
            run = Run("in-process")
            measure(InProcessExecutor(pipeline), sets, run, overhead_jobs)
            runs.append(run)
            for n in (1, 2):
                run = Run(f"dask local:{n}")
                t0 = time.perf_counter()
                ex = DaskExecutor.connect(
                    parse_dask_address(f"local:{n}"), pipeline, warm_up=warm,
                    trees_dir=cfg.storage.trees_path(),
                )  # fmt: skip
                run.setup_s = time.perf_counter() - t0
                try:
                    measure(ex, sets, run, overhead_jobs, ex.client)
                finally:
                    ex.close()
                runs.append(run)
        finally:
            station.close()

    base = runs[0]
    header = (
        f"{'executor':<16} {'parts/s':>8} {'CPU s/part':>11} {'cores busy':>11} "
        f"{'measure s':>10} {'dispatch ms':>12} {'set-up s':>9} {'same results':>13}"
    )
    print(header)
    ok = True
    for run in runs:
        pairs = zip(run.results, base.results, strict=True)
        diffs = [d for a, b in pairs for d in differences(a, b)]
        ok &= not diffs
        print(
            f"{run.name:<16} {run.parts_per_s:8.3f} {run.cpu_s / len(run.results):11.2f} "
            f"{run.cpu_s / run.wall_s:11.2f} {statistics.median(run.seconds):10.2f} "
            f"{statistics.median(run.overhead_s) * 1e3:12.1f} {run.setup_s:9.1f} "
            f"{'yes' if not diffs else 'NO':>13}"
        )
        for d in diffs[:5]:
            print(f"    {d}")
    statuses = ", ".join(f"{s}: {n}" for s, n in _counts(base.results).items())
    print(f"statuses (every executor): {statuses}")
    one, two = runs[1], runs[2]
    ratio = two.parts_per_s / one.parts_per_s
    print(
        f"2 workers / 1 worker: {ratio:.2f}x parts per second "
        f"(limit on {os.cpu_count()} cores: {min(2, os.cpu_count() or 1)}x); "
        f"1 worker / in-process: {one.parts_per_s / base.parts_per_s:.2f}x"
    )
    print(f"check: every executor gives the same results to {TOLERANCE_MM} mm: "
          f"{'yes' if ok else 'NO'}")  # fmt: skip
    return 0 if ok else 1


def _counts(results: list[Any]) -> dict[str, int]:
    out: dict[str, int] = {}
    for r in results:
        out[r.status.value] = out.get(r.status.value, 0) + 1
    return out


if __name__ == "__main__":
    raise SystemExit(main())
