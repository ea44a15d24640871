"""The comparison-point path against the cloud path, on the same frames; and perspective maps.

Two parts the project generates: the demo panel (400 x 260 mm) and a second
panel of another design (320 x 240 mm: higher crown, its character line,
embossing and holes elsewhere), each with ten comparison points on its top,
three of them dented (0.3, 0.5, 1.0 mm, flat-bottomed out to 16 mm), six
poses across the belt, seeds ``BENCH_CP_SEEDS`` (default 11,12). Frames are
rendered with ``Rig.nominal()`` (the truth) and measured with
``Rig.default()`` (the calibrated rig, as on the line).

Per part and path, on the same frames:

- **cloud**: the line's sequence (``measure_frames``, the line's parameters),
  its comparison points over 10 mm and, from the same cloud and fit, 4 mm;
- **local at the cloud's pose**: local photogrammetry at the ten points
  (``inspection.cadpoints.measure_points``) with the cloud path's final pose:
  the local measurement alone;
- **comparison-point path**: the same sequence with
  ``MeasureParams(path="comparison_points")``: a sparse first pass and the
  global search place the part, then local photogrammetry at that pose;
- **image pose + local**: the targetless alignment in the images alone
  (``inspection.cadpoints.imagepose.image_pose``: the outline fitted in the
  four views, then local photogrammetry at sites over the part fitted to
  the CAD), and the points measured at its pose;
- **local at the true pose**: what the local matching errs by itself.

The comparison-point path's CPU per stage of the sequence (``Measurement.cpu_ms``:
``reconstruct`` its sparse pass, ``align`` the global search and fit,
``points`` the local photogrammetry). Beside them, each path's pose against the
truth: rotation (deg) and the displacement of the part's origin (mm).

The truth at a comparison point is the same robust average of signed
distances over the support, taken over a dense sample of the dented surface
(16 points per mm^2) at the true pose. Printed: time per part (wall and CPU of
this process, median and p90) and the ratio of the cloud path's to each
other's; each comparison point's error (median, max, RMS) at 10 and 4 mm;
the goals are >= 10x faster than the cloud path, no less accurate (max and
RMS, on the points both paths measured: each leaves out the ones it cannot
measure, and the counts are printed beside), 20 ms per part for ten points,
0.02 mm RMS at 10 mm.

Perspective maps: cam0's view of the demo panel at the first pose, queried
under small motions (0.05 to 0.5 deg and 0.2 to 1.5 mm) against ray casting
the moved mesh with trimesh's Embree intersector (the peer, same pixels, same
run): ns per pixel, wall and CPU, medians of five, the ratio, how many pixels
the query ray casts itself, and the largest difference of the two (mm).

Run: ``python -m bench.bench_cadpoints`` (or ``make bench BENCH=cadpoints``).
"""

from __future__ import annotations

import math
import os
import statistics
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from bench.bench_endtoend import POSES  # noqa: E402

SPEED_GOAL = 10.0
TIME_GOAL_MS = 20.0
RMS_GOAL_MM = 0.02
RADII_MM = (10.0, 4.0)
AT_FIT = "local at the cloud's pose"
PATH = "comparison-point path"
IMAGE = "image pose + local"
DEPTHS = (0.3, 0.5, 1.0)
# Ten sites on each part's top (part frame, mm); the first three are dented.
PANEL_SITES = [
    (-60.0, 30.0),
    (60.0, -70.0),
    (125.0, 10.0),
    (-120.0, 75.0),
    (10.0, 10.0),
    (-150.0, -20.0),
    (100.0, 90.0),
    (-20.0, -95.0),
    (160.0, -60.0),
    (-80.0, -50.0),
]
SECOND_SITES = [(40.0, 30.0), (-90.0, 60.0), (100.0, -70.0), (0.0, -20.0), (-120.0, -70.0),
                (120.0, 80.0), (-40.0, 90.0), (60.0, -100.0), (-130.0, 10.0),
                (130.0, 0.0)]  # fmt: skip


def second_part():  # type: ignore[no-untyped-def]
    from inspection.panel import Hole, PanelSpec, sheet_metal_panel

    spec = PanelSpec(
        length_mm=320.0, width_mm=240.0, crown_length_mm=18.0, crown_width_mm=12.0,
        flange_mm=20.0, character_line_y_mm=-55.0, emboss_center_mm=(70.0, 50.0),
        emboss_size_mm=(90.0, 50.0), emboss_height_mm=4.0,
        holes=(Hole(-110.0, -85.0, 12.0), Hole(125.0, 95.0, 8.0)),
    )  # fmt: skip
    return sheet_metal_panel(spec, name="second")


def comparison_points(mesh, sites, radius_mm: float):  # type: ignore[no-untyped-def]
    from inspection.deviations import ComparisonPoint

    out = []
    for k, (x, y) in enumerate(sites):
        loc, _, tri = mesh.ray.intersects_location([[x, y, 500.0]], [[0.0, 0.0, -1.0]])
        i = int(np.argmax(loc[:, 2]))
        out.append(ComparisonPoint(f"p{k}", tuple(loc[i]), tuple(mesh.face_normals[tri[i]]),
                                   -0.2, 0.2, radius_mm))  # fmt: skip
    return out


def truths(part, dented, points) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Each point's deviation on the dented surface itself: a dense sample of it (16 per
    mm^2) around the points, pooled as the paths pool their measurements."""
    import trimesh

    from inspection.deviations import deviations

    centres = np.array([cp.position for cp in points])
    reach = max(cp.radius_mm for cp in points) + 3.0
    c = dented.triangles_center
    near = np.linalg.norm(c[:, None] - centres[None], axis=2).min(axis=1) <= reach
    patch = dented.submesh([np.flatnonzero(near)], append=True)
    sample, _ = trimesh.sample.sample_surface(patch, int(patch.area * 16), seed=0)
    dev = deviations(part.tree, np.asarray(sample), points, min_support=1)
    return np.array([c.deviation_mm for c in dev.comparison])


def _stats(errors: np.ndarray) -> str:
    e = np.abs(errors[np.isfinite(errors)])
    missing = int((~np.isfinite(errors)).sum())
    if len(e) == 0:
        return "nothing measured"
    rms = math.sqrt(float(np.mean(e**2)))
    tail = f", {missing} not measured" if missing else ""
    return f"median {np.median(e):.4f} max {e.max():.4f} RMS {rms:.4f} mm{tail}"


def pose_error(dT: np.ndarray) -> tuple[float, float]:
    """Rotation (deg) and the displacement of the origin (mm) of ``T_fit @ T_true``."""
    cos = (np.trace(dT[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))), float(np.linalg.norm(dT[:3, 3]))


def _p(values: list[float], q: float) -> float:
    return float(np.percentile(values, q))


def _timed(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[Any, float, float]:
    w, c = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, (time.perf_counter() - w) * 1e3, (time.process_time() - c) * 1e3


def bench_part(name, cad, sites, seeds, rig_true, rec) -> dict[str, Any]:  # type: ignore[no-untyped-def]
    from inspection.cadpoints import LocalModel, measure_points
    from inspection.cadpoints.imagepose import ImagePoseModel, image_pose
    from inspection.defects import Dent, press
    from inspection.deviations import deviations
    from inspection.errors import InvalidInput
    from inspection.measure import MeasureParams, PartModel, measure_frames
    from inspection.rig import belt_pose
    from inspection.simulate import simulate
    from inspection.surface import SurfaceParams
    from inspection.transforms import apply

    mesh = cad.to_trimesh()
    pts = {r: comparison_points(mesh, sites, r) for r in RADII_MM}
    dents = [Dent(cp.position, (0.0, 0.0, 1.0), d, 30.0, 16.0)
             for cp, d in zip(pts[10.0], DEPTHS, strict=False)]  # fmt: skip
    dented = press(mesh, dents)
    part = PartModel.build(cad, pts[10.0])
    truth = {r: truths(part, dented, pts[r]) for r in RADII_MM}
    local = {r: LocalModel.build(cad, pts[r], rec) for r in RADII_MM}
    img_model = ImagePoseModel.build(part, rec.rig)
    line = MeasureParams()
    on_points = MeasureParams(path="comparison_points", surface=SurfaceParams(fails_part=False))
    poses: dict[str, list[tuple[float, float]]] = {}
    times: dict[str, list[float]] = {}
    cpu: dict[str, list[float]] = {}
    errs: dict[tuple[str, float], list[np.ndarray]] = {}
    stages: dict[str, list[float]] = {}  # the comparison-point path's CPU ms per stage

    def lap(key: str, wall: float, c: float) -> None:
        times.setdefault(key, []).append(wall)
        cpu.setdefault(key, []).append(c)

    def local_errors(key: str, r: float, T_cad_rig: np.ndarray, frames) -> None:  # type: ignore[no-untyped-def]
        res = measure_points(local[r], frames, T_cad_rig)
        errs.setdefault((key, r), []).append(np.array([m.deviation_mm for m in res]) - truth[r])

    print(f"\n{name}: {len(cad.faces)} facets, {len(sites)} comparison points")
    for seed in seeds:
        for x, y, deg in POSES:
            T_rig_part = belt_pose(x, y, deg)
            frames = simulate(rig_true, dented, T_rig_part, seed=seed)
            if not times:  # warm-up: kernels compiled, caches filled
                measure_frames(part, rec, frames, line)
                measure_points(local[10.0], frames, np.linalg.inv(T_rig_part))
            m, w, c = _timed(measure_frames, part, rec, frames, line)
            lap("cloud", w, c)
            if m.transform is None or m.deviations is None:
                print(f"  seed {seed} ({x:+.0f}, {y:+.0f}, {deg:+.0f}): cloud path: {m.reason}")
                continue
            cloud10 = np.array([cp.deviation_mm for cp in m.deviations.comparison])
            small = deviations(part.tree, apply(m.transform, m.points), pts[4.0])
            cloud4 = np.array([cp.deviation_mm for cp in small.comparison])
            errs.setdefault(("cloud", 10.0), []).append(cloud10 - truth[10.0])
            errs.setdefault(("cloud", 4.0), []).append(cloud4 - truth[4.0])
            # Local photogrammetry at the cloud path's pose, and at the truth's.
            _, w, c = _timed(measure_points, local[10.0], frames, m.transform)
            lap(AT_FIT, w, c)
            for r in RADII_MM:
                local_errors(AT_FIT, r, m.transform, frames)
                local_errors("local at the true pose", r, np.linalg.inv(T_rig_part), frames)
            # The comparison-point path through the sequence, on the same frames.
            mc, w_c, c_c = _timed(measure_frames, part, rec, frames, on_points)
            lap(PATH, w_c, c_c)
            for stage, ms in mc.cpu_ms.items():
                stages.setdefault(stage, []).append(ms)
            if mc.transform is None or mc.deviations is None:
                print(f"  seed {seed} ({x:+.0f}, {y:+.0f}, {deg:+.0f}): {PATH}: {mc.reason}")
                continue
            errs.setdefault((PATH, 10.0), []).append(
                np.array([cp.deviation_mm for cp in mc.deviations.comparison]) - truth[10.0]
            )
            local_errors(PATH, 4.0, mc.transform, frames)
            for key, T_fit in (("cloud", m.transform), (PATH, mc.transform)):
                poses.setdefault(key, []).append(pose_error(T_fit @ T_rig_part))
            # The targetless alignment in the images alone (outline, then sites), and the
            # points measured at its pose.
            try:
                (img, _), w_i, c_i = _timed(image_pose, img_model, frames)
            except InvalidInput as exc:
                print(f"  seed {seed} ({x:+.0f}, {y:+.0f}, {deg:+.0f}): image pose: {exc}")
            else:
                _, w_l, c_l = _timed(measure_points, local[10.0], frames, img.transform)
                lap(IMAGE, w_i + w_l, c_i + c_l)
                lap("  of which the image pose", w_i, c_i)
                poses.setdefault("image pose", []).append(pose_error(img.transform @ T_rig_part))
                for r in RADII_MM:
                    local_errors(IMAGE, r, img.transform, frames)
            worst = {k: float(np.nanmax(np.abs(errs[(k, 10.0)][-1])))
                     for k in ("cloud", AT_FIT, PATH)}  # fmt: skip
            print(f"  seed {seed} ({x:+.0f}, {y:+.0f}, {deg:+.0f}): CPU ms: cloud "
                  f"{cpu['cloud'][-1]:5.0f}, local {cpu[AT_FIT][-1]:5.1f}, path "
                  f"{cpu[PATH][-1]:5.0f}; worst error at 10 mm: cloud {worst['cloud']:.3f}, "
                  f"local {worst[AT_FIT]:.3f}, path {worst[PATH]:.3f} mm",
                  flush=True)  # fmt: skip
    return {"times": times, "cpu": cpu, "errors": errs, "poses": poses, "stages": stages}


def report(name: str, out: dict[str, Any]) -> bool:
    times, cpu, errs = out["times"], out["cpu"], out["errors"]
    print(f"\n{name}: time per part, ms (CPU: this process, every thread)")
    print(f"  {'path':32s} {'wall p50':>9} {'wall p90':>9} {'CPU p50':>8} {'CPU p90':>8} "
          f"{'x faster (CPU p50)':>19}")  # fmt: skip
    base = statistics.median(cpu["cloud"])
    for key in times:
        print(f"  {key:32s} {statistics.median(times[key]):9.1f} {_p(times[key], 90):9.1f} "
              f"{statistics.median(cpu[key]):8.1f} {_p(cpu[key], 90):8.1f} "
              f"{base / statistics.median(cpu[key]):19.1f}")  # fmt: skip
    print(f"{name}: the comparison-point path per stage, CPU ms p50 (p90): " + ", ".join(
        f"{k} {statistics.median(v):.1f} ({_p(v, 90):.1f})" for k, v in out["stages"].items()
    ))  # fmt: skip
    print(f"{name}: comparison-point errors against the truth")
    ok = True
    for r in RADII_MM:
        cloud = np.concatenate(errs[("cloud", r)])
        for key in ("cloud", AT_FIT, PATH, IMAGE, "local at the true pose"):
            if (key, r) not in errs:
                continue
            e = np.concatenate(errs[(key, r)])
            print(f"  {r:4.0f} mm support, {key:26s} {_stats(e)}")
        if (PATH, r) in errs:
            # Each path leaves out the points it cannot measure, and not the same
            # ones: the two are held to each other on the points both measured.
            e = np.concatenate(errs[(PATH, r)])
            both = np.isfinite(e) & np.isfinite(cloud)
            ae, ac = np.abs(e[both]), np.abs(cloud[both])
            print(f"  {r:4.0f} mm support, the {int(both.sum())} of {len(e)} points both "
                  f"measured: cloud {_stats(cloud[both])}; comparison-point path "
                  f"{_stats(e[both])}")  # fmt: skip
            rms_ok = np.sqrt(np.mean(ae**2)) <= np.sqrt(np.mean(ac**2))
            ok = ok and ae.max() <= ac.max() and rms_ok
    for key, pe in out["poses"].items():
        a = np.array(pe)
        print(f"{name}: pose of the {key}: rotation median {np.median(a[:, 0]):.4f} max "
              f"{a[:, 0].max():.4f} deg, origin median {np.median(a[:, 1]):.3f} max "
              f"{a[:, 1].max():.3f} mm")  # fmt: skip
    if PATH in cpu:
        ratio = base / statistics.median(cpu[PATH])
        print(f"{name}: the comparison-point path is {ratio:.1f}x faster (CPU p50; "
              f"goal {SPEED_GOAL:.0f}x), no less accurate at both supports: {ok}")  # fmt: skip
        ok = ok and ratio >= SPEED_GOAL
    return ok


def bench_maps() -> None:
    import trimesh
    from scipy.spatial.transform import Rotation

    from inspection.panel import PanelSpec, sheet_metal_panel
    from inspection.perspective import PerspectiveMap, RayCaster, camera_rays
    from inspection.rig import Rig, belt_pose
    from inspection.transforms import apply

    cad = sheet_metal_panel(PanelSpec().scaled(400.0, 260.0))
    cam = Rig.nominal().cameras[0]
    T = belt_pose(*POSES[0])
    box = cam.project(apply(T, np.asarray(cad.to_trimesh().bounding_box.vertices)))
    x0, y0 = (max(int(v), 0) for v in box.min(axis=0) - 10)
    x1 = min(int(box[:, 0].max()) + 10, cam.width)
    y1 = min(int(box[:, 1].max()) + 10, cam.height)
    shape = (y1 - y0, x1 - x0)
    o, d = camera_rays(cam, (x0, y0), shape)
    caster = RayCaster(cad)
    pm, w_b, c_b = _timed(PerspectiveMap.build, caster, T, o, d, shape, corner=(x0, y0))
    idx = np.flatnonzero(pm.face >= 0)
    print(f"\nperspective map: cam0, {shape[1]} x {shape[0]} pixels around the demo panel, "
          f"{len(idx)} on it; built in {w_b:.0f} ms (CPU {c_b:.0f} ms), "
          f"validity: motions up to {pm.max_motion_mm} mm, {pm.margin_px} px from depth steps "
          f"ray cast ({pm.step[idx].mean():.1%} of the part's pixels)")  # fmt: skip
    print(f"  {'motion':>16} {'query ns/px':>11} {'CPU':>6} {'Embree ns/px':>12} {'CPU':>6} "
          f"{'ratio':>6} {'cast':>6} {'max diff mm':>11}")  # fmt: skip
    rng = np.random.default_rng(0)
    for deg, mm in ((0.05, 0.2), (0.2, 0.5), (0.5, 1.5)):
        axis = rng.normal(size=3)
        dT = np.eye(4)
        dT[:3, :3] = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
        t = rng.normal(size=3)
        dT[:3, 3] = mm * t / np.linalg.norm(t)
        mesh = trimesh.Trimesh(apply(dT @ T, cad.vertices), cad.faces, process=False)
        q_w, q_c, e_w, e_c = [], [], [], []
        for _ in range(5):
            (pts, _, cast), w, c = _timed(pm.query, idx, dT)
            q_w.append(w)
            q_c.append(c)
            (loc, ray, _), w, c = _timed(
                mesh.ray.intersects_location, pm.origins[idx], pm.directions[idx],
                multiple_hits=False,
            )  # fmt: skip
            e_w.append(w)
            e_c.append(c)
        ref = np.full((len(idx), 3), np.nan)
        ref[ray] = loc
        both = np.isfinite(ref[:, 0]) & np.isfinite(pts[:, 0])
        agree = int((np.isfinite(ref[:, 0]) != np.isfinite(pts[:, 0])).sum())
        ns = 1e6 / len(idx)
        diff = np.abs(ref[both] - pts[both]).max()
        print(f"  {f'{deg} deg, {mm} mm':>16} {statistics.median(q_w) * ns:11.1f} "
              f"{statistics.median(q_c) * ns:6.1f} {statistics.median(e_w) * ns:12.1f} "
              f"{statistics.median(e_c) * ns:6.1f} "
              f"{statistics.median(e_w) / statistics.median(q_w):6.1f} {cast:6d} {diff:11.2e}"
              + (f" ({agree} pixels hit in one only)" if agree else ""))  # fmt: skip


def main() -> int:
    from inspection.panel import PanelSpec, sheet_metal_panel
    from inspection.reconstruct import Reconstructor
    from inspection.rig import Rig

    seeds = [int(s) for s in os.environ.get("BENCH_CP_SEEDS", "11,12").split(",") if s]
    rig_true = Rig.nominal()
    rec = Reconstructor.build(Rig.default())
    bench_maps()
    ok = True
    parts = (
        ("demo panel", sheet_metal_panel(PanelSpec().scaled(400.0, 260.0)), PANEL_SITES),
        ("second part", second_part(), SECOND_SITES),
    )
    results = []
    for name, cad, sites in parts:
        results.append((name, bench_part(name, cad, sites, seeds, rig_true, rec)))
    for name, out in results:
        ok = report(name, out) and ok
    print(f"\nevery goal met: {ok}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
