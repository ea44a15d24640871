"""Robust fine registration of a measured cloud to the CAD: IRLS point-to-surface ICP.

The fit finds ``T_cad_data``, the rigid transform that maps the measured
points (data frame, e.g. the rig) into the CAD frame, by minimising a robust
cost of the residuals ``r_i(T)``: by default the signed distance of ``T p_i``
to the CAD surface, whose gradient is the face normal ``n_i`` where the
closest point ``q_i`` lies inside a face (there it equals the point-to-plane
residual ``n_i . (T p_i - q_i)``) and points towards the edge or corner
beyond it otherwise, so that points overhanging a border pull the part back
(``residual="plane"`` gives the classic point-to-plane ICP). Closest points
come from the CAD tree, re-queried as the pose moves (see below). The cost is

    E(T) = sum_i v_i sigma^2 rho(r_i / sigma) / sum_i v_i

with ``v_i`` the caller's per-point weights, ``rho`` one of the M-estimator
losses below (normalised so that ``sigma^2 rho(r / sigma) ~ r^2 / 2`` for small
residuals) and ``sigma`` a robust scale (1.4826 x the median absolute
residual, the MAD of a zero-centred residual).

Each iteration is one damped Gauss-Newton step on the IRLS surrogate
(Levenberg-Marquardt): with IRLS weights ``w_i = v_i psi(x)/x``, ``x = r_i /
sigma``, the 6x6 normal equations ``(H + lambda D) delta = -g`` give a small
twist ``delta = (omega L, t)`` about the centroid of the points. The step is
accepted only if the true cost, evaluated with fresh closest points at the
new pose, is lower; otherwise ``lambda`` grows and the step is retried
(a trust region). The gain ratio ``actual / predicted`` reduction steers
``lambda`` as in Nielsen's and Madsen's LM (Madsen, Nielsen & Tingleff,
"Methods for non-linear least squares problems", 2004, eq. 3.13-3.14).
For every loss here, ``psi(x)/x`` does not increase with ``|x|``, so the
half-quadratic IRLS surrogate majorises the robust cost (Huber's and
Black-Rangarajan's construction): the predicted reduction is a lower bound
of the true one whenever the linearised residuals are exact, and the
ratio sits near or above 1 close to the optimum.

Speed comes from a growing random subset of the points (a seeded
shuffle, each subset a prefix of the next, as in the published system).
A closest-point query costs far more than anything else per point, so the
fit is arranged to query few points, few times:

- The coarse stage runs on ``initial_subset`` points (512) until the pose
  has converged on them; then the subset grows ``subset_growth`` times
  (8) at a time up to ``max_subset`` (16384), each stage converging before
  the next. Only the new points are queried when a subset grows. The
  result is the optimum on the last subset: its pose is as good as the
  noise on those points allows (about 1-2 um on a well-constrained 300 mm
  part with 0.02 mm noise), and a step below a quarter of that statistical
  uncertainty ends a stage (stopping on a fixed absolute step size instead
  either wastes queries or, on a subset with a looser tolerance, stops
  several um short). Before the last stage, a step that lowers the cost by
  less than the subset's noise can tell apart (1 % of sigma^2 / n) ends it
  too: where a subset leaves a direction loose (512 points hold a handful
  of a panel's bend points), damped steps would otherwise crawl along it
  for every iteration left and end far off. A part whose pose the subset
  does not pin down to ``uncertainty_mm`` (a plate whose in-plane position
  rests on a few edges) continues on every point.
- Past the coarse stage, a step that moves the points by less than 0.02 mm
  is evaluated against each point's last closest face (its plane, while
  the foot point stays inside the triangle) instead of a fresh query; only
  the few points whose foot leaves that face's interior, or that cross its
  plane, are queried again. The distance to one face is at least the distance to the
  surface, so such a cost bounds the true one from above, and a step it
  accepts lowers the true cost too (the classic ICP argument).
- ``weights``, ``residuals``, ``rms_mm`` and ``inlier_fraction`` of every
  point need a query of all points at the final pose: it runs on first
  access of any of them, not before the transform is returned.

Robustness to the start offset: the scale starts wide (the 90th percentile
of the first residuals) and narrows 4 times each time the pose settles at
it (graduated non-convexity), so that points misfit by the start offset,
such as those overhanging the part's outline, pull the part into place
before the scale narrows to the noise and would reject them. When steps
keep the same direction (sliding along a weakly constrained direction,
where Gauss-Newton converges linearly), the rest of the geometric series
of steps (Aitken's extrapolation) and longer steps are tried, each kept
only if it lowers the cost.

Escape along a free rotation: a local fit cannot tell where a rotation that
its points do not constrain should end. A disc whose turn rests on a ring
of holes, started further off than the holes are wide, ends where it
happens to stop (flagged degenerate); a part with a toothed rim ends a few
teeth off, constrained there, with a large share of its points off the CAD.
When the final fit is flagged degenerate and its least constrained rotation
(with the translation free to follow it) is weak, or when it leaves more
than 10 % of its points misfit, that rotation is scanned over
``escape_deg`` either way in steps that move the points by ~2 mm, twice:
about the centroid (a disc turns about its centre), and with the shift that
follows the turn to first order (a plate standing on the belt that settled
turned in its own plane about a corner, 1.7 deg off, comes back only so).
Each angle is scored by the truncated distances of 4096 points to the CAD
(one query each), and the fit is run again, with everything else as given,
from up to three of the scans' local minima that score 10 % better than the
fit or more. A fit that leaves the points' truncated cost (three robust
scales of the first fit) 10 % lower or more replaces the first. A
constrained fit of a clean cloud pays nothing; the scans cost 20-200 ms
(points turned off the surface by more than the tree's band take its exact
path), a new fit what a fit costs. ``align`` searches the turn itself, and its final fit
runs without the scan. The scan is about one axis: a free translation (a
plate sliding in its plane) is left to the flag.

The cost only ever falls within an iteration (a step is accepted only if it
lowers the cost). Across iterations it falls too while the subset stays the
same: the scale ``sigma`` never grows from one iteration to the next, and
``sigma^2 rho(r / sigma)`` does not decrease with ``sigma`` for any loss
here, so a smaller scale cannot raise the cost. When the subset grows the
mean is taken over more points, the scale is estimated afresh on them and
the cost is re-based; ``cost_history`` keeps, per iteration, the cost
before and after its step so that both properties can be checked.

Determinism: the subsets come from a seeded generator, every reduction runs
in a fixed order in single-threaded numba kernels (no parallel reductions,
no BLAS on the hot path), so the same input gives a bit-identical transform.
"""

from __future__ import annotations

import enum
import logging
import numbers
import threading
import weakref
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numba
import numpy as np

from ._faces import face_planes
from ._linalg import cholesky_solve
from .arrays import Points, Scalars, Transform, Vectors
from .errors import InsufficientOverlap, InvalidInput

log = logging.getLogger(__name__)

__all__ = [
    "LOSSES",
    "ClosestLike",
    "ClosestPointQuery",
    "Registration",
    "StopReason",
    "register",
    "validate_points",
    "validate_transform",
]


class ClosestLike(Protocol):
    """What a closest-point query returns (``inspection.grid.Closest`` and friends).

    Attributes
    ----------
    points : (N, 3) float64, mm, CAD frame
        Closest CAD point of each query point.
    normals : (N, 3) float64
        Unit normal of the closest face (outward).
    distances : (N,) float64, mm
        Signed distance, positive on the outer side.
    face : (N,) int64
        Index of the closest face.
    """

    @property
    def points(self) -> Points: ...

    @property
    def normals(self) -> Vectors: ...

    @property
    def distances(self) -> Scalars: ...

    @property
    def face(self) -> np.ndarray: ...


@runtime_checkable
class ClosestPointQuery(Protocol):
    """Anything that answers closest-point queries on the CAD (a ``GridTree``)."""

    def query(self, points: Points) -> ClosestLike:  # pragma: no cover - protocol
        ...


class StopReason(enum.StrEnum):
    """Why the optimisation stopped."""

    CONVERGED = "converged"
    """The last step was below the tolerance, or no step could lower the cost
    and the predicted gain was negligible (a minimum)."""
    MAX_ITERATIONS = "max_iterations"
    """The iteration budget ran out before convergence."""
    NO_PROGRESS = "no_progress"
    """The trust region shrank to nothing without finding a lower cost while
    the model still predicted a real gain (a rough cost, e.g. correspondences
    jumping between faces)."""


# Loss ids for the numba kernels and their tuning constants for unit scale:
# the usual 95 % asymptotic efficiency constants under Gaussian noise.
LOSSES: dict[str, tuple[int, float]] = {
    "l2": (0, 1.0),
    "huber": (1, 1.345),
    "tukey": (2, 4.685),
    "cauchy": (3, 2.3849),
    "welsch": (4, 2.9846),
}

# |r| <= _INLIER_SIGMAS * sigma counts as an inlier in the summary figures.
_INLIER_SIGMAS = 3.0
# Residuals used to estimate the robust scale.
_SCALE_SAMPLE = 4096
# MAD to standard deviation for Gaussian noise.
_MAD_TO_SIGMA = 1.482602218505602
# Relative eigenvalue of the normalised normal matrix below which a direction
# of motion counts as unconstrained by the data.
_DEGENERATE_REL_EIG = 1e-3
# Graduated scale: it starts at this quantile of the first |residuals| and
# narrows by this factor each time the pose settles at it.
_GNC_QUANTILE = 0.9
_GNC_FACTOR = 4.0
# ... once a step lowers the cost by less than this fraction, or moves the
# points by less than this fraction of the scale.
_GNC_GAIN = 1e-3
# On a subset smaller than the last, a step that lowers the cost by less than
# this fraction of sigma^2 / (the subset's total weight) has settled: what
# the noise of that many points can tell apart is ~sigma^2 / n per
# parameter, so such steps only wander along a direction the subset leaves
# loose, and the next, larger subset decides it.
_SUBSET_GAIN = 1e-2
# With a view direction: faces turned further than this (cosine) from it
# cannot be seen; a residual this large puts a point on the loss's plateau.
_BACK_FACE_COS = -0.5
_FAR_MM = 1e30
# ... and when the steps that do lower the cost under that rule are damped
# this much as the pose settles (the trust region has shrunk to crawling: the
# rule's jumps make the quadratic model a poor one), the fit is stuck against
# the rule, as a part tilted far over an outline is when its overhanging
# points count as unseen and no longer pull it back.
_VIEW_STUCK_LAMBDA = 1.0
_GNC_STEP = 1e-3
# Steps moving the points by less than this (RMS, mm) are evaluated against
# each point's last closest face rather than with a fresh query.
_FIXED_FACE_STEP_MM = 0.02
# Escape along an unconstrained rotation (see the module notes): a rotation
# whose marginal eigenvalue (translation free) is below this, relative to the
# normal matrix's largest, is scanned ...
_ESCAPE_REL_EIG = 1e-2
# ... as is the least constrained rotation of a fit that leaves more than
# this fraction of its points misfit (beyond three robust scales) ...
_ESCAPE_MISFIT = 0.1
# ... on this many points, scored by their mean squared distance to the CAD
# truncated at this (mm; or 20 robust scales, if more), in steps that move
# the points by about this much at their RMS radius (at most 2 degrees) ...
_ESCAPE_POINTS = 4096
_ESCAPE_TRUNCATION_MM = 2.0
# ... and up to this many of the scan's local minima that score this
# fraction of the fit's score or less are fitted again; one replaces the fit
# when it leaves this fraction of its truncated cost (three robust scales of
# the first fit) or less.
_ESCAPE_STARTS = 3
_ESCAPE_GAIN = 0.9


class _FullPass:
    """The per-point figures over every input point, computed once on first use.

    The fit itself runs on a random subset; the weights, residuals, RMS and
    inlier fraction of *all* points need one closest-point query of the
    points the fit did not use, at the final pose. Most callers only want the
    transform (or want it first), so that query waits until a figure is asked
    for, and then runs once.
    """

    def __init__(
        self,
        evaluate,
        r_fit: np.ndarray,
        V: np.ndarray,
        perm: np.ndarray,
        max_distance_mm: float,
        sigma: float,
        loss_id: int,
        c: float,
    ) -> None:
        self._evaluate = evaluate
        self._r_fit = r_fit
        self._V = V
        self._perm = perm
        self._max_distance = max_distance_mm
        self._sigma = sigma
        self._loss = (loss_id, c)
        self._out: tuple[Scalars, Scalars, float, float] | None = None

    def get(self) -> tuple[Scalars, Scalars, float, float]:
        if self._out is None:
            m = len(self._r_fit)
            n = len(self._perm)
            V = self._V.copy()
            r = np.empty(n)
            r[:m] = self._r_fit
            if m < n:
                r2, d2 = self._evaluate(m, n)
                V[m:] *= np.abs(d2) <= self._max_distance
                r[m:] = r2
            w = _irls_weights(r, V, self._sigma, *self._loss)
            inl = (V > 0) & (np.abs(r) <= _INLIER_SIGMAS * self._sigma)
            rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("nan")
            weights = np.empty(n)
            weights[self._perm] = w
            resid = np.empty(n)
            resid[self._perm] = r
            weights.flags.writeable = False
            resid.flags.writeable = False
            self._out = (weights, resid, rms, float(inl.sum()) / n)
            self._evaluate = None  # drop the references to the tree and the points
        return self._out


@dataclass(frozen=True, eq=False)
class Registration:
    """The result of a fit of measured points to the CAD.

    The fit runs on a random subset of the points (see :func:`register`);
    ``weights``, ``residuals``, ``rms_mm`` and ``inlier_fraction`` describe
    *every* input point at the final pose. They are computed on first access
    of any of them (one closest-point query of the points the fit did not
    use, a few ms for 50k points) and kept; the transform does not wait
    for them.

    Attributes
    ----------
    transform : (4, 4) float64
        ``T_cad_data``: maps data-frame points into the CAD frame (mm).
    rms_mm : float
        Root mean square of the residuals of the inliers, mm (all points).
    inlier_fraction : float
        Fraction of all points with ``|r| <= 3 scale_mm`` (and a non-zero
        input weight).
    iterations : int
        Iterations run (each one an accepted step or the last attempt).
    converged : bool
    stop_reason : StopReason
    weights : (N,) float64
        Final robust weight of each input point (input weight x IRLS weight,
        in [0, 1] x input weight), in the order of the input points; 0 for
        points farther than ``max_distance_mm`` from the CAD. Read-only.
    residuals : (N,) float64, mm
        Final residual (signed distance, or point-to-plane distance with
        ``residual="plane"``) of each input point. Read-only.
    scale_mm : float
        Final robust scale ``sigma`` of the residuals, mm.
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
    pose_radius_mm : float
        ``L``, the RMS radius of the fitted points about ``pose_center``.
    pose_covariance : (6, 6) float64, mm^2
        Covariance of the twist ``(omega L, t)`` that the noise leaves in the
        pose, ``sigma^2 H^-1 / sum v`` over the constrained directions (the
        degenerate ones contribute nothing here: see
        ``degenerate_directions``).
    loss : str
    accepted_steps : int
    rejected_steps : int
    """

    transform: Transform
    iterations: int
    converged: bool
    stop_reason: StopReason
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
    full_pass: _FullPass = field(repr=False)
    """Computes the all-point figures on first use (internal)."""

    @property
    def weights(self) -> Scalars:
        return self.full_pass.get()[0]

    @property
    def residuals(self) -> Scalars:
        return self.full_pass.get()[1]

    @property
    def rms_mm(self) -> float:
        return self.full_pass.get()[2]

    @property
    def inlier_fraction(self) -> float:
        return self.full_pass.get()[3]

    @property
    def degenerate(self) -> bool:
        """True when at least one direction of motion is unconstrained."""
        return len(self.degenerate_directions) > 0


# ---------------------------------------------------------------------------
# numba kernels: serial loops in a fixed order, so results are bit-identical.


@numba.njit(cache=True)
def _rho_weight(r: float, sigma: float, loss: int, c: float) -> tuple[float, float]:
    """``sigma^2 rho(r / sigma)`` and the IRLS weight ``psi(x) / x``."""
    x = r / sigma
    if loss == 0:
        return 0.5 * r * r, 1.0
    if loss == 1:  # Huber
        a = abs(x)
        if a <= c:
            return 0.5 * r * r, 1.0
        return sigma * sigma * c * (a - 0.5 * c), c / a
    u = (x / c) * (x / c)
    if loss == 2:  # Tukey's biweight
        if u >= 1.0:
            return sigma * sigma * c * c / 6.0, 0.0
        v = 1.0 - u
        return sigma * sigma * c * c / 6.0 * (1.0 - v * v * v), v * v
    if loss == 3:  # Cauchy
        return sigma * sigma * c * c * 0.5 * np.log1p(u), 1.0 / (1.0 + u)
    # Welsch
    e = np.exp(-u)
    return sigma * sigma * c * c * 0.5 * (1.0 - e), e


@numba.njit(cache=True)
def _transform(R: np.ndarray, t: np.ndarray, P: np.ndarray) -> np.ndarray:
    n = P.shape[0]
    X = np.empty((n, 3))
    for i in range(n):
        for k in range(3):
            X[i, k] = R[k, 0] * P[i, 0] + R[k, 1] * P[i, 1] + R[k, 2] * P[i, 2] + t[k]
    return X


@numba.njit(cache=True)
def _residuals(X: np.ndarray, Q: np.ndarray, N: np.ndarray) -> np.ndarray:
    n = X.shape[0]
    r = np.empty(n)
    for i in range(n):
        r[i] = (
            N[i, 0] * (X[i, 0] - Q[i, 0])
            + N[i, 1] * (X[i, 1] - Q[i, 1])
            + N[i, 2] * (X[i, 2] - Q[i, 2])
        )
    return r


@numba.njit(cache=True)
def _distance_residuals(
    X: np.ndarray, Q: np.ndarray, N: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances and their gradients ``(x - q) / d`` (the face normal on the face)."""
    n = X.shape[0]
    r = np.empty(n)
    U = np.empty((n, 3))
    for i in range(n):
        di = d[i]
        r[i] = di
        ex = X[i, 0] - Q[i, 0]
        ey = X[i, 1] - Q[i, 1]
        ez = X[i, 2] - Q[i, 2]
        along = N[i, 0] * ex + N[i, 1] * ey + N[i, 2] * ez
        e2 = ex * ex + ey * ey + ez * ez
        # Off the face's interior the foot is on an edge or corner: the
        # distance grows along x - q, not along the face normal.
        if e2 > 1e-24 and e2 - along * along > 1e-6 * e2:
            s = 1.0 / di if di != 0.0 else 0.0
            U[i, 0] = ex * s
            U[i, 1] = ey * s
            U[i, 2] = ez * s
        else:
            U[i, 0] = N[i, 0]
            U[i, 1] = N[i, 1]
            U[i, 2] = N[i, 2]
    return r, U


@numba.njit(cache=True)
def _face_residuals(
    X: np.ndarray,
    face: np.ndarray,
    plane: np.ndarray,
    sign: np.ndarray,
    distance: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals and their gradients against one given face per point.

    ``plane[face[i]]`` (F, 12) float64 holds the face's unit normal n and
    ``n . a``, then the dual basis U, V of its edges ab, ac with ``U . a``
    and ``V . a`` (see :func:`face_planes`). The residual is the signed
    distance of ``x_i`` to the face's plane; with ``distance`` it stands
    for the distance to the triangle, which it equals while the foot point
    lies inside the triangle (barycentric coordinates from U and V). The distance
    to one face is at least the distance to the surface, so a cost evaluated
    this way bounds the true cost from above.

    Also returns, per point, whether another face may now be the closest (the
    caller queries those again and overwrites their residuals): with
    ``distance``, its foot point left the face's interior; in either mode, it
    crossed the face's plane (``sign[i]`` is the sign it had), such as a point
    overhanging a wall that moves back over the part.
    """
    n = X.shape[0]
    r = np.empty(n)
    U = np.empty((n, 3))
    recheck = np.empty(n, dtype=np.bool_)
    for i in range(n):
        f = face[i]
        px, py, pz = X[i, 0], X[i, 1], X[i, 2]
        nx, ny, nz = plane[f, 0], plane[f, 1], plane[f, 2]
        ri = nx * px + ny * py + nz * pz - plane[f, 3]
        r[i] = ri
        U[i, 0] = nx
        U[i, 1] = ny
        U[i, 2] = nz
        again = (ri >= 0.0) != (sign[i] >= 0.0)
        if distance and not again:
            u = plane[f, 4] * px + plane[f, 5] * py + plane[f, 6] * pz - plane[f, 7]
            v = plane[f, 8] * px + plane[f, 9] * py + plane[f, 10] * pz - plane[f, 11]
            again = not (u >= 0.0 and v >= 0.0 and u + v <= 1.0)
        recheck[i] = again
    return r, U, recheck


@numba.njit(cache=True)
def _partial_shuffle(n: int, k: int, seed: np.uint64) -> np.ndarray:
    """A permutation of ``range(n)`` whose first ``k`` entries are a uniform
    random sample in random order (Fisher-Yates stopped after ``k`` swaps),
    from a splitmix64 stream seeded with ``seed``: O(k), not O(n)."""
    out = np.arange(n)
    state = np.uint64(seed)
    for i in range(min(k, n - 1)):
        state += np.uint64(0x9E3779B97F4A7C15)
        z = state
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
        j = i + np.int64(z % np.uint64(n - i))
        out[i], out[j] = out[j], out[i]
    return out


@numba.njit(cache=True)
def _lm_step(H: np.ndarray, g: np.ndarray, lam: float) -> tuple[np.ndarray, float, bool]:
    """The damped step ``(H + lam D) delta = -g`` and its predicted reduction
    ``-(g . delta + delta . H delta / 2)``. ``D`` is Marquardt's scaling
    ``diag(H)`` plus a small isotropic term, so that directions the data do
    not constrain (``diag(H) ~ 0``) get no step at all."""
    n = H.shape[0]
    tr = 0.0
    for i in range(n):
        tr += H[i, i]
    eps = 1e-9 * max(tr, 1e-300)
    A = H.copy()
    for i in range(n):
        A[i, i] += lam * (H[i, i] + eps)
    delta, ok = cholesky_solve(A, -g)
    if not ok:
        return delta, 0.0, False
    pred = 0.0
    for i in range(n):
        hd = 0.0
        for k in range(n):
            hd += H[i, k] * delta[k]
        pred -= g[i] * delta[i] + 0.5 * delta[i] * hd
    return delta, pred, True


@numba.njit(cache=True)
def _trace_inverse(H: np.ndarray) -> float:
    """``trace(H^-1)`` of a symmetric positive definite ``H``; 0 when it is not."""
    n = H.shape[0]
    tr = 0.0
    for j in range(n):
        e = np.zeros(n)
        e[j] = 1.0
        x, ok = cholesky_solve(H, e)
        if not ok:
            return 0.0
        tr += x[j]
    return tr


@numba.njit(cache=True)
def _compose(T: np.ndarray, omega: np.ndarray, t: np.ndarray, center: np.ndarray) -> np.ndarray:
    """``x' = R(omega) (x - center) + center + t`` applied after ``T``, with
    ``R(omega)`` the rotation of the rotation vector ``omega`` (Rodrigues)."""
    theta = np.sqrt(omega[0] * omega[0] + omega[1] * omega[1] + omega[2] * omega[2])
    R = np.eye(3)
    if theta < 1e-12:
        # First order: exact to ~theta^2 / 2, below 1e-24.
        R[0, 1] = -omega[2]
        R[0, 2] = omega[1]
        R[1, 0] = omega[2]
        R[1, 2] = -omega[0]
        R[2, 0] = -omega[1]
        R[2, 1] = omega[0]
    else:
        kx, ky, kz = omega[0] / theta, omega[1] / theta, omega[2] / theta
        s = np.sin(theta)
        c1 = 1.0 - np.cos(theta)
        R[0, 0] = 1.0 - c1 * (ky * ky + kz * kz)
        R[1, 1] = 1.0 - c1 * (kx * kx + kz * kz)
        R[2, 2] = 1.0 - c1 * (kx * kx + ky * ky)
        R[0, 1] = c1 * kx * ky - s * kz
        R[1, 0] = c1 * kx * ky + s * kz
        R[0, 2] = c1 * kx * kz + s * ky
        R[2, 0] = c1 * kx * kz - s * ky
        R[1, 2] = c1 * ky * kz - s * kx
        R[2, 1] = c1 * ky * kz + s * kx
    out = np.eye(4)
    for i in range(3):
        for j in range(3):
            out[i, j] = R[i, 0] * T[0, j] + R[i, 1] * T[1, j] + R[i, 2] * T[2, j]
        out[i, 3] = (
            R[i, 0] * (T[0, 3] - center[0])
            + R[i, 1] * (T[1, 3] - center[1])
            + R[i, 2] * (T[2, 3] - center[2])
            + center[i]
            + t[i]
        )
    return out


@numba.njit(cache=True)
def _cost(r: np.ndarray, v: np.ndarray, sigma: float, loss: int, c: float) -> float:
    s = 0.0
    vs = 0.0
    for i in range(r.shape[0]):
        if v[i] > 0.0:
            rho, _ = _rho_weight(r[i], sigma, loss, c)
            s += v[i] * rho
            vs += v[i]
    return s / vs


@numba.njit(cache=True)
def _weighted_centroid(X: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid of the points with positive weight, and their RMS radius about it."""
    c = np.zeros(3)
    cnt = 0
    for i in range(X.shape[0]):
        if v[i] > 0.0:
            c[0] += X[i, 0]
            c[1] += X[i, 1]
            c[2] += X[i, 2]
            cnt += 1
    c /= max(cnt, 1)
    s = 0.0
    for i in range(X.shape[0]):
        if v[i] > 0.0:
            dx = X[i, 0] - c[0]
            dy = X[i, 1] - c[1]
            dz = X[i, 2] - c[2]
            s += dx * dx + dy * dy + dz * dz
    return c, np.sqrt(s / max(cnt, 1))


@numba.njit(cache=True)
def _cost_normal_equations(
    X: np.ndarray,
    N: np.ndarray,
    r: np.ndarray,
    v: np.ndarray,
    sigma: float,
    loss: int,
    c: float,
    center: np.ndarray,
    L: float,
) -> tuple[float, np.ndarray, np.ndarray]:
    """The robust cost and the IRLS normal equations, in one pass over the points.

    Row i of the Jacobian is ``J_i = [((x_i - center) x n_i) / L, n_i]`` for
    the twist ``(omega L, t)``; ``H = sum w J^T J``, ``g = sum w r J``.
    Returns the cost (as :func:`_cost`), H (6, 6) and g (6,), normalised by
    the sum of the input weights.
    """
    # 21 + 6 scalar accumulators: numba keeps them in registers.
    h00 = h01 = h02 = h03 = h04 = h05 = 0.0
    h11 = h12 = h13 = h14 = h15 = 0.0
    h22 = h23 = h24 = h25 = 0.0
    h33 = h34 = h35 = 0.0
    h44 = h45 = 0.0
    h55 = 0.0
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    inv_l = 1.0 / L
    vs = 0.0
    es = 0.0
    for i in range(X.shape[0]):
        vi = v[i]
        if vi <= 0.0:
            continue
        vs += vi
        rho, w = _rho_weight(r[i], sigma, loss, c)
        es += vi * rho
        w *= vi
        if w <= 0.0:
            continue
        px = X[i, 0] - center[0]
        py = X[i, 1] - center[1]
        pz = X[i, 2] - center[2]
        nx, ny, nz = N[i, 0], N[i, 1], N[i, 2]
        j0 = (py * nz - pz * ny) * inv_l
        j1 = (pz * nx - px * nz) * inv_l
        j2 = (px * ny - py * nx) * inv_l
        wj0, wj1, wj2, wj3, wj4, wj5 = w * j0, w * j1, w * j2, w * nx, w * ny, w * nz
        h00 += wj0 * j0
        h01 += wj0 * j1
        h02 += wj0 * j2
        h03 += wj0 * nx
        h04 += wj0 * ny
        h05 += wj0 * nz
        h11 += wj1 * j1
        h12 += wj1 * j2
        h13 += wj1 * nx
        h14 += wj1 * ny
        h15 += wj1 * nz
        h22 += wj2 * j2
        h23 += wj2 * nx
        h24 += wj2 * ny
        h25 += wj2 * nz
        h33 += wj3 * nx
        h34 += wj3 * ny
        h35 += wj3 * nz
        h44 += wj4 * ny
        h45 += wj4 * nz
        h55 += wj5 * nz
        ri = r[i]
        g0 += wj0 * ri
        g1 += wj1 * ri
        g2 += wj2 * ri
        g3 += wj3 * ri
        g4 += wj4 * ri
        g5 += wj5 * ri
    H = np.array(
        [
            [h00, h01, h02, h03, h04, h05],
            [h01, h11, h12, h13, h14, h15],
            [h02, h12, h22, h23, h24, h25],
            [h03, h13, h23, h33, h34, h35],
            [h04, h14, h24, h34, h44, h45],
            [h05, h15, h25, h35, h45, h55],
        ]
    )
    g = np.array([g0, g1, g2, g3, g4, g5])
    if vs > 0.0:
        H /= vs
        g /= vs
        es /= vs
    return es, H, g


@numba.njit(cache=True)
def _irls_weights(r: np.ndarray, v: np.ndarray, sigma: float, loss: int, c: float) -> np.ndarray:
    out = np.zeros(r.shape[0])
    for i in range(r.shape[0]):
        if v[i] > 0.0:
            _, w = _rho_weight(r[i], sigma, loss, c)
            out[i] = v[i] * w
    return out


# ---------------------------------------------------------------------------
# validation helpers (shared with alignment and deviations)


def validate_points(points: object, *, name: str = "points", min_points: int = 1) -> Points:
    """(N, 3) finite float64 array, a C-contiguous copy-free view where possible."""
    try:
        p = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{name} must be an (N, 3) array of numbers: {exc}") from exc
    if p.ndim != 2 or p.shape[1] != 3:
        raise InvalidInput(f"{name} must have shape (N, 3), got {p.shape}")
    if len(p) < min_points:
        raise InvalidInput(f"{name} needs at least {min_points} points, got {len(p)}")
    if not np.isfinite(p).all():
        bad = int((~np.isfinite(p)).any(axis=1).sum())
        raise InvalidInput(f"{name}: {bad} points have non-finite coordinates (NaN or inf)")
    return np.ascontiguousarray(p)


def validate_view(view_direction: Vectors | None, loss: str) -> np.ndarray | None:
    """``view_direction`` as a unit 3-vector (None stays None), checked
    against the loss it is used with (see :func:`register`).

    Raises
    ------
    InvalidInput
        Not a finite non-zero 3-vector, or a loss without a plateau.
    """
    if view_direction is None:
        return None
    view = np.asarray(view_direction, dtype=np.float64)
    if view.shape != (3,) or not np.isfinite(view).all() or not np.linalg.norm(view) > 0:
        raise InvalidInput(f"view_direction must be a finite non-zero 3-vector, got {view!r}")
    if loss not in ("tukey", "welsch"):
        raise InvalidInput(
            "view_direction needs a loss with a plateau (tukey or welsch), got " + repr(loss)
        )
    return view / np.linalg.norm(view)


def validate_transform(T: object, *, name: str = "init") -> Transform:
    """A finite rigid (4, 4) transform: orthonormal rotation, det +1, last row 0 0 0 1."""
    try:
        M = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{name} must be a (4, 4) array: {exc}") from exc
    if M.shape != (4, 4):
        raise InvalidInput(f"{name} must have shape (4, 4), got {M.shape}")
    if not np.isfinite(M).all():
        raise InvalidInput(f"{name} has non-finite entries")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InvalidInput(
            f"{name} is not a rigid transform (rotation not orthonormal with det +1)"
        )
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-12):
        raise InvalidInput(f"{name}: last row must be 0 0 0 1, got {M[3]}")
    return M.copy()


def _query(
    tree: ClosestPointQuery, X: Points
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    # One numba thread for the tree's parallel kernels: the queries here are
    # small (a few hundred to 50k points), and on a shared, loaded machine
    # every parallel launch waits for a second core; measured on 2 busy cores,
    # a 512-point query took 15 ms on two threads and 0.1 ms on one, and a
    # 50k-point one 20-28 ms against 12.5 ms. The answer does not depend on
    # the thread count.
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        cl = tree.query(X)
    finally:
        numba.set_num_threads(threads)
    Q = np.ascontiguousarray(cl.points, dtype=np.float64)
    N = np.ascontiguousarray(cl.normals, dtype=np.float64)
    d = np.asarray(cl.distances, dtype=np.float64)
    f = np.asarray(getattr(cl, "face", np.zeros(len(d), dtype=np.int64)), dtype=np.int64)
    return Q, N, d, f


# Face planes per tree, (F, 12) float64 (see face_planes): computed once per
# tree, keyed by id and checked by a weak reference.
_PLANES: dict[int, tuple[weakref.ref, np.ndarray]] = {}
_PLANES_LOCK = threading.Lock()


def _tree_geometry(tree: object) -> tuple[np.ndarray] | None:
    """The tree's face planes (:func:`face_planes`), in the numbering of its
    answers' ``face``, or None when it does not expose its triangles
    (``vertices`` and ``faces``)."""
    key = id(tree)
    with _PLANES_LOCK:
        hit = _PLANES.get(key)
    if hit is not None and hit[0]() is tree:
        return (hit[1],)
    vertices = getattr(tree, "vertices", None)
    faces = getattr(tree, "faces", None)
    if vertices is None or faces is None:
        return None
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        return None
    tri = vertices[faces]
    normals = getattr(tree, "face_normals", None)
    if normals is None or np.shape(normals) != (len(faces), 3):
        cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normals = cr / np.maximum(np.linalg.norm(cr, axis=1, keepdims=True), 1e-300)
    planes = face_planes(tri, np.asarray(normals, dtype=np.float64))
    try:
        ref = weakref.ref(tree)
    except TypeError:
        return (planes,)
    with _PLANES_LOCK:
        for k in [k for k, (r, _) in _PLANES.items() if r() is None]:
            del _PLANES[k]
        _PLANES[key] = (ref, planes)
    return (planes,)


def _orthonormalised(T: Transform) -> Transform:
    """``T`` with its rotation made orthonormal to the last bit (a few dozen
    compositions leave it off by ~1e-15)."""
    out = T.copy()
    U, _, Vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = U @ Vt
    return out


def _robust_scale(r: np.ndarray, v: np.ndarray, floor: float, sample: int = _SCALE_SAMPLE) -> float:
    # The points are in random order: a prefix is a random sample, and a few
    # thousand residuals give the median to ~2 %.
    return max(_MAD_TO_SIGMA * _median_abs(r, v, min(len(r), sample)), floor)


@numba.njit(cache=True)
def _median_abs(r: np.ndarray, v: np.ndarray, k: int) -> float:
    """Median of ``|r[i]|`` over the first ``k`` points with ``v[i] > 0`` (0 if none)."""
    a = np.empty(k)
    n = 0
    for i in range(k):
        if v[i] > 0.0:
            a[n] = abs(r[i])
            n += 1
    if n == 0:
        return 0.0
    return np.median(a[:n])


def _uncertainty(H: np.ndarray, sigma: float, v: np.ndarray) -> float:
    """RMS displacement, mm, that the noise ``sigma`` leaves in the pose fitted
    to the points with input weights ``v``, from the normal matrix ``H``
    (normalised by the weight sum): ``sigma sqrt(trace(H^-1) / sum v)``."""
    vs = float(v.sum())
    tr = _trace_inverse(H)
    if not np.isfinite(tr) or tr <= 0.0 or vs <= 0.0:
        return 0.0
    return sigma * float(np.sqrt(tr / vs))


def _escape(
    tree: ClosestPointQuery,
    P: Points,
    fit: Registration,
    H: np.ndarray,
    center: np.ndarray,
    L: float,
    span_rad: float,
    refit: Any,
    misfitting: bool,
) -> Registration:
    """Scan the rotation ``fit`` leaves unconstrained, and fit again from the
    most promising angles; the fit that leaves clearly the fewest points
    misfit is returned (``fit`` itself when none does better).

    ``H`` is the final normal matrix for the twist ``(omega L, t)`` about
    ``center`` (CAD frame); ``P`` the scan's points (data frame)."""
    # The rotation that costs least once the translation follows it: the
    # Schur complement of the translation block.
    S = H[:3, :3] - H[:3, 3:] @ np.linalg.pinv(H[3:, 3:]) @ H[3:, :3]
    eig, vec = np.linalg.eigh(0.5 * (S + S.T))
    # fit.observability: the eigenvalues of H, ascending.
    largest = max(float(fit.observability[-1]), 1e-300)
    if not misfitting and eig[0] >= _ESCAPE_REL_EIG * largest:
        return fit
    axis = vec[:, 0]
    trunc = max(_ESCAPE_TRUNCATION_MM, 20.0 * fit.scale_mm)
    step = min(trunc / L, np.radians(2.0))
    k = int(np.ceil(span_rad / step))
    angles = np.linspace(-span_rad, span_rad, 2 * k + 1)
    # Two lines are scanned: the turn about the centroid, and the turn with the
    # shift that follows it to first order (the least-cost shift per radian by
    # the Schur complement). A disc turns about its centre: the first. A plate
    # that settled turned in its own plane about one of its corners comes
    # back only along the second.
    follow = -np.linalg.pinv(H[3:, 3:]) @ H[3:, :3] @ (axis * L)
    found: list[tuple[float, int, Transform, float]] = []
    for line, shift in enumerate((np.zeros(3), follow)):
        starts = [_compose(fit.transform, axis * a, shift * a, center) for a in angles]
        score = np.empty(len(angles))
        for i, T_ in enumerate(starts):
            X = _transform(T_[:3, :3].copy(), T_[:3, 3].copy(), P)
            d = _query(tree, X)[2]
            score[i] = np.mean(np.minimum(d * d, trunc * trunc))
        # Local minima of the scan that place clearly more of the points on the
        # CAD than the fit does (the fit's neighbours are its own minimum).
        here = k
        minima = (score[1:-1] <= score[:-2]) & (score[1:-1] <= score[2:])
        found += [
            (float(score[i + 1]), line, starts[i + 1], float(angles[i + 1]))
            for i in range(len(minima))
            if minima[i] and abs(i + 1 - here) > 1 and score[i + 1] < _ESCAPE_GAIN * score[here]
        ]
    better = sorted(found, key=lambda f: (f[0], f[1], f[3]))[:_ESCAPE_STARTS]
    if not better:
        return fit

    tau2 = (_INLIER_SIGMAS * fit.scale_mm) ** 2

    def misfit(reg: Registration) -> float:
        r = reg.residuals
        return float(np.mean(np.minimum(r * r, tau2)))

    first = misfit(fit)
    best, best_cost = fit, _ESCAPE_GAIN * first
    turned = 0.0
    for _, _, T_start, angle in better:
        try:
            other = refit(T_start)
        except InsufficientOverlap:
            continue
        cost = misfit(other)
        log.debug(
            "escape: %.1f deg about %s, misfit %.4g against the first fit's %.4g",
            np.degrees(angle),
            np.round(axis, 3),
            cost,
            first,
        )
        if cost < best_cost:
            best, best_cost = other, cost
            turned = float(np.degrees(angle))
            if not other.degenerate:
                break
    if best is not fit:
        log.info(
            "register: the fit turned %.1f deg about %s fits better (misfit %.4g, was %.4g)",
            turned,
            np.round(axis, 3),
            best_cost,
            first,
        )
    return best


def register(
    tree: ClosestPointQuery,
    points: Points,
    *,
    init: Transform | None = None,
    loss: str = "tukey",
    weights: Scalars | None = None,
    max_iterations: int = 80,
    seed: int = 0,
    initial_subset: int = 512,
    max_subset: int | None = 16384,
    max_distance_mm: float = 50.0,
    min_points: int = 30,
    min_scale_mm: float = 1e-3,
    tolerance_rad: float = 1e-6,
    tolerance_mm: float = 2e-4,
    max_rejections: int = 10,
    subset_tolerance_factor: float = 10.0,
    residual: str = "distance",
    max_extensions: int = 6,
    subset_growth: int = 8,
    graduated: bool = True,
    uncertainty_mm: float | None = 2.5e-3,
    view_direction: Vectors | None = None,
    escape_deg: float | None = 30.0,
) -> Registration:
    """Fit measured points to the CAD with robust point-to-surface ICP.

    Parameters
    ----------
    tree : ClosestPointQuery
        The CAD's closest-point structure (``GridTree``), CAD frame, mm.
    points : (N, 3) float64, mm, data frame
        Measured points (e.g. the reconstructed cloud in the rig frame).
    init : (4, 4) float64, optional
        Initial ``T_cad_data``; identity when omitted.
    loss : {"tukey", "welsch", "cauchy", "huber", "l2"}
        M-estimator of the residuals. The redescending ones (tukey, welsch,
        cauchy) ignore gross outliers such as reflection blobs.
    weights : (N,) float64, optional
        Per-point input weights >= 0 (reconstruction quality); 1 when omitted.
    max_iterations : int
    seed : int
        Seeds the random subsets; the same seed and input give the same result
        bit for bit.
    initial_subset, max_subset : int
        Points in the first subset, and in the last one (None: all points).
        Each subset is a prefix of the next (a seeded permutation), grown
        ``subset_growth`` times once the pose has converged on the current
        one. The pose is the optimum of the last subset: with 0.02 mm noise
        16384 points put a well-constrained part to about 1-2 um; more points
        are slower and only help weakly constrained parts.
    max_distance_mm : float
        Points farther than this from the CAD when first seen (at the pose of
        their first query) are left out (background, far outliers).
    min_points : int
        At least this many points must lie within ``max_distance_mm`` of the
        CAD at the start and be inliers (of the last subset) at the end.
    min_scale_mm : float
        Floor of the robust scale (keeps the weights finite on perfect data).
    tolerance_rad, tolerance_mm : float
        Convergence: a step on the last subset below both ends the fit (the
        step is then below what the data resolve, and is not taken).
    max_rejections : int
        Trust-region retries per iteration before giving up.
    subset_tolerance_factor : float
        The tolerances are this much looser on the smaller subsets: the first
        step on the next, larger one finishes the job.
    residual : {"distance", "plane"}
        ``"distance"``: the signed distance to the CAD, whose gradient is the
        face normal on a face and points to the edge or corner beyond it (so
        points overhanging an edge pull the part back); ``"plane"``: the
        classic point-to-plane residual to the closest face's plane.
    max_extensions : int
        When consecutive steps keep the same direction (sliding along a weakly
        constrained direction), up to this many doublings of the step are
        tried; each is kept only if it lowers the cost.
    subset_growth : int
        Factor by which the subset grows once the pose has converged on it.
    uncertainty_mm : float or None
        Once the pose has converged on ``max_subset`` points, when the noise
        leaves it uncertain by more than this (RMS displacement of the points,
        ``sigma sqrt(trace(H^-1) / n)`` from the normal matrix ``H``), the
        fit continues on every point. A part seen from one side whose
        in-plane position rests on a few edges needs them all; a well
        constrained one does not. None: never.
    view_direction : (3,) float64, optional
        Direction from the part towards the sensor, data frame (e.g. +z of a
        rig looking down). When given, a point whose closest CAD face is
        turned away from it by more than 120 degrees counts as an outlier: a
        sensor cannot see such a face, and a plate tilted through its own
        thickness would otherwise fit half its points to its bottom. Needs
        ``loss`` tukey or welsch (a loss with a plateau for such points).
        Should no step lower the cost under that rule (points crossing onto
        back faces jump to the plateau), or only heavily damped ones when the
        pose settles, the fit goes on without it.
    graduated : bool
        Start with a wide robust scale and narrow it as the pose settles
        (graduated non-convexity), so that points misfit by the start offset,
        such as those overhanging the part's outline, pull the part into
        place before the scale narrows to the noise. Without it the scale is
        the residuals' MAD from the start.
    escape_deg : float or None
        When the fit ends with a rotation its points do not constrain (a
        disc whose turn rests on a ring of holes, started further off than
        the holes are wide), rotations about that axis within this many
        degrees are scanned, and the most promising are fitted again; a fit
        that leaves clearly fewer points misfit replaces the first one (see
        the module notes). None: never.

    Returns
    -------
    Registration

    Raises
    ------
    InvalidInput
        Bad shapes, non-finite values, an unknown loss, a non-rigid ``init``,
        negative weights, bad parameters.
    InsufficientOverlap
        Fewer than ``min_points`` points near the CAD at the start, or fewer
        than ``min_points`` inliers at the end.
    """
    # Every argument, for the fits from other starts that an escape runs.
    arguments = dict(locals())
    if not hasattr(tree, "query"):
        raise InvalidInput("tree must answer closest-point queries (have a .query(points) method)")
    if escape_deg is not None and not (
        isinstance(escape_deg, numbers.Real)
        and not isinstance(escape_deg, (bool, np.bool_))
        and 0 < escape_deg <= 180
    ):
        raise InvalidInput(f"escape_deg must be a number in (0, 180] or None, got {escape_deg!r}")
    if residual not in ("distance", "plane"):
        raise InvalidInput(f"residual must be 'distance' or 'plane', got {residual!r}")
    if loss not in LOSSES:
        raise InvalidInput(f"unknown loss {loss!r}; expected one of {', '.join(LOSSES)}")
    if max_iterations < 1:
        raise InvalidInput(f"max_iterations must be >= 1, got {max_iterations}")
    if initial_subset < 6:
        raise InvalidInput(f"initial_subset must be >= 6, got {initial_subset}")
    if max_subset is not None and max_subset < initial_subset:
        raise InvalidInput(
            f"max_subset ({max_subset}) must be >= initial_subset ({initial_subset})"
        )
    if uncertainty_mm is not None and not (np.isfinite(uncertainty_mm) and uncertainty_mm > 0):
        raise InvalidInput(
            f"uncertainty_mm must be a finite positive number, got {uncertainty_mm!r}"
        )
    if subset_growth < 2:
        raise InvalidInput(f"subset_growth must be >= 2, got {subset_growth}")
    for nm, val in (("max_distance_mm", max_distance_mm), ("min_scale_mm", min_scale_mm)):
        if not np.isfinite(val) or val <= 0:
            raise InvalidInput(f"{nm} must be a finite positive number, got {val!r}")
    min_points = max(int(min_points), 6)
    P_in = validate_points(points, min_points=min_points)
    n_all = len(P_in)
    T = np.eye(4) if init is None else validate_transform(init)
    if weights is None:
        v_in = np.ones(n_all)
    else:
        v_in = np.asarray(weights, dtype=np.float64)
        if v_in.shape != (n_all,):
            raise InvalidInput(f"weights must have shape ({n_all},), got {v_in.shape}")
        if not np.isfinite(v_in).all() or (v_in < 0).any():
            raise InvalidInput("weights must be finite and >= 0")
        if not (v_in > 0).any():
            raise InvalidInput("all weights are zero")
    loss_id, c = LOSSES[loss]
    view = validate_view(view_direction, loss)

    # A seeded permutation: every subset is a prefix of the next one.
    cap = n_all if max_subset is None else min(n_all, int(max_subset))
    perm = _partial_shuffle(n_all, cap, np.uint64(seed % (1 << 63)))
    # Only the points the fit can use are gathered now; the rest, if ever
    # needed, when the per-point figures are first asked for.
    # (np.take gathers rows several times faster than fancy indexing.)
    P = np.take(P_in, perm[:cap], axis=0)
    V = np.take(v_in, perm)  # becomes 0 for points gated out as far
    m = min(initial_subset, cap)

    # Before any query: a cloud that lies, at the initial pose, far outside
    # the CAD's bounding box cannot fit (and far queries are the slow ones).
    bounds = getattr(tree, "bounds", None)
    if bounds is not None:
        b = np.asarray(bounds, dtype=np.float64)
        if b.shape == (2, 3) and np.isfinite(b).all():
            k0 = min(cap, 1024)
            X0 = _transform(T[:3, :3].copy(), T[:3, 3].copy(), P[:k0])
            gap = np.linalg.norm(np.maximum(np.maximum(b[0] - X0, X0 - b[1]), 0.0), axis=1)
            inside = int(np.sum((gap <= max_distance_mm) & (V[:k0] > 0)))
            if inside < min(min_points, k0) or inside < 0.05 * k0:
                raise InsufficientOverlap(
                    f"only {inside} of {k0} sampled points lie within {max_distance_mm} mm "
                    "of the CAD's bounding box at the initial pose"
                )

    def evaluate(T_: Transform, lo: int, hi: int) -> tuple[np.ndarray, ...]:
        """Points at pose T_, their residual gradients, residuals, signed
        distances, closest face normals and closest faces (fresh queries)."""
        P_ = P[lo:hi] if hi <= cap else np.take(P_in, perm[lo:hi], axis=0)
        X_ = _transform(T_[:3, :3].copy(), T_[:3, 3].copy(), P_)
        Q_, N_, d_, f_ = _query(tree, X_)
        if residual == "distance":
            r_, U_ = _distance_residuals(X_, Q_, N_, d_)
            return X_, U_, r_, d_, N_, f_
        return X_, N_, _residuals(X_, Q_, N_), d_, N_, f_

    def seen(r_: np.ndarray, Fn_: np.ndarray, T_: Transform) -> np.ndarray:
        """The residuals for the cost: a point whose closest face is turned
        away from the sensor (more than 120 degrees from ``view_direction``)
        cannot have been measured on it; it counts as an outlier (the loss's
        plateau, no pull) rather than pulling the part onto a back face."""
        if view is None or not view_active:
            return r_
        back = Fn_ @ (T_[:3, :3] @ view) < _BACK_FACE_COS
        if not back.any():
            return r_
        out = r_.copy()
        out[back] = _FAR_MM
        return out

    # Small steps are evaluated against each point's last closest face
    # instead of a fresh query (see the module notes): possible when the tree
    # exposes its triangles.
    geometry = _tree_geometry(tree)

    X, Nrm, r, d, Fn, Fi = evaluate(T, 0, m)

    def trial(T_: Transform, step_mm: float) -> tuple[Any, ...]:
        """Points, residual gradients and residuals of the first m points at a
        trial pose T_, reached from the current one by a step moving the
        points by ``step_mm`` (RMS), and the faces they refer to. Past the
        coarse stage a small step keeps each point's closest face (an upper
        bound of the true cost, no query); otherwise a fresh query. (Allowing it
        in the coarse stage too saved ~6 % of the queries on some clouds and
        cost accuracy on one tray cloud, 2.5 -> 5.5 um.)"""
        if geometry is not None and gnc == 0.0 and m > initial_subset:
            if step_mm < _FIXED_FACE_STEP_MM:
                X_ = _transform(T_[:3, :3].copy(), T_[:3, 3].copy(), P[:m])
                r_, U_, again = _face_residuals(X_, Fi, *geometry, r, residual == "distance")
                idx = np.flatnonzero(again)
                if len(idx) == 0:
                    return X_, U_, r_, (Fn, Fi)
                # The few points near an edge, or that crossed their face's
                # plane, get a fresh query.
                Xi = np.ascontiguousarray(X_[idx])
                Q_, N_, d_, f_ = _query(tree, Xi)
                if residual == "distance":
                    ri, Ui = _distance_residuals(Xi, Q_, N_, d_)
                else:
                    ri, Ui = _residuals(Xi, Q_, N_), N_
                r_[idx] = ri
                U_[idx] = Ui
                Fn_, Fi_ = Fn.copy(), Fi.copy()
                Fn_[idx] = N_
                Fi_[idx] = f_
                return X_, U_, r_, (Fn_, Fi_)
        X_, U_, r_, _, Fn_, Fi_ = evaluate(T_, 0, m)
        return X_, U_, r_, (Fn_, Fi_)

    V[:m] *= np.abs(d) <= max_distance_mm
    near = int((V[:m] > 0).sum())
    if near < min(min_points, m) or near < 0.05 * m:
        raise InsufficientOverlap(
            f"only {near} of {m} sampled points lie within {max_distance_mm} mm of the CAD "
            "at the initial pose"
        )

    # Graduated scale: wide enough at first that nearly every point near the
    # CAD pulls (the residuals of a misplaced part are misfit, not outliers),
    # then narrowed whenever the pose settles at it, down to the MAD.
    gnc = 0.0
    if graduated and loss != "l2":
        a0 = np.abs(r[V[:m] > 0])
        gnc = float(np.quantile(a0, _GNC_QUANTILE)) if len(a0) else 0.0
    sigma = np.inf
    lam = 1e-4
    mad = -1.0  # robust scale of the current residuals; < 0 when stale
    debug = log.isEnabledFor(logging.DEBUG)
    view_active = view is not None
    prev_delta = np.zeros(6)
    extended = 0
    history: list[tuple[float, float]] = []
    sizes: list[int] = []
    accepted = rejected = 0
    stop = StopReason.MAX_ITERATIONS
    iterations = 0
    H = np.zeros((6, 6))
    H_pose_current = False
    for _ in range(max_iterations):
        iterations += 1
        v = V[:m]
        if mad < 0.0:  # the residuals changed since the last estimate
            mad = _robust_scale(r, v, min_scale_mm)
        if gnc <= mad:
            gnc = 0.0
        # The scale never grows: with sigma^2 rho(r/sigma) non-decreasing in
        # sigma, a smaller scale cannot raise the cost of the accepted pose.
        sigma = min(sigma, max(mad, gnc))
        center, L = _weighted_centroid(X, v)
        L = max(L, 1.0)
        e0, H, g = _cost_normal_equations(X, Nrm, seen(r, Fn, T), v, sigma, loss_id, c, center, L)
        H_pose_current = True
        # On a smaller subset, or at a scale still graduating, the pose need
        # only settle to what that stage resolves.
        if gnc > 0.0:
            tol_rad, tol_mm = np.inf, _GNC_STEP * gnc
        else:
            # A step well below the pose's statistical uncertainty on these
            # points (noise x sqrt(trace H^-1 / n), the RMS displacement it
            # causes) changes nothing that matters: up to 10 times the given
            # tolerances, a quarter of that uncertainty ends the stage.
            f = subset_tolerance_factor if m < cap else 1.0
            f = max(f, min(10.0, 0.25 * _uncertainty(H, sigma, v) / tolerance_mm))
            tol_rad, tol_mm = f * tolerance_rad, f * tolerance_mm
        step_ok = False
        tiny = False
        small = False
        delta = np.zeros(6)
        e1 = e0
        for _trial in range(max_rejections + 1):
            # Predicted reduction of the quadratic IRLS model (a lower bound of
            # the true reduction where the linearisation holds).
            delta, pred, ok = _lm_step(H, g, lam)
            if not ok:
                lam *= 4.0
                rejected += 1
                continue
            omega, t = delta[:3] / L, delta[3:]
            if gnc > 0.0:
                # Graduating: the RMS displacement of the points by the step.
                small = float(np.sqrt(delta @ delta)) < tol_mm
            else:
                small = float(np.sqrt(omega @ omega)) < tol_rad and float(np.sqrt(t @ t)) < tol_mm
            if pred <= 1e-15 * max(e0, 1e-300) or (small and lam <= 1e-3):
                tiny = True
                break
            T1 = _compose(T, omega, t, center)
            X1, N1, r1, F1 = trial(T1, float(np.sqrt(delta @ delta)))
            e1 = _cost(seen(r1, F1[0], T1), v, sigma, loss_id, c)
            if e1 < e0:
                # Gain ratio rho = actual / predicted (Madsen et al. eq. 3.14):
                # a good model lets the region grow, a poor one shrinks it.
                ratio = (e0 - e1) / pred
                if ratio > 0.75:
                    lam = max(lam / 3.0, 1e-9)
                elif ratio < 0.25:
                    lam *= 2.0
                T0 = T
                T, X, Nrm, r = T1, X1, N1, r1
                Fn, Fi = F1
                H_pose_current = False
                # Sliding along a weakly constrained direction: Gauss-Newton
                # overestimates the curvature there (a point overhanging an
                # edge by less than the noise pulls less than its linearised
                # residual says), so steps repeat in the same direction, each
                # a fraction q of the last: linear convergence. The rest of
                # that geometric series is q / (1 - q) of this step (Aitken's
                # extrapolation); then doublings. Each longer step is kept
                # only if the cost falls.
                dn = float(np.sqrt(delta @ delta))
                pn = float(np.sqrt(prev_delta @ prev_delta))
                if dn > 0.0 and pn > 0.0 and delta @ prev_delta > 0.8 * dn * pn:
                    q = min(float(delta @ prev_delta) / (pn * pn), 0.95)
                    factors = [1.0 / (1.0 - q)] if q < 0.5 * (1.0 + 1.0 / 1.5) else []
                    factors = [f for f in factors if f >= 1.5]
                    scale = 1.0
                    for f in factors + [2.0] * max_extensions:
                        s_ = scale * f
                        Ts = _compose(T0, s_ * omega, s_ * t, center)
                        Xs, Ns, rs, Fs = trial(Ts, s_ * dn)
                        es = _cost(seen(rs, Fs[0], Ts), v, sigma, loss_id, c)
                        if not es < e1:
                            if scale == 1.0 and f != 2.0:
                                continue  # the extrapolation overshot: try doublings
                            break
                        scale = s_
                        T, X, Nrm, r, e1 = Ts, Xs, Ns, rs, es
                        Fn, Fi = Fs
                    delta = scale * delta
                    extended += scale > 1.0
                prev_delta = delta
                mad = -1.0
                accepted += 1
                step_ok = True
                break
            lam *= 4.0
            rejected += 1
            e1 = e0
        history.append((e0, e1))
        sizes.append(m)
        if debug:
            log.debug(
                "iteration %d: m %d sigma %.4g gnc %.4g cost %.6g -> %.6g lambda %.2g "
                "accepted %s step %.3g",
                *(iterations, m, sigma, gnc, e0, e1, lam, step_ok, float(np.linalg.norm(delta))),
            )
        # A short step says the pose has settled only if it was not damped.
        settled = tiny or (step_ok and small and lam <= 1e-3) or not step_ok
        if gnc > 0.0 and step_ok and e0 - e1 < _GNC_GAIN * e0:
            # Sliding along a weakly constrained direction converges
            # linearly: short steps do not mean the pose has settled at this
            # scale, a cost that no longer falls does.
            settled = True
        if (
            gnc == 0.0
            and m < cap
            and step_ok
            and e0 - e1 < _SUBSET_GAIN * sigma * sigma / max(float(v.sum()), 1.0)
        ):
            settled = True
        if not settled:
            continue
        if view_active and ((not step_ok and not tiny) or lam > _VIEW_STUCK_LAMBDA):
            # No step lowers the cost with back faces ruled out, or only
            # crawling ones do: points that would cross onto one jump to the
            # loss's plateau, which can block every step (a part far off in
            # its plane). Go on without the rule; it only ever lowers the
            # cost (a plateau is the most a point can cost), so the cost
            # still never rises.
            view_active = False
            lam = 1e-4
            continue
        if gnc > 0.0:
            # Settled at this scale: narrow it.
            gnc = gnc / _GNC_FACTOR
            continue
        # A scale still shrinking re-weights the points and moves the optimum:
        # the pose has settled only once the scale has too.
        if step_ok:
            mad = _robust_scale(r, v, min_scale_mm)
            if mad < 0.9 * sigma:
                continue
        if (
            m == cap < n_all
            and uncertainty_mm is not None
            and _uncertainty(H, sigma, v) > uncertainty_mm
        ):
            # A weakly constrained pose: these points do not pin it down to
            # the uncertainty asked for, so the fit goes on with all of them.
            cap = n_all
            P = np.concatenate([P, np.take(P_in, perm[m:], axis=0)])
        if m < cap:
            # Only the new points are queried, at the current pose.
            m2 = min(cap, subset_growth * m)
            X2, N2, r2, d2, Fn2, Fi2 = evaluate(T, m, m2)
            V[m:m2] *= np.abs(d2) <= max_distance_mm
            X = np.concatenate([X, X2])
            Nrm = np.concatenate([Nrm, N2])
            r = np.concatenate([r, r2])
            Fn = np.concatenate([Fn, Fn2])
            Fi = np.concatenate([Fi, Fi2])
            m = m2
            mad = -1.0
            # A new cost on more points: the trust region starts afresh, and
            # the scale is estimated afresh on them (the smallest of many
            # noisy estimates on few points would be biased low).
            lam = 1e-4
            sigma = np.inf
            H_pose_current = False
            continue
        stop = StopReason.CONVERGED if (tiny or step_ok) else StopReason.NO_PROGRESS
        break

    v = V[:m]
    # The final scale, from every point of the last subset: the weights of
    # all points use it, and any prefix of a few thousand would make them
    # depend, by a few per cent, on which points the subset drew.
    sigma = _robust_scale(r, v, min_scale_mm, m)
    inl = (v > 0) & (np.abs(r) <= _INLIER_SIGMAS * sigma)
    n_inl = int(inl.sum())
    if n_inl < min(min_points, m):
        raise InsufficientOverlap(f"only {n_inl} of {m} points fit the CAD after registration")
    if not H_pose_current:
        # The last normal matrix was built at another pose or on fewer points.
        center, L = _weighted_centroid(X, v)
        L = max(L, 1.0)
        _, H, _ = _cost_normal_equations(X, Nrm, seen(r, Fn, T), v, sigma, loss_id, c, center, L)
    eig, vec = np.linalg.eigh(H)
    eig = np.maximum(eig, 0.0)
    free = eig < _DEGENERATE_REL_EIG * max(float(eig[-1]), 1e-300)
    degenerate = vec[:, free].T.copy()
    # Gauss-Newton's covariance of the twist: sigma^2 (sum w J J^T)^-1, and H
    # is that sum divided by the weight total.
    vs = max(float(np.sum(v[v > 0])), 1e-300)
    inv_eig = np.where(free, 0.0, 1.0 / np.where(free, 1.0, eig))
    covariance = (vec * inv_eig) @ vec.T * (float(sigma) ** 2 / vs)

    T = _orthonormalised(T)
    T_final = T

    # The points the fit did not use are queried later, when a per-point
    # figure is first asked for: keep a copy, the caller may reuse its array.
    P_keep = P_in.copy() if m < n_all else P_in[:0]

    def evaluate_rest(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        X_ = _transform(
            T_final[:3, :3].copy(), T_final[:3, 3].copy(), np.take(P_keep, perm[lo:hi], axis=0)
        )
        Q_, N_, d_, _ = _query(tree, X_)
        if residual == "distance":
            r_, _ = _distance_residuals(X_, Q_, N_, d_)
        else:
            r_ = _residuals(X_, Q_, N_)
        return r_, d_

    converged = stop is StopReason.CONVERGED
    log.debug(
        "register: %s after %d iterations (%d accepted, %d rejected, %d extended) on %d points",
        stop.value,
        iterations,
        accepted,
        rejected,
        extended,
        m,
    )
    result = Registration(
        transform=T,
        iterations=iterations,
        converged=converged,
        stop_reason=stop,
        scale_mm=float(sigma),
        cost_history=np.asarray(history, dtype=np.float64).reshape(-1, 2),
        subset_sizes=np.asarray(sizes, dtype=np.int64),
        observability=eig,
        degenerate_directions=degenerate,
        pose_center=np.asarray(center, dtype=np.float64).copy(),
        pose_radius_mm=float(L),
        pose_covariance=covariance,
        loss=loss,
        accepted_steps=accepted,
        rejected_steps=rejected,
        full_pass=_FullPass(
            evaluate_rest, r.copy(), V.copy(), perm, max_distance_mm, float(sigma), loss_id, c
        ),
    )
    if escape_deg is None:
        return result
    misfit = 1.0 - n_inl / max(int(np.sum(v > 0)), 1)
    if not (len(degenerate) or misfit > _ESCAPE_MISFIT):
        return result

    def refit(T_start: Transform) -> Registration:
        return register(**{**arguments, "init": T_start, "escape_deg": None})

    # Every point, not only those that fit here: those would fit here best.
    scan = P[: min(cap, _ESCAPE_POINTS)][V[: min(cap, _ESCAPE_POINTS)] > 0]
    return _escape(
        tree, scan, result, H, center, L, np.radians(escape_deg), refit, misfit > _ESCAPE_MISFIT
    )
