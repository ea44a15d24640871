"""``inspection run | router | ingest | worker | api``: the simulated line, whole or in pieces."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any

from .exits import EXIT_BAD_INPUT

log = logging.getLogger(__name__)

DEFAULT_CONFIG = "configs/line.toml"


def _stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM: every run stops cleanly on it."""
    stop = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def _config(args: argparse.Namespace, *, mode: str | None = None) -> Any:
    from service.config import ConfigError, line_config_from_env

    overrides: dict[tuple[str, str], Any] = {
        ("storage", "data_dir"): getattr(args, "data_dir", None),
        ("http", "port"): getattr(args, "http_port", None),
    }
    dask = getattr(args, "dask", None)
    if dask is not None:
        overrides[("station", "executor")] = "dask"
        overrides[("station", "dask_scheduler")] = str(dask)
    listen = getattr(args, "zenoh_listen", None)
    connect = getattr(args, "zenoh_connect", None)
    if listen is not None:
        overrides[("zenoh", "listen")] = listen
    if mode is not None:
        overrides[("zenoh", "mode")] = mode
    if mode == "client":
        overrides[("zenoh", "listen")] = listen or []
        overrides[("zenoh", "connect")] = connect
    if mode == "router":
        overrides[("zenoh", "connect")] = []  # the router listens; the others connect to it
    from service.api.access import AccessError, load_keys

    try:
        cfg = line_config_from_env(args.config, overrides=overrides)
        load_keys(cfg.api_keys_path())  # an unreadable key file stops here, not in the API
    except (ConfigError, AccessError) as exc:
        print(f"inspection: {exc}", file=sys.stderr)
        return None
    # Said now, not after minutes of building trees that could not be saved there.
    for what, path in (("data_dir", cfg.storage.data_path()), ("trees", cfg.storage.trees_path())):
        if path.exists() and not path.is_dir():
            print(f"inspection: {what} {path} is a file, not a directory", file=sys.stderr)
            return None
    return cfg


def cmd_run(args: argparse.Namespace) -> int:
    cfg = _config(args)
    if cfg is None:
        return EXIT_BAD_INPUT
    _say("starting: loading the software (zenoh, the API, the measuring code)")
    from service.line import run_line

    stop = _stop_on_signals()
    return _on_bus(lambda: run_line(cfg, stop, parts_limit=args.parts, out=_say))


def _say(line: str) -> None:
    """A start-up or status line, on stdout at once (a pipe would hold it back)."""
    print(line, flush=True)


def _on_bus(run: Any) -> int:
    """Run a piece of the line; a zenoh session or a result store that cannot open, a
    Dask cluster that cannot be reached, or a simulated part that is not to be had, is
    said, not a traceback."""
    from service.bus import BusError
    from service.config import ConfigError
    from service.executor import ExecutorError
    from service.store import StoreError

    try:
        return int(run())
    except (BusError, ConfigError, ExecutorError, StoreError) as exc:
        print(f"inspection: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


def _dask_address(text: str) -> Any:
    from service.config import parse_dask_address

    try:
        return parse_dask_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def cmd_router(args: argparse.Namespace) -> int:
    from service.bus import BusSettings
    from service.line import bus_settings, run_router

    if args.config is None:
        if not args.zenoh_listen:
            print("inspection router: --zenoh-listen or --config is needed", file=sys.stderr)
            return EXIT_BAD_INPUT
        try:
            settings = BusSettings(mode="router", listen=tuple(args.zenoh_listen))
        except ValueError as exc:
            print(f"inspection router: --zenoh-listen: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
    else:
        cfg = _config(args, mode="router")
        if cfg is None:
            return EXIT_BAD_INPUT
        settings = bus_settings(cfg)
    stop = _stop_on_signals()
    return _on_bus(lambda: run_router(settings, stop, out=lambda text: print(text, flush=True)))


def cmd_piece(args: argparse.Namespace) -> int:
    cfg = _config(args, mode="client")
    if cfg is None:
        return EXIT_BAD_INPUT
    if args.command != "api":
        _say("starting: loading the software (zenoh, the measuring code)")
    from service import line

    stop = _stop_on_signals()
    if args.command == "ingest":
        return _on_bus(lambda: line.run_ingest(cfg, stop, count=args.count, talk=_say))
    if args.command == "worker":
        return _on_bus(lambda: line.run_worker(cfg, stop, talk=_say))
    return _on_bus(lambda: line.run_api(cfg, stop))


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config", default=DEFAULT_CONFIG, help=f"line config (default {DEFAULT_CONFIG})"
    )
    p.add_argument(
        "--data-dir", help="where results, recordings and trees go (default from config)"
    )


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "run",
        help="run the whole simulated line in one process",
        description="Ingest, worker, REST API, result store and MCAP recorder on one zenoh "
        "peer session that listens only on --zenoh-listen.",
    )
    _common(p)
    p.add_argument("--http-port", type=int, help="REST API port (default from config; 0: any)")
    p.add_argument(
        "--zenoh-listen",
        action="append",
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    p.add_argument("--parts", type=int, metavar="N", help="stop cleanly after N results")
    p.set_defaults(func=cmd_run)

    p = subparsers.add_parser(
        "router",
        help="a zenoh router for the line's separate processes",
        description="A zenoh router listening on --zenoh-listen. With --config it takes the "
        "line's TLS certificates and access control from the [zenoh] section (and listens "
        "where it says unless --zenoh-listen is given).",
    )
    p.add_argument(
        "--config", help="line config whose [zenoh] TLS and access control the router applies"
    )
    p.add_argument("--zenoh-listen", action="append", metavar="ENDPOINT")
    p.set_defaults(func=cmd_router)

    for name, text in (
        ("ingest", "the ingest adapter (simulated rig) alone, as a zenoh client"),
        ("worker", "a worker alone (measure, publish, store, record), as a zenoh client"),
        ("api", "the REST API alone, as a zenoh client"),
    ):
        p = subparsers.add_parser(name, help=text)
        _common(p)
        p.add_argument("--zenoh-connect", action="append", required=True, metavar="ENDPOINT")
        if name == "api":
            p.add_argument("--http-port", type=int, help="REST API port (default from config)")
        if name == "ingest":
            p.add_argument("--count", type=int, help="stop after this many triggers")
        if name == "worker":
            p.add_argument(
                "--dask",
                type=_dask_address,
                metavar="ADDRESS",
                help="measure on a Dask cluster: tcp://HOST:PORT (its scheduler) or local:N "
                "(N single-threaded worker processes started here); the worker still accounts "
                "for every trigger. Default: [station] executor in the config",
            )
        p.set_defaults(func=cmd_piece)
