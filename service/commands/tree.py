"""``inspection build-tree`` and ``inspection info``: build, save and describe CAD trees.

``build-tree CAD OUT`` reads a CAD file (STL, OBJ, PLY; STEP with the
``step`` extra) or ``builtin:panel`` (the generated demo panel), builds its
closest-point grid and saves it as one file that the line preloads.
``info TREE`` prints what a saved tree holds: format version, CAD hash,
build parameters, sizes and memory.

Exit codes: 0 done; 2 bad input (an unreadable, empty or malformed CAD or
tree file, a tree of another CAD); 3 an internal error.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

from .exits import EXIT_BAD_INPUT, EXIT_OK, BadInput

log = logging.getLogger(__name__)

BUILTIN_PANEL = "builtin:panel"


def register(subparsers: argparse._SubParsersAction) -> None:
    b = subparsers.add_parser(
        "build-tree",
        help="build the closest-point tree of a CAD model and save it",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    b.add_argument("cad", metavar="CAD", help=f"CAD file (STL, OBJ, PLY, STEP) or {BUILTIN_PANEL}")
    b.add_argument("out", metavar="OUT", type=Path, help="tree file to write (.npz)")
    b.add_argument(
        "--scale", type=float, default=1.0, help="multiplies the CAD coordinates to give mm"
    )
    b.add_argument("--spacing-mm", type=float, default=None, help="fine cell edge, mm (default 1)")
    b.add_argument(
        "--band-mm",
        type=float,
        default=None,
        help="distance from the surface answered by the fast path, mm (default 4)",
    )
    b.add_argument("--quiet", action="store_true", help="no progress bar")
    b.set_defaults(func=cmd_build_tree)

    i = subparsers.add_parser(
        "info",
        help="describe a saved tree: format, CAD hash, parameters, sizes",
        description="Print what a saved CAD tree holds.",
    )
    i.add_argument("tree", metavar="TREE", type=Path, help="tree file written by build-tree")
    i.add_argument("--cad", default=None, help="also check that the tree belongs to this CAD file")
    i.add_argument("--scale", type=float, default=1.0, help="scale of --cad (default: 1)")
    i.add_argument("--json", action="store_true", help="print JSON instead of text")
    i.set_defaults(func=cmd_info)


def _load_cad(spec: str, scale: float) -> Any:
    from inspection.cad import load_cad

    if spec == BUILTIN_PANEL:
        from inspection.panel import sheet_metal_panel

        if scale != 1.0:
            raise BadInput(f"--scale does not apply to {BUILTIN_PANEL}")
        return sheet_metal_panel()
    return load_cad(spec, scale=scale)


def _peak_rss_mb() -> float | None:
    try:
        import resource
    except ImportError:  # not on this platform
        return None
    # Linux reports kilobytes, macOS bytes.
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024 / 1024 if sys.platform == "darwin" else rss / 1024


def cmd_build_tree(args: argparse.Namespace) -> int:
    from inspection.errors import InspectionError
    from inspection.grid import GridTree

    from .progress import FractionBar

    kwargs: dict[str, float] = {}
    if args.spacing_mm is not None:
        kwargs["spacing_mm"] = args.spacing_mm
    if args.band_mm is not None:
        kwargs["band_mm"] = args.band_mm
    try:
        t0 = time.perf_counter()
        cad = _load_cad(args.cad, args.scale)
        t_load = time.perf_counter() - t0
        print(
            f"CAD {cad.name}: {len(cad.faces)} faces, {cad.extents.round(1).tolist()} mm, "
            f"hash {cad.hash[:16]} (read in {t_load:.2f} s)"
        )
        t0 = time.perf_counter()
        with FractionBar(f"building the tree of {cad.name}", quiet=args.quiet) as progress:
            tree = GridTree.build(cad, progress=progress, **kwargs)
        t_build = time.perf_counter() - t0
        out = tree.save(args.out)
    except InspectionError as exc:
        print(f"inspection build-tree: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    rss = _peak_rss_mb()
    print(
        f"built in {t_build:.2f} s: {tree.n_blocks} blocks, {tree.nbytes / 1e6:.1f} MB"
        + (f", peak RSS {rss:.0f} MB" if rss is not None else "")
    )
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB), tree hash {tree.hash[:16]}")
    return EXIT_OK


def cmd_info(args: argparse.Namespace) -> int:
    from inspection.errors import InspectionError
    from inspection.grid import GridTree

    try:
        cad = _load_cad(args.cad, args.scale) if args.cad else None
        t0 = time.perf_counter()
        tree = GridTree.load(args.tree, cad=cad)
        t_load = time.perf_counter() - t0
    except InspectionError as exc:
        print(f"inspection info: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    info = tree.info()
    info["file"] = str(args.tree)
    info["file_bytes"] = args.tree.stat().st_size
    info["load_s"] = round(t_load, 4)
    if cad is not None:
        info["cad_check"] = "matches"
    if args.json:
        print(json.dumps(info, indent=2))
        return EXIT_OK
    p = info["params"]
    lines = [
        f"tree          {info['file']} ({info['file_bytes'] / 1e6:.1f} MB, "
        f"loaded in {t_load:.3f} s)",
        f"format        version {info['format_version']}",
        f"CAD           {info['name']}: {info['faces']} faces, {info['vertices']} vertices",
        f"CAD hash      {info['cad_hash']}" + (" (matches --cad)" if cad is not None else ""),
        f"tree hash     {info['tree_hash']}",
        f"parameters    spacing {p['spacing_mm']} mm, band {p['band_mm']} mm, "
        f"block {p['block']}^3 cells",
        "bounds mm     " + "  ".join(str([round(x, 2) for x in row]) for row in info["bounds_mm"]),
        f"grid          {info['blocks']} blocks of {info['coarse_dims']} coarse, "
        f"{info['fine_cells']} fine cells ({info['mixed_cells']} mixed, split in subcells of "
        f"which {info['mixed_subcells']} keep candidate lists; "
        f"{info['unknown_cells']} beyond the band)",
        f"memory        {info['nbytes'] / 1e6:.1f} MB in arrays",
    ]
    print("\n".join(lines))
    return EXIT_OK
