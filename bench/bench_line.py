"""The running line: a worker fed by a recording at 2 Hz, and the whole line at 1 Hz.

Every process is real and talks zenoh on loopback only, multicast scouting
off; the bench listens to results as a zenoh client, the way any subscriber
would. CPU time is read from ``/proc/<pid>/stat`` (user + system, every
thread of the process): wall times on a shared machine wander with the
load, CPU times much less.

0. Stage times, in this process before anything runs: the station as the
   worker loads it (warmed up), the ingest's simulated rig, and the one
   measuring sequence on ``BENCH_LINE_CPU_PARTS`` parts: ``simulate`` (the
   ingest's rendering), then each stage's wall and CPU time from the
   measurement's ``timings_ms`` and ``cpu_ms`` (the results on the bus carry
   the wall times only).
   Then the disk cost per part, on ``BENCH_LINE_DISK_PARTS`` of those parts
   measured again: for each recording choice (chunk compression none, lz4 or
   zstd; images raw or lossless PNG) the line's recorder writes them, and the
   table gives the bytes per part (median of the file's growth per trigger),
   the recorder's CPU per part, the once-per-file records (the cameras, the
   CAD), what replay spends reading a part back, whether the images come back
   bit for bit, and the shift (8 h at 0.5 Hz); then the same for the
   deviation archive (compressed npz, the line's; plain npz beside it) and
   the result store (SQLite), and a sweep of OpenCV's PNG settings on one
   frame set. ``BENCH_LINE_DISK_ONLY=1`` stops there.
1. A worker fed by a recording at 2 Hz. A shift of ``BENCH_LINE_SETS``
   FrameSets (default 64) is recorded once by the line's own pieces (the
   simulated rig, the pipeline, the MCAP recorder) and kept under
   ``.cache/bench/line`` (delete it to record again). Then, as separate
   processes: ``inspection router``, ``inspection worker`` (client, the
   line's config, a fresh data dir) and ``inspection replay --publish`` at the
   ``--speed`` that gives 2 Hz. Replay keeps the recorded ``triggered_ns``,
   so latency is measured from each FrameSet's arrival at this process's
   subscriber on the frames key (through the same router as the worker's) to
   its result's arrival. The worker's CPU per part: its CPU time read at each
   measured result's arrival, minus that at the previous measured result's
   (so what it spent on missed parts is counted with the next measured one).
   Goals: no missed part, CPU median <= 0.8 s, p99 < 1.5 s.
2. The whole simulated line in one process (``make run``'s configuration:
   configs/line.toml, ``inspection run``) at 1 Hz for
   ``BENCH_LINE_DURATION_S`` seconds: missed parts, latency from the
   ingest's ``triggered_ns`` (the same host's clock), and the process's CPU
   per measured part as above (it renders the frames too). Results count
   from the moment the line reports ready on ``/v1/health``, after a warm-up
   of two results. Goal: none missed.
3. Only with ``BENCH_LINE_RATES_HZ`` set: the whole line at each of those
   rates for ``BENCH_LINE_WINDOW_S`` seconds, until one is not sustained.

The tree cache is kept under ``.cache/bench/line/trees`` too (keyed by CAD
hash and build parameters, like every tree cache).

Environment: BENCH_SMOKE=1 (shorter: 1 Hz for 60 s, 3 parts for stage
times), BENCH_LINE_SETS (FrameSets in the recording, default 64),
BENCH_LINE_REPLAY_HZ (default 2), BENCH_LINE_HZ (the whole line's rate,
default 1), BENCH_LINE_DURATION_S (default 300; 60 with BENCH_SMOKE=1),
BENCH_LINE_CPU_PARTS (default 5; 0 skips the stage times),
BENCH_LINE_RATES_HZ (comma-separated; default none), BENCH_LINE_WINDOW_S
(default 45), BENCH_LINE_DISK_PARTS (default 4; 2 with BENCH_SMOKE=1; 0 skips
the disk cost), BENCH_LINE_DISK_ONLY=1 (stage times and disk cost only).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / ".cache" / "bench" / "line"
LINE, STATION = "line1", "st1"
RECORDED_PERIOD_S = 0.5
"""Trigger spacing written into the recording: replayed at ``--speed 1`` it is 2 Hz."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid``, every thread."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


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
    """A copy of configs/line.toml whose installation paths are absolute, whose tree
    cache is ``trees`` and whose lone worker serves its metrics on any free port; its
    station holds demo-panel alone, best fitted, so that the figures stay comparable
    (``make bench BENCH=features`` measures the part with holes and an RPS)."""
    conf = ROOT / "configs"
    text = (conf / "line.toml").read_text()
    both = 'parts = ["demo-panel", "demo-panel-features"]'
    if both not in text:
        raise SystemExit(f"{conf / 'line.toml'}: the station no longer reads {both}")
    text = text.replace(both, 'parts = ["demo-panel"]')
    text = text.replace('parts_dir = "parts"', f'parts_dir = "{conf / "parts"}"')
    text = text.replace('trees_dir = "trees"', f'trees_dir = "{trees}"')
    text = text.replace("metrics_port = 9464 ", "metrics_port = 0 ")
    path = tmp / "line.toml"
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- what arrives


@dataclass
class Arrival:
    seq: int
    status: str
    latency_s: float | None
    cpu_s: float
    """The measured process's CPU time when the result arrived."""
    timings_ms: dict[str, float]
    at_s: float
    """When it arrived (monotonic clock)."""


@dataclass
class Shift:
    """Results as they arrived, with the measuring process's CPU time at each."""

    pid: int
    warmup: int = 0
    arrivals: list[Arrival] = field(default_factory=list)
    seen: int = 0
    started: float = 0.0
    cpu_at_start: float = float("nan")
    _cond: threading.Condition = field(default_factory=threading.Condition)

    def add(self, seq: int, status: str, latency_s: float | None, timings: dict) -> None:
        cpu = _cpu_s(self.pid)
        with self._cond:
            self.seen += 1
            if self.seen <= self.warmup:
                self.cpu_at_start = cpu
                return
            if not self.started:
                self.started = time.monotonic()
            self.arrivals.append(Arrival(seq, status, latency_s, cpu, timings, time.monotonic()))
            self._cond.notify_all()

    def wait(self, done: Callable[[], bool], timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(done, timeout_s)

    @property
    def missed(self) -> int:
        return sum(a.status == "missed" for a in self.arrivals)

    @property
    def measured(self) -> list[Arrival]:
        return [a for a in self.arrivals if a.status != "missed"]

    def latencies(self) -> list[float]:
        return [a.latency_s for a in self.measured if a.latency_s is not None]

    def cpu_per_part(self) -> list[float]:
        """CPU seconds between consecutive measured results (the first needs a predecessor)."""
        m = self.measured
        return [b.cpu_s - a.cpu_s for a, b in zip(m, m[1:], strict=False)]

    def cpu_overall(self) -> float:
        """CPU seconds from the first result counted (or the warm-up's last) to the last
        measured one, per measured part after the first."""
        m = self.measured
        if np.isfinite(self.cpu_at_start) and m:
            return (m[-1].cpu_s - self.cpu_at_start) / len(m)
        if len(m) < 2:
            return float("nan")
        return (m[-1].cpu_s - m[0].cpu_s) / (len(m) - 1)

    def cpu_per_trigger(self) -> float:
        """CPU seconds from the first result to the last, per result (missed ones too)."""
        if len(self.arrivals) < 2:
            return float("nan")
        a, b = self.arrivals[0], self.arrivals[-1]
        return (b.cpu_s - a.cpu_s) / (len(self.arrivals) - 1)

    def cores_busy(self) -> float:
        """CPU seconds per wall second from the first result to the last: how many of the
        machine's cores the process kept busy."""
        if len(self.arrivals) < 2:
            return float("nan")
        a, b = self.arrivals[0], self.arrivals[-1]
        return (b.cpu_s - a.cpu_s) / (b.at_s - a.at_s)

    def sustained(self) -> bool:
        """No missed part, and the second half's median latency is not running away."""
        lat = self.latencies()
        n = len(lat)
        if n < 4 or self.missed:
            return False
        return float(np.median(lat[n // 2 :])) <= 1.5 * float(np.median(lat[: n // 2])) + 0.2


def _subscribe_results(session, shift: Shift, published: dict[int, int] | None):
    """Collect results into ``shift``; latency from ``published[seq]`` (ns) when given,
    else from the result's ``triggered_ns``."""
    from service import bus
    from service.protocol import Keys
    from service.worker import result_from_json

    def on_result(sample) -> None:
        now = time.time_ns()
        r = result_from_json(sample.payload.to_bytes())
        t0 = r.triggered_ns if published is None else published.get(r.seq)
        latency = None if t0 is None else (now - t0) / 1e9
        shift.add(r.seq, r.status.value, latency, dict(r.timings_ms))

    return bus.RingSubscriber(session, Keys(LINE).results(), on_result, capacity=1024)


def _wait_for_token(session, key: str, timeout_s: float) -> bool:
    """Wait for a worker's liveliness token (it is ready to measure)."""
    import zenoh

    sub = session.liveliness().declare_subscriber(key, zenoh.handlers.FifoChannel(16), history=True)
    pause = threading.Event()
    try:
        for _ in range(int(timeout_s / 0.2)):
            if sub.handler.try_recv() is not None:
                return True
            pause.wait(0.2)
        return False
    finally:
        sub.undeclare()


def _cli(*args: str, log: Path, env: dict[str, str] | None = None, **kw) -> subprocess.Popen:
    """``inspection ARGS`` in a process of its own; its log (stderr) goes to ``log``."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    cmd = [sys.executable, "-m", "service.cli", *args]
    with log.open("a") as err:
        return subprocess.Popen(cmd, cwd=ROOT, env=env, text=True, stderr=err, **kw)


def _tail(log: Path, n: int = 15) -> str:
    lines = log.read_text(errors="replace").splitlines() if log.exists() else []
    return "\n".join("    | " + line for line in lines[-n:])


def _stop(procs: list[subprocess.Popen]) -> None:
    """SIGINT each still running process (the newest first), then kill what lingers."""
    for p in reversed(procs):
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in reversed(procs):
        try:
            p.wait(60)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(30)


# --------------------------------------------------------------------------- 0: stage times


def _recording_key(cfg, station, n: int) -> str:
    """What the recorded frames depend on: the rig, the simulator and the parts."""
    what = {
        "calibration": station.stages.calibration_id,
        "projector": cfg.projector.model_dump(mode="json"),
        "simulator": cfg.simulator.model_dump(mode="json"),
        "line": cfg.line.model_dump(mode="json"),
        "cads": sorted(cad.hash for _, cad in station.cads.values()),
        "sets": n,
        "period_s": RECORDED_PERIOD_S,
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


def prepare(
    config: Path, n_sets: int, cpu_parts: int, disk_parts: int = 0, *, record: bool = True
) -> tuple[Path, dict[str, list[float]]]:
    """Stage times on ``cpu_parts`` parts, the disk cost per part on ``disk_parts`` parts
    (printed), and the recorded shift (made once, then cached; not with ``record=False``).

    Returns the recording's directory and, per stage, the wall and CPU ms.
    """
    from service.config import load_line_config
    from service.line import Station, stages_for

    cfg = load_line_config(config)
    t0 = time.perf_counter()
    station = Station.load(cfg)
    print(f"  (station loaded and warmed up in {time.perf_counter() - t0:.0f} s)", flush=True)
    stages: dict[str, list[float]] = {}
    try:
        rig = station.simulated_rig()
        for seq in range(1, cpu_parts + 1):
            w, c = time.perf_counter(), time.process_time()
            fs = rig.capture(seq, time.time_ns())
            stages.setdefault("simulate wall", []).append((time.perf_counter() - w) * 1e3)
            stages.setdefault("simulate CPU", []).append((time.process_time() - c) * 1e3)
            m = station.stages.measure(station.parts[fs.part], fs.images)
            for stage, ms in m.timings_ms.items():
                stages.setdefault(f"{stage} wall", []).append(ms)
            for stage, ms in m.cpu_ms.items():
                stages.setdefault(f"{stage} CPU", []).append(ms)
        if disk_parts:
            print_disk_cost(disk_parts, *disk_cost(station, rig, disk_parts))
        recording = CACHE / f"shift-{_recording_key(cfg, station, n_sets)}"
        if record and not (recording / "manifest.json").is_file():
            # The frames are what the replay publishes; the recorded results come from
            # one matching pass, which records the shift in a third of the time.
            one_pass = load_line_config(config, overrides={("station", "guided_matching"): False})
            recorder_station = Station(one_pass, stages_for(one_pass), station.parts)
            record_shift(recorder_station, rig, n_sets, recording)
    finally:
        station.close()
    return recording, stages


def record_shift(station, rig, n: int, out: Path) -> None:
    """Record ``n`` triggers ``RECORDED_PERIOD_S`` apart with the line's pieces: the
    simulated rig renders, the station's pipeline measures, its MCAP recorder writes
    (frames raw, as the line records them). Written aside and moved into place whole."""
    print(f"  recording a shift of {n} FrameSets into {out} (once) ...", flush=True)
    t0 = time.perf_counter()
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    recorder = station.recorder(tmp)
    pipeline = station.pipeline()
    start_ns = time.time_ns()
    statuses: dict[str, int] = {}
    try:
        for seq in range(n):
            fs = rig.capture(seq, start_ns + int(seq * RECORDED_PERIOD_S * 1e9))
            outcome = pipeline.run(fs)
            recorder.record(outcome, fs)
            s = outcome.result.status.value
            statuses[s] = statuses.get(s, 0) + 1
    finally:
        recorder.close()
    manifest = {
        "sets": n,
        "period_s": RECORDED_PERIOD_S,
        "statuses": statuses,
        "guided": station.stages.guided,
    }
    (tmp / "manifest.json").write_text(json.dumps(manifest))
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    print(f"  recorded in {time.perf_counter() - t0:.0f} s: {statuses}", flush=True)


# --------------------------------------------------------------------------- 0b: disk cost

SHIFT_PARTS = int(8 * 3600 * 0.5)
"""Parts in a shift: 8 h at the line's 0.5 Hz."""
DISK_WRITES = 12
"""Writes per recording choice at least (the parts are written again into new files)."""


@dataclass
class DiskRow:
    """What one way of keeping the parts costs, per part."""

    what: str
    bytes_per_part: float
    cpu_ms: list[float]
    per_file_bytes: float = 0.0
    read_cpu_ms: float = float("nan")
    lossless: bool | None = None


def _measured(station, rig, n: int) -> list:
    pipeline = station.pipeline()
    out = []
    for seq in range(100, 100 + n):
        fs = rig.capture(seq, time.time_ns())
        out.append((pipeline.run(fs), fs))
    return out


def disk_cost(station, rig, n: int) -> tuple[list[DiskRow], list[tuple[str, float, float]]]:
    """Each recording choice, the deviation archive and the store, on ``n`` measured parts;
    and the PNG settings swept on the first part's frames."""
    from service.recorder import COMPRESSIONS, IMAGE_ENCODINGS, read_recording
    from service.store import DeviationArchive, ResultStore

    triggers = _measured(station, rig, n)
    choices = [(c, i) for i in IMAGE_ENCODINGS for c in COMPRESSIONS]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        # Every choice writes each trigger in turn, so a change of the machine's load falls
        # on all of them alike; passes over the same triggers (new files) add CPU samples.
        cpu: dict[tuple[str, str], list[float]] = {k: [] for k in choices}
        sizes: dict[tuple[str, str], list[int]] = {}
        files: dict[tuple[str, str], Path] = {}
        for p in range(max(1, -(-DISK_WRITES // n))):
            with contextlib.ExitStack() as stack:
                recs = {
                    (c, i): stack.enter_context(
                        station_recorder(station, Path(tmp) / f"{c}-{i}-{p}", i, c)
                    )
                    for c, i in choices
                }
                if p == 0:
                    files = {k: r.files[0] for k, r in recs.items()}
                    sizes = {k: [f.stat().st_size] for k, f in files.items()}
                for outcome, fs in triggers:
                    for k, rec in recs.items():
                        t = time.process_time()
                        rec.record(outcome, fs)
                        cpu[k].append((time.process_time() - t) * 1e3)
                        if p == 0:
                            sizes[k].append(files[k].stat().st_size)
        for c, i in choices:
            growth = np.diff(sizes[(c, i)])
            t = time.process_time()
            _, back = read_recording([files[(c, i)]])
            read_ms = (time.process_time() - t) * 1e3 / n
            same = all(
                r.frameset is not None
                and all(
                    np.array_equal(a, b) for a, b in zip(r.frameset.images, fs.images, strict=True)
                )
                for r, (_, fs) in zip(back, triggers, strict=True)
            )
            per_part = float(np.median(growth[1:])) if n > 1 else float(growth[0])
            rows.append(
                DiskRow(
                    f"MCAP {c:>4}, images {i}",
                    per_part,
                    cpu[(c, i)],
                    float(growth[0]) - per_part,
                    read_ms,
                    same,
                )  # fmt: skip
            )
        clouds = [_cloud_bytes(o) for o, _ in triggers]
        frames = [sum(img.nbytes for img in fs.images) for _, fs in triggers]
        rows.append(DiskRow("  of which the cloud, raw", float(np.median(clouds)), []))
        rows.append(DiskRow("  of which the 4 images, raw", float(np.median(frames)), []))
        for label, compressed in (("deviation archive (npz, compressed)", True),
                                  ("  plain npz, for comparison", False)):  # fmt: skip
            archive = DeviationArchive(Path(tmp) / f"archive-{compressed}")
            save = archive.save if compressed else _plain_npz(archive)
            sizes, cpu = [], []
            for outcome, _ in triggers:
                pts = outcome.points_cad()
                c = time.process_time()
                target = save(outcome.result.id, pts, outcome.distances)
                cpu.append((time.process_time() - c) * 1e3)
                sizes.append(target.stat().st_size)
            rows.append(DiskRow(label, float(np.median(sizes)), cpu))
        db = Path(tmp) / "results.sqlite"
        store = ResultStore(db)
        try:
            before, cpu = _sqlite_bytes(db), []
            for outcome, _ in triggers:
                c = time.process_time()
                store.put(outcome.result)
                cpu.append((time.process_time() - c) * 1e3)
            rows.append(DiskRow("result store (SQLite)", (_sqlite_bytes(db) - before) / n, cpu))
        finally:
            store.close()
    return rows, png_sweep(triggers[0][1].images)


def _cloud_bytes(outcome) -> int:
    """The recorded cloud message of one part (x, y, z, deviation as float32)."""
    from service import foxglove

    if outcome.points is None:
        return 0
    return len(foxglove.cloud(outcome.points, outcome.distances, 0).SerializeToString())


def _plain_npz(archive):
    def save(id_: str, points: np.ndarray, distances: np.ndarray) -> Path:
        target = archive.path(id_)
        target.parent.mkdir(parents=True, exist_ok=True)
        keep = np.linspace(0, len(points) - 1, archive.max_points).round().astype(np.int64)
        np.savez(target, points=points[keep].astype(np.float32),
                 distances=distances[keep].astype(np.float32))  # fmt: skip
        return target

    return save


def _sqlite_bytes(db: Path) -> int:
    """The database with its write-ahead log."""
    return sum(p.stat().st_size for p in db.parent.glob(db.name + "*"))


@contextlib.contextmanager
def station_recorder(station, directory: Path, images: str, compression: str) -> Iterator:
    """The station's own recorder (calibrations, CAD, markers) with one recording choice."""
    from service.line import Station

    storage = station.cfg.storage.model_copy(
        update={"mcap_image_encoding": images, "mcap_compression": compression}
    )
    cfg = station.cfg.model_copy(update={"storage": storage})
    rec = Station(cfg, station.stages, station.parts).recorder(directory)
    try:
        yield rec
    finally:
        rec.close()


def png_sweep(frames: list[np.ndarray]) -> list[tuple[str, float, float]]:
    """OpenCV's PNG settings (and lossless WebP) on one frame set: ratio to raw, ms a frame."""
    import cv2

    P, S = cv2.IMWRITE_PNG_COMPRESSION, cv2.IMWRITE_PNG_STRATEGY
    choices = [
        ("png level 1", [P, 1]),
        ("png level 3", [P, 3]),
        ("png level 6", [P, 6]),
        ("png level 9", [P, 9]),
        ("png level 1, huffman only", [P, 1, S, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]),
        ("png level 1, rle", [P, 1, S, cv2.IMWRITE_PNG_STRATEGY_RLE]),
        ("webp lossless", [cv2.IMWRITE_WEBP_QUALITY, 101]),
    ]
    raw = sum(f.nbytes for f in frames)
    out = []
    for name, params in choices:
        ext = ".webp" if "webp" in name else ".png"
        size, ms = 0, []
        for f in frames:
            c = time.process_time()
            ok, buf = cv2.imencode(ext, f, params)
            ms.append((time.process_time() - c) * 1e3)
            assert ok
            size += len(buf)
        out.append((name, size / raw, float(np.median(ms))))
    return out


def print_disk_cost(n: int, rows: list[DiskRow], sweep: list[tuple[str, float, float]]) -> None:
    writes = len(rows[0].cpu_ms) if rows else 0
    print(
        f"\n0b. disk cost per part: {n} parts measured, written {writes} times by each "
        "recording choice in turn"
    )
    print(f"  {'':36} {'MB/part':>8} {'CPU ms':>7} {'GB/shift':>9} {'per file':>9} "
          f"{'read ms':>8} {'bytes':>6} {'CPU':>7}  lossless")  # fmt: skip
    peer = rows[0]  # MCAP none, images raw: what the line wrote before the choice existed
    peer_cpu = float(np.median(peer.cpu_ms))
    for r in rows:
        mcap = r.lossless is not None
        lossless = "" if not mcap else ("yes" if r.lossless else "NO")
        per_file = f"{r.per_file_bytes / 1e6:7.2f}MB" if mcap else ""
        read = f"{r.read_cpu_ms:8.0f}" if mcap else ""
        cpu = f"{np.median(r.cpu_ms):7.1f}" if r.cpu_ms else ""
        vs = (
            f"{r.bytes_per_part / peer.bytes_per_part:6.3f} {np.median(r.cpu_ms) - peer_cpu:+7.1f}"
            if mcap
            else ""
        )
        print(
            f"  {r.what:36} {r.bytes_per_part / 1e6:8.3f} {cpu:>7} "
            f"{r.bytes_per_part * SHIFT_PARTS / 1e9:9.1f} {per_file:>9} {read:>8} {vs:>14}  "
            f"{lossless}",
            flush=True,
        )
    print("  (CPU: median ms per part, this process; bytes, CPU: ratio and ms against the")
    print("  first row, measured alike; read: replay's CPU reading a part back)")
    print(f"  (a shift: {SHIFT_PARTS} parts, 8 h at 0.5 Hz)")
    print("  lossless image encodings on one frame set:   size/raw   CPU ms a frame")
    for name, ratio, ms in sweep:
        print(f"  {name:44} {ratio:8.3f} {ms:8.1f}", flush=True)


# --------------------------------------------------------------------------- 1: worker at 2 Hz


@dataclass
class ReplayRun:
    shift: Shift
    published: dict[int, int]
    replay_said: str


def run_replay(config: Path, recording: Path, rate_hz: float) -> ReplayRun:
    """Router, worker and replay as separate processes; results collected here."""
    from service import bus
    from service.protocol import Keys, peek_identity

    manifest = json.loads((recording / "manifest.json").read_text())
    speed = manifest["period_s"] * rate_hz
    files = sorted(str(p) for p in (recording / "mcap").glob("*.mcap"))
    port = _free_port()
    ep = f"tcp/127.0.0.1:{port}"
    published: dict[int, int] = {}
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory() as data:
        log = Path(data) / "processes.log"
        try:
            router = _cli("router", "--zenoh-listen", ep, log=log, stdout=subprocess.PIPE)
            procs.append(router)
            assert router.stdout is not None
            if not router.stdout.readline().startswith("zenoh router listening"):
                raise RuntimeError(f"the router did not start:\n{_tail(log)}")
            settings = bus.BusSettings(mode="client", connect=(ep,))
            with bus.open_session(settings) as session:
                worker = _cli(
                    "worker", "--config", str(config), "--data-dir", data, "--zenoh-connect", ep,
                    log=log,
                )  # fmt: skip
                procs.append(worker)
                shift = Shift(worker.pid)

                def on_frames(sample) -> None:
                    now = time.time_ns()
                    seq = peek_identity(sample.payload.to_bytes()).get("seq")
                    if seq is not None:
                        published.setdefault(seq, now)

                frames = bus.RingSubscriber(
                    session, Keys(LINE).frames(STATION), on_frames, capacity=256
                )
                results = _subscribe_results(session, shift, published)
                try:
                    t0 = time.perf_counter()
                    if not _wait_for_token(session, Keys(LINE).workers(), 600):
                        raise RuntimeError(f"the worker did not become ready:\n{_tail(log)}")
                    print(f"  (worker ready in {time.perf_counter() - t0:.0f} s)", flush=True)
                    replay = _cli(
                        "replay", *files, "--publish", "--zenoh-connect", ep,
                        "--speed", f"{speed:g}", "--linger", "2",
                        log=log, stdout=subprocess.PIPE,
                    )  # fmt: skip
                    procs.append(replay)
                    said, _ = replay.communicate(timeout=600 + manifest["sets"] / rate_hz)
                    # The worker's queue may hold a few parts still; each takes seconds.
                    if not shift.wait(lambda: len(shift.arrivals) >= len(published), 120):
                        print(f"  (results still missing after 120 s:)\n{_tail(log)}")
                finally:
                    results.close()
                    frames.close()
        finally:
            _stop(procs)
    return ReplayRun(shift, published, said.strip())


# --------------------------------------------------------------------------- 2: the whole line


def run_line(
    period_s: float, duration_s: float, config: Path, warmup: int = 2
) -> tuple[Shift, float]:
    """``inspection run`` at ``period_s`` for ``duration_s`` seconds of results; returns
    them and the process's CPU seconds per trigger period over the counted span."""
    from service import bus

    port = _free_port()
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "line.log"
        proc = _cli(
            "run", "--config", str(config), "--data-dir", tmp, "--http-port", "0",
            "--zenoh-listen", f"tcp/127.0.0.1:{port}",
            log=log, env={"INSPECTION_TRIGGER_PERIOD_S": str(period_s)}, stdout=subprocess.PIPE,
        )  # fmt: skip
        procs.append(proc)
        shift = Shift(proc.pid, warmup=warmup)
        try:
            assert proc.stdout is not None
            docs = None
            for line in proc.stdout:
                if "API docs:" in line:
                    docs = line.split("API docs:")[1].strip()
                if line.startswith("  data:"):
                    break
            else:
                raise RuntimeError(f"the line did not start:\n{_tail(log)}")
            if docs is not None:
                # Count from readiness on: the API's part registry loads its trees at
                # start-up and competes with the first parts for CPU.
                _wait_ready(docs.replace("/docs", "/v1/health"), 300)
            settings = bus.BusSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
            with bus.open_session(settings) as session:
                sub = _subscribe_results(session, shift, None)
                try:
                    if not shift.wait(lambda: bool(shift.started), warmup * period_s + 120):
                        print(f"  (no result came in:)\n{_tail(log)}", flush=True)
                    else:
                        end = shift.started + duration_s
                        pause = threading.Event()
                        while time.monotonic() < end:
                            pause.wait(min(1.0, end - time.monotonic()))
                finally:
                    sub.close()
        finally:
            _stop(procs)
    return shift, duration_s


# --------------------------------------------------------------------------- printing


def _row(name: str, values: list[float], scale: float = 1.0, fmt: str = "8.0f") -> str:
    if not values:
        return f"  {name:>18}        -"
    a = np.asarray(values) * scale
    return (
        f"  {name:>18} {np.median(a):{fmt}} {np.percentile(a, 90):{fmt}} "
        f"{np.percentile(a, 99):{fmt}} {a.max():{fmt}}  n={len(a)}"
    )


def _goal(what: str, ok: bool, measured: str) -> str:
    return f"  goal {what}: {'met' if ok else 'NOT met'} ({measured})"


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def _load() -> str:
    a, b, c = os.getloadavg()
    return f"{a:.1f} {b:.1f} {c:.1f}"


def print_stages(stages: dict[str, list[float]]) -> None:
    print(f"  ms, this process:  {'p50':>8} {'p90':>8} {'p99':>8} {'max':>8}")
    order = ("simulate", "reconstruct", "guide", "align", "deviations", "total")
    for stage in order:
        for kind in ("wall", "CPU"):
            values = stages.get(f"{stage} {kind}")
            if values:
                print(_row(f"{stage} {kind}", values), flush=True)


def print_shift(shift: Shift, *, published: int | None = None) -> None:
    lat = shift.latencies()
    cpu = shift.cpu_per_part()
    n = len(shift.arrivals)
    head = f"  results {n}" if published is None else f"  published {published}, results {n}"
    print(
        f"{head}, measured {len(shift.measured)}, missed {shift.missed}"
        + ("" if published is None else f", without a result {max(published - n, 0)}"),
        flush=True,
    )
    print(f"  s:                 {'p50':>8} {'p90':>8} {'p99':>8} {'max':>8}")
    print(_row("latency", lat, fmt="8.3f"), flush=True)
    print(_row("CPU per part", cpu, fmt="8.3f"), flush=True)
    print(
        f"  {'CPU overall':>18} {shift.cpu_overall():8.3f} per measured part, "
        f"{shift.cpu_per_trigger():.3f} per trigger (missed ones too); "
        f"{shift.cores_busy():.2f} cores busy from the first result to the last",
        flush=True,
    )
    totals = [a.timings_ms["total"] / 1e3 for a in shift.measured if "total" in a.timings_ms]
    for stage in ("reconstruct", "guide", "align", "deviations", "total"):
        values = [a.timings_ms[stage] / 1e3 for a in shift.measured if stage in a.timings_ms]
        print(_row(f"{stage} wall", values, fmt="8.3f"), flush=True)
    if totals:
        # One worker measures one part at a time: its rate cannot exceed this.
        print(f"  capacity: 1 / median measuring time = {1 / float(np.median(totals)):.2f} Hz")


# --------------------------------------------------------------------------- main


def main() -> int:
    smoke = os.environ.get("BENCH_SMOKE") == "1"
    n_sets = int(os.environ.get("BENCH_LINE_SETS", "64"))
    replay_hz = float(os.environ.get("BENCH_LINE_REPLAY_HZ", "2"))
    line_hz = float(os.environ.get("BENCH_LINE_HZ", "1"))
    duration = float(os.environ.get("BENCH_LINE_DURATION_S", "60" if smoke else "300"))
    cpu_parts = int(os.environ.get("BENCH_LINE_CPU_PARTS", "3" if smoke else "5"))
    rates = [float(r) for r in os.environ.get("BENCH_LINE_RATES_HZ", "").split(",") if r.strip()]
    window = float(os.environ.get("BENCH_LINE_WINDOW_S", "45"))
    disk_parts = int(os.environ.get("BENCH_LINE_DISK_PARTS", "2" if smoke else "4"))
    disk_only = os.environ.get("BENCH_LINE_DISK_ONLY") == "1"
    print(f"load average before: {_load()}  ({os.cpu_count()} cores)", flush=True)
    CACHE.mkdir(parents=True, exist_ok=True)
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        config = line_config(Path(tmp), CACHE / "trees")

        print(f"\n0. stage times, {cpu_parts} parts measured one at a time in this process")
        recording, stages = prepare(config, n_sets, cpu_parts, disk_parts, record=not disk_only)
        print_stages(stages)
        if disk_only:
            return 0

        print(
            f"\n1. worker fed by a recording at {replay_hz:g} Hz: router, worker and "
            f"replay --publish as separate processes ({recording.name}); "
            f"load average {_load()}",
            flush=True,
        )
        print("  latency: result arrival minus its FrameSet's arrival at this process's")
        print("  frames subscriber (replay keeps the recorded triggered_ns); CPU: the worker")
        print("  process, every thread, between consecutive measured results", flush=True)
        rep = run_replay(config, recording, replay_hz)
        print(f"  replay: {rep.replay_said}", flush=True)
        print_shift(rep.shift, published=len(rep.published))
        lat, cpu = rep.shift.latencies(), rep.shift.cpu_per_part()
        unanswered = max(len(rep.published) - len(rep.shift.arrivals), 0)
        med_cpu, p99 = _pct(cpu, 50), _pct(lat, 99)
        checks = [
            ("no missed part", rep.shift.missed == 0 and not unanswered and rep.published,
             f"{rep.shift.missed} missed, {unanswered} without a result, "
             f"of {len(rep.published)}"),
            ("worker CPU per part median <= 0.8 s", med_cpu <= 0.8, f"{med_cpu:.3f} s"),
            ("p99 trigger-to-result < 1.5 s", p99 < 1.5, f"{p99:.3f} s"),
        ]  # fmt: skip
        for what, met, measured in checks:
            print(_goal(what, bool(met), measured), flush=True)
            ok &= bool(met)

        print(
            f"\n2. the whole line in one process (inspection run, configs/line.toml) at "
            f"{line_hz:g} Hz for {duration:.0f} s; load average {_load()}",
            flush=True,
        )
        print("  latency: result arrival minus triggered_ns (the ingest's clock, this host);")
        print("  CPU: the line's process (it renders the frames too)", flush=True)
        shift, _ = run_line(1.0 / line_hz, duration, config)
        print_shift(shift)
        met = bool(shift.arrivals) and shift.missed == 0
        print(_goal("none missed", met, f"{shift.missed} of {len(shift.arrivals)}"), flush=True)
        ok &= met

        if rates:
            print(f"\n3. the whole line at rising rates, {window:.0f} s each", flush=True)
            print(f"  {'rate Hz':>8} {'n':>4} {'missed':>6} {'p50 s':>7} {'p99 s':>7}  sustained")
            for hz in rates:
                w, _ = run_line(1.0 / hz, window, config)
                lat = w.latencies()
                sustained = w.sustained()
                print(
                    f"  {hz:8.2f} {len(w.arrivals):4d} {w.missed:6d} {_pct(lat, 50):7.3f} "
                    f"{_pct(lat, 99):7.3f}  {'yes' if sustained else 'no'}",
                    flush=True,
                )
                if not sustained:
                    break
    print(f"\nload average after: {_load()}", flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
