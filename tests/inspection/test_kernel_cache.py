"""The kernels' cache: one folder per version of the package's sources."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import inspection
from inspection import _kernel_cache

PACKAGE = Path(inspection.__file__).resolve().parent


def _copy(tmp_path: Path, *, checkout: bool) -> Path:
    """A copy of the package's sources, in a checkout (beside a pyproject.toml) or not."""
    root = tmp_path / ("checkout" if checkout else "site-packages")
    shutil.copytree(PACKAGE, root / "inspection", ignore=shutil.ignore_patterns("__pycache__"))
    if checkout:
        (root / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    return root / "inspection"


def test_a_change_to_any_source_file_moves_the_cache(tmp_path: Path) -> None:
    package = _copy(tmp_path, checkout=True)
    first = _kernel_cache.default_dir(package)
    assert first.parent == package.parent / ".cache" / "numba"
    # A helper that kernels of other files compile in: numba alone would not notice.
    helper = package / "_linalg.py"
    original = helper.read_bytes()
    helper.write_bytes(original + b"\n# changed\n")
    changed = _kernel_cache.default_dir(package)
    assert changed != first and changed.parent == first.parent
    # A new file counts too, and the same sources give the same folder again.
    helper.write_bytes(original)
    assert _kernel_cache.default_dir(package) == first
    (package / "extra.py").write_text("X = 1\n")
    assert _kernel_cache.default_dir(package) != first


def test_an_installed_package_keeps_its_kernels_in_the_users_cache(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    package = _copy(tmp_path, checkout=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    folder = _kernel_cache.default_dir(package)
    assert folder.parent == tmp_path / "xdg" / "inspection" / "numba"
    assert folder.name == _kernel_cache.sources_hash(package)


def _cache_seen_by_numba(package: Path, env: dict[str, str]) -> list[str]:
    code = (
        "import os, sys; sys.path.insert(0, sys.argv[1]); import inspection, numba; "
        "print(inspection.__file__); print(os.environ['NUMBA_CACHE_DIR']); "
        "print(numba.config.CACHE_DIR)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(package.parent)],
        env=env, capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    return out.stdout.split("\n")[:3]


def test_importing_the_package_points_numba_at_its_cache(tmp_path: Path) -> None:
    package = _copy(tmp_path, checkout=True)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    where, told, used = _cache_seen_by_numba(package, env)
    assert Path(where).resolve().parent == package.resolve()
    expected = str(_kernel_cache.default_dir(package.resolve()))
    assert told == used == expected
    # A folder the user names is kept.
    mine = str(tmp_path / "mine")
    assert _cache_seen_by_numba(package, {**env, "NUMBA_CACHE_DIR": mine})[1:] == [mine, mine]
