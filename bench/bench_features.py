"""Holes, slots, trim edges and character lines against the simulator's truth; RPS residuals.

The demo panel with a slot, its holes drawn with a fine rim
(``PanelSpec.hole_spacing_mm``): each part's holes are shifted and resized at
random (``inspection.panel.vary_holes``, as the line's simulator does), the
part rendered with ``Rig.nominal()`` in six poses and two render seeds, and
measured as the line measures (``measure_frames``, ``Rig.default()``)
against the drawn panel. Per hole: the centre's error along the hole's x and
y and the diameter's (and a slot's length), from the images (the measuring
sequence) and, as the peer, from the cloud's rim alone
(``hole_from_cloud``), whose bias at edges the images are there to avoid;
the images' errors less the fit's pose error at the hole (where the fitted
pose puts the true hole: the cloud's fit, which every feature's entry
carries); and from the images at the true pose with the rig as built (what
the edge search alone leaves, without the fit's and the calibration's
errors). The edge search predicts the flash's speckle with the rig's
projector (``Flash``), built per part as the line builds it.
Trim edges: points on the round holes' rims, whose true offset follows from
the hole's shift and radius, varying along the rim: the curve fitted to the
edge points (the ``.trim`` entry, its mean offset over the measured span)
beside the single robust offset of the same points, both against the truth at
the point (the entry also less the fit's pose error there) and the fitted
curve's ``.trim_max`` against the true largest offset over the span.
Character lines: extra parts, the holes as drawn and the character line bent
across itself near each point (a smooth bump 80 mm wide, up to 0.5 mm),
``.line`` and ``.line_max`` against the truth carried into the CAD frame by
the fit's pose.
RPS: a hole fixing x and y, the slot (its axis pointing at that hole) the
direction across its axis, three surface points fixing z, and a second hole's
x (seven directions, so the datums have residuals): the residuals after the
RPS alignment beside those the best fit leaves at the same datums; and the
holes in the RPS frame, the measured ones placed by the measured datums
against the made ones placed by the made datums, which is how a drawing
locates them (no fit's pose in it).

Goals: holes within 0.05 mm in position and diameter, trim edges within 0.1 mm.
``BENCH_FEATURE_POSES`` (default 6) and ``BENCH_FEATURE_SEEDS`` (default "11,12").
Run: ``make bench BENCH=features``.
"""

from __future__ import annotations

import math
import os
import statistics

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

POSES = [
    (0.0, 0.0, 0.0),
    (40.0, -30.0, 25.0),
    (-100.0, 80.0, 90.0),
    (120.0, 60.0, -40.0),
    (-60.0, -70.0, 160.0),
    (80.0, -90.0, 230.0),
]
GOAL_HOLE_MM = 0.05
GOAL_TRIM_MM = 0.1


def scene():
    """The drawn panel, its comparison points (holes and rim trim edges) and RPS datums."""
    from inspection.alignment.rps import Datum
    from inspection.deviations import ComparisonPoint
    from inspection.panel import Hole, PanelSpec, surface_point

    spec = PanelSpec(
        holes=(
            Hole(170.0, 110.0, 16.0),
            Hole(150.0, -100.0, 10.0, length_mm=40.0, angle_deg=84.56),
            Hole(-200.0, 120.0, 10.5),
        ),
        hole_spacing_mm=0.7,
    ).scaled(400.0, 260.0)
    cps = []
    for name, h in zip(("H1", "S2", "H3"), spec.holes, strict=True):
        pos, n = surface_point(spec, h.x_mm, h.y_mm)
        a = math.radians(h.angle_deg)
        cps.append(
            ComparisonPoint(
                name,
                pos,
                n,
                -0.2,
                0.2,
                5.0,
                kind="hole",
                diameter_mm=2 * h.radius_mm,
                length_mm=h.length_mm,
                axis=(math.cos(a), math.sin(a), 0.0),
            )  # fmt: skip
        )
    for name, x in (("C1", -60.0), ("C2", 60.0)):
        pos, _ = surface_point(spec, x, spec.character_line_y_mm)
        cps.append(
            ComparisonPoint(name, pos, (0.0, 1.0, 0.0), -0.3, 0.3, 20.0, kind="character_line")
        )
    trims = []
    for name, h, ang in (("E1", spec.holes[0], 0.0), ("E2", spec.holes[0], 120.0),
                         ("E3", spec.holes[2], -90.0)):  # fmt: skip
        u = np.array([math.cos(math.radians(ang)), math.sin(math.radians(ang))])
        pos, _ = surface_point(spec, h.x_mm + h.radius_mm * u[0], h.y_mm + h.radius_mm * u[1])
        cps.append(
            ComparisonPoint(
                name, pos, (-u[0], -u[1], 0.0), -0.2, 0.2, 3.0, kind="trim_edge", min_support=5
            )  # fmt: skip
        )
        trims.append((name, spec.holes.index(h), u))
    zs = [(-150.0, -90.0), (150.0, 0.0), (-60.0, 100.0)]
    for i, (x, y) in enumerate(zs):
        pos, n = surface_point(spec, x, y)
        cps.append(ComparisonPoint(f"Z{i + 1}", pos, n, -0.5, 0.5, 8.0))
    by = {cp.name: cp for cp in cps}
    s2 = spec.holes[1]
    a = math.radians(s2.angle_deg)
    datums = (
        Datum("H1", cps[0].position, ("x", "y")),
        # The slot fixes the direction across its axis.
        Datum("S2", cps[1].position, ((-math.sin(a), math.cos(a), 0.0),)),
        Datum("Z1", by["Z1"].position, ("z",)),
        Datum("Z2", by["Z2"].position, ("z",)),
        Datum("Z3", by["Z3"].position, ("z",)),
        Datum("H3", cps[2].position, ("x",)),
    )
    return spec, cps, trims, datums


def main() -> int:
    from inspection.alignment.rps import rps_align
    from inspection.deviations import robust_location
    from inspection.feature_checks import hole_spec
    from inspection.features import (
        Flash,
        boundary_samples,
        hole_frame,
        hole_from_cloud,
        measure_hole,
        measure_trim_edge,
    )
    from inspection.measure import PartModel, measure_frames
    from inspection.panel import sheet_metal_panel, vary_holes
    from inspection.reconstruct import Reconstructor
    from inspection.rig import Rig, belt_pose
    from inspection.simulate import simulate
    from inspection.transforms import apply

    n_poses = int(os.environ.get("BENCH_FEATURE_POSES", "6"))
    seeds = [int(s) for s in os.environ.get("BENCH_FEATURE_SEEDS", "11,12").split(",")]
    spec, cps, trims, datums = scene()
    part = PartModel.build(sheet_metal_panel(spec), cps)
    rec = Reconstructor.build(Rig.default())
    truth_rig = Rig.nominal()
    flash = Flash.build(rec.rig.projector)
    by_name = {cp.name: cp for cp in cps}
    img_err: dict[str, list[float]] = {"x": [], "y": [], "d": [], "len": []}
    cloud_err: dict[str, list[float]] = {"x": [], "y": [], "d": []}
    oracle_err: dict[str, list[float]] = {"x": [], "y": [], "d": []}
    unposed_err: dict[str, list[float]] = {"x": [], "y": []}
    trim_err: list[float] = []
    unposed_trim: list[float] = []
    robust_err: list[float] = []
    trim_max_err: list[float] = []
    rps_res: list[float] = []
    bf_res: list[float] = []
    rps_err: dict[str, list[float]] = {"x": [], "y": []}
    rps_trim: list[float] = []
    wall, cpu = [], []
    unmeasured = 0
    print(f"{'part':>10} {'hole':>4} {'dx img':>8} {'dy img':>8} {'dd img':>8} "
          f"{'dx cloud':>8} {'dy cloud':>8} {'dd cloud':>8}")  # fmt: skip
    for pi, pose in enumerate(POSES[:n_poses]):
        for seed in seeds:
            rng = np.random.default_rng([seed, pi])
            truth_spec, shifts = vary_holes(spec, rng)
            T_rig_part = belt_pose(*pose)
            frames = simulate(truth_rig, sheet_metal_panel(truth_spec), T_rig_part, seed=seed)
            m = measure_frames(part, rec, frames)
            if m.deviations is None or m.transform is None:
                print(f"pose {pi} seed {seed}: not measured: {m.reason}")
                unmeasured += 1
                continue
            # The stage and the flash's slide it predicts the speckle with, built per part.
            wall.append(m.timings_ms.get("features", math.nan) + m.timings_ms.get("flash", 0.0))
            cpu.append(m.cpu_ms.get("features", math.nan) + m.cpu_ms.get("flash", 0.0))
            entries = {c.name: c for c in m.deviations.comparison}
            pts_cad = apply(m.transform, m.points)
            # Where the fit's pose puts a point of the part against where it lies (the
            # calibrated rig's frame taken as the rig's): every feature's entry carries it.
            pose_error = m.transform @ T_rig_part

            def displaced(q: np.ndarray, pose_error: np.ndarray = pose_error) -> np.ndarray:
                return apply(pose_error, np.asarray(q, dtype=np.float64)[None])[0] - q

            for hi, name in enumerate(("H1", "S2", "H3")):
                cp = by_name[name]
                x, y, _ = hole_frame(cp.normal, hole_spec(cp).axis)
                sh = shifts[hi]
                true = {
                    "x": float(np.dot([sh.dx_mm, sh.dy_mm, 0.0], x)),
                    "y": float(np.dot([sh.dx_mm, sh.dy_mm, 0.0], y)),
                    "d": 2 * sh.dr_mm,
                    "len": 2 * sh.dr_mm,
                }
                row = []
                for key in ("x", "y", "d", "len"):
                    e = entries.get(f"{name}.{key}")
                    if e is None:
                        continue
                    err = e.deviation_mm - true[key]
                    if math.isfinite(err):
                        img_err[key].append(err)
                        if key in ("x", "y"):
                            axis = x if key == "x" else y
                            shift = float(displaced(np.asarray(cp.position)) @ axis)
                            unposed_err[key].append(err - shift)
                    row.append(err)
                cm, _ = hole_from_cloud(hole_spec(cp), pts_cad)
                cl = [math.nan] * 3
                if cm is not None:
                    cl = [cm.offset_mm[0] - true["x"], cm.offset_mm[1] - true["y"],
                          cm.diameter_mm - cp.diameter_mm - true["d"]]  # fmt: skip
                    for key, v in zip(("x", "y", "d"), cl, strict=True):
                        cloud_err[key].append(v)
                om, _ = measure_hole(hole_spec(cp), truth_rig.cameras, frames,
                                     np.linalg.inv(T_rig_part), flash=flash)  # fmt: skip
                if om is not None:
                    oracle_err["x"].append(om.offset_mm[0] - true["x"])
                    oracle_err["y"].append(om.offset_mm[1] - true["y"])
                    oracle_err["d"].append(om.diameter_mm - cp.diameter_mm - true["d"])
                print(f"{pi}/{seed:>7} {name:>4} " + " ".join(f"{v:8.3f}" for v in row[:3])
                      + " " + " ".join(f"{v:8.3f}" for v in cl))  # fmt: skip
            trims_found = []
            for name, hi, u in trims:
                sh = shifts[hi]
                true_trim = -(sh.dx_mm * u[0] + sh.dy_mm * u[1] + sh.dr_mm)
                e = entries[f"{name}.trim"]
                if math.isfinite(e.deviation_mm):
                    trim_err.append(e.deviation_mm - true_trim)
                    trims_found.append((by_name[name], e.deviation_mm, true_trim))
                    cp = by_name[name]
                    shift = float(displaced(np.asarray(cp.position)) @ np.asarray(cp.normal))
                    unposed_trim.append(e.deviation_mm - true_trim - shift)
                # Both estimators on the same edge points: the fitted curve and the single
                # robust offset, the surface's offset taken as the check takes it.
                cp = by_name[name]
                r = np.linalg.norm(pts_cad - np.asarray(cp.position), axis=1)
                band = (r >= 2.0) & (r <= 8.0 + cp.radius_mm)
                band &= np.abs(m.deviations.distances) <= 1.0
                lift = robust_location(m.deviations.distances[band])[0] if band.sum() >= 10 else 0.0
                smp, out, nrm = boundary_samples(part.cad.vertices, part.cad.faces,
                                                 part.cad.face_normals, cp.position,
                                                 cp.radius_mm, 0.5)  # fmt: skip
                tm, _ = measure_trim_edge(smp, out, nrm, rec.rig.cameras, frames, m.transform,
                                          surface_offset_mm=lift, min_support=5,
                                          flash=flash)  # fmt: skip
                if tm is None:
                    continue
                robust_err.append(tm.robust_mm - true_trim)
                # The true offset along the measured span: the hole's shift and radius seen
                # along each nominal point's direction from the drawn centre.
                h = spec.holes[hi]
                d = tm.curve.points[:, :2] - [h.x_mm, h.y_mm]
                d /= np.linalg.norm(d, axis=1, keepdims=True)
                true_along = -(sh.dx_mm * d[:, 0] + sh.dy_mm * d[:, 1] + sh.dr_mm)
                trim_max_err.append(tm.max_mm - true_along[np.argmax(np.abs(true_along))])
            # RPS: the measured datums in the rig frame, from the best fit's CAD frame.
            T_bf = m.transform
            measured_cad = []
            for d in datums:
                cp = by_name[d.name]
                if cp.kind == "hole":
                    x, y, _ = hole_frame(cp.normal, hole_spec(cp).axis)
                    ex, ey = entries[f"{d.name}.x"], entries[f"{d.name}.y"]
                    measured_cad.append(np.asarray(cp.position)
                                        + ex.deviation_mm * x + ey.deviation_mm * y)  # fmt: skip
                else:
                    dev = entries[d.name].deviation_mm
                    measured_cad.append(np.asarray(cp.position) + dev * np.asarray(cp.normal))
            measured_cad = np.array(measured_cad)
            if not np.isfinite(measured_cad).all():
                continue
            measured_rig = apply(np.linalg.inv(T_bf), measured_cad)
            rps = rps_align(datums, measured_rig, init=T_bf)
            bf = rps_align(datums, measured_rig, init=T_bf, hold=True)
            rps_res += [abs(v) for r in rps.residuals for v in r.residuals_mm]
            # The best fit's own residuals at the datums: the measured minus nominal.
            P = np.array([d.position for d in datums])
            for i, d in enumerate(datums):
                for v in d.directions:
                    bf_res.append(abs(float(np.dot(v, measured_cad[i] - P[i]))))
            del bf
            # The holes in the RPS frame: the measured ones placed by the measured datums,
            # against the made ones placed by the made datums (surface points stay put).
            made = {n: np.asarray(by_name[n].position) + [sh.dx_mm, sh.dy_mm, 0.0]
                    for n, sh in zip(("H1", "S2", "H3"), shifts, strict=True)}  # fmt: skip
            T_true = rps_align(
                datums, np.array([made.get(d.name, np.asarray(d.position)) for d in datums])
            ).transform
            # From the best fit's CAD frame to the measured datums'.
            to_rps = rps.transform @ np.linalg.inv(T_bf)
            for name in ("H1", "S2", "H3"):
                cp = by_name[name]
                x, y, _ = hole_frame(cp.normal, hole_spec(cp).axis)
                ex, ey = entries[f"{name}.x"], entries[f"{name}.y"]
                q = np.asarray(cp.position) + ex.deviation_mm * x + ey.deviation_mm * y
                e = apply(to_rps, q[None])[0] - apply(T_true, made[name][None])[0]
                fixed = [np.asarray(v) for d in datums if d.name == name for v in d.directions]
                for key, axis in (("x", x), ("y", y)):
                    # A direction its own datum fixes is placed there by construction.
                    if not any(abs(float(axis @ v)) > 0.99 for v in fixed):
                        rps_err[key].append(float(e @ axis))
            # A trim edge's offset in the RPS frame: the measured one moved as the datums move
            # the best fit's frame, the made one as the made datums move the drawn part's.
            for cp, measured, true_trim in trims_found:
                q, n = np.asarray(cp.position), np.asarray(cp.normal)
                moved = apply(to_rps, q[None])[0] - q
                made_moved = apply(T_true, q[None])[0] - q
                rps_trim.append(measured + moved @ n - (true_trim + made_moved @ n))

    def stats(xs: list[float]) -> str:
        if not xs:
            return "   -        -     (0)"
        a = np.abs(np.asarray(xs))
        return f"{np.median(a):7.3f}  {a.max():7.3f}  ({len(a)})"

    print("\nerrors against the truth, mm: median |e|, max |e| (count)")
    for key in ("x", "y", "d"):
        print(
            f"  hole {key:>3}  images {stats(img_err[key])}   cloud (peer) {stats(cloud_err[key])}"
        )
        if key in unposed_err:
            print(f"            images, less the fit's pose error there {stats(unposed_err[key])}")
        print(f"            images at the true pose, rig as built {stats(oracle_err[key])}")
    ratio = [
        float(np.median(np.abs(img_err[k])) / np.median(np.abs(cloud_err[k])))
        for k in ("x", "y", "d")
        if img_err[k] and cloud_err[k]
    ]
    print("  images / cloud, median |e| (x, y, d): " + ", ".join(f"{r:.2f}" for r in ratio))
    print(f"  slot len  images {stats(img_err['len'])}")
    print(f"  trim      images, fitted curve (the entry)   {stats(trim_err)}")
    print(f"            the same, less the fit's pose error {stats(unposed_trim)}")
    print(f"            images, single robust offset       {stats(robust_err)}")
    print(f"  trim_max  images, fitted curve's largest     {stats(trim_max_err)}")
    line_err, line_max_err = character_lines(part, rec, spec, n_poses, seeds[0])
    print(f"  line      cloud (first pass), fitted curve   {stats(line_err)}")
    print(f"  line_max  cloud (first pass), its largest    {stats(line_max_err)}")
    print(
        f"\nRPS datum residuals, mm: median, max  RPS {stats(rps_res)}   best fit {stats(bf_res)}"
    )
    print("in the RPS frame against the made part in its own RPS frame (the directions no "
          "datum fixes at the hole), mm: holes "
          f"x {stats(rps_err['x'])}  y {stats(rps_err['y'])}  trim {stats(rps_trim)}")  # fmt: skip
    print(f"features stage (with the flash's slide) per part: median wall "
          f"{statistics.median(wall):.0f} ms, "
          f"cpu {statistics.median(cpu):.0f} ms; {unmeasured} parts not measured")  # fmt: skip
    pos = max((np.abs(img_err[k]).max() for k in ("x", "y") if img_err[k]), default=math.inf)
    dia = float(np.abs(img_err["d"]).max()) if img_err["d"] else math.inf
    trm = np.abs(trim_err).max() if trim_err else math.inf

    def met(v: float, goal: float) -> str:
        return f"{'met' if v <= goal else 'not met'} (max {v:.3f})"

    print(
        f"goal: holes within {GOAL_HOLE_MM} mm: position {met(pos, GOAL_HOLE_MM)}, "
        f"diameter {met(dia, GOAL_HOLE_MM)}; trim within {GOAL_TRIM_MM} mm: "
        f"{met(trm, GOAL_TRIM_MM)}  (the best fit's frame)"
    )
    pos_rps = max((np.abs(rps_err[k]).max() for k in ("x", "y") if rps_err[k]), default=math.inf)
    trm_rps = np.abs(rps_trim).max() if rps_trim else math.inf
    print(
        f"      in the RPS frame: position {met(pos_rps, GOAL_HOLE_MM)}; "
        f"trim {met(trm_rps, GOAL_TRIM_MM)}"
    )
    return 0


def character_lines(part, rec, spec, n_poses: int, seed: int) -> tuple[list[float], list[float]]:
    """The character lines' errors on parts whose line is bent across itself near each
    point (a smooth bump of random size up to 0.5 mm and place), the truth carried into the
    CAD frame by the fit's pose: ``.line`` minus the true mean offset over the measured
    span, ``.line_max`` minus the true largest."""
    from inspection.measure import measure_frames
    from inspection.panel import move_character_line, surface_point
    from inspection.rig import Rig, belt_pose
    from inspection.simulate import simulate
    from inspection.transforms import apply

    yc = spec.character_line_y_mm
    err: list[float] = []
    err_max: list[float] = []
    lines = [cp for cp in part.comparison_points if cp.kind == "character_line"]
    for pi, pose in enumerate(POSES[:n_poses]):
        rng = np.random.default_rng([seed, pi, 7])
        bumps = [(cp.position[0] + rng.uniform(-10, 10), rng.uniform(-0.5, 0.5)) for cp in lines]

        def shift(x: np.ndarray, bumps=bumps) -> np.ndarray:
            out = np.zeros_like(x)
            for xb, a in bumps:
                u = np.clip((x - xb) / 40.0, -1.0, 1.0)
                out += a * np.cos(0.5 * math.pi * u) ** 2
            return out

        T_rig_part = belt_pose(*pose)
        frames = simulate(Rig.nominal(), move_character_line(spec, shift), T_rig_part, seed=seed)
        m = measure_frames(part, rec, frames)
        if m.deviations is None or m.transform is None:
            continue
        entries = {c.name: c for c in m.deviations.comparison}
        T = m.transform @ T_rig_part
        for cp in lines:
            xs = np.linspace(cp.position[0] - cp.radius_mm, cp.position[0] + cp.radius_mm, 81)
            nominal = np.array([surface_point(spec, x, yc)[0] for x in xs])
            moved = yc + shift(xs)
            made = np.array([surface_point(spec, x, y)[0] for x, y in zip(xs, moved, strict=True)])
            true = (apply(T, made) - nominal) @ np.asarray(cp.normal)
            line, top = entries[f"{cp.name}.line"], entries[f"{cp.name}.line_max"]
            if math.isfinite(line.deviation_mm):
                err.append(line.deviation_mm - float(true.mean()))
                err_max.append(top.deviation_mm - float(true[np.argmax(np.abs(true))]))
            print(f"{pi}/{seed:>7} {cp.name:>4} true mean {true.mean():6.3f} "
                  f"max {true[np.argmax(np.abs(true))]:6.3f}  line {line.deviation_mm:6.3f} "
                  f"max {top.deviation_mm:6.3f}")  # fmt: skip
    return err, err_max
