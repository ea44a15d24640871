"""Simulator speed: one flash frame set (four 1280 x 1024 frames) of the demo panel.

Also what a long flash costs: 2 ms at 1 m/s smears the frames along the belt
and is rendered as the average of sub-exposures.

Wall time and CPU time (all threads) are both printed: on a shared machine
the CPU time says what a frame set costs, the wall time what it took.

Peer, measured in the same run: trimesh's Embree ray caster finding only the
first hit of every pixel's ray of the four cameras (geometry alone, no
shading, shadows or sensor), which is what a ray-traced renderer would pay
before anything else. Medians after a warm-up.

Run: ``python -m bench.bench_simulate`` (or ``make bench``).
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time; the CPU time (all threads) of each call goes to _CPU."""
    times = []
    cpu = []
    for _ in range(repeats):
        start = time.perf_counter()
        c0 = time.process_time()
        fn()
        cpu.append(time.process_time() - c0)
        times.append(time.perf_counter() - start)
    _CPU.append(statistics.median(cpu))
    return statistics.median(times)


_CPU: list[float] = []


def main() -> int:
    from inspection.panel import PanelSpec, sheet_metal_panel
    from inspection.rig import Rig
    from inspection.simulate import RenderOptions, simulate, simulator_for

    rig = Rig.nominal()
    cad = sheet_metal_panel(PanelSpec().scaled(400.0, 260.0))
    mesh = cad.to_trimesh()
    a = np.deg2rad(30.0)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = (60.0, -40.0, 0.0)

    start = time.perf_counter()
    simulator_for(rig)
    build_s = time.perf_counter() - start
    for _ in range(2):  # warm-up: numba loads its cached kernels
        simulate(rig, mesh, T, seed=0)
    repeats = 7
    seeds = iter(range(1, 1000))
    sim_s = _median_time(lambda: simulate(rig, mesh, T, seed=next(seeds)), repeats)
    clean_s = _median_time(
        lambda: simulate(rig, mesh, T, seed=0, options=RenderOptions.clean()), repeats
    )
    truth_s = _median_time(lambda: simulate(rig, mesh, T, seed=0, return_truth=True), 3)
    # The line's flash (50 us) moves the part a tenth of a pixel: one exposure. A 2 ms
    # flash smears the frames by 2 mm along the belt: the average of sub-exposures.
    long_flash = RenderOptions(flash_us=2000.0)
    smear_s = _median_time(lambda: simulate(rig, mesh, T, seed=0, options=long_flash), 3)

    rows = [
        ("simulate (faults, noise)", sim_s, _CPU[0]),
        ("simulate (clean)", clean_s, _CPU[1]),
        ("simulate + ground truth", truth_s, _CPU[2]),
        ("simulate, 2 ms flash at 1 m/s (motion blur)", smear_s, _CPU[3]),
    ]
    peer_s = None
    try:
        import trimesh

        posed = mesh.copy()
        posed.apply_transform(T)
        belt = trimesh.creation.box((3000.0, 3000.0, 1.0))
        belt.apply_translation((0.0, 0.0, -0.5))
        scene = trimesh.util.concatenate([posed, belt])
        intersector = scene.ray  # type: ignore[attr-defined]
        origins, dirs = [], []
        for cam in rig.cameras:
            o, d = cam.rays(cam.pixel_grid())
            origins.append(o)
            dirs.append(d)
        o_all = np.concatenate(origins)
        d_all = np.concatenate(dirs)
        intersector.intersects_first(o_all[:1000], d_all[:1000])  # warm-up
        peer_s = _median_time(lambda: intersector.intersects_first(o_all, d_all), 3)
        name = type(intersector).__module__.split(".")[-1]
        rows.append((f"peer: trimesh {name} first hits only", peer_s, _CPU[-1]))
    except Exception as exc:  # a bench must report, not die, when a peer is unavailable
        print(f"peer skipped: {exc}")

    n_px = sum(c.width * c.height for c in rig.cameras)
    print(
        f"rig {rig.id}, 4 x {rig.cameras[0].width} x {rig.cameras[0].height} px, "
        f"panel {len(cad.faces)} faces, "
        f"OMP/numba threads {os.environ.get('NUMBA_NUM_THREADS', 'default')}"
    )
    print(f"one-off set-up (rays, slide, belt): {build_s:.2f} s")
    print(f"load average (1 min) {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'what':<44} {'median s':>9} {'CPU s':>7} {'Mpx/s':>7} {'vs simulate':>12}")
    for name, s, cpu in rows:
        print(f"{name:<44} {s:9.3f} {cpu:7.3f} {n_px / s / 1e6:7.1f} {s / sim_s:12.2f}")
    ok = sim_s <= 1.0
    print(
        f"check: simulate <= 1 s per frame set: {'yes' if ok else 'NO'} ({sim_s:.3f} s; aim 0.3 s)"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
