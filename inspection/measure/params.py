"""The measuring sequence's settings: how a cloud is fitted, and how a part is judged."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ..errors import InvalidInput
from ..registration import LOSSES, validate_view

Frame = Literal["rig", "cad", "data"]
"""The frame a cloud is given in: ``rig`` (seen from above, anywhere on the
belt), ``data`` (any frame, anywhere), ``cad`` (already near the CAD frame:
only the fine registration runs)."""


@dataclass(frozen=True)
class RegisterParams:
    """How a cloud is fitted to the CAD (the arguments of :func:`~inspection.register`).

    Attributes
    ----------
    loss : str
        M-estimator of the residuals (see :func:`~inspection.register`).
    max_iterations : int
    max_distance_mm : float
        Points farther than this from the CAD are outliers.
    seed : int
        Seeds the random subsets.
    view_direction : (3,) tuple of float or None
        Direction towards the sensor in the rig frame (+z for a rig looking
        down): a point is not fitted onto a face turned away from it. Used for
        clouds in the rig frame only. Needs ``loss`` tukey or welsch.
    """

    loss: str = "tukey"
    max_iterations: int = 50
    max_distance_mm: float = 10.0
    seed: int = 0
    view_direction: tuple[float, float, float] | None = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise InvalidInput(f"loss must be one of {sorted(LOSSES)}, got {self.loss!r}")
        if not (isinstance(self.max_iterations, int) and self.max_iterations >= 1):
            raise InvalidInput(f"max_iterations must be an integer >= 1, got {self.max_iterations}")
        if not (math.isfinite(self.max_distance_mm) and self.max_distance_mm > 0):
            raise InvalidInput(f"max_distance_mm must be positive, got {self.max_distance_mm}")
        if self.view_direction is not None:
            view = validate_view(np.asarray(self.view_direction, dtype=np.float64), self.loss)
            assert view is not None
            object.__setattr__(self, "view_direction", tuple(float(c) for c in view))

    def kwargs(self, frame: Frame) -> dict[str, object]:
        """Keyword arguments of ``align`` / ``register`` for a cloud in ``frame``."""
        out: dict[str, object] = {
            "loss": self.loss,
            "max_iterations": self.max_iterations,
            "max_distance_mm": self.max_distance_mm,
        }
        if self.seed:
            out["seed"] = self.seed
        if frame == "rig" and self.view_direction is not None:
            out["view_direction"] = self.view_direction
        return out


@dataclass(frozen=True)
class MeasureParams:
    """The measuring sequence's settings; the defaults are the line's.

    Attributes
    ----------
    path : {"cloud"}
        What is measured: the whole reconstructed cloud. (The comparison
        points' own path is refused until it exists.)
    guided : bool
        Match the frames a second time with the CAD at the first fit's pose.
    use_weights : bool
        Fit with the reconstruction's per-point quality as input weights.
    max_points : int
        Clouds are subsampled (evenly strided) to this size to fit.
    min_inlier_fraction : float
        A fit keeping fewer of the points is an error.
    max_rms_mm : float
        A fit with a larger residual is an error.
    ambiguous_is_error : bool
        A pose the global search calls ambiguous is an error (else measured,
        and the reason says so).
    min_support : int
        Points needed at a comparison point (unless it sets its own).
    uncertainty_fraction : float
        A comparison point whose deviation the pose leaves uncertain by more
        than this fraction of its tolerance band (3 sigma along its normal)
        is not measurable.
    register : RegisterParams
    """

    path: Literal["cloud", "comparison_points"] = "cloud"
    guided: bool = True
    use_weights: bool = True
    max_points: int = 150_000
    min_inlier_fraction: float = 0.5
    max_rms_mm: float = 1.0
    ambiguous_is_error: bool = False
    min_support: int = 10
    uncertainty_fraction: float = 0.1
    register: RegisterParams = field(default_factory=RegisterParams)

    def __post_init__(self) -> None:
        if self.path == "comparison_points":
            raise InvalidInput(
                "path 'comparison_points' (photogrammetry at the comparison points) is not "
                "available yet; measure with path 'cloud'"
            )
        if self.path != "cloud":
            raise InvalidInput(f"path must be 'cloud' or 'comparison_points', got {self.path!r}")
        if not (isinstance(self.max_points, int) and self.max_points >= 100):
            raise InvalidInput(f"max_points must be an integer >= 100, got {self.max_points}")
        if not 0.0 <= self.min_inlier_fraction <= 1.0:
            raise InvalidInput(
                f"min_inlier_fraction must lie in [0, 1], got {self.min_inlier_fraction}"
            )
        if not self.max_rms_mm > 0:
            raise InvalidInput(f"max_rms_mm must be positive, got {self.max_rms_mm}")
        if not (isinstance(self.min_support, int) and self.min_support >= 1):
            raise InvalidInput(f"min_support must be an integer >= 1, got {self.min_support}")
        if not self.uncertainty_fraction > 0:
            raise InvalidInput(
                f"uncertainty_fraction must be positive, got {self.uncertainty_fraction}"
            )
        if not isinstance(self.register, RegisterParams):
            raise InvalidInput(
                f"register must be RegisterParams, got {type(self.register).__name__}"
            )
