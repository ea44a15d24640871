"""The ``inspection`` command line: one console script, one module per subcommand.

Each module in :mod:`service.commands` defines ``register(subparsers)``, which
adds its parser and sets ``func`` (``args -> exit code``). Modules are
imported only when the CLI starts, so ``inspection --help`` stays quick.
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="inspection",
        description="In-line shape inspection: CAD trees, registration, the simulated line.",
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-vv: debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in dict.fromkeys(COMMANDS.values()):
        importlib.import_module(f"service.commands.{module}").register(sub)
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
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
