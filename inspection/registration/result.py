"""What a fit returns: the pose, why the optimisation stopped, and every point's figures."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from ..arrays import Scalars, Transform

INLIER_SIGMAS = 3.0
"""A point with ``|r| <= INLIER_SIGMAS * scale_mm`` (and a non-zero weight) is an inlier."""


class StopReason(enum.StrEnum):
    """Why the optimisation stopped."""

    CONVERGED = "converged"
    """The last step was below the tolerance, or no step could lower the cost
    while the Gauss-Newton step lay within the pose's own uncertainty (a
    minimum, on a cost rough at that scale, e.g. correspondences trading faces)."""
    MAX_ITERATIONS = "max_iterations"
    """The iteration budget ran out before convergence."""
    NO_PROGRESS = "no_progress"
    """The trust region shrank to nothing without finding a lower cost while
    the Gauss-Newton step still reached beyond the pose's uncertainty (or a
    direction was unconstrained): the pose may be short of its minimum."""


@dataclass(frozen=True, eq=False)
class Registration:
    """The result of a fit of measured points to the CAD.

    The fit runs on a random subset of the points (see :func:`register`);
    ``weights``, ``residuals``, ``rms_mm`` and ``inlier_fraction`` describe
    *every* input point at the final pose (the fit ends with one
    closest-point query of the points it did not use).

    Attributes
    ----------
    transform : (4, 4) float64
        ``T_cad_data``: maps data-frame points into the CAD frame (mm).
    iterations : int
        Iterations run (each one an accepted step or the last attempt).
    converged : bool
    stop_reason : StopReason
    rms_mm : float, mm
        Root mean square of the residuals of the inliers (all points).
    inlier_fraction : float
        Fraction of all points with ``|r| <= 3 scale_mm`` (and a non-zero
        input weight).
    weights : (N,) float64
        Final robust weight of each input point (input weight x IRLS weight,
        in [0, 1] x input weight), in the order of the input points; 0 for
        points farther than ``max_distance_mm`` from the CAD. Read-only.
    residuals : (N,) float64, mm
        Final residual (signed distance, or point-to-plane distance with
        ``residual="plane"``) of each input point. Read-only.
    scale_mm : float, mm
        Final robust scale ``sigma`` of the residuals.
    cost_history : (K, 2) float64
        Per iteration, the robust cost before and after its step (same subset,
        same scale). Column 1 never exceeds column 0.
    subset_sizes : (K,) int64
        Points used in each iteration.
    observability : (6,) float64
        Eigenvalues, ascending, of the final normal matrix normalised by the
        total weight, in the parametrisation (rotation x L, translation)
        with ``L`` the RMS radius of the points (so all six are in the same
        units; 1 means "as constrained as a translation along a normal").
    degenerate_directions : (K, 6) float64
        Unit eigenvectors ``(omega L, t)`` of the directions the data do not
        constrain (eigenvalue below 1e-3 of the largest); empty when the pose
        is fully determined. A flat plate seen from one side has three.
    pose_center : (3,) float64, mm, CAD frame
        The point the twist ``(omega, t)`` of ``observability`` and
        ``pose_covariance`` turns about (the weighted centroid of the fitted
        points at the final pose).
    pose_radius_mm : float, mm
        ``L``, the RMS radius of the fitted points about ``pose_center``.
    pose_covariance : (6, 6) float64, mm^2
        Covariance of the twist ``(omega L, t)`` that the noise leaves in the
        pose, ``sigma^2 H^-1 / sum v``. A degenerate direction counts with its
        small eigenvalue (a large variance); one whose eigenvalue is zero to
        rounding (below 1e-9 of the largest: the data do not resolve it at
        all) is left out, and is free.
    loss : str
    accepted_steps : int
    rejected_steps : int
    opposed_fraction : float
        The share of the inliers' weight on faces turned against the rest
        (normals more than 120 degrees from their weighted mean). A cloud
        seen from one side rests on faces turned one way: a share well above
        zero is a cloud laid through a thin wall onto both its sides, a
        minimum that only the sensor's side (``view_direction``) tells apart.
    """

    transform: Transform
    iterations: int
    converged: bool
    stop_reason: StopReason
    rms_mm: float
    inlier_fraction: float
    weights: Scalars
    residuals: Scalars
    scale_mm: float
    cost_history: np.ndarray
    subset_sizes: np.ndarray
    observability: np.ndarray
    degenerate_directions: np.ndarray
    pose_center: np.ndarray
    pose_radius_mm: float
    pose_covariance: np.ndarray
    loss: str
    accepted_steps: int
    rejected_steps: int
    opposed_fraction: float = 0.0

    @property
    def degenerate(self) -> bool:
        """True when at least one direction of motion is unconstrained."""
        return len(self.degenerate_directions) > 0
