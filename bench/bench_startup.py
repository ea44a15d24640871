"""Start-up of the line: how long until it runs, and how long it stays silent.

Runs ``inspection run --parts 1`` (the whole line in one process) three ways
from one temporary folder:

- ``first start``: no compiled kernels (an empty ``NUMBA_CACHE_DIR``) and no
  cached tree: a new machine;
- ``new part``: the kernels cached, the tree cache empty: a part the line
  has not seen;
- ``later start``: both cached: every start after the first.

Each start's stdout is read line by line as it comes. Printed per start:
wall seconds until "the line is running", the process's CPU seconds (user +
system, its whole run of one part), the lines it said before running, the
longest silence between two of them and the line that ended it, and
whether it called itself a first start (the summary line of the parts).
Ratios are against the later start of the same run. ``BENCH_STARTUP_ROUNDS``
(default 1) repeats the three and prints medians.
"""

from __future__ import annotations

import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from bench.bench_line import ROOT, _free_port, line_config

READY = "the line is running"


@dataclass
class Start:
    ready_s: float
    cpu_s: float
    lines: int
    silence_s: float
    after_silence: str
    summary: str


def _start(tmp: Path, numba: Path, trees: Path) -> Start:
    config = line_config(tmp, trees)
    env = {
        **os.environ,
        "NUMBA_CACHE_DIR": str(numba),
        "OPENBLAS_NUM_THREADS": "1",
        "PYTHONUNBUFFERED": "1",
    }
    cmd = [
        sys.executable, "-m", "service.cli", "run", "--config", str(config),
        "--data-dir", str(tmp / "data"), "--parts", "1", "--http-port", "0",
        "--zenoh-listen", f"tcp/127.0.0.1:{_free_port()}",
    ]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    said: list[tuple[float, str]] = [(0.0, "(started)")]
    ready = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            said.append((time.perf_counter() - t0, line.rstrip("\n")))
            if line.startswith(READY):
                ready.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    if proc.wait(1800) != 0:
        raise RuntimeError(f"inspection run exited {proc.returncode}: {said[-3:]}")
    reader.join(10)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    upto = next(k for k, (_, text) in enumerate(said) if text.startswith(READY))
    gaps = [(said[k][0] - said[k - 1][0], said[k][1]) for k in range(1, upto + 1)]
    silence, after_silence = max(gaps)
    summary = next((text for _, text in said if "parts ready in" in text), "")
    return Start(said[upto][0], cpu, upto, silence, after_silence, summary.split("; ", 1)[-1])


def main() -> int:
    rounds = int(os.environ.get("BENCH_STARTUP_ROUNDS", "1"))
    runs: dict[str, list[Start]] = {"first start": [], "new part": [], "later start": []}
    for _ in range(rounds):
        tmp = Path(tempfile.mkdtemp(prefix="bench-startup-"))
        try:
            numba, trees = tmp / "numba", tmp / "trees"
            runs["first start"].append(_start(tmp, numba, trees))
            shutil.rmtree(trees)
            shutil.rmtree(tmp / "data")
            runs["new part"].append(_start(tmp, numba, trees))
            shutil.rmtree(tmp / "data")
            runs["later start"].append(_start(tmp, numba, trees))
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    base = statistics.median(s.ready_s for s in runs["later start"])
    base_cpu = statistics.median(s.cpu_s for s in runs["later start"])
    print(f"inspection run --parts 1, {rounds} round(s), medians; {os.cpu_count()} cores")
    print(
        f"{'start':<12} {'ready s':>8} {'x later':>8} {'CPU s':>7} {'x later':>8} "
        f"{'lines':>6} {'silence s':>10}  longest silence ended by / summary"
    )
    for name, starts in runs.items():
        ready = statistics.median(s.ready_s for s in starts)
        cpu = statistics.median(s.cpu_s for s in starts)
        lines = statistics.median(s.lines for s in starts)
        worst = max(starts, key=lambda s: s.silence_s)
        print(
            f"{name:<12} {ready:8.1f} {ready / base:8.1f} {cpu:7.1f} {cpu / base_cpu:8.1f} "
            f"{lines:6.0f} {worst.silence_s:10.1f}  {worst.after_silence[:70]!r}"
        )
        print(f"{'':<12} {'':>8} {'':>8} {'':>7} {'':>8} {'':>6} {'':>10}  {worst.summary!r}")
    # The truth about a first start: said only where trees were built.
    told = {name: all("first start" in s.summary for s in st) for name, st in runs.items()}
    ok = told == {"first start": True, "new part": True, "later start": False}
    print(f"first start told where trees were built, and only there: {'yes' if ok else 'NO'}")
    return 0 if ok else 1
