"""The one rule for line, station, part and serial names: safe in zenoh keys, URLs and paths.

A name is 1 to 64 characters from ``[A-Za-z0-9._-]`` and is not made of dots
alone. The character set keeps a name from adding a level to a key
expression or acting as a wildcard; refusing ``.``, ``..``, ``...`` keeps it
from naming the current or parent folder when it becomes a file name.
Everything that accepts a name (the config models, the API's bodies, paths
and queries, the wire protocol) checks it against this module.
"""

from __future__ import annotations

import re

NAME_MAX_LEN = 64
"""The longest name, in characters."""

_BODY = r"[A-Za-z0-9._-]*[A-Za-z0-9_-][A-Za-z0-9._-]*"

NAME_PATTERN = rf"^{_BODY}$"
"""The rule as a regular expression (no length bound): at least one character not a dot.

Written without look-arounds so that pydantic's regex engine, JSON Schema and
OpenAPI clients all read it the same way.
"""

KEY_PREFIX_PATTERN = rf"^{_BODY}(/{_BODY})*$"
"""A zenoh key prefix: one or more names joined by ``/``."""

NAME_RULE = "1 to 64 characters from `[A-Za-z0-9._-]`, not made of dots alone"
"""The rule in words, as docs/protocol.md and error messages state it."""

ID_SEPARATOR = "~"
"""Joins the names and numbers of a result id: no name may contain it, so an id
splits back into its fields one way only (``a.b`` ``c`` and ``a`` ``b.c`` differ)."""

ID_PATTERN = r"^[A-Za-z0-9._~-]*[A-Za-z0-9_~-][A-Za-z0-9._~-]*$"
"""A result id: the name characters and :data:`ID_SEPARATOR`, not made of dots alone."""

_NAME_RE = re.compile(NAME_PATTERN)


def is_valid_name(value: object) -> bool:
    """Whether ``value`` may be used as a line, station, part or serial name."""
    return (
        isinstance(value, str)
        and 0 < len(value) <= NAME_MAX_LEN
        and _NAME_RE.fullmatch(value) is not None
    )
