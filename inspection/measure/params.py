"""The measuring sequence's settings: how a cloud is fitted, and how a part is judged."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from ..cadpoints import LocalParams
from ..errors import InvalidInput
from ..registration import RegisterParams
from ..surface import SurfaceParams

Frame = Literal["rig", "cad", "data"]
"""The frame a cloud is given in: ``rig`` (seen from above, anywhere on the
belt), ``data`` (any frame, anywhere), ``cad`` (already near the CAD frame:
only the fine registration runs)."""

MeasurePath = Literal["cloud", "comparison_points"]
"""What is measured: the whole reconstructed cloud, or the comparison points alone."""


LINE_REGISTER = RegisterParams(
    max_iterations=50, max_distance_mm=10.0, view_direction=(0.0, 0.0, 1.0)
)
"""The line's fit: fewer iterations and a tighter gate than :func:`~inspection.register`'s
defaults (the global search has placed the part), seen from above (+z of the rig)."""


@dataclass(frozen=True)
class MeasureParams:
    """The measuring sequence's settings; the defaults are the line's.

    Attributes
    ----------
    path : {"cloud", "comparison_points"}
        What is measured: the whole reconstructed cloud (``cloud``), or each
        comparison point by local photogrammetry around it alone, the part
        placed by a sparse first pass (``comparison_points``: no guided pass,
        no colour map, the surface between the points is not checked, so a
        ``surface`` whose defects fail parts needs the cloud path).
    guided : bool
        Match the frames a second time with the CAD at the first fit's pose.
    use_weights : bool
        Fit with the reconstruction's per-point quality as input weights.
    max_points : int
        Clouds are subsampled (evenly strided) to this size to fit.
    guide_points : int
        ... and to this size for the fits that only place the CAD guide of the
        next matching pass (the first pass's, the guided pass's before its
        bends are matched again): the guide needs the pose, not its last
        micrometre, which the final fit on ``max_points`` gives.
    pose_points : int
        ... and to this size on the comparison-point path, whose one fit
        places the part for the points' windows: their deviations are taken
        along the CAD's normals, which a pose slightly off barely moves.
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
        The fit (default :data:`LINE_REGISTER`); its view direction applies to
        clouds in the rig frame only (:meth:`fit_params`).
    surface : SurfaceParams
        The band the whole surface must stay in, the smallest defect, and
        whether a defect fails the part (a spec's ``[surface]``).
    local : LocalParams
        How the comparison-point path matches each point's windows.
    """

    path: MeasurePath = "cloud"
    guided: bool = True
    use_weights: bool = True
    max_points: int = 150_000
    guide_points: int = 60_000
    pose_points: int = 15_000
    min_inlier_fraction: float = 0.5
    max_rms_mm: float = 1.0
    ambiguous_is_error: bool = False
    min_support: int = 10
    uncertainty_fraction: float = 0.1
    register: RegisterParams = field(default_factory=lambda: LINE_REGISTER)
    surface: SurfaceParams = field(default_factory=SurfaceParams)
    local: LocalParams = field(default_factory=LocalParams)

    def __post_init__(self) -> None:
        if self.path not in ("cloud", "comparison_points"):
            raise InvalidInput(f"path must be 'cloud' or 'comparison_points', got {self.path!r}")
        if not isinstance(self.surface, SurfaceParams):
            raise InvalidInput(f"surface must be SurfaceParams, got {type(self.surface).__name__}")
        if self.path == "comparison_points" and self.surface.fails_part:
            raise InvalidInput(
                "path 'comparison_points' does not check the surface between the points, so "
                "its defects cannot fail a part: measure with path 'cloud', or set the "
                "surface's fails_part to false"
            )
        if not isinstance(self.local, LocalParams):
            raise InvalidInput(f"local must be LocalParams, got {type(self.local).__name__}")
        if not (isinstance(self.max_points, int) and self.max_points >= 100):
            raise InvalidInput(f"max_points must be an integer >= 100, got {self.max_points}")
        if not (isinstance(self.guide_points, int) and self.guide_points >= 100):
            raise InvalidInput(f"guide_points must be an integer >= 100, got {self.guide_points}")
        if not (isinstance(self.pose_points, int) and self.pose_points >= 100):
            raise InvalidInput(f"pose_points must be an integer >= 100, got {self.pose_points}")
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

    def fit_params(self, frame: Frame) -> RegisterParams:
        """The fit's parameters for a cloud in ``frame``: the view direction (the
        sensor above the belt) applies to clouds in the rig frame only."""
        if frame == "rig" or self.register.view_direction is None:
            return self.register
        return dataclasses.replace(self.register, view_direction=None)
