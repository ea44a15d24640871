"""End to end: how well the line places a part and measures its dents, over poses and seeds.

The line's own sequence, ``inspection.measure_frames`` with the line's
parameters, on the demo panel (400 x 260 mm) with dents of 0.3, 0.5 and
1.0 mm pressed in at three comparison points and two comparison points on
the undented surface: frames rendered with ``Rig.nominal()`` (the truth),
measured with ``Rig.default()`` (the calibrated rig, as on the line), the
comparison points over a support radius of 10 mm. Six poses across the
belt, seeds ``BENCH_E2E_SEEDS`` (default 11,12); ``BENCH_E2E_GUIDED=0``
stops after the first pass; ``BENCH_E2E_WEIGHTS=1`` (or 0) fits with (or
without) the reconstruction's per-point weights, and ``BENCH_E2E_MAX_POINTS``
subsamples the clouds to that many points to fit (``BENCH_E2E_GUIDE_POINTS``
for the fits that place the guide), ``BENCH_E2E_STRIDE``
refines every n-th column of the rectified images, and ``BENCH_E2E_RECON``
(``name=value`` pairs, comma-separated, e.g. ``warp_passes=1,shading=0``)
sets any other field of ``ReconstructParams``, instead of the line's
choices. Then the same poses rendered with a longer flash
(``BENCH_E2E_LONG_FLASH_US``, default 2000; 0 leaves it out): what a slow
flash costs when the part moves during the exposure. Last
(``BENCH_E2E_RPS=0`` leaves it out), the default line's second part, aligned
by its RPS: the pose its datums give beside the best fit it starts from.

Per trial: the rotation error of the fitted pose; the largest displacement
of the part's bounding-box corners (also after the first pass and after the
guided pass, which shows what each later step gains); the displacement of
the part's origin (the centre of its footprint); the largest
comparison-point error, also at the true pose, which separates the
reconstruction's local error from the fit's, and with a 4 mm support
beside it; and the seconds from frames to result. Then, per stage, the CPU
seconds (this process, every thread) and wall seconds per part, median and
p90: the sequence's goal is 0.6 CPU-s per part. Goals (the line's): the
pose within 0.05 deg and 0.1 mm, comparison points within +-0.05 mm. The
pose's 0.1 mm is its translation: the displacement of the part's origin.
The corners are printed as well but not held to 0.1 mm: 0.05 deg, the
rotation the goal allows, alone moves them by 0.2 mm. No peer: the figures
are the line's accuracy, not a speed.

Run: ``python -m bench.bench_endtoend`` (or ``make bench BENCH=endtoend``).
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

POSES = [  # (x mm, y mm, rotation about z in degrees)
    (40.0, -30.0, 25.0),
    (0.0, 0.0, 0.0),
    (-100.0, 80.0, 90.0),
    (120.0, -60.0, -40.0),
    (-50.0, -150.0, 160.0),
    (80.0, 150.0, -120.0),
]
# Comparison points on the panel's top (panel frame, mm) and the dent pressed in there.
SITES = {
    "dent_0.3": (-60.0, 30.0, 0.3),
    "dent_0.5": (60.0, -70.0, 0.5),
    "dent_1.0": (125.0, 10.0, 1.0),
    "flat_a": (-120.0, 75.0, 0.0),
    "flat_b": (10.0, 10.0, 0.0),
}
RADIUS_MM = 10.0
SMALL_RADIUS_MM = 4.0
ROTATION_GOAL_DEG = 0.05
SHIFT_GOAL_MM = 0.1
DEVIATION_GOAL_MM = 0.05


def comparison_points(mesh, radius_mm: float = RADIUS_MM):  # type: ignore[no-untyped-def]
    """The comparison points of SITES on the (undented) mesh's top, tolerance +-0.2 mm."""
    from inspection.deviations import ComparisonPoint

    out = []
    for name, (x, y, _) in SITES.items():
        loc, _, tri = mesh.ray.intersects_location([[x, y, 500.0]], [[0.0, 0.0, -1.0]])
        k = int(np.argmax(loc[:, 2]))
        normal = mesh.face_normals[tri[k]]
        out.append(ComparisonPoint(name, tuple(loc[k]), tuple(normal), -0.2, 0.2, radius_mm))
    return out


def params():  # type: ignore[no-untyped-def]
    """The line's measuring parameters (those the demo part's spec gives)."""
    from inspection.measure import MeasureParams

    return MeasureParams()


def dents():  # type: ignore[no-untyped-def]
    """The dents of SITES: flat-bottomed out to 16 mm, so that the truth over the
    10 mm support radius is the depth itself."""
    from inspection.defects import Dent

    return [Dent((x, y, 0.0), (0.0, 0.0, 1.0), d, 30.0, 16.0) for x, y, d in SITES.values()]


def main() -> int:
    import trimesh

    from inspection.defects import press
    from inspection.deviations import deviations
    from inspection.measure import PartModel, measure_frames
    from inspection.panel import PanelSpec, sheet_metal_panel
    from inspection.reconstruct import Reconstructor, ReconstructParams
    from inspection.rig import Rig, belt_pose
    from inspection.simulate import RenderOptions, simulate
    from inspection.transforms import apply

    seeds = [int(s) for s in os.environ.get("BENCH_E2E_SEEDS", "11,12").split(",") if s]
    p = params()
    if "BENCH_E2E_GUIDED" in os.environ:
        p = dataclasses.replace(p, guided=os.environ["BENCH_E2E_GUIDED"] != "0")
    if "BENCH_E2E_WEIGHTS" in os.environ:
        p = dataclasses.replace(p, use_weights=os.environ["BENCH_E2E_WEIGHTS"] != "0")
    if "BENCH_E2E_GUIDE_POINTS" in os.environ:
        p = dataclasses.replace(p, guide_points=int(os.environ["BENCH_E2E_GUIDE_POINTS"]))
    if "BENCH_E2E_MAX_POINTS" in os.environ:
        p = dataclasses.replace(p, max_points=int(os.environ["BENCH_E2E_MAX_POINTS"]))
    cad = sheet_metal_panel(PanelSpec().scaled(400.0, 260.0))
    mesh = cad.to_trimesh()
    dented = press(mesh, dents())
    part = PartModel.build(cad, comparison_points(mesh))  # once per part, as the line does
    small = comparison_points(mesh, SMALL_RADIUS_MM)
    rp = ReconstructParams()
    if "BENCH_E2E_STRIDE" in os.environ:
        rp = dataclasses.replace(rp, stride=int(os.environ["BENCH_E2E_STRIDE"]))
    for item in filter(None, os.environ.get("BENCH_E2E_RECON", "").split(",")):
        key, _, value = item.partition("=")
        kind = type(getattr(rp, key))
        rp = dataclasses.replace(rp, **{key: value != "0" if kind is bool else kind(value)})
    rec = Reconstructor.build(Rig.default(), rp)
    truth_rig = Rig.nominal()
    corners = trimesh.bounds.corners(cad.bounds)

    def site_error(T_cad_rig: np.ndarray, cloud_points: np.ndarray, points) -> tuple[float, str]:  # type: ignore[no-untyped-def]
        dev = deviations(part.tree, apply(T_cad_rig, cloud_points), points)
        errors = {c.name: c.deviation_mm + SITES[c.name][2] for c in dev.comparison}
        worst = max(errors, key=lambda k: abs(errors[k]))
        return errors[worst], worst

    def pose_error(dT: np.ndarray) -> tuple[float, float]:
        cos = (np.trace(dT[:3, :3]) - 1.0) / 2.0
        angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        return angle, float(np.linalg.norm(apply(dT, corners) - corners, axis=1).max())

    print(
        f"CAD-guided second pass: {p.guided}; per-point weights in the fit: {p.use_weights}; "
        f"clouds fitted on at most {p.max_points} points"
    )
    print(
        f"{'seed':>4} {'pose (x, y, deg)':>20} {'rot deg':>8} {'corners mm':>10} "
        f"{'1st pass':>8} {'guided':>8} {'centre':>8} {'site err mm':>11} {'(where)':>9} "
        f"{'at true pose':>12} {'4 mm supp.':>10} {'s':>5}"
    )
    rows = []
    stage_wall: dict[str, list[float]] = {}
    stage_cpu: dict[str, list[float]] = {}
    for seed in seeds:
        for x, y, deg in POSES:
            T_rig_part = belt_pose(x, y, deg)
            frames = simulate(truth_rig, dented, T_rig_part, seed=seed)
            start = time.perf_counter()
            m = measure_frames(part, rec, frames, p)
            seconds = time.perf_counter() - start
            for stage, ms in m.timings_ms.items():
                stage_wall.setdefault(stage, []).append(ms / 1e3)
            for stage, ms in m.cpu_ms.items():
                stage_cpu.setdefault(stage, []).append(ms / 1e3)
            if m.transform is None:
                print(f"{seed:4d} ({x:+.0f}, {y:+.0f}, {deg:+.0f}): not measured: {m.reason}")
                rows.append((np.inf,) * 8)
                continue
            fits = [q.fit.transform for q in m.passes if q.fit is not None]
            first = fits[0] @ T_rig_part
            mid = (fits[1] if len(fits) > 2 else fits[-1]) @ T_rig_part
            dT = m.transform @ T_rig_part
            angle, shift = pose_error(dT)
            centre = float(np.linalg.norm(dT[:3, 3]))
            _, shift_first = pose_error(first)
            _, shift_mid = pose_error(mid)
            errors = {c.name: c.deviation_mm + SITES[c.name][2] for c in m.deviations.comparison}
            where = max(errors, key=lambda k: abs(errors[k]))
            err = errors[where]
            err_true, _ = site_error(np.linalg.inv(T_rig_part), m.points, part.comparison_points)
            err_small, _ = site_error(m.transform, m.points, small)
            rows.append(
                (angle, shift, shift_first, shift_mid, centre, abs(err), abs(err_true),
                 abs(err_small))
            )  # fmt: skip
            print(
                f"{seed:4d} {f'({x:+.0f}, {y:+.0f}, {deg:+.0f})':>20} {angle:8.4f} {shift:10.3f} "
                f"{shift_first:8.3f} {shift_mid:8.3f} {centre:8.3f} {err:+11.3f} {where:>9} "
                f"{err_true:+12.3f} {err_small:+10.3f} "
                f"{seconds:5.2f}",
                flush=True,
            )
    angles, shifts, firsts, mids, centres, errs, errs_true, errs_small = (
        np.array(c) for c in zip(*rows, strict=True)
    )
    print()
    checks = [  # (label, values, goal, unit, a goal of the line)
        ("rotation", angles, ROTATION_GOAL_DEG, "deg", True),
        ("displacement of the origin", centres, SHIFT_GOAL_MM, "mm", True),
        ("corner displacement", shifts, SHIFT_GOAL_MM, "mm", False),
        ("  the same after the 1st pass", firsts, SHIFT_GOAL_MM, "mm", False),
        ("  ... after the guided pass", mids, SHIFT_GOAL_MM, "mm", False),
        ("comparison-point error", errs, DEVIATION_GOAL_MM, "mm", True),
        ("  the same at the true pose", errs_true, DEVIATION_GOAL_MM, "mm", False),
        (f"  ... with a {SMALL_RADIUS_MM:.0f} mm support", errs_small, DEVIATION_GOAL_MM, "mm",
         False),
    ]  # fmt: skip
    ok = True
    for label, values, goal, unit, checked in checks:
        within = int(np.sum(values <= goal))
        print(
            f"{label:28s} median {statistics.median(values):.4f} max {values.max():.4f} {unit}; "
            f"within {goal} {unit}: {within} of {len(values)}"
        )
        if checked:
            ok = ok and within == len(values)
    print(f"every trial within the goals: {ok}")
    print(
        "\nper part and stage, s (CPU: this process, every thread; goal: total CPU median <= 0.6)"
    )
    print(f"  {'stage':>12} {'CPU p50':>8} {'CPU p90':>8} {'wall p50':>9} {'wall p90':>9}")
    for stage in ("reconstruct", "guide", "align", "deviations", "total"):
        c, w = stage_cpu.get(stage, []), stage_wall.get(stage, [])
        if c and w:
            print(f"  {stage:>12} {np.median(c):8.3f} {np.percentile(c, 90):8.3f} "
                  f"{np.median(w):9.3f} {np.percentile(w, 90):9.3f}")  # fmt: skip

    # What a longer flash costs: the part moves during the exposure, and the
    # frames smear along the belt.
    flash_us = float(os.environ.get("BENCH_E2E_LONG_FLASH_US", "2000"))
    if flash_us > 0:
        print(f"\nflash of {flash_us:.0f} us at the belt's speed (seed {seeds[0]}; the line's: "
              f"{RenderOptions().flash_us:.0f} us)")  # fmt: skip
        worst = [0.0, 0.0, 0.0]
        for x, y, deg in POSES:
            T_rig_part = belt_pose(x, y, deg)
            options = RenderOptions(flash_us=flash_us)
            frames = simulate(truth_rig, dented, T_rig_part, seed=seeds[0], options=options)
            m = measure_frames(part, rec, frames, p)
            if m.transform is None:
                print(f"  ({x:+.0f}, {y:+.0f}, {deg:+.0f}): not measured: {m.reason}")
                continue
            dT = m.transform @ T_rig_part
            angle, _ = pose_error(dT)
            centre = float(np.linalg.norm(dT[:3, 3]))
            err = max(abs(c.deviation_mm + SITES[c.name][2]) for c in m.deviations.comparison)
            worst = [max(worst[0], angle), max(worst[1], centre), max(worst[2], err)]
            print(f"  ({x:+.0f}, {y:+.0f}, {deg:+.0f}): rotation {angle:.4f} deg, origin "
                  f"{centre:.3f} mm, worst comparison point {err:.3f} mm")  # fmt: skip
        print(f"  max: rotation {worst[0]:.4f} deg, origin {worst[1]:.3f} mm, "
              f"comparison point {worst[2]:.3f} mm")  # fmt: skip
    if os.environ.get("BENCH_E2E_RPS", "1") != "0":
        rps_beside(rec, truth_rig, seeds, pose_error)
    return 0 if ok else 1


def rps_beside(rec, truth_rig, seeds, pose_error) -> None:  # type: ignore[no-untyped-def]
    """The default line's second part (configs/parts/demo-panel-features.toml, holes as
    drawn) at the same poses: the pose its RPS gives beside the best fit it starts from,
    against the truth (its datums' own place)."""
    import tempfile
    from pathlib import Path

    import trimesh

    from inspection.measure import measure_frames
    from inspection.rig import belt_pose
    from inspection.simulate import simulate
    from service.config import load_part_spec
    from service.parts import load_part

    parts = Path(__file__).resolve().parents[1] / "configs" / "parts"
    spec = load_part_spec(parts / "demo-panel-features.toml")
    with tempfile.TemporaryDirectory() as trees:
        loaded = load_part(spec, parts, Path(trees))
    mesh = trimesh.Trimesh(loaded.cad.vertices, loaded.cad.faces, process=False)
    print(f"\n{spec.name}, aligned by its RPS (H1, the slot, three surface points), the same "
          "poses: rotation deg and origin mm of the RPS pose | of its best fit")  # fmt: skip
    rps, fit = [], []
    for seed in seeds:
        for x, y, deg in POSES:
            T_rig_part = belt_pose(x, y, deg)
            m = measure_frames(loaded.model, rec, simulate(truth_rig, mesh, T_rig_part, seed=seed),
                               loaded.params)  # fmt: skip
            if m.rps is None or m.transform is None or m.registration is None:
                print(f"{seed:4d} ({x:+.0f}, {y:+.0f}, {deg:+.0f}): not aligned: {m.reason}")
                continue
            row = []
            for T, out in ((m.transform, rps), (m.registration.transform, fit)):
                dT = np.asarray(T) @ T_rig_part
                out.append((pose_error(dT)[0], float(np.linalg.norm(dT[:3, 3]))))
                row.append(out[-1])
            (ar, orr), (af, of) = row
            where = f"({x:+.0f}, {y:+.0f}, {deg:+.0f})"
            print(f"{seed:4d} {where:>20} {ar:8.4f} {orr:7.3f} | {af:8.4f} {of:7.3f}")
    for label, rows in (("RPS", rps), ("best fit", fit)):
        if rows:
            a, o = (np.array(c) for c in zip(*rows, strict=True))
            print(
                f"  {label:8s} rotation median {np.median(a):.4f} max {a.max():.4f} deg, "
                f"origin median {np.median(o):.3f} max {o.max():.3f} mm ({len(a)} trials)"
            )


if __name__ == "__main__":
    raise SystemExit(main())
