"""Test parts for the holographic head, and deviations with known truth.

The key case is a plate with a step deeper than one phase interval (half
the synthetic wavelength), a sloped facet ending in a smaller step, and
dents that the CAD does not have.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import trimesh

from ..errors import InvalidInput
from .head import HoloHead


def stepped_plate(
    size_mm: float = 24.0, step_mm: float = 0.8, ramp_mm: float = 0.4
) -> trimesh.Trimesh:
    """A square plate, top face at z = 0 (part frame), with a raised pad
    ``step_mm`` high over x > 1 mm and, over x in [-8, -2], y < 0, a facet rising
    to ``ramp_mm`` and ending in a step down."""
    if not (size_mm > 16 and step_mm > 0 and ramp_mm >= 0):
        raise InvalidInput("size_mm must be > 16, step_mm > 0, ramp_mm >= 0")
    half = size_mm / 2.0
    base = trimesh.creation.box((size_mm, size_mm, 3.0))
    base.apply_translation((0.0, 0.0, -1.5))
    pad_w = half - 1.0
    pad = trimesh.creation.box((pad_w, size_mm, 3.0 + step_mm))
    pad.apply_translation((1.0 + pad_w / 2.0, 0.0, -1.5 + step_mm / 2.0))
    parts = [base, pad]
    if ramp_mm > 0:
        x0, x1, y0, y1 = -8.0, -2.0, -half, 0.0
        corners = [
            (x0, y0, -1.0),
            (x0, y1, -1.0),
            (x1, y0, -1.0),
            (x1, y1, -1.0),
            (x0, y0, 0.0),
            (x0, y1, 0.0),
            (x1, y0, ramp_mm),
            (x1, y1, ramp_mm),
        ]
        parts.append(trimesh.convex.convex_hull(np.array(corners)))
    mesh = trimesh.util.concatenate(parts)
    assert isinstance(mesh, trimesh.Trimesh)
    return mesh


@dataclass(frozen=True)
class Dent:
    """A smooth dent (Gaussian profile) at ``(x_mm, y_mm)`` of the head frame:
    ``depth_mm`` into the material along the normal at its centre, 1/e radius
    ``radius_mm``."""

    x_mm: float
    y_mm: float
    depth_mm: float
    radius_mm: float

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.x_mm, self.y_mm, self.depth_mm)):
            raise InvalidInput("a dent's position and depth must be finite")
        if not self.radius_mm > 0:
            raise InvalidInput(f"radius_mm must be > 0, got {self.radius_mm}")


def dent_map(head: HoloHead, dents: Sequence[Dent]) -> npt.NDArray[np.float64]:
    """The deviation (n, n) float64, mm, along the outward normal (negative: into
    the material) that ``dents`` make at each pixel."""
    x, y = head.grid()
    out = np.zeros_like(x)
    for d in dents:
        out -= d.depth_mm * np.exp(-((x - d.x_mm) ** 2 + (y - d.y_mm) ** 2) / d.radius_mm**2)
    return out
