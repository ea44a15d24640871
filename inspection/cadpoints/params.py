"""The settings of the comparison-point path: local photogrammetry at each point."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import InvalidInput


@dataclass(frozen=True)
class LocalParams:
    """How each comparison point is matched in the frames.

    Attributes
    ----------
    window : int
        Side of a matching window (odd, px of the rectified views).
    norm_window : int
        Box of the local normalisation (odd, px), as the cloud path's.
    stride : int
        A window at every ``stride``-th pixel of the support, in x and y.
    iterations : int
        Gauss-Newton iterations per window.
    min_score : float
        Smallest normalised cross-correlation of an accepted window.
    converged_px : float
        An accepted window's last step is at most this (px).
    max_shift_px : float
        ... and its disparity at most this far from the CAD's (px).
    min_windows : int
        A pair with fewer accepted windows at a point gives nothing there.
    max_view_deg : float
        A camera sees a point when its ray makes at most this angle with the
        point's normal.
    occlusion_mm : float
        A camera's ray to the point meeting the part this far from it: occluded.
    calibration_px : float
        The rig calibration's disparity error (1 sigma, px), for the uncertainty.
    max_sigma_fraction : float
        A point whose own uncertainty (3 sigma) exceeds this fraction of its
        tolerance band is not measurable.
    shading_bend : float
        A window spans a bend when a slope of the CAD's disparity field
        (px/px) varies by more than this over it; there it also fits light
        that changes with the surface's orientation, as the cloud path's
        guided windows do (``ReconstructParams.shading_bend``). inf: nowhere.
    """

    window: int = 9
    norm_window: int = 15
    stride: int = 2
    iterations: int = 5
    min_score: float = 0.9
    converged_px: float = 0.05
    max_shift_px: float = 1.5
    min_windows: int = 5
    max_view_deg: float = 65.0
    occlusion_mm: float = 1.0
    calibration_px: float = 0.02
    max_sigma_fraction: float = 0.25
    shading_bend: float = 0.01

    def __post_init__(self) -> None:
        for name in ("window", "norm_window"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 3 and v % 2 == 1):
                raise InvalidInput(f"LocalParams.{name} must be an odd int >= 3, got {v!r}")
        for name, top in (("stride", 8), ("iterations", 50), ("min_windows", 10_000)):
            v = getattr(self, name)
            if not (isinstance(v, int) and 1 <= v <= top):
                raise InvalidInput(f"LocalParams.{name} must be an int in [1, {top}], got {v!r}")
        if not 0.0 < self.min_score < 1.0:
            raise InvalidInput(f"LocalParams.min_score must lie in (0, 1), got {self.min_score}")
        if not 0.0 < self.max_view_deg < 90.0:
            raise InvalidInput(
                f"LocalParams.max_view_deg must lie in (0, 90), got {self.max_view_deg}"
            )
        for name in ("converged_px", "max_shift_px", "occlusion_mm", "max_sigma_fraction"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InvalidInput(f"LocalParams.{name} must be finite and > 0, got {v!r}")
        v = self.shading_bend
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and v > 0):
            raise InvalidInput(f"LocalParams.shading_bend must be > 0, got {self.shading_bend!r}")
        if not (math.isfinite(self.calibration_px) and self.calibration_px >= 0):
            raise InvalidInput(
                f"LocalParams.calibration_px must be finite and >= 0, got {self.calibration_px}"
            )


__all__ = ["LocalParams"]
