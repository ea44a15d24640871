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


_SOLVES = """
import sys
import numpy as np
if sys.argv[1] == "window fits first":
    from inspection.reconstruct.kernels import refine_warped_shaded
    rng = np.random.default_rng(0)
    left = rng.normal(size=(40, 60)).astype(np.float32)
    right = rng.normal(size=(40, 70)).astype(np.float32)
    ones, zeros = np.ones((40, 60), np.float32), np.zeros((40, 60), np.float32)
    out = [np.empty(1, np.float32) for _ in range(3)]
    refine_warped_shaded(
        left, right, ones, np.ones_like(right), zeros, ones, zeros, zeros, 1e-3,
        np.array([30]), np.array([20]), np.array([2.0], np.float32), 4, 3, *out,
    )
from inspection.registration.kernels import lm_step, trace_inverse
rng = np.random.default_rng(1)
A = rng.normal(size=(6, 6))
H = A @ A.T + 6.0 * np.eye(6)
g = rng.normal(size=6)
steps = [lm_step(H, g, lam) for lam in (1e-4, 1e-2, 1.0)]
print(np.concatenate([np.r_[d, p] for d, p, _ in steps] + [[trace_inverse(H)]]).tobytes().hex())
"""


def _solves(order: str, cache: Path) -> str:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    out = subprocess.run(
        [sys.executable, "-c", _SOLVES, order],
        env=env, capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    return out.stdout.strip()


def test_the_fit_s_arithmetic_does_not_depend_on_which_kernels_compiled_first(
    tmp_path: Path,
) -> None:
    # The window fits (fastmath) share the registration's linear solver.
    alone = _solves("registration alone", tmp_path / "fresh")
    after = _solves("window fits first", tmp_path / "shared")
    # ... and a process that finds the solver in a cache another process filled.
    cached = _solves("registration alone", tmp_path / "shared")
    assert alone == after == cached
