"""``inspection align`` and ``inspection check``: measure a cloud against the CAD.

Both measure through :func:`inspection.measure.measure_cloud`, the sequence
the line and the REST API measure with; this module only builds the part
model from the command line, maps the options onto
:class:`~inspection.measure.MeasureParams` and prints the
:class:`~inspection.measure.Measurement`.

``align CAD_OR_TREE CLOUD`` finds T_cad_data, the transform that maps the
cloud into the CAD frame. Where the cloud lies decides how:

- by default (frame ``data``) the cloud lies anywhere, in a frame with z up:
  a global search over the part's resting poses, then robust fine
  registration;
- ``--seen-from-above`` (frame ``rig``): the same, and the cloud was
  measured from +z of its frame, so no point is fitted onto a face turned
  away from the sensor (loss tukey or welsch);
- ``--no-global`` (frame ``cad``): the cloud is already roughly in the CAD
  frame; only the fine registration runs, from the identity.

``check CAD_OR_TREE CLOUD --points POINTS.json`` also measures the
deviations, over the whole cloud and at each comparison point, and gives the
part's verdict; ``--write-ply`` writes the cloud in the CAD frame with each
point's signed deviation.

Both print the fit (transform, residual, inliers, why it stopped,
observability, the directions the data leave free, the global search's
candidates) and its quality as the service reports it (the free directions
by name, the observability ratio, the runner-up pose's score), and the
measurement's reason.

CAD_OR_TREE is a CAD file (STL, OBJ, PLY, STEP; its tree is built on the
fly), ``builtin:panel``, or a tree saved by ``build-tree`` (.npz; the CAD is
taken from the vertices and faces it stores). CLOUD is a PLY, XYZ/TXT/CSV or
NPY file of points in mm. POINTS.json is a list of comparison points (name,
position, normal, lower_mm, upper_mm, radius_mm).

``align`` also says whether the cloud matches the CAD at all: a fit that
keeps too few of the points, or whose residual is far above the cloud's own
noise (estimated from local planes, without the CAD), does not match,
whatever its optimiser says of its convergence.

Exit codes: 0 a usable, unambiguous fit of a cloud that matches the CAD
(align) or a part that passes (check); 1 a cloud that does not match the CAD,
a fit that is not usable (did not converge, too few inliers, too high a
residual) or is ambiguous, or a part that fails or cannot be judged (not
measurable); 2 bad input (message on stderr): also a POINTS.json without
comparison points, which leaves check nothing to judge; 3 an internal error.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .exits import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK

if TYPE_CHECKING:
    from inspection.deviations import ComparisonPoint
    from inspection.measure import Frame, Measurement, MeasureParams, PartModel
    from inspection.registration import Registration

log = logging.getLogger(__name__)

BUILTIN_PANEL = "builtin:panel"
TREE_SUFFIXES = (".npz",)
MATCH_RESIDUAL_RATIO = 5.0
"""A cloud matches its CAD when the fit's RMS residual stays within this many
times the cloud's own noise: the right CAD leaves the noise itself, a wrong
one a residual of the shapes' difference."""


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
        where = p.add_mutually_exclusive_group()
        where.add_argument(
            "--no-global",
            action="store_true",
            help="the cloud is roughly in the CAD frame: fine registration from the identity",
        )
        where.add_argument(
            "--seen-from-above",
            action="store_true",
            help="the cloud was measured from above (+z of its frame): points are not fitted "
            "onto faces turned away from the sensor, such as a thin part's underside "
            "(loss tukey or welsch)",
        )
        p.add_argument("--seed", type=int, default=0, help="seed of the random subsets (0)")
        p.add_argument("--json", action="store_true", help="print JSON instead of text")
        p.add_argument("--quiet", action="store_true", help="no progress bar of the tree build")

    a = subparsers.add_parser(
        "align",
        help="fit a measured cloud to the CAD (global search + robust registration)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    common(a)
    a.set_defaults(func=cmd_align, points=None, min_support=None, write_ply=None)

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
        "--min-support",
        type=int,
        default=None,
        help="points needed at a comparison point (the line's default, 10)",
    )
    c.add_argument(
        "--write-ply",
        metavar="OUT.ply",
        type=Path,
        default=None,
        help="write the cloud in the CAD frame with its signed deviation",
    )
    c.set_defaults(func=cmd_check)


# --------------------------------------------------------------------------- inputs


def frame_of(args: argparse.Namespace) -> Frame:
    """The frame the cloud is given in, from ``--no-global`` and ``--seen-from-above``."""
    if args.no_global:
        return "cad"
    return "rig" if args.seen_from_above else "data"


def measure_params(args: argparse.Namespace) -> MeasureParams:
    """The line's MeasureParams with the command line's loss, seed and minimum support.

    Raises
    ------
    InvalidInput
        A view direction with a loss without a plateau, a bad minimum support.
    """
    from inspection.measure import LINE_REGISTER, MeasureParams

    register = dataclasses.replace(
        LINE_REGISTER,
        loss=args.loss,
        seed=args.seed,
        view_direction=(0.0, 0.0, 1.0) if args.seen_from_above else None,
    )
    if args.min_support is None:
        return MeasureParams(register=register)
    return MeasureParams(register=register, min_support=args.min_support)


def load_model(
    spec: str,
    scale: float,
    points: Sequence[ComparisonPoint] = (),
    *,
    alignment: bool,
    quiet: bool = True,
) -> PartModel:
    """The part model of a CAD file, ``builtin:panel`` or a saved tree.

    Parameters
    ----------
    spec : str
        CAD_OR_TREE.
    scale : float
        Multiplies the CAD's coordinates to give mm (not for a saved tree).
    points : sequence of ComparisonPoint
    alignment : bool
        Compute the global search's model (needed unless the cloud is given
        in the CAD frame).
    quiet : bool
        No progress bar of the tree build (there is none off a terminal).

    Raises
    ------
    CadLoadError
        An unreadable CAD file.
    InvalidInput
        A missing or unreadable tree file, ``--scale`` with a tree.
    TreeMismatch
        A tree whose stored mesh is not the geometry it claims to be built for.
    """
    from inspection.alignment import alignment_model
    from inspection.cad import CadModel, load_cad
    from inspection.deviations import check_comparison_points
    from inspection.errors import InvalidInput, TreeMismatch
    from inspection.grid import GridTree
    from inspection.measure import PartModel

    if Path(spec).suffix.lower() in TREE_SUFFIXES:
        if scale != 1.0:
            raise InvalidInput("--scale does not apply to a saved tree (its CAD is in mm)")
        tree = GridTree.load(spec)
        cad = CadModel.from_arrays(tree.vertices, tree.faces, name=tree.name, source=spec)
        if cad.hash != tree.cad_hash:
            raise TreeMismatch(
                f"{spec}: the mesh stored in the tree hashes to {cad.hash[:12]}, "
                f"the tree claims CAD {tree.cad_hash[:12]}"
            )
        return PartModel(cad, tree, alignment_model(cad) if alignment else None, tuple(points))
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
    from .progress import FractionBar

    # The tree built here with its bar, then the part as PartModel.build makes it.
    with FractionBar(f"building the tree of {cad.name}", quiet=quiet) as progress:
        tree = GridTree.build(cad, progress=progress)
    model = alignment_model(cad) if alignment else None
    return PartModel(cad, tree, model, check_comparison_points(points))


def _measure(
    args: argparse.Namespace, points: Sequence[ComparisonPoint] = ()
) -> tuple[PartModel, Measurement, dict[str, float], np.ndarray]:
    """Read the inputs and measure the cloud; the timings of reading added."""
    from inspection.cloud_io import read_cloud
    from inspection.measure import measure_cloud

    params = measure_params(args)
    frame = frame_of(args)
    t0 = time.perf_counter()
    cloud = read_cloud(args.cloud)
    read_ms = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    part = load_model(args.model, args.scale, points, alignment=frame != "cad", quiet=args.quiet)
    part_ms = (time.perf_counter() - t0) * 1e3
    m = measure_cloud(part, cloud, params, frame=frame)
    return part, m, {"read": read_ms, "part": part_ms, **m.timings_ms}, cloud


def _bad_input(command: str, exc: Exception) -> int:
    print(f"inspection {command}: {exc}", file=sys.stderr)
    return EXIT_BAD_INPUT


@dataclasses.dataclass(frozen=True)
class Match:
    """Whether a cloud matches the CAD it was fitted to, by the fit's own diagnostics."""

    matches: bool
    noise_mm: float
    residual_ratio: float | None
    reason: str | None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def line(self, reg: Registration | None) -> str:
        if not self.matches or reg is None:
            return f"match: the cloud DOES NOT MATCH the CAD: {self.reason}"
        return (
            f"match: the cloud matches the CAD (residual {reg.rms_mm:.4f} mm, "
            f"{self.residual_ratio:.1f}x the cloud's own noise of {self.noise_mm:.4f} mm; "
            f"{100 * reg.inlier_fraction:.1f} % of the points kept)"
        )


def cloud_match(reg: Registration | None, points: np.ndarray, min_inlier_fraction: float) -> Match:
    """Does the fit ``reg`` of ``points`` say the cloud is of this CAD?

    It does not when the fit keeps fewer than ``min_inlier_fraction`` of the
    points, or when its RMS residual exceeds :data:`MATCH_RESIDUAL_RATIO`
    times the cloud's own noise (:func:`inspection.noise.surface_noise_mm`):
    a fit of the wrong CAD can converge, at millimetres where the right one
    leaves the sensor's noise.
    """
    from inspection.noise import surface_noise_mm

    noise = surface_noise_mm(points)
    if reg is None:
        return Match(False, noise, None, "nothing was fitted")
    ratio = float(reg.rms_mm / noise) if noise > 0 else math.inf
    if not reg.inlier_fraction >= min_inlier_fraction:
        why = (
            f"the fit keeps {100 * reg.inlier_fraction:.1f} % of the points, "
            f"below the {100 * min_inlier_fraction:.0f} % a match keeps"
        )
        return Match(False, noise, ratio, why)
    if not ratio <= MATCH_RESIDUAL_RATIO:
        why = (
            f"the fit's residual {reg.rms_mm:.3f} mm is {ratio:.0f}x the cloud's own noise "
            f"({noise:.4f} mm); a match stays within {MATCH_RESIDUAL_RATIO:.0f}x"
        )
        return Match(False, noise, ratio, why)
    return Match(True, noise, ratio, None)


# --------------------------------------------------------------------------- output


def registration_dict(reg: Registration) -> dict[str, Any]:
    """JSON-ready summary of a Registration (or Alignment)."""
    from inspection.alignment import Alignment

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
    if isinstance(reg, Alignment):
        out["ambiguous"] = bool(reg.ambiguous)
        out["candidates"] = [
            {"pose_index": c.pose_index, "angle_deg": c.angle_deg, "score_mm2": c.score}
            for c in reg.candidates
        ]
    return out


def measurement_dict(m: Measurement) -> dict[str, Any]:
    """The verdict, reason, frame and fit quality of ``m``, JSON-ready."""
    q = m.quality
    return {
        "verdict": None if m.verdict is None else m.verdict.value,
        "reason": m.reason,
        "frame": m.frame,
        "quality": None
        if q is None
        else {
            "converged": q.converged,
            "stop_reason": q.stop_reason,
            "iterations": q.iterations,
            "observability": q.observability,
            "weak_directions": list(q.weak_directions),
            "ambiguous": q.ambiguous,
            "runner_up_score": q.runner_up_score,
        },
    }


def _print_registration(reg: Registration) -> None:
    from inspection.alignment import Alignment

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
    if isinstance(reg, Alignment):
        scores = ", ".join(f"{c.score:.3g}" for c in reg.candidates[:4])
        word = "AMBIGUOUS: another pose fits as well" if reg.ambiguous else "unambiguous"
        print(f"global search: {word} (candidate scores, mm^2: {scores})")


def _print_measurement(m: Measurement) -> None:
    """The fit, its quality and the reason, as text."""
    if m.registration is not None:
        _print_registration(m.registration)
    else:
        print("no fit")
    q = m.quality
    if q is not None:
        print(quality_line(q.observability, q.weak_directions, q.runner_up_score))
    if m.reason:
        print(f"reason: {m.reason}")


def quality_line(
    observability: float, weak_directions: Sequence[str], runner_up_score: float | None
) -> str:
    """One line on what the fit says of itself."""
    weak = ", ".join(weak_directions) or "none"
    line = f"fit quality: observability ratio {observability:.3g}, weak directions: {weak}"
    if runner_up_score is not None:
        line += f", runner-up pose at {runner_up_score:.2f} of the chosen one's score"
    return line


def _timings_line(timings: dict[str, float]) -> str:
    return "time: " + ", ".join(f"{k} {v:.0f} ms" for k, v in timings.items())


def _usable(m: Measurement) -> bool:
    """A fit the part can be measured from, and not ambiguous."""
    return m.verdict is not None and not (m.quality is not None and m.quality.ambiguous)


# --------------------------------------------------------------------------- commands


def cmd_align(args: argparse.Namespace) -> int:
    from inspection.errors import InspectionError

    try:
        _, m, timings, cloud = _measure(args)
    except (InspectionError, OSError) as exc:
        return _bad_input("align", exc)
    match = cloud_match(m.registration, cloud, measure_params(args).min_inlier_fraction)
    if args.json:
        fit = registration_dict(m.registration) if m.registration is not None else {}
        doc = {**fit, **measurement_dict(m), "match": match.to_dict(), "timings_ms": timings}
        print(json.dumps(doc, indent=2))
    else:
        _print_measurement(m)
        print(match.line(m.registration))
        print(_timings_line(timings))
    return EXIT_OK if _usable(m) and match.matches else EXIT_FAILED


def cmd_check(args: argparse.Namespace) -> int:
    from inspection.cloud_io import write_ply
    from inspection.deviations import load_comparison_points
    from inspection.errors import InspectionError, InvalidInput

    try:
        points = load_comparison_points(args.points)
        if not points:
            # A verdict over no comparison point would pass any part.
            return _bad_input(
                "check",
                InvalidInput(
                    f"{args.points}: no comparison points, so nothing to judge the part by "
                    "(give at least one; align fits a cloud without them)"
                ),
            )
        _, m, timings, _ = _measure(args, points)
        points_cad = m.points_cad()
        if args.write_ply is not None:
            if m.deviations is None or points_cad is None:
                log.warning("%s not written: the cloud has no usable fit", args.write_ply)
            else:
                write_ply(args.write_ply, points_cad, scalars={"deviation": m.deviations.distances})
    except (InspectionError, OSError) as exc:
        return _bad_input("check", exc)
    devs = m.deviations
    if args.json:
        doc = {
            **measurement_dict(m),
            "registration": None if m.registration is None else registration_dict(m.registration),
            "comparison": [] if devs is None else [c.to_dict() for c in devs.comparison],
            "field": None if devs is None else devs.summary.to_dict(),
            "timings_ms": timings,
        }
        print(json.dumps(doc, indent=2))
    else:
        _print_measurement(m)
        if devs is not None:
            s = devs.summary
            print(
                f"field: {s.n} points ({s.inliers} inliers), mean {s.mean_mm:+.4f} mm, "
                f"std {s.std_mm:.4f} mm, p05 {s.p05_mm:+.4f}, p95 {s.p95_mm:+.4f}, "
                f"max |d| {s.max_abs_mm:.4f} mm"
            )
            width = max([len(c.name) for c in devs.comparison] + [4])
            print(
                f"{'name':<{width}}  {'deviation':>10}  {'tolerance':>19}  {'support':>7}  verdict"
            )
            for c in devs.comparison:
                dev = "-" if np.isnan(c.deviation_mm) else f"{c.deviation_mm:+.4f}"
                tol = f"[{c.lower_mm:+.3f}, {c.upper_mm:+.3f}]"
                why = f"  ({c.reason})" if c.reason else ""
                print(
                    f"{c.name:<{width}}  {dev:>10}  {tol:>19}  {c.support:>7}  "
                    f"{c.verdict.value}{why}"
                )
        print(f"part: {'NO VERDICT' if m.verdict is None else m.verdict.value.upper()}")
        print(_timings_line(timings))
    from inspection.deviations import Verdict

    # Fails and not measurable alike: measured, and the part did not pass.
    return EXIT_OK if _usable(m) and m.verdict is Verdict.PASS else EXIT_FAILED
