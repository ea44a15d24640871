"""The flash: a pinhole projector and the random speckle slide it projects."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from ..errors import InvalidInput
from .checks import as_matrix, check_points, rotation_ok


@dataclass(frozen=True)
class Pattern:
    """The projected pattern: a random binary speckle, blurred by the optics.

    Attributes
    ----------
    kind : str
        ``"speckle"`` (the only kind: see :mod:`inspection.rig` for why).
    seed : int
        Seed of the random pattern (the pattern is a property of the projector
        slide, fixed for a rig).
    grain_px : float
        Correlation length of the speckle in projector pixels (the standard
        deviation of the Gaussian that smooths the white noise before it is
        thresholded into black and white).
    blur_px : float
        Optical blur of the projector (Gaussian sigma, projector pixels).
    low, high : float
        Relative intensity of dark and bright speckle (a projector never
        reaches black).
    """

    kind: str = "speckle"
    seed: int = 7
    grain_px: float = 1.6
    blur_px: float = 0.7
    low: float = 0.2
    high: float = 1.0

    def __post_init__(self) -> None:
        if self.kind != "speckle":
            raise InvalidInput(f"pattern kind must be 'speckle', got {self.kind!r}")
        if not (self.grain_px > 0 and self.blur_px >= 0 and 0.0 <= self.low < self.high <= 1.0):
            raise InvalidInput("pattern needs grain_px > 0, blur_px >= 0 and 0 <= low < high <= 1")

    def image(self, width: int, height: int) -> npt.NDArray[np.float32]:
        """Render the slide.

        Returns
        -------
        (height, width) float32
            Relative intensity in [low, high].
        """
        import cv2

        rng = np.random.default_rng(self.seed)
        noise = rng.standard_normal((height, width), dtype=np.float32)
        smooth = cv2.GaussianBlur(noise, (0, 0), self.grain_px, borderType=cv2.BORDER_REFLECT)
        binary = (np.asarray(smooth) > 0).astype(np.float32)
        if self.blur_px > 0:
            binary = np.asarray(
                cv2.GaussianBlur(binary, (0, 0), self.blur_px, borderType=cv2.BORDER_REFLECT),
                dtype=np.float32,
            )
        return (self.low + (self.high - self.low) * binary).astype(np.float32)


@dataclass(frozen=True, eq=False)
class Projector:
    """The flash: a pinhole projector (no distortion) with a speckle slide.

    Attributes
    ----------
    width, height : int
        Slide resolution in projector pixels.
    K : (3, 3) float64
        Intrinsics of the projector lens, pixels.
    R : (3, 3) float64
        Rotation rig -> projector.
    t : (3,) float64, mm
        Translation rig -> projector.
    pattern : Pattern
    power : float
        Irradiance scale of the flash at 1300 mm (1.0 nominal).
    """

    width: int
    height: int
    K: npt.NDArray[np.float64]
    R: npt.NDArray[np.float64]
    t: npt.NDArray[np.float64]
    pattern: Pattern = field(default_factory=Pattern)
    power: float = 1.0

    def __post_init__(self) -> None:
        for attr in ("width", "height"):
            value = getattr(self, attr)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, np.integer))
                or not 16 <= value <= 20000
            ):
                raise InvalidInput(f"projector {attr} must be an int in [16, 20000], got {value!r}")
            object.__setattr__(self, attr, int(value))
        K = as_matrix(self.K, (3, 3), "projector K")
        R = as_matrix(self.R, (3, 3), "projector R")
        rotation_ok(R, "projector R")
        if not (self.power > 0 and math.isfinite(self.power)):
            raise InvalidInput("projector power must be positive")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", as_matrix(self.t, (3,), "projector t"))

    @property
    def centre(self) -> npt.NDArray[np.float64]:
        """(3,) float64, mm: the projector's optical centre in the rig frame."""
        return -self.R.T @ self.t

    def project(self, points_rig: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Rig-frame points (N, 3) mm -> slide pixel coordinates (N, 2)."""
        pc = check_points(points_rig) @ self.R.T + self.t
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = pc[:, :2] / pc[:, 2:3]
        return np.stack(
            [
                self.K[0, 0] * xy[:, 0] + self.K[0, 1] * xy[:, 1] + self.K[0, 2],
                self.K[1, 1] * xy[:, 1] + self.K[1, 2],
            ],
            axis=1,
        )
