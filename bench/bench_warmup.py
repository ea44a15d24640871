"""What the Docker image's build-time warm-up saves a fresh container.

docker/Dockerfile runs ``inspection run --parts 1`` at build time: numba's
cache in the image then holds every kernel the line runs, and the demo
part's tree goes into the volume it seeds. This bench makes the same start
here, as separate processes:

- ``build``: the Dockerfile's step, on an empty numba cache and an empty data
  directory (once);
- ``image's cache``: a fresh container: a copy of the cache the build filled,
  and the trees it built;
- ``no cache`` (the peer): the same start with the trees but an empty numba
  cache, as an image without the warm-up would start.

Each start is ``inspection run --parts 1`` to its exit: parts loaded, kernels
warmed up, one part measured, the line stopped. Per start: wall time and the
child's CPU seconds (user + system), medians over the runs, and the ratio of
the peer to the warmed start, both measured in this run. ``NUMBA_DEBUG_CACHE``
counts the kernels each start compiled and saved: a start from the image's
cache that compiles any is a warm-up that missed a kernel, and fails the
bench's check (the kernels are named).

Environment: BENCH_SMOKE=1 or BENCH_WARMUP_RUNS (default 3) runs of each.

Run: ``python -m bench.bench_warmup`` (or ``make bench BENCH=warmup``).
"""

from __future__ import annotations

import os
import re
import resource
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAVED = re.compile(r"\[cache\] data saved to '([^']+)'")
LOADED = re.compile(r"\[cache\] data loaded from '([^']+)'")


@dataclass
class Start:
    """One start of the line: wall and CPU seconds, kernels compiled and loaded."""

    wall_s: float
    cpu_s: float
    compiled: list[str] = field(default_factory=list)
    loaded: int = 0


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start(cache: Path, data: Path) -> Start:
    """``inspection run --parts 1`` with numba's cache in ``cache``, data in ``data``."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "NUMBA_DEBUG_CACHE": "1",
           "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}  # fmt: skip
    argv = [sys.executable, "-m", "service.cli", "run", "--config", "configs/line.toml",
            "--data-dir", str(data), "--parts", "1", "--http-port", str(_port()),
            "--zenoh-listen", f"tcp/127.0.0.1:{_port()}"]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1800)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"the line's start failed ({done.returncode}): {done.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    compiled = [Path(p).name for p in SAVED.findall(done.stdout)]
    return Start(wall, cpu, compiled, len(LOADED.findall(done.stdout)))


def _row(name: str, starts: list[Start]) -> str:
    wall = statistics.median(s.wall_s for s in starts)
    cpu = statistics.median(s.cpu_s for s in starts)
    compiled = statistics.median(len(s.compiled) for s in starts)
    loaded = statistics.median(s.loaded for s in starts)
    return f"{name:<16} {len(starts):>4} {wall:>9.1f} {cpu:>8.1f} {compiled:>9.0f} {loaded:>7.0f}"


def main() -> int:
    runs = 1 if os.environ.get("BENCH_SMOKE") else int(os.environ.get("BENCH_WARMUP_RUNS", "3"))
    print(f"inspection run --parts 1, {runs} run(s) of each start; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="bench-warmup-") as tmp:
        base = Path(tmp)
        image_cache, built = base / "image-cache", base / "build"
        build = start(image_cache, built)
        trees = built / "trees"
        cache_mb = sum(p.stat().st_size for p in image_cache.rglob("*") if p.is_file()) / 1e6
        trees_mb = sum(p.stat().st_size for p in trees.rglob("*") if p.is_file()) / 1e6
        warmed: list[Start] = []
        cold: list[Start] = []
        for i in range(runs):
            for name, into in (("warm", warmed), ("cold", cold)):
                run_dir = base / f"{name}-{i}"
                (run_dir / "data").mkdir(parents=True)
                shutil.copytree(trees, run_dir / "data" / "trees")
                cache = run_dir / "cache"
                if name == "warm":
                    shutil.copytree(image_cache, cache)
                into.append(start(cache, run_dir / "data"))
    print(f"\n{'start':<16} {'runs':>4} {'wall s':>9} {'CPU s':>8} {'compiled':>9} "
          f"{'loaded':>7}   (medians)")  # fmt: skip
    print(_row("build", [build]))
    print(_row("image's cache", warmed))
    print(_row("no cache", cold))
    cpu_ratio = statistics.median(s.cpu_s for s in cold) / statistics.median(
        s.cpu_s for s in warmed
    )
    wall_ratio = statistics.median(s.wall_s for s in cold) / statistics.median(
        s.wall_s for s in warmed
    )
    print(f"\nno cache / image's cache: {cpu_ratio:.1f}x CPU, {wall_ratio:.1f}x wall")
    print(f"the image carries {cache_mb:.1f} MB of numba cache and {trees_mb:.0f} MB of trees")
    missed = sorted({k for s in warmed for k in s.compiled})
    if missed:
        print(f"CHECK FAILED: a start from the image's cache compiled {len(missed)} kernel(s): "
              f"{', '.join(missed)}")  # fmt: skip
        return 1
    print("check: a start from the image's cache compiled no kernel")
    return 0


if __name__ == "__main__":
    sys.exit(main())
