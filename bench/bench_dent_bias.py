"""Where a dent's depth error comes from: the cloud around it, stage by stage, against the truth.

The dented parts of ``bench_defects`` (the same poses, dents and render
seeds), measured as the line measures them (``measure_frames`` with
``MeasureParams()``). Each stage's points are compared with the pressed mesh
at the true pose (exact closest point on the mesh within 50 mm of the dent;
the calibrated rig's own error is in it, which the 25-40 mm ring shows):

- ``square``: the square windows of the first pass, every pair's points
  triangulated before any warp and pooled (not fused);
- ``first``: the first pass, warped by the measured field, fused;
- ``guided``: the pass whose windows follow the CAD at the first fit's pose;
- ``bends``: the windows on bends matched again: the cloud that is judged.

Errors are signed along the dent's depth (positive: the dent measured deeper
than it is, or a bump higher) and binned by the distance from the dent's
axis: 0-4 and 4-7 mm lie on the flat bottom (the 6 mm support of the defect
search sees these), 7-10 mm is where the rim starts (its curvature is
highest), 10-14 mm the rim. Per bin, the median over the parts of each
part's median, for rims up to 10 degrees and steeper, and for the frames
rendered as usual and rendered clean (``RenderOptions.clean()``: no sheen,
mirror lobe, dirt or noise): what is left clean is the windows' geometry,
the difference is light and noise. The same spot of the same part rendered
without its dent (``undented``, against the CAD) shows the matcher's error
there when the part does not depart from its CAD. The defect search's depth error
(``peak_mm`` against the depth) is printed per part beside its cloud's, and
per render the scatter of the field the search smooths, away from the dent
and the edges (``bench_defects.field_scatter``): rendered clean, what the
windows' geometry leaves; as rendered, the light and the noise too.

``BENCH_DENT_PARTS`` (default 16) dented parts from ``BENCH_DEFECTS_SEED``
(default 1). Run: ``make bench BENCH=dent_bias``. No goal, no peer: a
measurement of the error's origin.
"""

from __future__ import annotations

import os
import statistics
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

BINS_MM = [(0.0, 4.0), (4.0, 7.0), (7.0, 10.0), (10.0, 14.0), (25.0, 40.0)]
STAGES = ("square", "first", "guided", "bends")
STEEP_DEG = 10.0


def main() -> int:
    from bench.bench_defects import draw, field_scatter, rim_slope_deg, scene
    from inspection.defects import press
    from inspection.measure import measure_frames
    from inspection.simulate import RenderOptions, simulate
    from inspection.transforms import apply

    n_parts = int(os.environ.get("BENCH_DENT_PARTS", "16"))
    seed = int(os.environ.get("BENCH_DEFECTS_SEED", "1"))
    mesh, part, rec, truth_rig, params = scene()
    # (pressed?, options) per render; "undented": the same spot of the same part
    # without its dent, against the CAD (the matcher's error there when nothing departs).
    renders = {
        "as rendered": (True, RenderOptions()),
        "clean": (True, RenderOptions.clean()),
        "undented": (False, RenderOptions()),
    }
    bins = " ".join(f"{f'{a:.0f}-{b:.0f}':>6}" for a, b in BINS_MM)
    print(f"{n_parts} dented parts, seed {seed}; error along the depth (mm) by r from the axis")
    print(f"{'part':>4} {'depth':>6} {'slope':>5} {'render':>11} {'stage':>6} {bins} {'defect':>7}")
    # (render, stage, steep) -> per part, per bin: the part's median error
    table: dict[tuple[str, str, bool], list[list[float]]] = {}
    scatter: dict[str, list[float]] = {}
    found_errors: list[float] = []
    clean_errors: list[float] = []
    for k in range(1, 2 * n_parts, 2):  # bench_defects dents the odd parts
        _, T_rig_part, dent, frame_seed = draw(mesh, seed, k)
        shape = press(mesh, [dent])
        near = np.linalg.norm(shape.triangles_center - np.asarray(dent.center_mm), axis=1) < 50
        truths = {
            True: shape.submesh([np.flatnonzero(near)], append=True),
            False: mesh.submesh(
                [
                    np.flatnonzero(
                        np.linalg.norm(mesh.triangles_center - dent.center_mm, axis=1) < 50
                    )
                ],
                append=True,
            ),
        }
        T_part_rig = np.linalg.inv(T_rig_part).astype(np.float64)
        slope = rim_slope_deg(dent)
        for name, (pressed, options) in renders.items():
            seen = shape if pressed else mesh
            frames = simulate(truth_rig, seen, T_rig_part, seed=frame_seed, options=options)
            _, matching = rec.match(frames)
            square = np.concatenate(
                [_square_points(rec.pairs[j], r.state) for j, r in enumerate(matching.results)
                 if r.state is not None]
            )  # fmt: skip
            m = measure_frames(part, rec, frames, params)
            clouds = {"square": square} | {p.name: p.points for p in m.passes}
            found = _defect_error(m, dent) if pressed else float("nan")
            if m.deviations is not None:
                away = (dent.center_mm, dent.radius_mm + 10.0)
                scatter.setdefault(name, []).append(field_scatter(part, m, params, beyond=away))
            if np.isfinite(found):
                (found_errors if name == "as rendered" else clean_errors).append(found)
            for stage in STAGES:
                if stage not in clouds:
                    continue
                q = apply(T_part_rig, clouds[stage])
                medians = _binned(truths[pressed], dent, q)
                table.setdefault((name, stage, slope > STEEP_DEG), []).append(medians)
                cells = " ".join(f"{v:+6.3f}" if np.isfinite(v) else f"{'-':>6}" for v in medians)
                tail = f"{found:+7.3f}" if stage == "bends" and np.isfinite(found) else ""
                head = f"{k:4d} {-dent.depth_mm:+6.2f} {slope:5.1f} {name:>11} {stage:>6}"
                print(f"{head} {cells} {tail}", flush=True)
    print()
    # The median says what is systematic; the RMS over the parts, how far one part's
    # error strays (the bins hold few points on the flat bottom: one window's worth).
    for title, stat, fmt in (
        ("median over parts", _median, "+6.3f"),
        ("RMS over parts", _rms, "6.3f"),
    ):
        print(f"\n{title:>21} {'render':>11} {'stage':>6} {bins}")
        for steep in (False, True):
            label = f"rim > {STEEP_DEG:.0f} deg" if steep else f"rim <= {STEEP_DEG:.0f} deg"
            for name in renders:
                for stage in STAGES:
                    rows = table.get((name, stage, steep), [])
                    if not rows:
                        continue
                    cols = np.array(rows).T
                    cells = " ".join(
                        f"{stat(c[np.isfinite(c)]):{fmt}}" if np.isfinite(c).any() else f"{'-':>6}"
                        for c in cols
                    )
                    print(f"{label:>16} ({len(rows):2d}) {name:>11} {stage:>6} {cells}")
    if scatter:
        cells = ", ".join(f"{name} {statistics.median(v):.4f}" for name, v in scatter.items())
        print(f"\nfield smoothed over the support, away from the dent and the edges: "
              f"standard deviation, median over the parts: {cells} mm")  # fmt: skip
    defect = np.array(found_errors)
    if defect.size:
        print(
            f"\ndefect depth error (as rendered): RMS {_rms(defect):.3f}, "
            f"max {np.abs(defect).max():.3f} mm over {defect.size} dents found; clean: "
            f"RMS {_rms(np.array(clean_errors)):.3f} mm"
        )
    return 0


def _median(v: np.ndarray) -> float:
    return float(statistics.median(v))


def _rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(v))))


def _square_points(pair: Any, state: Any) -> np.ndarray:
    """The square-window matches of one pair's first pass, triangulated (rig frame, mm)."""
    x = (state.px + state.x0).astype(np.float64)
    y = (state.py + state.y0).astype(np.float64)
    ok = np.isfinite(state.d_square) & (state.score >= 0.9)
    d = (state.d_square - np.float32(state.shift)).astype(np.float64)
    return pair.triangulate(x[ok], y[ok], d[ok])


def _binned(local: Any, dent: Any, q: np.ndarray) -> list[float]:
    """Per bin of :data:`BINS_MM`, the median signed distance of the points ``q`` (part
    frame) from the mesh ``local`` (pressed, or not), along the dent's depth (NaN: too few
    points)."""
    import trimesh

    r = dent.axis_distance(q)
    keep = r < BINS_MM[-1][1]
    q, r = q[keep], r[keep]
    closest, dist, tri = trimesh.proximity.closest_point(local, q)
    outward = np.sign(np.einsum("ij,ij->i", q - closest, local.face_normals[tri])) * dist
    along_depth = -np.sign(dent.depth_mm) * outward
    out = []
    for lo, hi in BINS_MM:
        sel = (r >= lo) & (r < hi)
        out.append(float(np.median(along_depth[sel])) if sel.sum() > 5 else float("nan"))
    return out


def _defect_error(m: Any, dent: Any) -> float:
    """The depth error of the defect that bench_defects matches to the dent (NaN: none)."""
    if m.deviations is None:
        return float("nan")
    centre = np.asarray(dent.center_mm)
    hits = [
        f for f in m.deviations.defects
        if np.sign(f.peak_mm) == -np.sign(dent.depth_mm)
        and np.linalg.norm(f.center_mm - centre) <= dent.radius_mm
    ]  # fmt: skip
    if not hits:
        return float("nan")
    f = min(hits, key=lambda f: np.linalg.norm(f.center_mm - centre))
    return float(abs(f.peak_mm) - abs(dent.depth_mm))


if __name__ == "__main__":
    raise SystemExit(main())
