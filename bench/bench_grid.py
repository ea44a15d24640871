"""Closest-point queries: GridTree against kd-trees and an exact ray-casting scene.

On the generated 600 x 400 mm sheet-metal panel (flange, holes, character
line, embossing), in one run:

- 50,000 queries within 3 mm of the surface (both sides) and 2,000 queries
  10-30 mm off it, in random order;
- GridTree.query (exact local correction) against scipy's cKDTree
  (workers=-1) and pykdtree on 1,000,000 area-uniform surface samples (the
  nearest sample, an approximation) and Open3D's RaycastingScene exact
  closest points (float32), when those peers import;
- accuracy of every method against the exact closest point (Open3D's, or
  trimesh's near the surface when Open3D is missing);
- build time, tree memory and peak RSS for the panel and (when ../shared is
  there) the 84k-face counter model, and the load time of a saved tree.

Times are medians over repeats after a warm-up; the near queries of all
methods are timed in interleaved rounds, so that load from elsewhere hits
them alike, and the median of the rounds' own cKDTree / GridTree ratios is
printed too. Ratios are peer time / grid time; the first line starting
``RATIO`` gives the headline one: against cKDTree with one thread each
(numba's threads set to 1, ``workers=1``), wall and CPU time; the second the
same pair on every core, its CPU time read over calls back to back (see
:mod:`bench.cpu`). On a shared machine a parallel launch of a few
milliseconds waits for a core held elsewhere far longer than one of a second
does (and OpenMP's threads spin while they wait, which counts as CPU time),
so only the one-thread pair compares the searches alike under load.
Exit status 1 when, and only when, an accuracy check fails: speed and build
times are printed beside their goals, never asserted, as they depend on the
machine's load.

Run: ``python -m bench.bench_grid`` (or ``make bench``).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import resource  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from bench.cpu import cpu_per_call  # noqa: E402

N_NEAR = 50_000
N_FAR = 2_000
N_SAMPLES = 1_000_000
# Interleaved timing rounds of the near queries (GridTree GRID_PER_ROUND
# times per round, each peer once).
ROUNDS = 9
GRID_PER_ROUND = 3
# GridTree calls back to back for its CPU time on every core.
CPU_CALLS = 30
KD_CPU_CALLS = 3
# The near queries' speed against cKDTree in the same run.
RATIO_GOAL = 100.0
SHARED_COUNTER = Path(__file__).resolve().parents[1].parent / "shared/data/cad/counter.unitsmm.STL"


def _times(fn: Callable[[], object], repeats: int, warmup: int = 1) -> list[float]:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def _median_time(fn: Callable[[], object], repeats: int, warmup: int = 1) -> float:
    return statistics.median(_times(fn, repeats, warmup))


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _surface(cad, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    tri = cad.vertices[cad.faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    f = rng.choice(len(area), n, p=area / area.sum())
    uv = rng.random((n, 2))
    flip = uv.sum(1) > 1
    uv[flip] = 1 - uv[flip]
    p = tri[f, 0] + uv[:, :1] * (tri[f, 1] - tri[f, 0]) + uv[:, 1:] * (tri[f, 2] - tri[f, 0])
    return p, f


def _queries(cad, n: int, lo: float, hi: float, rng: np.random.Generator) -> np.ndarray:  # type: ignore[no-untyped-def]
    p, f = _surface(cad, n, rng)
    d = rng.uniform(lo, hi, n) * rng.choice([-1.0, 1.0], n)
    return np.ascontiguousarray(p + cad.face_normals[f] * d[:, None])


def _open3d_scene(cad):  # type: ignore[no-untyped-def]
    try:
        import open3d as o3d
    except Exception as exc:  # ImportError, or OSError for a missing libusb
        print(f"note: Open3D peer skipped ({type(exc).__name__}: {exc})")
        return None
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(cad.vertices.astype(np.float32)),
        o3d.core.Tensor(cad.faces.astype(np.uint32)),
    )

    def closest(q: np.ndarray) -> np.ndarray:
        out = scene.compute_closest_points(o3d.core.Tensor(q.astype(np.float32)))
        return out["points"].numpy().astype(np.float64)

    return closest


def _exact_reference(cad, q: np.ndarray, o3d_closest) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Exact closest points: Open3D when present, else trimesh (slow far away)."""
    if o3d_closest is not None:
        return o3d_closest(q)
    import trimesh

    mesh = trimesh.Trimesh(cad.vertices, cad.faces, process=False)
    return np.asarray(trimesh.proximity.closest_point(mesh, q)[0])


def _errors(q: np.ndarray, got: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|distance error| and closest-point displacement, mm."""
    d_err = np.abs(np.linalg.norm(q - got, axis=1) - np.linalg.norm(q - ref, axis=1))
    return d_err, np.linalg.norm(got - ref, axis=1)


def _single_threaded(tree, kd, near: np.ndarray) -> dict[str, list[float]]:  # type: ignore[no-untyped-def]
    """Wall times of the near queries with one thread each: GridTree with one
    numba thread, cKDTree with ``workers=1``, in interleaved rounds.

    On a shared machine a parallel launch waits for a second core that other
    work holds: a query of a few milliseconds can wait longer than it runs,
    while a query of a second hardly notices. One thread each compares the
    two searches, not the scheduler."""
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        runs: dict[str, Callable[[], object]] = {
            "grid": lambda: tree.query(near),
            "kd": lambda: kd.query(near, workers=1),
        }
        out: dict[str, list[float]] = {name: [] for name in runs}
        out.update({f"{name} cpu": [] for name in runs})
        for fn in runs.values():
            fn()
        for _ in range(ROUNDS):
            for name, fn in runs.items():
                for _ in range(GRID_PER_ROUND if name == "grid" else 1):
                    start, cpu = time.perf_counter(), time.process_time()
                    fn()
                    out[name].append(time.perf_counter() - start)
                    out[f"{name} cpu"].append(time.process_time() - cpu)
    finally:
        numba.set_num_threads(threads)
    return out


def main() -> int:
    from scipy.spatial import cKDTree

    from inspection.grid import GridTree, warmup
    from inspection.panel import sheet_metal_panel

    rng = np.random.default_rng(0)
    compile_s = warmup()
    cad = sheet_metal_panel()
    print(
        f"part: generated panel, {len(cad.faces)} faces, {cad.extents.round(1).tolist()} mm; "
        f"kernels ready in {compile_s:.2f} s"
    )

    # ---- build, memory, save/load
    rss0 = _peak_rss_mb()
    t0 = time.perf_counter()
    tree = GridTree.build(cad)
    build_s = time.perf_counter() - t0
    builds = [("panel", len(cad.faces), build_s, tree.nbytes, _peak_rss_mb() - rss0)]
    with tempfile.TemporaryDirectory() as tmp:
        path = tree.save(Path(tmp) / "panel.npz")
        load_s = _median_time(lambda: GridTree.load(path, cad=cad), 5)
        file_mb = path.stat().st_size / 1e6
    counter_load_s = None
    if SHARED_COUNTER.is_file():
        from inspection.cad import load_cad

        counter = load_cad(SHARED_COUNTER)
        rss0 = _peak_rss_mb()
        t0 = time.perf_counter()
        ctree = GridTree.build(counter)
        cbuild_s = time.perf_counter() - t0
        drss = _peak_rss_mb() - rss0
        builds.append(("counter", len(counter.faces), cbuild_s, ctree.nbytes, drss))
        with tempfile.TemporaryDirectory() as tmp:
            cpath = ctree.save(Path(tmp) / "counter.npz")
            counter_load_s = _median_time(lambda: GridTree.load(cpath, cad=counter), 5)
        del ctree
    else:
        print(f"note: {SHARED_COUNTER} not found; counter build skipped")

    # ---- queries and peers
    near = _queries(cad, N_NEAR, 0.0, 3.0, rng)
    far = _queries(cad, N_FAR, 10.0, 30.0, rng)
    samples, _ = _surface(cad, N_SAMPLES, rng)
    t0 = time.perf_counter()
    kd = cKDTree(samples)
    kd_build_s = time.perf_counter() - t0
    o3d_closest = _open3d_scene(cad)
    ref_near = _exact_reference(cad, near, o3d_closest)
    ref_far = _exact_reference(cad, far, o3d_closest)

    methods: list[tuple[str, Callable[[np.ndarray], np.ndarray]]] = [
        ("GridTree.query", lambda q: tree.query(q).points),
        ("scipy cKDTree(workers=-1), 1M samples", lambda q: samples[kd.query(q, workers=-1)[1]]),
    ]
    try:
        from pykdtree.kdtree import KDTree

        pkd = KDTree(samples)
        methods.append(("pykdtree, 1M samples", lambda q: samples[pkd.query(q, k=1)[1]]))
    except ImportError as exc:
        print(f"note: pykdtree peer skipped ({exc})")
    if o3d_closest is not None:
        methods.append(("Open3D RaycastingScene (exact, f32)", o3d_closest))

    # The near queries of all methods are timed in interleaved rounds, so
    # that a burst of load from elsewhere hits every method alike; each
    # round's own ratio to GridTree is kept too (paired ratios).
    near_times: dict[str, list[float]] = {name: [] for name, _ in methods}
    for _, fn in methods:
        fn(near)  # warm-up
    for _ in range(ROUNDS):
        for name, fn in methods:
            for _ in range(GRID_PER_ROUND if name.startswith("GridTree") else 1):
                start = time.perf_counter()
                fn(near)
                near_times[name].append(time.perf_counter() - start)
    # CPU on every core over calls back to back, the threads' spinning after
    # them included (see bench.cpu: read around one parallel call, the clock
    # misses the other threads' share).
    near_cpu = {
        name: cpu_per_call(
            lambda fn=fn: fn(near), CPU_CALLS if name.startswith("GridTree") else KD_CPU_CALLS
        )
        for name, fn in methods[:2]
    }
    single = _single_threaded(tree, kd, near)
    rows = []
    for name, fn in methods:
        times = near_times[name]
        t_near, best_near = statistics.median(times), min(times)
        t_far = _median_time(lambda fn=fn: fn(far), 5 if name.startswith("GridTree") else 3)
        e_near, _ = _errors(near, fn(near), ref_near)
        e_far, disp_far = _errors(far, fn(far), ref_far)
        rows.append((name, t_near, t_far, e_near, e_far, disp_far, best_near))
    grid_rounds = np.median(
        np.array(near_times[methods[0][0]]).reshape(ROUNDS, GRID_PER_ROUND), axis=1
    )
    paired = np.array(near_times[methods[1][0]]) / grid_rounds

    # ---- report
    grid_near, grid_far, grid_best = rows[0][1], rows[0][2], rows[0][6]
    print(f"\n{N_NEAR} queries within 3 mm, {N_FAR} queries 10-30 mm off (random order);")
    print("errors against the exact closest point; ratio = method time / GridTree time")
    print("(medians; 'best' is the fastest repeat, i.e. the least disturbed by other load)")
    print(f"machine load average: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores\n")
    head = (
        f"{'method':40s} {'near ms':>8s} {'Mq/s':>6s} {'ratio':>7s} {'mean um':>9s} {'p99 um':>8s}"
        f" {'max um':>8s}"
        f" | {'far ms':>7s} {'ratio':>6s} {'max disp mm':>11s} | {'best ms':>7s} {'ratio':>6s}"
    )
    print(head)
    print("-" * len(head))
    for name, t_near, t_far, e_near, _e_far, disp_far, best in rows:
        print(
            f"{name:40s} {t_near * 1e3:8.2f} {N_NEAR / t_near / 1e6:6.1f} {t_near / grid_near:7.1f}"
            f" {e_near.mean() * 1e3:9.3f} {np.percentile(e_near, 99) * 1e3:8.3f}"
            f" {e_near.max() * 1e3:8.3f}"
            f" | {t_far * 1e3:7.1f} {t_far / grid_far:6.1f} {disp_far.max():11.4f}"
            f" | {best * 1e3:7.2f} {best / grid_best:6.1f}"
        )
    print(f"\n(kd-tree build on 1M samples: {kd_build_s:.2f} s, not counted above)")

    print(f"\n{'build':10s} {'faces':>7s} {'build s':>8s} {'tree MB':>8s} {'RSS +MB':>8s}")
    for name, nf, bs, nbytes, drss in builds:
        print(f"{name:10s} {nf:7d} {bs:8.2f} {nbytes / 1e6:8.1f} {drss:8.0f}")
    print(f"peak RSS of this process: {_peak_rss_mb():.0f} MB")
    print(f"panel tree file {file_mb:.1f} MB, load (with hash check) {load_s * 1e3:.0f} ms")
    if counter_load_s is not None:
        print(f"counter tree load (with hash check) {counter_load_s * 1e3:.0f} ms")

    # ---- the headline ratio, then the checks (Done-when figures)
    _, _, _, e_near, e_far, disp_far, _ = rows[0]
    kd_ratio = rows[1][1] / grid_near
    kd_best = rows[1][6] / grid_best
    kd_paired = float(np.median(paired))
    grid_name, kd_name = methods[0][0], methods[1][0]
    kd_cpu = near_cpu[kd_name] / near_cpu[grid_name]
    s_grid = np.array(single["grid"])
    s_kd = np.array(single["kd"])
    s_ratio = float(np.median(s_kd) / np.median(s_grid))
    s_best = float(s_kd.min() / s_grid.min())
    s_paired = float(np.median(s_kd / np.median(s_grid.reshape(ROUNDS, GRID_PER_ROUND), axis=1)))
    s_cpu = float(np.median(single["kd cpu"]) / np.median(single["grid cpu"]))
    threads = os.cpu_count()
    print(
        f"\nRATIO  one thread each (numba 1 thread, cKDTree workers=1): GridTree.query is "
        f"{s_ratio:.1f}x faster than scipy cKDTree on {N_NEAR // 1000}k queries within 3 mm "
        f"(medians {np.median(s_grid) * 1e3:.2f} ms and {np.median(s_kd) * 1e3:.1f} ms; "
        f"{s_cpu:.1f}x in CPU time; {s_best:.1f}x best repeats; {s_paired:.1f}x median of the "
        f"rounds' own ratios); goal >= {RATIO_GOAL:g}x: "
        f"{'met' if s_ratio >= RATIO_GOAL else 'NOT met'} at load {os.getloadavg()[0]:.1f}"
    )
    print(
        f"RATIO  every core: GridTree.query is {kd_ratio:.1f}x faster than scipy "
        f"cKDTree(workers=-1) on {N_NEAR // 1000}k queries within 3 mm (medians; "
        f"{kd_best:.1f}x best repeats; "
        f"{kd_paired:.1f}x median of the {ROUNDS} rounds' own ratios; {kd_cpu:.1f}x in CPU "
        f"time over {CPU_CALLS} calls, {near_cpu[grid_name] * 1e3:.2f} ms per call, the threads' "
        f"spinning included), both on every core ({threads}: numba's threads, cKDTree's workers)"
    )
    off = e_near > 1e-3
    print(
        f"GridTree near answers off by more than 1 um: {int(off.sum())} of {len(e_near)} "
        f"({off.mean():.2%}), at most {e_near.max() * 1e3:.1f} um (faces of a finely meshed "
        "bend closest at none of a cell's corners: see the accuracy notes of inspection.grid)"
    )
    # Accuracy decides the exit status; speed and build figures depend on
    # the machine and its load, so they are reported beside their goals.
    accuracy = [
        ("near mean |error| <= 1 um", e_near.mean() <= 1e-3),
        ("near p99 |error| <= 20 um", np.percentile(e_near, 99) <= 0.02),
        # A far point can have several equally close points (a tie): then the
        # distance, not the point, is what must agree.
        (
            "far closest point within 0.1 mm",
            bool(np.all((disp_far <= 0.1) | (e_far <= 1e-3))),
        ),
    ]
    g = RATIO_GOAL
    goals = [
        (f"near speed >= {g:g}x cKDTree, one thread each (got {s_ratio:.1f}x)", s_ratio >= g),
        (f"near speed >= {g:g}x cKDTree, every core, medians (got {kd_ratio:.1f}x)", kd_ratio >= g),
        (f"near speed >= {g:g}x cKDTree, best repeats (got {kd_best:.1f}x)", kd_best >= g),
        (f"near speed >= {g:g}x cKDTree, paired rounds (got {kd_paired:.1f}x)", kd_paired >= g),
    ]
    if len(builds) > 1:
        cb = builds[1][2]
        goals.append((f"counter build <= 10 s (got {cb:.1f} s)", cb <= 10))
    if counter_load_s is not None:
        cl = counter_load_s
        goals.append((f"counter load <= 0.2 s (got {cl:.3f} s)", cl <= 0.2))
    print("\naccuracy checks (exit status 1 if any fails):")
    for label, ok in accuracy:
        print(f"  {'PASS' if ok else 'FAIL'}  {label}")
    print("speed and build goals (reported only, never the exit status):")
    for label, ok in goals:
        print(f"  {'met    ' if ok else 'NOT met'}  {label}")
    failed = not all(ok for _, ok in accuracy)
    print(f"\nexit status {1 if failed else 0}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
