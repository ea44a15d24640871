"""Fixtures of the line's tests: one tree cache, one PostgreSQL server and one set of
upload-measuring processes for the session, and a part quick to build per module."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from linekit import PART, PARTS_DIR
from pgserver import PgServer, ServerUnavailable

from inspection.measure import PartModel
from inspection.panel import sheet_metal_panel
from service.api.measurer import UploadMeasurer
from service.config import load_part_spec
from service.parts import LoadedPart, measure_params


@pytest.fixture(scope="session")
def trees(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tree cache every test of the session shares: the demo panel's tree is built
    once, then loaded (by this process and by the line processes the tests start)."""
    return tmp_path_factory.mktemp("trees")


@pytest.fixture(scope="module")
def quick_part() -> LoadedPart:
    """The demo panel on a coarse tree and without its alignment model: quick to build, for
    tests of the worker's plumbing rather than of the measurement."""
    spec = load_part_spec(PARTS_DIR / f"{PART}.toml")
    model = PartModel.build(sheet_metal_panel(name=PART), spacing_mm=5.0, alignment=False)
    return LoadedPart(spec, model, "quick-tree", measure_params(spec))


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
    """One measuring process for the API's uploads, shared by the apps of the session
    as one app keeps its own for its life: the first upload pays for its start."""
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
