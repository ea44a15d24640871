"""``inspection align`` and ``inspection check``: fit a measured cloud to the CAD.

``align CAD_OR_TREE CLOUD`` finds T_cad_data, the transform that maps the
cloud into the CAD frame: a global search over the part's resting poses
(the cloud in a frame with z up, the part lying anywhere), then robust fine
registration. With ``--no-global`` only the fine registration runs, from the
identity (a cloud already roughly in the CAD frame).

``check CAD_OR_TREE CLOUD --points POINTS.json`` also measures the
deviations: over the whole cloud and at each comparison point, with the
verdict.

CAD_OR_TREE is a CAD file (STL, OBJ, PLY, STEP; its tree is built on the
fly), ``builtin:panel``, or a tree saved by ``build-tree`` (.npz). CLOUD is a
PLY, XYZ/TXT/CSV or NPY file of points in mm. POINTS.json is a list of
comparison points (name, position, normal, lower_mm, upper_mm, radius_mm).

Exit codes: 0 a converged, unambiguous fit (align) or a part that passes
(check); 1 a fit that did not converge or is ambiguous, or a failed part;
3 a part that cannot be judged (not measurable); 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

BUILTIN_PANEL = "builtin:panel"
TREE_SUFFIXES = (".npz",)
EXIT_OK, EXIT_BAD_FIT, EXIT_ERROR, EXIT_NOT_MEASURABLE = 0, 1, 2, 3


def register(subparsers: argparse._SubParsersAction) -> None:
    from inspection.registration import LOSSES

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "model", metavar="CAD_OR_TREE", help="CAD file, builtin:panel, or tree (.npz)"
        )
        p.add_argument(
            "cloud", metavar="CLOUD", type=Path, help="measured points: PLY, XYZ or NPY, mm"
        )
        p.add_argument(
            "--loss", choices=sorted(LOSSES), default="tukey", help="robust loss (tukey)"
        )
        p.add_argument(
            "--scale", type=float, default=1.0, help="multiplies CAD coordinates to give mm"
        )
        p.add_argument(
            "--no-global",
            action="store_true",
            help="skip the global search: fine registration from the identity",
        )
        p.add_argument(
            "--seen-from-above",
            action="store_true",
            help="the cloud was measured from above (+z of its frame): points are not fitted "
            "onto faces turned away from the sensor, such as a thin part's underside "
            "(loss tukey or welsch)",
        )
        p.add_argument("--seed", type=int, default=0, help="seed of the random subsets (0)")
        p.add_argument("--json", action="store_true", help="print JSON instead of text")

    a = subparsers.add_parser(
        "align",
        help="fit a measured cloud to the CAD (global search + robust registration)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    common(a)
    a.set_defaults(func=cmd_align)

    c = subparsers.add_parser(
        "check",
        help="fit a cloud and measure its deviations at comparison points",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    common(c)
    c.add_argument(
        "--points", metavar="POINTS.json", type=Path, required=True, help="comparison points (JSON)"
    )
    c.add_argument(
        "--min-support", type=int, default=10, help="points needed at a comparison point (10)"
    )
    c.add_argument(
        "--write-ply",
        metavar="OUT.ply",
        type=Path,
        default=None,
        help="write the cloud in the CAD frame with its signed deviation",
    )
    c.set_defaults(func=cmd_check)


def _load_tree(spec: str, scale: float) -> Any:
    """A GridTree from a saved file, or built from a CAD file or the built-in panel."""
    from inspection.cad import load_cad
    from inspection.grid import GridTree

    if Path(spec).suffix.lower() in TREE_SUFFIXES:
        if scale != 1.0:
            raise SystemExit("--scale does not apply to a saved tree")
        return GridTree.load(spec)
    if spec == BUILTIN_PANEL:
        from inspection.panel import sheet_metal_panel

        cad = sheet_metal_panel()
    else:
        cad = load_cad(spec, scale=scale)
    log.info(
        "building the tree of %s (%d faces); save it with build-tree to skip this",
        cad.name,
        len(cad.faces),
    )
    return GridTree.build(cad)


def _fit(args: argparse.Namespace) -> tuple[Any, Any, np.ndarray, dict[str, float]]:
    from inspection.alignment import align
    from inspection.cloud_io import read_cloud
    from inspection.registration import register as fine

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    tree = _load_tree(args.model, args.scale)
    timings["tree_ms"] = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    points = read_cloud(args.cloud)
    timings["read_ms"] = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    view = np.array([0.0, 0.0, 1.0]) if args.seen_from_above else None
    if args.no_global:
        reg = fine(tree, points, loss=args.loss, seed=args.seed, view_direction=view)
    else:
        reg = align(tree, points, loss=args.loss, seed=args.seed, view_direction=view)
    timings["fit_ms"] = (time.perf_counter() - t0) * 1e3
    return tree, reg, points, timings


def registration_dict(reg: Any) -> dict[str, Any]:
    """JSON-ready summary of a Registration (or Alignment)."""
    out: dict[str, Any] = {
        "transform": np.asarray(reg.transform).tolist(),
        "rms_mm": float(reg.rms_mm),
        "inlier_fraction": float(reg.inlier_fraction),
        "iterations": int(reg.iterations),
        "converged": bool(reg.converged),
        "stop_reason": str(reg.stop_reason),
        "scale_mm": float(reg.scale_mm),
        "loss": reg.loss,
        "observability": np.asarray(reg.observability).tolist(),
        "degenerate_directions": np.asarray(reg.degenerate_directions).tolist(),
    }
    if hasattr(reg, "ambiguous"):
        out["ambiguous"] = bool(reg.ambiguous)
        out["candidates"] = [
            {"pose_index": c.pose_index, "angle_deg": c.angle_deg, "score_mm2": c.score}
            for c in reg.candidates
        ]
    return out


def _print_registration(reg: Any) -> None:
    T = np.asarray(reg.transform)
    print("T_cad_data (maps the cloud into the CAD frame, mm):")
    for row in T:
        print("  " + " ".join(f"{v:12.6f}" for v in row))
    print(
        f"rms {reg.rms_mm:.4f} mm, inliers {100 * reg.inlier_fraction:.1f} %, "
        f"{reg.iterations} iterations, {reg.stop_reason}"
    )
    obs = np.asarray(reg.observability)
    free = len(reg.degenerate_directions)
    print(
        f"observability: weakest {obs[0]:.3g}, strongest {obs[-1]:.3g}"
        + (f"; {free} unconstrained direction(s): the pose is not unique" if free else "")
    )
    if hasattr(reg, "ambiguous"):
        scores = ", ".join(f"{c.score:.3g}" for c in reg.candidates[:4])
        word = "AMBIGUOUS: another pose fits as well" if reg.ambiguous else "unambiguous"
        print(f"global search: {word} (candidate scores, mm^2: {scores})")


def cmd_align(args: argparse.Namespace) -> int:
    from inspection.errors import InspectionError

    try:
        _, reg, _, timings = _fit(args)
    except InspectionError as exc:
        print(f"inspection align: {exc}", file=sys.stderr)
        return EXIT_ERROR
    good = reg.converged and not getattr(reg, "ambiguous", False)
    if args.json:
        print(json.dumps({**registration_dict(reg), "timings_ms": timings}, indent=2))
    else:
        _print_registration(reg)
        print(f"time: fit {timings['fit_ms']:.0f} ms (tree {timings['tree_ms']:.0f} ms)")
    return EXIT_OK if good else EXIT_BAD_FIT


def cmd_check(args: argparse.Namespace) -> int:
    from inspection.cloud_io import write_ply
    from inspection.deviations import Verdict, deviations, load_comparison_points
    from inspection.errors import InspectionError

    try:
        points_spec = load_comparison_points(args.points)
        tree, reg, points, timings = _fit(args)
        T = np.asarray(reg.transform)
        points_cad = points @ T[:3, :3].T + T[:3, 3]
        t0 = time.perf_counter()
        devs = deviations(tree, points_cad, points_spec, min_support=args.min_support)
        timings["deviations_ms"] = (time.perf_counter() - t0) * 1e3
        if args.write_ply is not None:
            write_ply(args.write_ply, points_cad, scalars={"deviation": devs.distances})
    except InspectionError as exc:
        print(f"inspection check: {exc}", file=sys.stderr)
        return EXIT_ERROR
    ambiguous = bool(getattr(reg, "ambiguous", False))
    if args.json:
        doc = {
            "verdict": devs.verdict.value,
            "registration": registration_dict(reg),
            "comparison": [c.to_dict() for c in devs.comparison],
            "field": devs.summary.to_dict(),
            "timings_ms": timings,
        }
        print(json.dumps(doc, indent=2))
    else:
        _print_registration(reg)
        s = devs.summary
        print(
            f"field: {s.n} points, mean {s.mean_mm:+.4f} mm, std {s.std_mm:.4f} mm, "
            f"p05 {s.p05_mm:+.4f}, p95 {s.p95_mm:+.4f}, max |d| {s.max_abs_mm:.4f} mm"
        )
        width = max([len(c.name) for c in devs.comparison] + [4])
        print(f"{'name':<{width}}  {'deviation':>10}  {'tolerance':>19}  {'support':>7}  verdict")
        for c in devs.comparison:
            dev = "-" if np.isnan(c.deviation_mm) else f"{c.deviation_mm:+.4f}"
            tol = f"[{c.lower_mm:+.3f}, {c.upper_mm:+.3f}]"
            print(f"{c.name:<{width}}  {dev:>10}  {tol:>19}  {c.support:>7}  {c.verdict.value}")
        print(f"part: {devs.verdict.value.upper()}")
    if ambiguous or not reg.converged:
        log.warning("the fit is %s", "ambiguous" if ambiguous else "not converged")
        return EXIT_BAD_FIT
    return {
        Verdict.PASS: EXIT_OK,
        Verdict.FAIL: EXIT_BAD_FIT,
        Verdict.NOT_MEASURABLE: EXIT_NOT_MEASURABLE,
    }[devs.verdict]
