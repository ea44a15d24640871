"""What a starting station tells: each phase by name, its progress, and whether
this is a first start.

A first start builds each part's tree and compiles the numerical kernels
(minutes); a later one loads both from their caches (seconds). Which of the
two happens is read from the caches themselves, never assumed: the tree
cache is the part registry's (a job says "building tree" only when no cached
tree matches), the kernel cache is numba's (``NUMBA_CACHE_DIR``, which the
``inspection`` package points at a folder per version of its sources when it
is not set).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from numba.core import event

from .models import Job, JobState
from .parts import PartRegistry

Talk = Callable[[str], None]
"""Where start-up lines go (stdout in the CLI; a log in tests)."""

_STEP = 10
"""A tree build's progress is told every this many per cent."""
_UNTOLD = frozenset({"queued", "starting", "ready"})
"""Job messages that name no phase (the part's readiness is told with its time)."""


def kernel_cache_dir() -> Path:
    """Where numba keeps compiled kernels: ``NUMBA_CACHE_DIR``, which importing
    ``inspection`` (as this module does, through the part registry) always sets."""
    return Path(os.environ["NUMBA_CACHE_DIR"])


def cached_kernels(root: Path | None = None) -> int:
    """How many compiled kernels (numba index files) the cache holds."""
    base = root if root is not None else kernel_cache_dir()
    if not base.is_dir():
        return 0
    return sum(1 for _ in base.rglob("*.nbi"))


def kernels_line(root: Path | None = None) -> str:
    """One line on the kernel cache: found, or a first start that compiles."""
    base = root if root is not None else kernel_cache_dir()
    n = cached_kernels(base)
    if n == 0:
        return (
            f"kernels: none compiled yet in {base}: a first start, they compile during the "
            "warm-up (minutes on two cores)"
        )
    return f"kernels: {n} compiled kernels cached in {base} (loaded during the warm-up)"


class _KernelCompiles(event.Listener):
    """Counts our kernels as numba compiles them (a kernel loaded from the cache
    compiles nothing) and tells the count at most every ``every_s`` seconds;
    :meth:`tick` tells a kernel that is still compiling after ``every_s``
    (one alone can take minutes on a loaded machine)."""

    def __init__(self, talk: Talk, every_s: float, ours: tuple[str, ...]) -> None:
        self.talk, self.every_s, self.ours = talk, every_s, ours
        self.compiled = 0
        self._lock = threading.Lock()
        self._t0 = self._told = time.monotonic()
        self._compiling: list[tuple[str, float]] = []  # nested: a kernel calls kernels

    def _name(self, ev: event.Event) -> str | None:
        func = ev.data["dispatcher"].py_func
        if not func.__module__.startswith(self.ours):  # numba's own overloads compile too
            return None
        return f"{func.__module__.removeprefix('inspection.')}.{func.__qualname__}"

    def on_start(self, ev: event.Event) -> None:
        name = self._name(ev)
        if name is not None:
            with self._lock:
                self._compiling.append((name, time.monotonic()))

    def on_end(self, ev: event.Event) -> None:
        name = self._name(ev)
        if name is None:
            return
        with self._lock:
            if self._compiling:
                self._compiling.pop()
            self.compiled += 1
            now = time.monotonic()
            if now - self._told < self.every_s:
                return
            self._told = now
            n = self.compiled
        self.talk(f"kernels: compiling, {n} done in {now - self._t0:.0f} s (latest {name})")

    def tick(self) -> None:
        """Tell the kernel compiling now if nothing was told for ``every_s``."""
        with self._lock:
            now = time.monotonic()
            if not self._compiling or now - self._told < self.every_s:
                return
            self._told = now
            name, since = self._compiling[-1]
            n = self.compiled
        self.talk(f"kernels: compiling {name} for {now - since:.0f} s ({n} done)")


_OURS = ("inspection.", "service.")


@contextlib.contextmanager
def kernel_compiles(
    talk: Talk, *, every_s: float = 5.0, ours: tuple[str, ...] = _OURS
) -> Iterator[_KernelCompiles]:
    """Tell the kernels numba compiles meanwhile (a first start's long phase): their
    count, or the one still compiling, every ``every_s`` seconds, and the total at
    the end if any compiled. ``ours``: the module prefixes whose kernels count."""
    listener = _KernelCompiles(talk, every_s, ours)
    done = threading.Event()

    def ticking() -> None:
        while not done.wait(min(1.0, every_s) or 0.1):
            listener.tick()

    ticker = threading.Thread(target=ticking, name="kernel-talk", daemon=True)
    t0 = time.monotonic()
    with event.install_listener("numba:compile", listener):
        ticker.start()
        try:
            yield listener
        finally:
            done.set()
            ticker.join()
    if listener.compiled:
        talk(
            f"kernels: {listener.compiled} compiled in {time.monotonic() - t0:.0f} s "
            "(cached for the next start)"
        )


def phase(job: Job) -> str:
    """A job's phase as told: its message, with the per cent of a tree build."""
    if job.state is JobState.failed:
        return f"failed: {job.message}"
    if job.message == "building tree":
        pct = int(100 * job.progress) // _STEP * _STEP
        return f"no cached tree: building it (a first start of this part), {pct}%"
    return job.message


def preload(registry: PartRegistry, talk: Talk) -> dict[str, bool]:
    """Build or load every registered part's tree, one part after the other, telling
    each phase as it starts (and a tree build every 10 %).

    Returns
    -------
    dict of part name to bool
        True where the tree was built (a tree file appeared in the cache),
        False where it was loaded.
    """
    told: dict[str, str] = {}

    def on_job(job: Job) -> None:
        if job.message in _UNTOLD:
            return
        line = phase(job)
        if told.get(job.part) != line:
            told[job.part] = line
            talk(f"part {job.part}: {line}")

    built: dict[str, bool] = {}
    unwatch = registry.watch(on_job)
    try:
        for name in registry.names():
            t0 = time.perf_counter()
            before = _cached_files(registry.trees_dir)
            final = registry.wait(registry.start(name).id)
            built[name] = bool(_cached_files(registry.trees_dir) - before)
            if final.state is JobState.done:
                talk(f"part {name}: ready in {time.perf_counter() - t0:.1f} s")
    finally:
        unwatch()
    return built


def _cached_files(folder: Path) -> set[str]:
    """The tree files of a cache (its alignment models are cached beside them)."""
    if not folder.is_dir():
        return set()
    return {p.name for p in folder.glob("*.npz") if "-align-" not in p.name}
