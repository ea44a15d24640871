"""A shift at the line's rate: memory and disk over time, and the line under upload load.

Runs ``inspection run`` (the whole simulated line in one process: ingest,
worker, API, store, recorder, janitor) at 0.5 Hz for ``BENCH_SOAK_S`` seconds
(default 3600; 600 with ``BENCH_SMOKE=1``), with retention budgets small
enough to be reached within the run. Every ``BENCH_SOAK_SAMPLE_S`` seconds
(default 60; 20 with ``BENCH_SMOKE=1``) it samples the line process's RSS
and CPU time and the disk use of the recordings, the deviation archive and
the SQLite store, and beside them the RSS and CPU time of the processes the
line started (the API's measuring processes). For the second half of the run
four clients upload a large cloud each (``BENCH_SOAK_UPLOAD_POINTS``,
default 4,000,000 points, a 96 MB ``.npy``) over and over, waiting as told
when the API answers 503.

Printed: the samples; the slopes of RSS after warm-up (the first fifth of
the run) in MB/h and as a share of its mean (goal: flat within 5 %); each
directory's use against its budget at every sample (goal: never above);
parts measured and missed in the quiet half and in the upload half (goal:
no part missed at 0.5 Hz with the uploads running); the line's CPU seconds
per trigger beside the trigger period (the uploads are measured in processes
of their own, whose CPU is printed apart); uploads answered, refused (503)
and failed.
"""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

import numpy as np

from bench.bench_line import ROOT, _free_port, _wait_ready, line_config

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

BUDGETS_MB = {"mcap": 3000.0, "deviations": 150.0, "results": 20.0}
"""Retention budgets of the soak's line: reached within an hour at 0.5 Hz."""


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    """The processes ``pid`` started (the API's measuring processes among them)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass  # the thread ended while we looked
    return out


def _children_use(pid: int) -> tuple[float, float]:
    """RSS (MB) and CPU time (s) of the processes ``pid`` runs now, together."""
    rss = cpu = 0.0
    for child in _children(pid):
        try:
            rss += _rss_mb(child)
            cpu += _cpu_s(child)
        except OSError:
            pass  # it ended while we looked
    return rss, cpu


def _du_mb(path: Path) -> float:
    if path.is_file():
        return path.stat().st_size / 1e6
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            try:
                total += (Path(root) / f).stat().st_size
            except FileNotFoundError:
                pass  # deleted by retention while we walked
    return total / 1e6


def _npy(points: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, points)
    return buf.getvalue()


def _multipart(fields: dict[str, str], file_bytes: bytes) -> tuple[bytes, str]:
    boundary = uuid.uuid4().hex
    parts = []
    for k, v in fields.items():
        parts.append(
            f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'.encode()
        )
    parts.append(
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="c.npy"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n".encode()
    )
    body = b"".join(parts) + file_bytes + f"\r\n--{boundary}--\r\n".encode()
    return body, f"multipart/form-data; boundary={boundary}"


class Uploader(threading.Thread):
    """Posts the same large cloud again and again until stopped."""

    def __init__(self, url: str, body: bytes, ctype: str, stop: threading.Event) -> None:
        super().__init__(daemon=True)
        self.url, self.body, self.ctype, self.stop = url, body, ctype, stop
        self.ok = self.busy = self.failed = 0
        self.why: dict[str, int] = {}

    def run(self) -> None:
        while not self.stop.is_set():
            req = urllib.request.Request(
                self.url, data=self.body, headers={"Content-Type": self.ctype}, method="POST"
            )
            try:
                with urllib.request.urlopen(req, timeout=600) as resp:
                    resp.read()
                    self.ok += 1
            except urllib.error.HTTPError as exc:
                exc.read()
                if exc.code == 503:
                    self.busy += 1
                    self.stop.wait(float(exc.headers.get("Retry-After", "5")))
                else:
                    self._fail(f"HTTP {exc.code}")
            except OSError as exc:
                self._fail(f"{type(exc).__name__}: {getattr(exc, 'reason', exc)}")
                self.stop.wait(1.0)

    def _fail(self, why: str) -> None:
        self.failed += 1
        self.why[why] = self.why.get(why, 0) + 1


def _slope(t_h: np.ndarray, y: np.ndarray) -> float:
    return float(np.polyfit(t_h, y, 1)[0]) if len(t_h) >= 3 else float("nan")


def _config(tmp: Path, trees: Path) -> Path:
    path = line_config(tmp, trees)
    text = path.read_text()
    text = text.replace("max_total_mb = 10000.0", f"max_total_mb = {BUDGETS_MB['mcap']}")
    text = text.replace("mcap_rotate_mb = 512.0", "mcap_rotate_mb = 256.0")
    text = text.replace(
        "deviations_max_mb = 5000.0", f"deviations_max_mb = {BUDGETS_MB['deviations']}"
    )
    text = text.replace("results_max_mb = 2000.0", f"results_max_mb = {BUDGETS_MB['results']}")
    path.write_text(text)
    return path


def _upload_cloud(n: int) -> bytes:
    """``n`` points on the demo panel's CAD surface with 0.03 mm noise, CAD frame."""
    from service.config import load_part_spec
    from service.parts import load_part_cad

    spec_path = ROOT / "configs" / "parts" / "demo-panel.toml"
    mesh = load_part_cad(load_part_spec(spec_path), spec_path.parent).to_trimesh()
    pts, _ = mesh.sample(n, return_index=True)
    rng = np.random.default_rng(0)
    return _npy(np.asarray(pts) + rng.normal(0, 0.03, (n, 3)))


def main() -> int:
    from service import bus
    from service.protocol import Keys
    from service.worker import result_from_json

    smoke = os.environ.get("BENCH_SMOKE") == "1"
    duration = float(os.environ.get("BENCH_SOAK_S", "600" if smoke else "3600"))
    every = float(os.environ.get("BENCH_SOAK_SAMPLE_S", "20" if smoke else "60"))
    n_points = int(os.environ.get("BENCH_SOAK_UPLOAD_POINTS", "4000000"))
    period = 2.0
    print(f"soak: {duration:.0f} s at {1 / period:.1f} Hz, samples every {every:.0f} s, "
          f"uploads of {n_points:,} points in the second half", flush=True)  # fmt: skip
    cloud = _upload_cloud(n_points)
    print(f"  upload body: {len(cloud) / 1e6:.0f} MB", flush=True)
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        config = _config(tmp, tmp / "trees")
        data = tmp / "data"
        port = _free_port()
        env = {**os.environ, "INSPECTION_TRIGGER_PERIOD_S": str(period), "PYTHONUNBUFFERED": "1"}
        cmd = [sys.executable, "-m", "service.cli", "run", "--config", str(config),
               "--data-dir", str(data), "--http-port", "0",
               "--zenoh-listen", f"tcp/127.0.0.1:{port}"]  # fmt: skip
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True)
        statuses: list[tuple[float, str]] = []
        lock = threading.Lock()

        def on_result(sample) -> None:
            r = result_from_json(sample.payload.to_bytes())
            with lock:
                statuses.append((time.monotonic(), r.status.value))

        try:
            assert proc.stdout is not None
            base = None
            for line in proc.stdout:
                if "API docs:" in line:
                    base = line.split("API docs:")[1].strip().removesuffix("/docs")
                if line.startswith("  data:"):
                    break
            if base is None:
                raise RuntimeError("the line did not start")
            _wait_ready(f"{base}/v1/health", 600)
            settings = bus.BusSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
            with bus.open_session(settings) as session:
                sub = bus.RingSubscriber(session, Keys("line1").results(), on_result, capacity=1024)
                try:
                    return _soak(proc.pid, data, base, cloud, duration, every, period, statuses,
                                 lock)  # fmt: skip
                finally:
                    sub.close()
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(120)
            except subprocess.TimeoutExpired:
                proc.kill()


def _soak(pid, data, base, cloud, duration, every, period, statuses, lock) -> int:
    t0 = time.monotonic()
    cpu0 = _cpu_s(pid)
    body, ctype = _multipart({"part": "demo-panel", "frame": "cad"}, cloud)
    stop = threading.Event()
    uploaders: list[Uploader] = []
    half = t0 + duration / 2
    samples = []
    print(f"\n  {'t s':>6} {'RSS MB':>7} {'CPU s':>7} {'mcap MB':>8} {'dev MB':>7} "
          f"{'sqlite MB':>9} {'results':>7} {'missed':>6} {'meas. RSS MB':>12} "
          f"{'meas. CPU s':>11}", flush=True)  # fmt: skip
    try:
        while (now := time.monotonic()) < t0 + duration:
            if not uploaders and now >= half:
                uploaders = [Uploader(f"{base}/v1/inspections", body, ctype, stop)
                             for _ in range(4)]  # fmt: skip
                for u in uploaders:
                    u.start()
                print("  -- four uploaders started --", flush=True)
            with lock:
                n = len(statuses)
                missed = sum(s == "missed" for _, s in statuses)
            row = (
                now - t0, _rss_mb(pid), _cpu_s(pid) - cpu0, _du_mb(data / "mcap"),
                _du_mb(data / "deviations"),
                sum(_du_mb(p) for p in data.glob("results.sqlite*")), n, missed,
                *_children_use(pid),
            )  # fmt: skip
            samples.append(row)
            print(f"  {row[0]:6.0f} {row[1]:7.0f} {row[2]:7.0f} {row[3]:8.0f} {row[4]:7.1f} "
                  f"{row[5]:9.1f} {row[6]:7d} {row[7]:6d} {row[8]:12.0f} {row[9]:11.0f}",
                  flush=True)  # fmt: skip
            stop.wait(max(0.0, every - (time.monotonic() - now)))
    finally:
        stop.set()
        for u in uploaders:
            u.join(60)
    a = np.asarray([s[:6] for s in samples], dtype=float)
    # Each half on its own: the uploads hold their bodies and clouds (hundreds of MB)
    # while they last, a plateau of its own; the goal is no growth within either.
    # The first fifth of the run, and of the upload half, is warm-up.
    quiet_h = (a[:, 0] >= 0.2 * duration) & (a[:, 0] < half - t0)
    loaded_h = a[:, 0] >= (half - t0) + 0.2 * duration / 2
    print()
    for label, sel, span_s in (("quiet half", quiet_h, 0.3 * duration),
                               ("upload half", loaded_h, 0.4 * duration)):  # fmt: skip
        rss = a[sel, 1]
        if len(rss) < 3:
            print(f"RSS {label}: too few samples")
            continue
        slope = _slope(a[sel, 0] / 3600.0, rss)
        share = slope * (span_s / 3600.0) / float(np.mean(rss))
        print(f"RSS {label:>11} after warm-up: mean {np.mean(rss):.0f} MB, slope "
              f"{slope:+.1f} MB/h, {100 * share:+.1f} % of the mean over its span "
              f"(goal: within 5 %)")  # fmt: skip
    for col, name in ((3, "mcap"), (4, "deviations"), (5, "results")):
        peak = float(a[:, col].max())
        slope_d = _slope(a[:, 0] / 3600, a[:, col])
        # The store's budget counts its JSON; the file holds its indexes beside it.
        slack = 1.3 if name == "results" else 1.0
        verdict = "within" if peak <= BUDGETS_MB[name] * slack else "ABOVE"
        print(f"disk {name:>10}: max {peak:8.1f} MB, slope {slope_d:+8.1f} MB/h, "
              f"budget {BUDGETS_MB[name]:.0f} MB: {verdict}")  # fmt: skip
    with lock:
        quiet = [s for t, s in statuses if t < half]
        loaded = [s for t, s in statuses if t >= half]
    for name, part in (("quiet half", quiet), ("upload half", loaded)):
        missed = sum(s == "missed" for s in part)
        print(f"{name:>12}: {len(part)} results, {missed} missed "
              f"({', '.join(f'{k} {part.count(k)}' for k in sorted(set(part)))})")  # fmt: skip
    cpu_total = samples[-1][2]
    n_results = max(1, samples[-1][6])
    print(
        f"line CPU: {cpu_total:.0f} s over {samples[-1][0]:.0f} s wall, "
        f"{cpu_total / n_results:.2f} CPU-s per trigger (period {period:.1f} s); the measuring "
        f"processes: {samples[-1][9]:.0f} CPU-s, at most {max(s[8] for s in samples):.0f} MB"
    )
    why: dict[str, int] = {}
    for u in uploaders:
        for k, v in u.why.items():
            why[k] = why.get(k, 0) + v
    print(
        f"uploads: {sum(u.ok for u in uploaders)} measured, "
        f"{sum(u.busy for u in uploaders)} refused busy, {sum(u.failed for u in uploaders)} "
        f"failed {why or ''}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
