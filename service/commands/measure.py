"""``inspection measure``: measure one trigger's frames of a part, as the line's worker does.

``measure FRAMES... --part PART.toml [--rig RIG.toml] [--trees DIR] [--no-guided] [--json]``

FRAMES is either one file holding one FrameSet's bytes (the wire format of
``docs/protocol.md``: what the line records and publishes), or one 8-bit grey
image file per camera of the rig (PNG), in the rig's camera order.

The part is a part spec (TOML, as in ``configs/parts/``; its CAD relative to
the spec's folder, or ``generated:panel``), loaded with the line's own
:func:`service.parts.load_part`: its tree and alignment model are cached
under ``--trees`` (default ``$XDG_CACHE_HOME/inspection/trees``, else
``~/.cache/inspection/trees``; a folder in the temporary directory when that
cannot be created), keyed by the CAD's hash, so only the first run of a part
builds them. The rig is ``--rig`` (a calibration written by
``inspection calibrate``) or ``Rig.default()``.

The frames are measured by :func:`inspection.measure.measure_frames` with the
part's parameters (``--no-guided``: without the CAD-guided second matching
pass), and the measurement is mapped onto an InspectionResult by
:func:`service.results.outcome`, exactly as the worker publishes it: with
``--json`` that result's JSON, otherwise a text summary. A FrameSet gives the
result its identity (line, station, serial, seq, trigger time, calibration);
images are measured as line ``cli``, station ``cli``, serial ``cli``.

A FrameSet of another part than ``--part``, or taken for another calibration
than the rig's, is refused, as the worker refuses it.

Exit codes: 0 the part passes; 1 it fails, cannot be judged
(``not_measurable``) or could not be measured (status ``error``); 2 bad input
(unreadable or malformed frames, frames that do not fit the rig, a bad part
spec or rig file): a message on stderr; 3 an internal error.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from inspection.errors import InspectionError, InvalidInput

from .align import quality_line
from .exits import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK

if TYPE_CHECKING:
    from inspection.rig import Rig
    from service.models import InspectionResult
    from service.parts import LoadedPart
    from service.protocol import FrameSet
    from service.results import Trigger

log = logging.getLogger(__name__)

CLI_NAME = "cli"
"""Line, station and serial of images measured outside a FrameSet."""


def register(subparsers: argparse._SubParsersAction) -> None:
    m = subparsers.add_parser(
        "measure",
        help="measure one trigger's frames (a FrameSet file or one image per camera)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    m.add_argument(
        "frames",
        metavar="FRAMES",
        type=Path,
        nargs="+",
        help="one FrameSet file, or one 8-bit grey image (PNG) per camera in the rig's order",
    )
    m.add_argument(
        "--part", metavar="PART.toml", type=Path, required=True, help="the part spec (TOML)"
    )
    m.add_argument(
        "--rig",
        metavar="RIG.toml",
        type=Path,
        default=None,
        help="the calibrated rig (default: Rig.default(), the line's)",
    )
    m.add_argument(
        "--trees",
        metavar="DIR",
        type=Path,
        default=None,
        help="cache of trees and alignment models (default: ~/.cache/inspection/trees)",
    )
    m.add_argument(
        "--no-guided",
        action="store_true",
        help="skip the CAD-guided second matching pass",
    )
    m.add_argument("--json", action="store_true", help="print the InspectionResult JSON")
    m.add_argument("--quiet", action="store_true", help="no progress bar of a tree build")
    m.set_defaults(func=cmd_measure)


# --------------------------------------------------------------------------- inputs


@dataclass(frozen=True, eq=False)
class Frames:
    """What FRAMES holds: one image per camera, and the FrameSet they came in (if any)."""

    images: list[np.ndarray]
    frameset: FrameSet | None = None


def read_frames(paths: Sequence[Path]) -> Frames:
    """One FrameSet file, or one grey image file per camera.

    Raises
    ------
    InvalidInput
        An unreadable file, bytes that are not a FrameSet, an image that is
        not 8-bit grey.
    """
    from service.protocol import ProtocolError, decode_frameset

    if len(paths) == 1:
        path = paths[0]
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise InvalidInput(f"{path}: cannot read: {exc.strerror or exc}") from exc
        try:
            fs = decode_frameset(data)
        except ProtocolError as exc:
            raise InvalidInput(f"{path}: {exc}") from exc
        return Frames(list(fs.images), fs)
    return Frames([read_image(p) for p in paths])


def read_image(path: Path) -> np.ndarray:
    """An (H, W) uint8 image from a file (PNG), unchanged.

    Raises
    ------
    InvalidInput
        Missing, unreadable, or not 8-bit single-channel.
    """
    import cv2

    if not path.is_file():
        raise InvalidInput(f"{path}: no such file")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InvalidInput(f"{path}: not an image OpenCV can read")
    if img.dtype != np.uint8 or img.ndim != 2:
        raise InvalidInput(
            f"{path}: a frame is an 8-bit grey image (mono8), got {img.dtype} of shape {img.shape}"
        )
    return np.asarray(img)


def check_frames(frames: Frames, rig: Rig) -> None:
    """One image per camera of ``rig``, each of the camera's size.

    Raises
    ------
    InvalidInput
    """

    n, cams = len(frames.images), len(rig.cameras)
    names = ", ".join(rig.names)
    if n != cams and frames.frameset is not None:
        raise InvalidInput(f"the FrameSet carries {n} images; the rig has {cams} cameras ({names})")
    if n != cams:
        raise InvalidInput(
            f"{n} image files given; the rig has {cams} cameras ({names}): "
            "give one FrameSet file, or one image per camera"
        )
    for i, (img, cam) in enumerate(zip(frames.images, rig.cameras, strict=True)):
        if img.shape != cam.shape:
            raise InvalidInput(
                f"image {i} is {img.shape[1]} x {img.shape[0]} px; "
                f"camera {cam.name} takes {cam.width} x {cam.height} px"
            )


def check_frameset(fs: FrameSet, part: str, rig: Rig) -> None:
    """A FrameSet of ``part``, taken for ``rig``'s calibration (or for none named).

    Raises
    ------
    InvalidInput
    """

    if fs.part != part:
        raise InvalidInput(f"the FrameSet is of part {fs.part!r}; --part gives {part!r}")
    if fs.calibration_id and fs.calibration_id != rig.id:
        raise InvalidInput(
            f"the FrameSet was taken for calibration {fs.calibration_id!r}; the rig is "
            f"{rig.id!r}: pass the matching calibration with --rig"
        )


def default_trees_dir() -> Path:
    """``$XDG_CACHE_HOME/inspection/trees`` (``~/.cache/...`` without it), made if missing;
    a folder in the temporary directory when that cannot be made (a read-only home)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    path = Path(base) / "inspection" / "trees"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        fallback = Path(tempfile.gettempdir()) / "inspection-trees"
        log.warning("cannot use %s for the tree cache (%s); using %s", path, exc, fallback)
        fallback.mkdir(parents=True, exist_ok=True)
        return fallback
    return path


def trigger_of(frames: Frames, part: LoadedPart, rig: Rig) -> Trigger:
    """The identity of the result: the FrameSet's, or that of images measured by hand."""
    from service.models import make_result_id
    from service.results import upload_trigger

    fs = frames.frameset
    if fs is None:
        now = time.time_ns()
        trigger = upload_trigger(
            part,
            id=make_result_id(CLI_NAME, CLI_NAME, 0, now),
            line=CLI_NAME,
            station=CLI_NAME,
            serial=CLI_NAME,
            triggered_ns=now,
        )
        return dataclasses.replace(trigger, calibration_id=rig.id)
    trigger = upload_trigger(
        part,
        id=make_result_id(fs.line, fs.station, fs.seq, fs.triggered_ns),
        line=fs.line,
        station=fs.station,
        serial=fs.serial,
        triggered_ns=fs.triggered_ns,
    )
    return dataclasses.replace(trigger, seq=fs.seq, calibration_id=fs.calibration_id or rig.id)


# --------------------------------------------------------------------------- output


def print_result(r: InspectionResult, part_ms: float) -> None:
    """A text summary of ``r``: status and reason, the fit, each comparison point, timings."""
    print(f"{r.part} {r.serial}: {r.status.value.upper()}")
    if r.reason:
        print(f"reason: {r.reason}")
    if r.transform is not None:
        print("T_cad_rig (maps rig points into the CAD frame, mm):")
        for row in r.transform:
            print("  " + " ".join(f"{v:12.6f}" for v in row))
    if r.rms_mm is not None and r.inlier_fraction is not None:
        print(
            f"rms {r.rms_mm:.4f} mm, inliers {100 * r.inlier_fraction:.1f} %, "
            f"{r.iterations} iterations, {r.stop_reason}"
        )
    if r.observability is not None:
        print(quality_line(r.observability, r.weak_directions, r.runner_up_score))
    if r.comparison:
        width = max([len(c.name) for c in r.comparison] + [4])
        print(f"{'name':<{width}}  {'deviation':>10}  {'tolerance':>19}  {'support':>7}  verdict")
        for c in r.comparison:
            dev = "-" if c.deviation_mm is None else f"{c.deviation_mm:+.4f}"
            tol = f"[{c.lower_mm:+.3f}, {c.upper_mm:+.3f}]"
            why = f"  ({c.reason})" if c.reason else ""
            print(
                f"{c.name:<{width}}  {dev:>10}  {tol:>19}  {c.support:>7}  {c.verdict.value}{why}"
            )
    stages = ", ".join(f"{k} {v:.0f} ms" for k, v in r.timings_ms.items())
    print(f"time: {stages} (part loaded in {part_ms:.0f} ms)")


def exit_code(r: InspectionResult) -> int:
    from service.models import Status

    return EXIT_OK if r.status is Status.passed else EXIT_FAILED


# --------------------------------------------------------------------------- the command


def cmd_measure(args: argparse.Namespace) -> int:
    from inspection.measure import measure_frames
    from inspection.reconstruct import Reconstructor
    from inspection.rig import Rig
    from service.config import load_part_spec
    from service.parts import load_part
    from service.results import outcome

    from .progress import FractionBar

    def bad(message: object) -> int:
        print(f"inspection measure: {message}", file=sys.stderr)
        return EXIT_BAD_INPUT

    # The quick checks first: a bad file is refused before the part is built.
    try:
        frames = read_frames(args.frames)
        spec = load_part_spec(args.part)
        rig = Rig.load(args.rig) if args.rig is not None else Rig.default()
        check_frames(frames, rig)
        if frames.frameset is not None:
            check_frameset(frames.frameset, spec.name, rig)
        trees = args.trees if args.trees is not None else default_trees_dir()
        t0 = time.perf_counter()
        with FractionBar(f"loading part {spec.name}", quiet=args.quiet) as progress:
            part = load_part(spec, args.part.parent, trees, progress)
        part_ms = (time.perf_counter() - t0) * 1e3
    except (InspectionError, ValueError, OSError) as exc:
        # ValueError: a part spec that does not validate (service.config.ConfigError).
        return bad(exc)
    params = dataclasses.replace(part.params, guided=not args.no_guided)
    try:
        measured = measure_frames(part.model, Reconstructor.build(rig), frames.images, params)
    except InvalidInput as exc:
        return bad(exc)
    except InspectionError as exc:
        print(f"inspection measure: the frames could not be measured: {exc}", file=sys.stderr)
        return EXIT_FAILED
    result = outcome(measured, trigger_of(frames, part, rig)).result
    if args.json:
        print(result.model_dump_json(indent=2))
    else:
        print_result(result, part_ms)
    return exit_code(result)
