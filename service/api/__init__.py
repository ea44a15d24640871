"""The REST API (FastAPI): parts, inspections, trends, live stream, health, metrics."""

from __future__ import annotations

from .app import create_app
from .events import ResultHub

__all__ = ["ResultHub", "create_app"]
