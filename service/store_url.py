"""Where a result store lives: a ``postgresql://`` URL, else an SQLite file.

A URL is checked the way the driver (libpq) will read it, so a typo fails when
the configuration loads rather than when the first result is stored; and it
is shown without its password, because the effective configuration goes into
the logs and into every recording.
"""

from __future__ import annotations

from pathlib import Path
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

SCHEMES = ("postgresql://", "postgres://")
"""The URL schemes libpq takes."""


def is_postgres_url(target: str | Path) -> bool:
    """Whether ``target`` names a PostgreSQL database rather than an SQLite file."""
    return isinstance(target, str) and target.startswith(SCHEMES)


def check_postgres_url(url: str) -> str:
    """``url`` unchanged when libpq can read it as a PostgreSQL URL.

    Raises
    ------
    ValueError
        Another scheme, or a URL libpq cannot parse; the message never holds
        the password.
    """
    if not is_postgres_url(url):
        scheme = url.split("://", 1)[0] + "://" if "://" in url else repr(redact_url(url))
        raise ValueError(
            f"a postgresql://user@host:port/database URL is needed, not {scheme} "
            "(without a URL the results go to the SQLite file in data_dir)"
        )
    from psycopg import ProgrammingError
    from psycopg.conninfo import conninfo_to_dict

    try:
        conninfo_to_dict(url)
    except ProgrammingError as exc:
        # libpq may quote the part it could not read, which can be the password:
        # keep only its reason, and the name of an unknown query parameter.
        reason = str(exc).strip().split(" in URI", 1)[0]
        if not reason.startswith("invalid URI query parameter"):
            reason = reason.split(":", 1)[0].strip()
        raise ValueError(f"not a valid PostgreSQL URL ({reason}): {redact_url(url)}") from None
    return url


def redact_url(url: str) -> str:
    """``url`` with any password (in the user part or the query) replaced by ``***``."""
    try:
        parts = urlsplit(url)
    except ValueError:
        return "<a URL that cannot be read>"
    netloc = parts.netloc
    userinfo, at, hosts = netloc.rpartition("@")
    if at and ":" in userinfo:
        netloc = f"{userinfo.split(':', 1)[0]}:***@{hosts}"
    query = parts.query
    pairs = parse_qsl(query, keep_blank_values=True)
    if any(k == "password" for k, _ in pairs):
        query = urlencode([(k, "***" if k == "password" else v) for k, v in pairs], safe="*")
    return urlunsplit(parts._replace(netloc=netloc, query=query))
