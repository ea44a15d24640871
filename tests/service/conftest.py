"""Fixtures of the line's tests: one tree cache, one PostgreSQL server and one set of
upload-measuring processes for the session."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from pgserver import PgServer, ServerUnavailable

from service.api.measurer import UploadMeasurer


@pytest.fixture(scope="session")
def trees(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tree cache every test of the session shares: the demo panel's tree is built
    once, then loaded (by this process and by the line processes the tests start)."""
    return tmp_path_factory.mktemp("trees")


@pytest.fixture(scope="session")
def pg_server() -> Iterator[PgServer]:
    """A PostgreSQL server on loopback for the whole session; its tests skip where
    the server's binaries are not installed."""
    try:
        server = PgServer.start()
    except ServerUnavailable as exc:
        pytest.skip(str(exc))
    yield server
    server.stop()


@pytest.fixture(scope="session")
def upload_measurer() -> Iterator[UploadMeasurer]:
    """The process that measures the API's uploads, shared by the apps of the session:
    started once (the first upload pays its start), as one app starts it for its life."""
    measurer = UploadMeasurer(1)
    yield measurer
    measurer.close()


@pytest.fixture(params=["sqlite", "postgresql"])
def store_target(request: pytest.FixtureRequest, tmp_path: Path) -> str | Path:
    """Where a new, empty result store goes: an SQLite file, or a database of its
    own on the session's PostgreSQL server. One test body, both backends."""
    if request.param == "sqlite":
        return tmp_path / "results.sqlite"
    server: PgServer = request.getfixturevalue("pg_server")
    return server.new_database()
