"""``inspection calibrate``: calibrate the rig from ChArUco board images and write its TOML.

Without ``--images`` the board is rendered by the simulator with the rig as
built (``Rig.nominal()``), which is how the packaged ``inspection/data/rig.toml`` is produced; the
command then also reports how far the estimate is from that truth.

With ``--images DIR`` it reads real images: one sub-directory per board view
(sorted by name; the first is the reference view, the board lying flat on the
belt at its fixture), each holding one PNG per camera named after the camera
(``cam0.png`` .. ``cam3.png``).

The rig is written to ``--out`` only if no such file exists: ``--replace``
overwrites one (checked before any work, so minutes of calibration are not
lost to it). A progress bar follows rendering, detection and refinement on a
terminal (``--quiet``: none).

Exit codes: 0 calibrated and written; 1 the images were read but do not
calibrate the rig (a camera saw too few boards, or missed the reference
view); 2 bad input (a missing or unreadable image, too few views, an
existing ``--out`` without ``--replace``); 3 an internal error.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from .exits import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, BadInput

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate the four cameras from ChArUco images (rendered by default)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("rig.toml"),
        help="rig TOML to write, a new file unless --replace (default: %(default)s)",
    )
    p.add_argument("--replace", action="store_true", help="overwrite --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--images",
        type=Path,
        default=None,
        help="directory of real board images (DIR/<view>/<camera>.png); default: render them",
    )
    p.add_argument(
        "--views", type=int, default=20, help="board views to render (default: %(default)s)"
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the rendered poses and noise (default: %(default)s)",
    )
    p.add_argument(
        "--save-images",
        type=Path,
        default=None,
        help="also write the rendered board images as PNG under this directory",
    )
    p.set_defaults(func=cmd_calibrate)


def _read_views(root: Path, names: tuple[str, ...]) -> list[list[np.ndarray]]:
    import cv2

    dirs = sorted(d for d in root.iterdir() if d.is_dir())
    if not dirs:
        raise BadInput(f"{root}: no view directories (expected {root}/<view>/<camera>.png)")
    views = []
    for d in dirs:
        row = []
        for name in names:
            path = d / f"{name}.png"
            if not path.is_file():
                raise BadInput(f"missing image {path}")
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise BadInput(f"{path}: not an image OpenCV can read")
            row.append(img)
        views.append(row)
    return views


def cmd_calibrate(args: argparse.Namespace) -> int:
    from inspection.calibration import (
        calibrate,
        centre_errors,
        render_calibration_views,
        stereo_errors,
    )
    from inspection.errors import CalibrationError, InspectionError
    from inspection.pictures import write_png
    from inspection.rig import Rig

    from .progress import FractionBar

    def bad(message: object, code: int = EXIT_BAD_INPUT) -> int:
        print(f"inspection calibrate: {message}", file=sys.stderr)
        return code

    if args.out.exists() and not args.replace:
        return bad(f"{args.out} exists: give --replace to overwrite it, or another --out")
    if args.out.is_dir():
        return bad(f"--out {args.out} is a directory")
    truth = Rig.nominal()
    try:
        if args.images is not None:
            if not args.images.is_dir():
                return bad(f"{args.images} is not a directory")
            views = _read_views(args.images, truth.names)
            origin = f"{len(views)} board views from {args.images}"
        else:
            if args.views < 4:
                return bad("--views must be at least 4")
            with FractionBar("rendering", quiet=args.quiet) as progress:
                views, _ = render_calibration_views(
                    truth, args.views, seed=args.seed, progress=progress
                )
            origin = f"{len(views)} rendered board views (seed {args.seed})"
            if args.save_images is not None:
                for v, view in enumerate(views):
                    for name, img in zip(truth.names, view, strict=True):
                        write_png(args.save_images / f"view{v:02d}" / f"{name}.png", img)
        with FractionBar("calibrating", quiet=args.quiet) as progress:
            cal = calibrate(views, progress=progress)
    except (BadInput, CalibrationError) as exc:
        return bad(exc, EXIT_FAILED if isinstance(exc, CalibrationError) else EXIT_BAD_INPUT)
    except InspectionError as exc:
        return bad(exc)
    print(f"calibration from {origin}")
    print(cal.summary())
    if args.images is None:
        err = centre_errors(cal.rig, truth)
        print(
            "simulation check: camera centres vs the rig as built, after one rigid alignment: "
            + ", ".join(f"{e:.3f}" for e in err)
            + " mm"
        )
        for (a, b), (rms, worst) in stereo_errors(cal.rig, truth).items():
            print(
                f"simulation check: pair {truth.names[a]}-{truth.names[b]} triangulates the volume "
                f"with RMS {rms:.3f} mm, max {worst:.3f} mm (after one rigid alignment)"
            )
    if args.out.exists() and not args.replace:  # appeared while calibrating
        return bad(f"{args.out} exists: give --replace to overwrite it, or another --out")
    out = cal.rig.save(args.out)
    print(f"wrote {out} (calibration id {cal.rig.id})")
    return EXIT_OK
