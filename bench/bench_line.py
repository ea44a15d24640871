"""The running line: stage times, trigger-to-result latency on zenoh, the highest sustained rate.

Runs ``inspection run`` (the whole simulated line on the flash rig: ingest,
worker, API, store, recorder in one process) as a subprocess and listens to
its results as a zenoh client, the way any subscriber would. Latency is the
result's arrival time minus its ``triggered_ns`` (both from this host's
clock): it includes rendering the frames (the simulated exposure), sending
them, reconstruction, alignment and deviations.

0. Stage times: ``simulate`` timed in this process before the line starts
   (the same call the ingest makes); ``reconstruct``, ``guide`` (the first
   alignment and the CAD-guided second reconstruction), ``align`` (the fit
   of the guided cloud) and ``deviations`` from the ``timings_ms`` of the
   results at 0.5 Hz, i.e. inside the running line, medians and p90. Beside them the CPU time of
   each stage (this process's, all threads), measured here one part at a
   time before the line starts: wall times on a shared machine wander with
   the load, CPU times much less.
1. At 0.5 Hz for ``BENCH_LINE_DURATION_S`` seconds (default 300; 40 with
   ``BENCH_SMOKE=1``): p50 and p99 latency; the goal is p50 <= 1 s and
   p99 <= 2 s on this 2-core machine.
2. Rising rates, a short window each: the highest rate the line sustains
   (no missed parts, and latency not growing from the first to the second
   half of the window).

Results count from the moment the line reports ready on ``/v1/health`` (its
trees loaded), after a warm-up of two results.

Every run shares one tree cache, so only the first builds the demo part's
tree and alignment model.

Environment: BENCH_SMOKE, BENCH_LINE_DURATION_S, BENCH_LINE_RATES_HZ
(comma-separated), BENCH_LINE_WINDOW_S, BENCH_LINE_CPU_PARTS (parts measured
for the CPU times; 0 skips them).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Window:
    period_s: float
    latencies_s: list[float] = field(default_factory=list)
    statuses: list[str] = field(default_factory=list)
    stages_ms: dict[str, list[float]] = field(default_factory=dict)
    started: float = 0.0

    @property
    def missed(self) -> int:
        return sum(s == "missed" for s in self.statuses)

    def pct(self, q: float) -> float:
        return float(np.percentile(self.latencies_s, q)) if self.latencies_s else float("nan")

    def sustained(self) -> bool:
        """No missed part, and the second half's median latency is not running away."""
        n = len(self.latencies_s)
        if n < 4 or self.missed:
            return False
        first, second = self.latencies_s[: n // 2], self.latencies_s[n // 2 :]
        return float(np.median(second)) <= 1.5 * float(np.median(first)) + 0.2


def _wait_ready(url: str, timeout_s: float) -> None:
    import urllib.error
    import urllib.request

    deadline = time.monotonic() + timeout_s
    pause = threading.Event()
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(url, timeout=5) as resp:
                if resp.status == 200:
                    return
        except (urllib.error.URLError, OSError):
            pass
        pause.wait(0.5)
    print(f"  (the line was not ready after {timeout_s:.0f} s; measuring anyway)", flush=True)


def line_config(tmp: Path, trees: Path) -> Path:
    """A copy of configs/line.toml whose installation paths are absolute and whose
    tree cache is ``trees`` (shared by every run of the bench)."""
    conf = ROOT / "configs"
    text = (conf / "line.toml").read_text()
    text = text.replace('parts_dir = "parts"', f'parts_dir = "{conf / "parts"}"')
    text = text.replace('trees_dir = "trees"', f'trees_dir = "{trees}"')
    path = tmp / "line.toml"
    path.write_text(text)
    return path


def run_line(period_s: float, duration_s: float, config: Path, warmup: int = 2) -> Window:
    """Run the line at ``period_s`` and collect ``duration_s`` seconds of results."""
    from service import bus
    from service.protocol import Keys
    from service.worker import result_from_json

    port = _free_port()
    win = Window(period_s)
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "INSPECTION_TRIGGER_PERIOD_S": str(period_s), "PYTHONUNBUFFERED": "1"}
        cmd = [
            sys.executable, "-m", "service.cli", "run",
            "--config", str(config),
            "--data-dir", tmp, "--http-port", "0",
            "--zenoh-listen", f"tcp/127.0.0.1:{port}",
        ]  # fmt: skip
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None
            docs = None
            for line in proc.stdout:
                if "API docs:" in line:
                    docs = line.split("API docs:")[1].strip()
                if line.startswith("  data:"):
                    break
            else:
                raise RuntimeError("the line did not start")
            if docs is not None:
                # Count from readiness on: the API's part registry builds its
                # trees at start-up and competes with the first parts for CPU.
                _wait_ready(docs.replace("/docs", "/v1/health"), 300)
            seen = [0]
            lock = threading.Lock()

            def on_result(sample) -> None:
                now = time.time_ns()
                r = result_from_json(sample.payload.to_bytes())
                with lock:
                    seen[0] += 1
                    if seen[0] <= warmup:
                        return
                    if not win.started:
                        win.started = time.monotonic()
                    win.statuses.append(r.status.value)
                    if r.status.value != "missed":
                        win.latencies_s.append((now - r.triggered_ns) / 1e9)
                    for k, v in r.timings_ms.items():
                        win.stages_ms.setdefault(k, []).append(v)

            settings = bus.BusSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
            with bus.open_session(settings) as session:
                sub = bus.RingSubscriber(session, Keys("line1").results(), on_result, capacity=1024)
                stop = threading.Event()
                deadline = time.monotonic() + duration_s + warmup * period_s + 60
                while time.monotonic() < deadline:
                    if win.started and time.monotonic() - win.started >= duration_s:
                        break
                    stop.wait(0.5)
                sub.close()
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
    return win


def simulate_ms(n: int = 5) -> list[float]:
    """Time the ingest's rendering of ``n`` parts (the line's config, this process)."""
    from service.config import load_line_config
    from service.line import Station

    cfg = load_line_config(ROOT / "configs" / "line.toml")
    rig = Station.load(cfg, build_trees=False, warm_up=False).simulated_rig()
    rig.capture(0, 0)  # compile
    out = []
    for seq in range(1, n + 1):
        t0 = time.perf_counter()
        rig.capture(seq, 0)
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def stage_cpu_ms(config: Path, data_dir: Path, n: int) -> dict[str, list[float]]:
    """CPU time (ms, this process) of the whole measurement of ``n`` parts, and the
    wall time of each of its stages as the sequence reports it (``timings_ms``).

    The line's own pieces, one part at a time: the station as the worker loads
    it (warmed up), the ingest's simulated rig, and the station's one measure
    callable (``inspection.measure_frames``).
    """
    from service.config import load_line_config
    from service.line import Station

    cfg = load_line_config(config, overrides={("storage", "data_dir"): str(data_dir)})
    station = Station.load(cfg)
    out: dict[str, list[float]] = {"measure CPU": []}
    try:
        rig, stages = station.simulated_rig(), station.stages
        for seq in range(n):
            fs = rig.capture(seq, 0)
            t = time.process_time()
            m = stages.measure(station.parts[fs.part], fs.images)
            out["measure CPU"].append((time.process_time() - t) * 1e3)
            for stage, ms in m.timings_ms.items():
                out.setdefault(f"{stage} wall", []).append(ms)
    finally:
        station.close()
    return out


def _stage_line(name: str, values: list[float]) -> str:
    if not values:
        return f"  {name:>12}      -"
    a = np.asarray(values)
    return (
        f"  {name:>12} {np.median(a):8.0f} {np.percentile(a, 90):8.0f} {a.max():8.0f}  n={len(a)}"
    )


def main() -> int:
    smoke = os.environ.get("BENCH_SMOKE") == "1"
    duration = float(os.environ.get("BENCH_LINE_DURATION_S", "40" if smoke else "300"))
    window = float(os.environ.get("BENCH_LINE_WINDOW_S", "20" if smoke else "45"))
    rates = [
        float(r)
        for r in os.environ.get("BENCH_LINE_RATES_HZ", "1,2" if smoke else "1,1.5,2,3,4").split(",")
    ]
    cpu_parts = int(os.environ.get("BENCH_LINE_CPU_PARTS", "5"))
    load = os.getloadavg()
    print(f"load average before: {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}", flush=True)
    with tempfile.TemporaryDirectory() as shared:
        trees = Path(shared) / "trees"
        config = line_config(Path(shared), trees)
        sim = simulate_ms()
        cpu = stage_cpu_ms(config, Path(shared) / "cpu", cpu_parts) if cpu_parts > 0 else {}
        return _measure(config, duration, window, rates, sim, cpu)


def _measure(
    config: Path,
    duration: float,
    window: float,
    rates: list[float],
    sim: list[float],
    cpu: dict[str, list[float]],
) -> int:
    print(f"line latency at 0.5 Hz over {duration:.0f} s (trigger -> result on zenoh)", flush=True)
    base = run_line(2.0, duration, config)
    p50, p99 = base.pct(50), base.pct(99)
    print(f"  stage times, ms: {'p50':>8} {'p90':>8} {'max':>8}", flush=True)
    print(_stage_line("simulate", sim) + "  (alone, before the line)", flush=True)
    for name in ("reconstruct", "guide", "align", "deviations", "total"):
        print(_stage_line(name, base.stages_ms.get(name, [])), flush=True)
    if cpu:
        print(f"  stage CPU, ms:   {'p50':>8} {'p90':>8} {'max':>8}   (alone, before the line)")
        for name, values in cpu.items():
            print(_stage_line(name, values), flush=True)
    print(
        f"  n={len(base.latencies_s)} missed={base.missed} p50={p50:.3f} s p99={p99:.3f} s "
        f"max={max(base.latencies_s, default=float('nan')):.3f} s   (goal p50 <= 1 s, p99 <= 2 s)",
        flush=True,
    )
    print(f"\nsustained rate: {window:.0f} s per rate", flush=True)
    print(
        f"  {'rate Hz':>8} {'n':>4} {'missed':>6} {'p50 s':>7} {'p99 s':>7}  sustained", flush=True
    )
    best = 0.5 if base.sustained() else 0.0
    if not best:
        rates = []  # faster than a rate it cannot keep: nothing to learn
        print("  (0.5 Hz is not sustained: higher rates are not tried)", flush=True)
    for hz in rates:
        w = run_line(1.0 / hz, window, config)
        ok = w.sustained()
        print(
            f"  {hz:8.2f} {len(w.statuses):4d} {w.missed:6d} {w.pct(50):7.3f} {w.pct(99):7.3f}  "
            f"{'yes' if ok else 'no'}",
            flush=True,
        )
        if not ok:
            break
        best = hz
    print(f"\nhighest sustained rate: {best:.2f} Hz", flush=True)
    totals = base.stages_ms.get("total", [])
    if totals:
        # One worker measures one part at a time: its rate cannot exceed this.
        print(
            f"worker capacity at 0.5 Hz load: 1 / median measuring time = "
            f"{1e3 / float(np.median(totals)):.2f} Hz",
            flush=True,
        )
    return 0 if p50 <= 1.0 and p99 <= 2.0 and not base.missed else 1


if __name__ == "__main__":
    sys.exit(main())
