"""Where numba keeps the package's compiled kernels: one folder per version of its sources.

numba checks a cached kernel against the time stamp of its own file only. A
kernel that calls (and so compiles in) a function of another file would
outlive a change there and go on running the old code, with no error. The
cache is therefore kept in a folder named by a hash of every source file of
the package, so that any change compiles the kernels afresh: in a checkout
beside it (``.cache/numba/<hash>``), for an installed package in the user's
cache (``$XDG_CACHE_HOME/inspection/numba/<hash>``, by default under
``~/.cache``). An explicit ``NUMBA_CACHE_DIR`` is kept as it is: it is the
user's choice (a container image fills its own once).

Importing this module configures the cache; the package imports it first.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent


def sources_hash(package: Path = PACKAGE) -> str:
    """A hash of the names and contents of every ``.py`` file under ``package``."""
    h = hashlib.sha1()
    for path in sorted(package.rglob("*.py"), key=lambda p: p.relative_to(package).as_posix()):
        h.update(path.relative_to(package).as_posix().encode())
        h.update(b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:12]


def default_dir(package: Path = PACKAGE) -> Path:
    """The kernel cache of this version of ``package``'s sources (see the module notes)."""
    root = package.parent
    if (root / "pyproject.toml").is_file():
        base = root / ".cache" / "numba"
    else:
        home = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        base = Path(home) / "inspection" / "numba"
    return base / sources_hash(package)


def configure() -> str:
    """Point numba's cache at :func:`default_dir` unless ``NUMBA_CACHE_DIR`` is set; the
    folder in use. Set in the environment too, so that worker processes started from this
    one share it."""
    folder = os.environ.get("NUMBA_CACHE_DIR") or str(default_dir())
    os.environ["NUMBA_CACHE_DIR"] = folder
    if "numba" in sys.modules:  # numba read its environment when it was imported
        from numba.core import config

        config.CACHE_DIR = folder  # type: ignore[attr-defined]  # set from the environment
    return folder


configure()
