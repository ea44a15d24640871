"""The ``inspection`` command line: one console script, one module per subcommand.

Each module in :mod:`service.commands` defines ``register(subparsers)``, which
adds its parser and sets ``func`` (``args -> exit code``). Modules are
imported only when the CLI starts, so ``inspection --help`` stays quick.

Every command exits with the codes of :mod:`service.commands.exits`. What a
command does not catch itself is sorted here: our errors about input (bad
files, configs, endpoints) exit 2 with their message, anything else is a
defect and exits 3; neither prints a traceback unless ``-vv`` asks for it.
"""

from __future__ import annotations

import os

# Before numpy or numba load: one BLAS thread (the hot paths are small products
# that spinning BLAS threads slow down), and a numba threading layer that stays
# safe when the worker and the API run kernels from different threads at once.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_THREADING_LAYER", "threadsafe")

import argparse  # noqa: E402
import importlib  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import traceback  # noqa: E402

from service.commands.exits import (  # noqa: E402
    EPILOG,
    EXIT_BAD_INPUT,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
)

# Subcommand -> module in service.commands, in the order --help lists them.
COMMANDS = {
    "build-tree": "tree",
    "info": "tree",
    "align": "align",
    "check": "align",
    "measure": "measure",
    "calibrate": "calibrate",
    "run": "line",
    "router": "line",
    "ingest": "line",
    "worker": "line",
    "api": "line",
    "replay": "replay",
    "store": "store",
}

# Errors that mean the input (a file, a config, an endpoint, a store or cluster
# address) cannot be used: exit 2. Named, not imported, so that sorting an
# error never imports zenoh or the store.
BAD_INPUT_ERRORS = frozenset(
    {
        "service.commands.exits.BadInput",
        "inspection.errors.InspectionError",
        "service.config.ConfigError",
        "service.protocol.ProtocolError",
        "service.api.access.AccessError",
        "service.parts.PartError",
        "service.bus.BusError",
        "service.store.StoreError",
        "service.executor.ExecutorError",
        "service.replay.ReplayError",
        "builtins.OSError",
    }
)


def is_bad_input(exc: BaseException) -> bool:
    """True for an error about the input rather than a defect of ours."""
    return any(f"{k.__module__}.{k.__qualname__}" in BAD_INPUT_ERRORS for k in type(exc).__mro__)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="inspection",
        description="In-line shape inspection: CAD trees, registration, the simulated line.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-vv: debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in dict.fromkeys(COMMANDS.values()):
        importlib.import_module(f"service.commands.{module}").register(sub)
    for command in sub.choices.values():
        command.epilog = EPILOG
        if command.formatter_class is argparse.HelpFormatter:
            command.formatter_class = argparse.RawDescriptionHelpFormatter
    return parser


def configure_logging(verbosity: int) -> None:
    level = logging.WARNING - 10 * min(verbosity, 2)
    logging.basicConfig(
        level=level,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    if os.environ.get("RUST_LOG"):
        # zenoh logs nothing unless asked; its log alone says why a TLS link was
        # refused (no certificate, unknown CA, wrong host name).
        import zenoh

        zenoh.init_log_from_env_or("warn")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # usage errors exit 2 here
    configure_logging(args.verbose)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print(f"inspection {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:
        code = EXIT_BAD_INPUT if is_bad_input(exc) else EXIT_INTERNAL
        if args.verbose >= 2:
            traceback.print_exc(file=sys.stderr)
        print(f"inspection {args.command}: {describe(exc, code)}", file=sys.stderr)
        return code


def describe(exc: BaseException, code: int) -> str:
    """One line on ``exc``: its message (an OSError's file and reason), and for a
    defect of ours its type and where to find the traceback."""
    if isinstance(exc, OSError) and exc.strerror:
        text = f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    else:
        text = " ".join(str(exc).split()) or type(exc).__name__
    if code == EXIT_INTERNAL:
        return f"internal error ({type(exc).__name__}: {text}); -vv shows the traceback"
    return text


if __name__ == "__main__":
    sys.exit(main())
