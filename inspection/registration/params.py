"""The fine registration's parameters: one frozen record, checked when it is made."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

from ..errors import InvalidInput
from ..validate import validate_view
from .kernels import LOSSES


def _real(x: object) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _integer(x: object) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


@dataclass(frozen=True, kw_only=True)
class RegisterParams:
    """How :func:`~inspection.register` fits measured points to the CAD.

    The defaults fit a cloud that starts within ~10 degrees and ~20 mm of its
    pose; the line's measuring sequence narrows them
    (:class:`~inspection.MeasureParams`).

    Attributes
    ----------
    loss : {"tukey", "welsch", "cauchy", "huber", "l2"}
        M-estimator of the residuals. The redescending ones (tukey, welsch,
        cauchy) ignore gross outliers such as reflection blobs.
    residual : {"distance", "plane"}
        ``"distance"``: the signed distance to the CAD, whose gradient is the
        face normal on a face and points to the edge or corner beyond it (so
        points overhanging an edge pull the part back); ``"plane"``: the
        classic point-to-plane residual to the closest face's plane.
    max_distance_mm : float, mm
        Points farther than this from the CAD when first seen (at the pose of
        their first query) are left out (background, far outliers).
    view_direction : (3,) tuple of float or None
        Direction from the part towards the sensor, data frame (e.g. +z of a
        rig looking down); stored as a unit vector. When given, a point whose
        closest CAD face is turned away from it by more than 120 degrees
        counts as an outlier: a sensor cannot see such a face, and a plate
        tilted through its own thickness would otherwise fit half its points
        to its bottom. Needs ``loss`` tukey or welsch (a loss with a plateau
        for such points). Should no step lower the cost under that rule
        (points crossing onto back faces jump to the plateau), or only heavily
        damped ones when the pose settles, the fit goes on without it.
    graduated : bool
        Start with a wide robust scale and narrow it as the pose settles
        (graduated non-convexity), so that points misfit by the start offset,
        such as those overhanging the part's outline, pull the part into
        place before the scale narrows to the noise. Without it the scale is
        the residuals' MAD from the start.
    min_scale_mm : float, mm
        Floor of the robust scale (keeps the weights finite on perfect data).
    max_iterations : int
        Iterations in all, over every subset.
    tolerance_rad, tolerance_mm : float, rad and mm
        Convergence: a step on the last subset below both ends the fit (the
        step is then below what the data resolve, and is not taken).
    max_rejections : int
        Trust-region retries per iteration before giving up.
    max_extensions : int
        When consecutive steps keep the same direction (sliding along a weakly
        constrained direction), up to this many doublings of the step are
        tried; each is kept only if it lowers the cost.
    seed : int
        Seeds the random subsets; the same seed and input give the same result
        bit for bit.
    initial_subset : int
        Points in the first subset (at least 6).
    max_subset : int or None
        Points in the last subset (None: all points). Each subset is a prefix
        of the next (a seeded permutation), grown ``subset_growth`` times once
        the pose has converged on the current one. The pose is the optimum of
        the last subset; more points are slower and only help weakly
        constrained parts (see ``uncertainty_mm``).
    subset_growth : int
        Factor by which the subset grows once the pose has converged on it
        (straight to the last subset when a grown one would leave out fewer
        points than it holds).
    subset_tolerance_factor : float
        The tolerances are this much looser on the smaller subsets: the first
        step on the next, larger one finishes the job.
    uncertainty_mm : float or None, mm
        Once the pose has converged on ``max_subset`` points, when the noise
        leaves it uncertain by more than this (RMS displacement of the points,
        ``sigma sqrt(trace(H^-1) / n)`` from the normal matrix ``H``), the
        fit continues on every point. A part seen from one side whose
        in-plane position rests on a few edges needs them all; a well
        constrained one does not. None: never.
    min_points : int
        At least this many points (and at least 6) must lie within
        ``max_distance_mm`` of the CAD at the start and be inliers (of the
        last subset) at the end.
    escape_deg : float or None, degrees
        When the fit ends with a rotation its points do not constrain (a
        disc whose turn rests on a ring of holes, started further off than
        the holes are wide), or with many points misfit, rotations about
        that axis within this many degrees are scanned, and the most
        promising are fitted again; a fit that leaves clearly fewer points
        misfit replaces the first one (see :mod:`.escape`). In (0, 180];
        None: never.

    Raises
    ------
    InvalidInput
        Any field out of its range, or a view direction with a loss without
        a plateau.
    """

    loss: str = "tukey"
    residual: str = "distance"
    max_distance_mm: float = 50.0
    view_direction: tuple[float, float, float] | None = None
    graduated: bool = True
    min_scale_mm: float = 1e-3
    max_iterations: int = 80
    tolerance_rad: float = 1e-6
    tolerance_mm: float = 2e-4
    max_rejections: int = 10
    max_extensions: int = 6
    seed: int = 0
    initial_subset: int = 512
    max_subset: int | None = 16384
    subset_growth: int = 8
    subset_tolerance_factor: float = 10.0
    uncertainty_mm: float | None = 2.5e-3
    min_points: int = 30
    escape_deg: float | None = 30.0

    def __post_init__(self) -> None:
        if self.escape_deg is not None and not (
            _real(self.escape_deg) and 0 < self.escape_deg <= 180
        ):
            raise InvalidInput(
                f"escape_deg must be a number in (0, 180] or None, got {self.escape_deg!r}"
            )
        if self.residual not in ("distance", "plane"):
            raise InvalidInput(f"residual must be 'distance' or 'plane', got {self.residual!r}")
        if self.loss not in LOSSES:
            raise InvalidInput(f"unknown loss {self.loss!r}; expected one of {', '.join(LOSSES)}")
        if not (_integer(self.max_iterations) and self.max_iterations >= 1):
            raise InvalidInput(f"max_iterations must be an integer >= 1, got {self.max_iterations}")
        if not (_integer(self.initial_subset) and self.initial_subset >= 6):
            raise InvalidInput(f"initial_subset must be an integer >= 6, got {self.initial_subset}")
        if self.max_subset is not None and not (
            _integer(self.max_subset) and self.max_subset >= self.initial_subset
        ):
            raise InvalidInput(
                f"max_subset ({self.max_subset}) must be an integer >= initial_subset "
                f"({self.initial_subset})"
            )
        if self.uncertainty_mm is not None and not (
            _real(self.uncertainty_mm)
            and math.isfinite(self.uncertainty_mm)
            and self.uncertainty_mm > 0
        ):
            raise InvalidInput(
                f"uncertainty_mm must be a finite positive number, got {self.uncertainty_mm!r}"
            )
        if not (_integer(self.subset_growth) and self.subset_growth >= 2):
            raise InvalidInput(f"subset_growth must be an integer >= 2, got {self.subset_growth}")
        for name in ("max_distance_mm", "min_scale_mm"):
            value = getattr(self, name)
            if not (_real(value) and math.isfinite(value) and value > 0):
                raise InvalidInput(f"{name} must be a finite positive number, got {value!r}")
        if self.view_direction is not None:
            view = validate_view(self.view_direction, self.loss)
            assert view is not None
            object.__setattr__(self, "view_direction", tuple(float(c) for c in view))
