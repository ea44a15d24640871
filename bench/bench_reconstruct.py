"""Reconstruction: speed and accuracy on simulated frames of the demo panel.

For a 400 x 260 mm sheet-metal panel in several poses across the conveyor,
frames are rendered with ``Rig.nominal()`` (the truth) and reconstructed with
the same rig (the algorithm alone) and with ``Rig.default()`` (the calibrated
rig of configs/, as on the line: calibration error included), and, as the
line does, matched again with the CAD at the pose ``align`` finds in that
cloud guiding the windows (``Reconstructor.guided``), and its windows on
bends once more with the CAD at the pose fitted to that
(``Reconstructor.rematch_bends``). Accuracy is the exact
point-to-mesh distance to the truly posed mesh (trimesh's closest point, on
the points a dense surface sample puts within 2 mm): RMS of the points within
1 mm, and the fraction of points within 1 mm.

Peer, measured in the same run: OpenCV's StereoSGBM (3-way) at full
resolution over the same rectified images and disparity range, triangulated
the same way (what the refinement and fusion add, in time and accuracy).
Medians after a warm-up.

Run: ``python -m bench.bench_reconstruct`` (or ``make bench``).
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

POSES = [  # (x mm, y mm, rotation about z in degrees)
    (0.0, 0.0, 0.0),
    (60.0, -40.0, 30.0),
    (-150.0, 70.0, 75.0),
    (170.0, 90.0, -120.0),
]
RMS_GOAL_MM = 0.15
TIME_GOAL_S = 0.5
MIN_POINTS = 100_000


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def distances_to_mesh(mesh, points: np.ndarray, search_mm: float = 2.0) -> np.ndarray:
    """Exact distance of each point to the mesh (inf beyond ``search_mm``).

    trimesh's closest point is exact but slow far from the surface, so a
    dense surface sample (spacing ~0.3 mm) first rules out the far points.
    """
    import trimesh
    from scipy.spatial import cKDTree

    samples, _ = trimesh.sample.sample_surface(mesh, 1_500_000, seed=0)
    coarse, _ = cKDTree(samples).query(points, distance_upper_bound=search_mm)
    out = np.full(len(points), np.inf)
    near = coarse <= search_mm
    if near.any():
        _, d, _ = trimesh.proximity.closest_point(mesh, points[near])
        out[near] = d
    return out


def _accuracy(dist: np.ndarray) -> tuple[float, float, float]:
    near = dist <= 1.0
    rms = float(np.sqrt(np.mean(dist[near] ** 2))) if near.any() else float("nan")
    med = float(np.median(dist[near])) if near.any() else float("nan")
    return rms, med, float(near.mean()) if len(dist) else 0.0


def _sgbm_peer(rec, frames):  # type: ignore[no-untyped-def]
    """Full-resolution SGBM over the reconstructor's rectified pairs, triangulated."""
    import cv2

    pts = []
    for k, pair in enumerate(rec.pairs):
        left = cv2.remap(frames[pair.left], *pair.maps_left, cv2.INTER_LINEAR)
        right = cv2.remap(frames[pair.right], *pair.maps_right, cv2.INTER_LINEAR)
        d_min, d_max = pair.disparity_range(rec.volume_lo, rec.volume_hi)
        lo = int(np.floor(d_min)) - 2
        num = int(np.ceil((d_max - lo + 2) / 16.0)) * 16
        sgbm = cv2.StereoSGBM_create(
            minDisparity=lo,
            numDisparities=num,
            blockSize=5,
            P1=200,
            P2=800,
            disp12MaxDiff=1,
            uniquenessRatio=10,
            speckleWindowSize=100,
            speckleRange=2,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )
        raw = sgbm.compute(left, right)
        d = raw.astype(np.float64) / 16.0
        fg = (raw > (lo - 1) * 16) & (d > rec.foreground_disparity[k])
        ys, xs = np.nonzero(fg)
        p = pair.triangulate(xs.astype(np.float64), ys.astype(np.float64), d[ys, xs])
        pts.append(p[p[:, 2] >= rec.params.z_min_mm])
    return np.concatenate(pts)


def main() -> int:
    from inspection.measure import MeasureParams, PartModel, measure_frames
    from inspection.panel import PanelSpec, sheet_metal_panel
    from inspection.reconstruct import Reconstructor
    from inspection.rig import Rig, belt_pose
    from inspection.simulate import simulate

    truth = Rig.nominal()
    cad = sheet_metal_panel(PanelSpec().scaled(400.0, 260.0))
    rigs = {"nominal": truth}
    try:
        rigs["default"] = Rig.default()
    except FileNotFoundError as exc:
        print(f"(no calibrated rig: {exc})")

    start = time.perf_counter()
    recs = {name: Reconstructor.build(r) for name, r in rigs.items()}
    build_s = (time.perf_counter() - start) / len(recs)

    part = PartModel.build(cad)
    ok = True
    rows = []
    guided_times: list[float] = []
    sim_times: list[float] = []
    rec_times: list[float] = []
    rec_cpu: list[float] = []
    peer_times: list[float] = []
    stage_ms: dict[str, list[float]] = {}
    for i, (x, y, deg) in enumerate(POSES):
        T = belt_pose(x, y, deg)
        mesh = cad.to_trimesh()
        mesh.apply_transform(T)
        frames = simulate(truth, cad.to_trimesh(), T, seed=i)  # warm-up on the first pose
        sim_times.append(
            _median_time(lambda T=T, i=i: simulate(truth, cad.to_trimesh(), T, seed=i), 3)
        )
        for name, rec in recs.items():
            rec(frames)  # warm-up (numba loads its cached kernel)
            cloud = rec(frames)
            if name == "nominal":
                # Reconstruction and peer alternate, so that both see the same load.
                _sgbm_peer(rec, frames)
                for _ in range(5):
                    start, cpu = time.perf_counter(), time.process_time()
                    rec(frames)
                    rec_times.append(time.perf_counter() - start)
                    rec_cpu.append(time.process_time() - cpu)
                    start = time.perf_counter()
                    _sgbm_peer(rec, frames)
                    peer_times.append(time.perf_counter() - start)
                for key, v in cloud.report.timings_ms.items():
                    stage_ms.setdefault(key, []).append(v)
            dist = distances_to_mesh(mesh, cloud.points)
            rms, med, frac = _accuracy(dist)
            rows.append(
                (f"pose {i} ({x:+.0f}, {y:+.0f}, {deg:+.0f} deg)", name, len(cloud), frac, rms, med)
            )
            if name == "nominal":
                ok &= len(cloud) >= MIN_POINTS and rms <= RMS_GOAL_MM
            else:
                # The line's passes, as its sequence makes them: guided by the CAD at
                # the pose fitted to this cloud, then the bends again.
                m = measure_frames(part, rec, frames, MeasureParams())
                labels = {"guided": "  then guided (CAD at fitted pose)",
                          "bends": "  then its bends again"}  # fmt: skip
                for p in m.passes[1:]:
                    rms, med, frac = _accuracy(distances_to_mesh(mesh, p.points))
                    rows.append((labels[p.name], name, len(p.points), frac, rms, med))
                guided_times.append(m.timings_ms["guide"] / 1e3)
        if i == 0:
            rec = recs["nominal"]
            peer_pts = _sgbm_peer(rec, frames)
            rms, med, frac = _accuracy(distances_to_mesh(mesh, peer_pts))
            rows.append(("pose 0, peer: full-res SGBM", "nominal", len(peer_pts), frac, rms, med))

    print("accuracy against the true posed mesh (exact point-to-mesh distance)")
    print(f"{'frames':34s} {'rig':8s} {'points':>8s} {'<=1mm':>7s} {'RMS mm':>8s} {'median':>8s}")
    for label, name, n, frac, rms, med in rows:
        print(f"{label:34s} {name:8s} {n:8d} {frac:7.1%} {rms:8.3f} {med:8.3f}")
    rec_s = statistics.median(rec_times)
    sim_s = statistics.median(sim_times)
    peer_s = statistics.median(peer_times)
    print()
    print(f"Reconstructor.build: {build_s * 1e3:.0f} ms (once per rig)")
    print(f"simulate (four 1280x1024 frames):     {sim_s * 1e3:7.0f} ms  (median over poses)")
    print(
        f"reconstruct (four 1280x1024 frames):  {rec_s * 1e3:7.0f} ms  "
        f"goal <= {TIME_GOAL_S * 1e3:.0f} ms"
    )
    if guided_times:
        guided_ms = statistics.median(guided_times) * 1e3
        print(f"guided passes (first fit, guided pass, its fit, bends again): {guided_ms:7.0f} ms")
    cpu_s = statistics.median(rec_cpu)
    cores = os.cpu_count() or 1
    print(
        f"reconstruct CPU time (all threads):   {cpu_s * 1e3:7.0f} ms  "
        f"(/ {cores} cores = {cpu_s / cores * 1e3:.0f} ms: the wall time on idle cores "
        "if all of it ran in parallel)"
    )
    print(
        f"peer full-res SGBM, two pairs:        {peer_s * 1e3:7.0f} ms  ratio reconstruct/peer "
        f"{rec_s / peer_s:.2f}"
    )
    print(
        "reconstruct stages (median ms): "
        + ", ".join(f"{k} {statistics.median(v):.0f}" for k, v in stage_ms.items())
    )
    # The machine is shared: wall times move with the load, so speed is reported
    # (with the load and the ratio to the peer measured alongside) but only the
    # accuracy checks decide the exit status.
    load = os.getloadavg()[0]
    met = "met" if rec_s <= TIME_GOAL_S else "NOT met"
    print(
        f"RATIO reconstruct/full-res SGBM {rec_s / peer_s:.2f}; load average {load:.1f} on "
        f"{os.cpu_count()} cores; speed goal {TIME_GOAL_S} s: {met}"
    )
    print(
        f"checks: points >= {MIN_POINTS} and RMS <= {RMS_GOAL_MM} mm (nominal rig) in every pose:",
        "pass" if ok else "FAIL",
    )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
