"""Fixtures shared by every test package.

The real CAD meshes live outside the repository (../shared/data/cad beside the
clone, or wherever INSPECTION_SHARED_CAD points). A user's clone has none, so
tests that need them skip with a reason instead of failing.
"""

from __future__ import annotations

import os

# As in the service's entry point: set before numpy and numba load.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_THREADING_LAYER", "threadsafe")

from pathlib import Path  # noqa: E402

import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_cad_dir() -> Path:
    env = os.environ.get("INSPECTION_SHARED_CAD")
    return Path(env) if env else REPO.parent / "shared" / "data" / "cad"


@pytest.fixture(scope="session")
def shared_cad():
    """Return a function giving the path of a shared CAD file, skipping when absent."""

    def get(name: str) -> Path:
        path = shared_cad_dir() / name
        if not path.is_file():
            pytest.skip(f"shared CAD mesh {name} not available at {path.parent}")
        return path

    return get
