"""``inspection store migrate``: copy an SQLite result store into a PostgreSQL database."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "store",
        help="the result store: copy an SQLite store into PostgreSQL",
        description="Work on result stores.",
    )
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    m = actions.add_parser(
        "migrate",
        help="copy an SQLite store into a PostgreSQL database",
        description="Copy everything an SQLite store holds (results, alarms, frozen control "
        "limits, and every revision of the parts created over the API) into the PostgreSQL "
        "database at --to, creating its schema there. A row already in the database is "
        "written again as the same row, so running it twice copies nothing twice; an alarm "
        "acknowledged there stays acknowledged, and a part deleted there stays deleted. A "
        "database holding other data under the same keys (a part revision of the same name "
        "and number with another spec or CAD, say from another station's store) is refused "
        "before anything is copied, naming each conflict. An older "
        "store file is first brought to the current schema, as when the line opens it. The "
        "per-point deviations stay in the data directory.",
    )
    m.add_argument(
        "--from",
        dest="source",
        required=True,
        metavar="PATH",
        help="the SQLite file, or a data directory holding results.sqlite",
    )
    m.add_argument(
        "--to",
        dest="target",
        required=True,
        metavar="URL",
        help="postgresql://user@host:port/database (a password: PGPASSWORD or ~/.pgpass)",
    )
    m.set_defaults(func=cmd_migrate)


def cmd_migrate(args: argparse.Namespace) -> int:
    from service.config import StorageSection
    from service.store import ResultStore, StoreError, copy_store
    from service.store_url import check_postgres_url

    def bad(message: str) -> int:
        print(f"inspection store migrate: {message}", file=sys.stderr)
        return 2

    try:
        url = check_postgres_url(args.target)
    except ValueError as exc:
        return bad(f"--to: {exc}")
    source = Path(args.source)
    if source.is_dir():
        source = source / StorageSection().database
    if not source.is_file():
        return bad(f"--from: no SQLite store at {source}")
    try:
        with ResultStore(source) as src, ResultStore(url) as dst:
            before = dst.count()
            copied = copy_store(src, dst)
            after = dst.count()
    except StoreError as exc:
        return bad(str(exc))
    print(
        f"copied {copied.results} results from {source} to {dst.where} "
        f"({after - before} new; the database holds {after}), {copied.alarms} alarms, "
        f"{copied.baselines} frozen baselines and {copied.parts} part revisions"
    )
    return 0
