"""Fixtures of the line's tests: one tree cache for the whole session."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def trees(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tree cache every test of the session shares: the demo panel's tree is built
    once, then loaded (by this process and by the line processes the tests start)."""
    return tmp_path_factory.mktemp("trees")
