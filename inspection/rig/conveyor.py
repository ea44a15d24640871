"""The belt under the rig: its speed, its surface (z = 0 of the rig frame) and how it looks."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import InvalidInput


@dataclass(frozen=True)
class Conveyor:
    """The belt under the rig.

    Attributes
    ----------
    speed_mm_s : float
        Belt speed along +x, mm/s.
    surface_z_mm : float
        Height of the belt surface in the rig frame (0 by definition of the frame).
    width_mm : float
        Belt width across y (the belt ends at ``|y| = width_mm / 2``; beyond it
        the cameras see the dark machine floor).
    albedo : float
        Mean diffuse reflectance of the belt (dark rubber ~0.2).
    texture_contrast : float
        Relative amplitude of the belt's texture (fabric and wear).
    texture_seed : int
        Seed of the belt texture.
    """

    speed_mm_s: float = 1000.0
    surface_z_mm: float = 0.0
    width_mm: float = 900.0
    albedo: float = 0.22
    texture_contrast: float = 0.35
    texture_seed: int = 11

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speed_mm_s) and self.speed_mm_s >= 0):
            raise InvalidInput("conveyor speed_mm_s must be finite and >= 0")
        if self.surface_z_mm != 0.0:
            raise InvalidInput(
                "conveyor surface_z_mm must be 0: the belt surface defines z = 0 of the rig frame"
            )
        if not (self.width_mm > 0 and 0 < self.albedo <= 1 and 0 <= self.texture_contrast < 1):
            raise InvalidInput(
                "conveyor needs width_mm > 0, 0 < albedo <= 1, 0 <= texture_contrast < 1"
            )
