"""``inspection replay FILE.mcap [--compare] [--publish]``: re-measure or re-publish a run.

Every file is checked to be an MCAP file (its magic) before any part is
loaded. Re-measuring shows a progress bar on a terminal (``--quiet``: none).

Exit codes: 0 replayed (and, with ``--compare``, every result the same); 1
a result differs (``--compare``); 2 bad input (no such recording, a file
that is not MCAP, a recording that cannot be replayed); 3 an internal error.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from .exits import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK

log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"


def not_mcap(path: Path) -> str | None:
    """Why ``path`` is not an MCAP file, or None."""
    try:
        with path.open("rb") as fh:
            head = fh.read(len(MCAP_MAGIC))
    except OSError as exc:
        return f"{path}: cannot read: {exc.strerror or exc}"
    if not head:
        return f"{path}: empty file, not an MCAP recording"
    if head != MCAP_MAGIC:
        return f"{path}: not an MCAP recording (no MCAP magic)"
    return None


def cmd_replay(args: argparse.Namespace) -> int:
    from service.recorder import recover
    from service.replay import ReplayError, Tolerances, recording_files, replay

    from .progress import bar

    files = [f for p in args.files for f in recording_files(p)]
    missing = [str(f) for f in files if not f.is_file()]
    if not files or missing:
        print(
            f"inspection replay: no such recording: {', '.join(missing) or ' '.join(args.files)}",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    for f in files:
        why = not_mcap(f)
        if why is not None:
            print(f"inspection replay: {why}", file=sys.stderr)
            return EXIT_BAD_INPUT
    if args.recover:
        for f in files:
            r = recover(f)
            print(f"recovered {r.messages} messages of {f} into {r.path}")
        return 0
    if args.publish:
        return _publish(args, files)
    with bar("replaying", None, quiet=args.quiet, unit="part") as progress:

        def advance(done: int, total: int) -> None:
            progress.total = total
            progress.update(done - progress.n)

        try:
            report = replay(
                files,
                parts_dir=args.parts_dir,
                trees_dir=args.trees_dir,
                tolerances=Tolerances(args.transform_tol, args.deviation_tol),
                progress=advance,
            )
        except ReplayError as exc:
            progress.close()
            print(f"inspection replay: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
    print(report.summary())
    if args.compare and not report.ok:
        return EXIT_FAILED
    return EXIT_OK


def _publish(args: argparse.Namespace, files: list[Any]) -> int:
    from service import bus
    from service.protocol import Keys
    from service.recorder import read_recording
    from service.replay import publish

    if not args.zenoh_connect and not args.zenoh_listen:
        print(
            "inspection replay --publish needs --zenoh-connect or --zenoh-listen", file=sys.stderr
        )
        return 2
    settings = bus.BusSettings(
        mode="client" if args.zenoh_connect else "peer",
        connect=tuple(args.zenoh_connect or ()),
        listen=tuple(args.zenoh_listen or ()),
    )
    _, triggers = read_recording(files)
    first = next((t.frameset for t in triggers if t.frameset is not None), None)
    if first is None:
        print("the recording holds no frames to publish", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    session = bus.open_session(settings)
    try:
        pub = bus.frame_publisher(session, Keys(first.line, args.prefix).frames(first.station))
        if args.wait_subscriber and not bus.wait_for_subscribers(pub, args.wait_subscriber):
            print("no subscriber appeared; publishing anyway", file=sys.stderr)
        n = publish(files, pub.put, speed=args.speed, stop=stop)
        # A put returns once the frames are queued, not delivered, and closing
        # the session drops what is still queued: give the transport time to drain.
        stop.wait(args.linger)
        pub.undeclare()
    finally:
        session.close()
    print(f"published {n} frame sets")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "replay",
        help="re-run a recorded run through the pipeline, compare, or publish it again",
        description="Re-measure every FrameSet of MCAP recordings (files or run directories) "
        "with the line's pipeline. --compare exits 1 on any difference beyond tolerance.",
    )
    p.add_argument("files", nargs="+", metavar="FILE.mcap")
    p.add_argument("--compare", action="store_true", help="exit 1 if a result differs")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--publish", action="store_true", help="publish the frames on zenoh instead")
    p.add_argument(
        "--recover", action="store_true", help="repair unfinished files (a killed recorder)"
    )
    p.add_argument("--speed", type=float, default=1.0, help="publish rate vs recorded (0: at once)")
    p.add_argument("--zenoh-connect", action="append", metavar="ENDPOINT")
    p.add_argument("--zenoh-listen", action="append", metavar="ENDPOINT")
    p.add_argument("--prefix", default="insp/v1", help="key prefix to publish under")
    p.add_argument(
        "--linger",
        type=float,
        default=2.0,
        metavar="S",
        help="keep the session open S seconds after the last frame set so it is delivered "
        "(default 2)",
    )
    p.add_argument(
        "--wait-subscriber",
        type=float,
        default=10.0,
        metavar="S",
        help="wait up to S seconds for a frames subscriber before publishing",
    )
    p.add_argument("--parts-dir", default="configs/parts", help="where non-generated CAD files are")
    p.add_argument(
        "--trees-dir", default="runs/trees", help="tree cache (the line's data dir + trees)"
    )
    p.add_argument("--transform-tol", type=float, default=1e-9)
    p.add_argument("--deviation-tol", type=float, default=1e-6, help="mm")
    p.set_defaults(func=cmd_replay)
