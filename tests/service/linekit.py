"""Shared set-up for the line's tests: the demo part on the depth rig, ports, zenoh settings."""

from __future__ import annotations

import functools
import socket
from pathlib import Path

from inspection.panel import sheet_metal_panel
from service.bus import BusSettings
from service.config import load_part_spec
from service.ingest import SimPart, SimulatedRig, SimulationSettings
from service.pipeline import Pipeline, PreparedPart, Stages, depth_stages, prepare_part

ROOT = Path(__file__).resolve().parents[2]
LINE, STATION, PART = "line1", "st1", "demo-panel"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def peer(port: int) -> BusSettings:
    return BusSettings(mode="peer", listen=(endpoint(port),))


def client(port: int) -> BusSettings:
    return BusSettings(mode="client", connect=(endpoint(port),))


@functools.cache
def demo() -> tuple[Stages, PreparedPart]:
    """The depth rig and the demo panel with its tree (built once per test process)."""
    stages = depth_stages()
    spec = load_part_spec(ROOT / "configs" / "parts" / f"{PART}.toml")
    return stages, prepare_part(spec, sheet_metal_panel(name=PART), stages)


def pipeline() -> Pipeline:
    stages, part = demo()
    return Pipeline(stages, {PART: part}, line=LINE, station=STATION)


def rig(defect_rate: float = 0.3, seed: int = 1) -> SimulatedRig:
    stages, part = demo()
    return SimulatedRig(
        stages,
        [SimPart.from_cad(PART, part.cad)],
        line=LINE,
        station=STATION,
        settings=SimulationSettings(defect_rate=defect_rate, seed=seed),
    )
