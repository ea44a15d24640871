"""Shared set-up for the line's tests: the demo part on the flash rig, ports, zenoh settings."""

from __future__ import annotations

import contextlib
import functools
import socket
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

from service.bus import BusSettings
from service.config import load_part_spec
from service.ingest import SimPart, SimulatedRig, SimulationSettings
from service.parts import LoadedPart, PartRegistry
from service.pipeline import Pipeline, Stages, flash_stages

ROOT = Path(__file__).resolve().parents[2]
LINE, STATION, PART = "line1", "st1", "demo-panel"
PARTS_DIR = ROOT / "configs" / "parts"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def uvicorn_server(app, before_stop: Callable[[], None] = lambda: None) -> Iterator[int]:
    """``app`` on a real uvicorn server on a free loopback port (yields the port).

    ``before_stop`` runs first when the block ends: close the app's event hub
    there, since uvicorn waits for open responses (event streams) before it stops.
    """
    import uvicorn

    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    sock.listen(64)  # connections queue here until uvicorn accepts: no waiting needed
    srv = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=srv.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        yield sock.getsockname()[1]
    finally:
        before_stop()
        srv.should_exit = True
        thread.join(30)
        sock.close()
    assert not thread.is_alive()


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def peer(port: int) -> BusSettings:
    return BusSettings(mode="peer", listen=(endpoint(port),))


def client(port: int) -> BusSettings:
    return BusSettings(mode="client", connect=(endpoint(port),))


@functools.cache
def demo(trees: Path) -> tuple[Stages, LoadedPart]:
    """The flash rig (the line's stages) and the demo panel loaded by a part registry, as the
    line loads it: tree from the cache in ``trees``, alignment model, warm-up.
    Done once per test process."""
    stages = flash_stages()
    registry = PartRegistry(trees, trees / "uploads")
    try:
        registry.add(load_part_spec(PARTS_DIR / f"{PART}.toml"), PARTS_DIR, configured=True)
        registry.preload()
        return stages, registry.get(PART)
    finally:
        registry.close()


def pipeline(trees: Path) -> Pipeline:
    stages, part = demo(trees)
    return Pipeline(stages, {PART: part}, line=LINE, station=STATION)


def rig(stages: Stages, part: LoadedPart, defect_rate: float = 0.3, seed: int = 1) -> SimulatedRig:
    return SimulatedRig(
        stages,
        [SimPart.from_cad(PART, part.cad)],
        line=LINE,
        station=STATION,
        settings=SimulationSettings(defect_rate=defect_rate, seed=seed),
    )
