"""What a render takes and returns besides images: options, the truth record, fixed scales.

They live apart from the renderer so that callers who only configure a render
(the service's config, the line) read one small module, and so that the
scene, exposure and simulator modules share one set of constants.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..errors import InvalidInput

_TEXEL_MM = 0.5  # belt texture resolution
_BELT_PERIOD_MM = 1024.0  # the belt texture repeats every metre or so
_BOARD_PX_PER_MM = 8.0
_FLOOR_ALBEDO = 0.04  # the machine floor beyond the belt's edges


@dataclass(frozen=True)
class RenderOptions:
    """Photometric and fault parameters of the simulator.

    Attributes
    ----------
    exposure_dn : float
        Grey value (DN) of a white Lambertian surface facing the flash at the
        reference distance (1300 mm) under the bright speckle.
    ambient : float
        Stray light relative to the flash (what lights the projector's shadows).
    part_albedo : float
        Diffuse reflectance of the part (bare steel ~0.45).
    specular_sharp, shininess_sharp : float
        Mirror lobe of the part: strength relative to the flash, Blinn-Phong
        exponent. The default saturates in blobs of a few centimetres.
    specular_broad, shininess_broad : float
        Broad sheen lobe.
    blur_px : float
        Optical blur (Gaussian sigma, pixels).
    pixel_samples : int
        The sensor integrates light over each pixel's area: the projected
        pattern is averaged over the pixel's footprint on the part with
        ``pixel_samples`` x ``pixel_samples`` samples (1: the pixel's centre
        only, which aliases the speckle; see :mod:`inspection.simulate`). The empty
        belt, precomputed per rig, always uses the default.
    edge_samples : int
        A pixel that straddles the part's outline (a hole's rim, the part's
        edge against the belt, an occluding flange) collects light from both
        sides: ``edge_samples`` x ``edge_samples`` rays through its area, each
        finding its own surface, are averaged (1: its centre decides, and
        outlines fall on whole pixels).
    shot_noise : float
        Variance of the shot noise per DN of signal.
    read_noise_dn : float
        Standard deviation of the read noise, DN.
    part_dirt_spots : int
        Dirt spots on the part's surface (radius 1.5-5 mm).
    lens_dirt_spots : int
        Dust blobs per lens.
    belt_shift_mm : float
        How far the belt has moved (its texture moves with it).
    flash_us : float
        Duration of the flash (the exposure), µs. The belt moves
        ``rig.conveyor.speed_mm_s * flash_us`` during it and the frame is the
        average over that travel, centred on the pose rendered; a travel
        that moves no point of the scene by
        :data:`~inspection.simulate.exposure.MIN_SMEAR_PX` in any image is not
        rendered (the default: 0.05 mm at 1 m/s, 0.075 px).
    board_white_dn : float
        Grey value of the white board paper in calibration images.
    """

    exposure_dn: float = 430.0
    ambient: float = 0.03
    part_albedo: float = 0.45
    specular_sharp: float = 8.0
    shininess_sharp: float = 5000.0
    specular_broad: float = 0.12
    shininess_broad: float = 40.0
    blur_px: float = 0.6
    pixel_samples: int = 3
    edge_samples: int = 4
    shot_noise: float = 0.3
    read_noise_dn: float = 1.2
    part_dirt_spots: int = 6
    lens_dirt_spots: int = 1
    belt_shift_mm: float = 0.0
    flash_us: float = 50.0
    board_white_dn: float = 200.0

    def __post_init__(self) -> None:
        for name in (
            "exposure_dn",
            "ambient",
            "part_albedo",
            "specular_sharp",
            "shininess_sharp",
            "specular_broad",
            "shininess_broad",
            "blur_px",
            "shot_noise",
            "read_noise_dn",
            "board_white_dn",
            "flash_us",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise InvalidInput(f"RenderOptions.{name} must be finite and >= 0, got {value!r}")
        if not 0 < self.part_albedo <= 1:
            raise InvalidInput("RenderOptions.part_albedo must be in (0, 1]")
        for name in ("pixel_samples", "edge_samples"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise InvalidInput(f"RenderOptions.{name} must be an int")
            if not 1 <= value <= 8:
                raise InvalidInput(f"RenderOptions.{name} must be in 1..8, got {value}")
        if self.part_dirt_spots < 0 or self.lens_dirt_spots < 0:
            raise InvalidInput("dirt spot counts must be >= 0")
        if not np.isfinite(self.belt_shift_mm):
            raise InvalidInput("belt_shift_mm must be finite")

    @classmethod
    def clean(cls) -> RenderOptions:
        """No faults: no mirror lobe, no dirt, no noise (for tests of geometry)."""
        return cls(
            specular_sharp=0.0,
            specular_broad=0.0,
            shot_noise=0.0,
            read_noise_dn=0.0,
            part_dirt_spots=0,
            lens_dirt_spots=0,
        )


@dataclass(frozen=True, eq=False)
class CameraTruth:
    """What one camera really saw (ground truth for tests and benchmarks).

    Attributes
    ----------
    points : (H, W, 3) float32, mm, rig frame
        The surface point on each pixel's ray (the part, or the belt at z = 0).
    part : (H, W) bool
        The pixel sees the part.
    lit : (H, W) bool
        The point receives the projected pattern (not in the projector's shadow).
    saturated : (H, W) bool
        The pixel is at 255.
    """

    points: npt.NDArray[np.float32]
    part: npt.NDArray[np.bool_]
    lit: npt.NDArray[np.bool_]
    saturated: npt.NDArray[np.bool_]
