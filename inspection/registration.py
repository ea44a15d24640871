"""Robust fine registration of a measured cloud to the CAD: IRLS point-to-surface ICP.

The fit finds ``T_cad_data``, the rigid transform that maps the measured
points (data frame, e.g. the rig) into the CAD frame, by minimising a robust
cost of the residuals ``r_i(T)``: by default the signed distance of ``T p_i``
to the CAD surface, whose gradient is the face normal ``n_i`` where the
closest point ``q_i`` lies inside a face (there it equals the point-to-plane
residual ``n_i . (T p_i - q_i)``) and points towards the edge or corner
beyond it otherwise, so that points overhanging a border pull the part back
(``residual="plane"`` gives the classic point-to-plane ICP). Closest points
come from the CAD tree, re-queried at every pose. The cost is

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
permutation, each subset a prefix of the next, as in the published system):
early iterations use a few hundred points, doubling up to ``max_subset``;
once the pose and the scale have settled there, the last one or two
iterations use every point (bringing in the full data's statistics and
giving per-point weights, the RMS and the inlier fraction). When steps keep
the same direction (sliding along a weakly constrained direction), longer
steps along it are tried and kept only if they lower the cost. The scale
shrinks no faster than the pose settles (it stays above the last step's
motion), so that points misfit by that much are not yet taken for outliers.

The cost only ever falls within an iteration (a step is accepted only if it
lowers the cost). Across iterations it falls too while the subset stays the
same: the scale ``sigma`` never grows from one iteration to the next, and
``sigma^2 rho(r / sigma)`` does not decrease with ``sigma`` for any loss
here, so a smaller scale cannot raise the cost. When the subset grows the
mean is taken over more points and the cost is re-based; ``cost_history``
keeps, per iteration, the cost before and after its step so that both
properties can be checked.

Determinism: the subsets come from a seeded generator, every reduction runs
in a fixed order in single-threaded numba kernels (no parallel reductions,
no BLAS on the hot path), so the same input gives a bit-identical transform.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numba
import numpy as np

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
_SCALE_SAMPLE = 8192
# MAD to standard deviation for Gaussian noise.
_MAD_TO_SIGMA = 1.482602218505602
# Relative eigenvalue of the normalised normal matrix below which a direction
# of motion counts as unconstrained by the data.
_DEGENERATE_REL_EIG = 1e-3


@dataclass(frozen=True, eq=False)
class Registration:
    """The result of a fit of measured points to the CAD.

    Attributes
    ----------
    transform : (4, 4) float64
        ``T_cad_data``: maps data-frame points into the CAD frame (mm).
    rms_mm : float
        Root mean square of the point-to-plane residuals of the inliers, mm.
    inlier_fraction : float
        Fraction of all points with ``|r| <= 3 scale_mm`` (and a non-zero
        input weight).
    iterations : int
        Iterations run (each one an accepted step or the last attempt).
    converged : bool
    stop_reason : StopReason
    weights : (N,) float64
        Final robust weight of each input point (input weight x IRLS weight,
        in [0, 1] x input weight), in the order of the input points.
    residuals : (N,) float64, mm
        Final point-to-plane residual of each input point.
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
    loss : str
    accepted_steps : int
    rejected_steps : int
    """

    transform: Transform
    rms_mm: float
    inlier_fraction: float
    iterations: int
    converged: bool
    stop_reason: StopReason
    weights: Scalars
    residuals: Scalars
    scale_mm: float
    cost_history: np.ndarray
    subset_sizes: np.ndarray
    observability: np.ndarray
    degenerate_directions: np.ndarray
    loss: str
    accepted_steps: int
    rejected_steps: int

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
def _normal_equations(
    X: np.ndarray,
    N: np.ndarray,
    r: np.ndarray,
    v: np.ndarray,
    sigma: float,
    loss: int,
    c: float,
    center: np.ndarray,
    L: float,
) -> tuple[np.ndarray, np.ndarray, float]:
    """IRLS point-to-plane normal equations, normalised by the input weight sum.

    Row i of the Jacobian is ``J_i = [((x_i - center) x n_i) / L, n_i]`` for
    the twist ``(omega L, t)``; ``H = sum w J^T J``, ``g = sum w r J``.
    Returns H (6, 6), g (6,) and the sum of IRLS weights (normalised).
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
    ws = 0.0
    for i in range(X.shape[0]):
        vi = v[i]
        if vi <= 0.0:
            continue
        vs += vi
        _, w = _rho_weight(r[i], sigma, loss, c)
        w *= vi
        if w <= 0.0:
            continue
        ws += w
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
        ws /= vs
    return H, g, ws


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


def _query(tree: ClosestPointQuery, X: Points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    return Q, N, d


def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _rodrigues(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``omega`` (rad)."""
    theta = float(np.sqrt(omega @ omega))
    if theta < 1e-12:
        return np.eye(3) + _skew(omega)
    K = _skew(omega / theta)
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def _compose(T: Transform, omega: np.ndarray, t: np.ndarray, center: np.ndarray) -> Transform:
    """``x' = R(omega) (x - center) + center + t`` applied after ``T``."""
    R = _rodrigues(omega)
    out = np.eye(4)
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = R @ (T[:3, 3] - center) + center + t
    # Keep the rotation orthonormal to the last bit over many compositions.
    U, _, Vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = U @ Vt
    return out


def _robust_scale(r: np.ndarray, v: np.ndarray, floor: float) -> float:
    # The points are in random order: a prefix is a random sample, and a few
    # thousand residuals give the median to ~1 %.
    k = min(len(r), _SCALE_SAMPLE)
    a = np.abs(r[:k][v[:k] > 0.0])
    if len(a) == 0:
        return floor
    return max(_MAD_TO_SIGMA * float(np.median(a)), floor)


def register(
    tree: ClosestPointQuery,
    points: Points,
    *,
    init: Transform | None = None,
    loss: str = "tukey",
    weights: Scalars | None = None,
    max_iterations: int = 60,
    seed: int = 0,
    initial_subset: int = 512,
    max_subset: int | None = 8192,
    max_distance_mm: float = 50.0,
    min_points: int = 30,
    min_scale_mm: float = 1e-3,
    tolerance_rad: float = 1e-5,
    tolerance_mm: float = 2e-3,
    max_rejections: int = 10,
    subset_tolerance_factor: float = 10.0,
    residual: str = "distance",
    max_extensions: int = 6,
) -> Registration:
    """Fit measured points to the CAD with robust point-to-plane ICP.

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
        Points in the first iteration's subset, doubled each iteration up to
        ``max_subset`` (None: all points). Once the pose has settled on the
        largest subset, the last iterations use every point.
    max_distance_mm : float
        Points farther than this from the CAD when first seen (at the pose of
        their first query) are left out (background, far outliers).
    min_points : int
        At least this many points must lie within ``max_distance_mm`` of the
        CAD at the start and be inliers at the end.
    min_scale_mm : float
        Floor of the robust scale (keeps the weights finite on perfect data).
    tolerance_rad, tolerance_mm : float
        Convergence: an accepted step on the full-size subset below both.
    max_rejections : int
        Trust-region retries per iteration before giving up.
    subset_tolerance_factor : float
        The tolerances are this much looser while working on a subset: the
        last steps on every point finish the job.
    residual : {"distance", "plane"}
        ``"distance"``: the signed distance to the CAD, whose gradient is the
        face normal on a face and points to the edge or corner beyond it (so
        points overhanging an edge pull the part back); ``"plane"``: the
        classic point-to-plane residual to the closest face's plane.
    max_extensions : int
        When consecutive steps keep the same direction (sliding along a weakly
        constrained direction), up to this many doublings of the step are
        tried; each is kept only if it lowers the cost.

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
    if not hasattr(tree, "query"):
        raise InvalidInput("tree must answer closest-point queries (have a .query(points) method)")
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

    # A seeded permutation: every subset is a prefix of the next one.
    perm = np.random.default_rng(seed).permutation(n_all)
    P = np.ascontiguousarray(P_in[perm])
    V = np.ascontiguousarray(v_in[perm])  # becomes 0 for points gated out as far
    cap = n_all if max_subset is None else min(n_all, int(max_subset))
    m = min(initial_subset, cap)

    # Before any query: a cloud that lies, at the initial pose, far outside
    # the CAD's bounding box cannot fit (and far queries are the slow ones).
    bounds = getattr(tree, "bounds", None)
    if bounds is not None:
        b = np.asarray(bounds, dtype=np.float64)
        if b.shape == (2, 3) and np.isfinite(b).all():
            k0 = min(n_all, 4096)
            X0 = _transform(T[:3, :3].copy(), T[:3, 3].copy(), P[:k0])
            gap = np.linalg.norm(np.maximum(np.maximum(b[0] - X0, X0 - b[1]), 0.0), axis=1)
            inside = int(np.sum((gap <= max_distance_mm) & (V[:k0] > 0)))
            if inside < min(min_points, k0) or inside < 0.05 * k0:
                raise InsufficientOverlap(
                    f"only {inside} of {k0} sampled points lie within {max_distance_mm} mm "
                    "of the CAD's bounding box at the initial pose"
                )

    def evaluate(
        T_: Transform, lo: int, hi: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        X_ = _transform(T_[:3, :3].copy(), T_[:3, 3].copy(), P[lo:hi])
        Q_, N_, d_ = _query(tree, X_)
        if residual == "distance":
            r_, U_ = _distance_residuals(X_, Q_, N_, d_)
            return X_, U_, r_, d_
        return X_, N_, _residuals(X_, Q_, N_), d_

    X, Nrm, r, d = evaluate(T, 0, m)
    V[:m] *= np.abs(d) <= max_distance_mm
    near = int((V[:m] > 0).sum())
    if near < min(min_points, m) or near < 0.05 * m:
        raise InsufficientOverlap(
            f"only {near} of {m} sampled points lie within {max_distance_mm} mm of the CAD "
            "at the initial pose"
        )

    sigma = np.inf
    motion = 0.0
    lam = 1e-4
    prev_delta = np.zeros(6)
    extended = 0
    history: list[tuple[float, float]] = []
    sizes: list[int] = []
    accepted = rejected = 0
    stop = StopReason.MAX_ITERATIONS
    iterations = 0
    for _ in range(max_iterations):
        iterations += 1
        v = V[:m]
        # The scale never grows: with sigma^2 rho(r/sigma) non-decreasing in
        # sigma, a smaller scale cannot raise the cost of the accepted pose.
        # It shrinks no faster than the pose settles: while the last step
        # still moved the points by `motion` mm, residuals of that size may be
        # misfit rather than outliers (KISS-ICP's adaptive threshold follows
        # the same idea), so they keep their weight and pull along weakly
        # constrained directions instead of being ignored.
        sigma = min(sigma, max(_robust_scale(r, v, min_scale_mm), motion))
        e0 = _cost(r, v, sigma, loss_id, c)
        center, L = _weighted_centroid(X, v)
        L = max(L, 1.0)
        H, g, _ = _normal_equations(X, Nrm, r, v, sigma, loss_id, c, center, L)
        # Marquardt's scaling plus a small isotropic term so that directions
        # the data do not constrain (diag(H) ~ 0) get no step at all.
        D = np.diag(np.diag(H) + 1e-9 * max(np.trace(H), 1e-300))
        step_ok = False
        tiny = False
        small = False
        motion = 0.0
        delta = np.zeros(6)
        e1 = e0
        for _trial in range(max_rejections + 1):
            try:
                delta = np.linalg.solve(H + lam * D, -g)
            except np.linalg.LinAlgError:
                lam *= 4.0
                rejected += 1
                continue
            # Predicted reduction of the quadratic IRLS model (a lower bound of
            # the true reduction where the linearisation holds).
            pred = -(g @ delta + 0.5 * delta @ H @ delta)
            omega, t = delta[:3] / L, delta[3:]
            # On a subset the pose need only settle to what its points resolve.
            f = 1.0 if m == n_all else subset_tolerance_factor
            small = (
                float(np.linalg.norm(omega)) < f * tolerance_rad
                and float(np.linalg.norm(t)) < f * tolerance_mm
            )
            if pred <= 1e-15 * max(e0, 1e-300) or (small and lam <= 1e-3):
                tiny = True
                break
            T1 = _compose(T, omega, t, center)
            X1, N1, r1, _ = evaluate(T1, 0, m)
            e1 = _cost(r1, v, sigma, loss_id, c)
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
                # Sliding along a weakly constrained direction: the robust
                # weights keep each step about one inlier band long, so steps
                # repeat in the same direction. Then try longer steps along
                # it (2, 4, 8... times), keeping each only if the cost falls.
                dn = float(np.sqrt(delta @ delta))
                pn = float(np.sqrt(prev_delta @ prev_delta))
                if dn > 0.0 and pn > 0.0 and delta @ prev_delta > 0.9 * dn * pn and dn > 0.5 * pn:
                    scale = 1.0
                    for _ext in range(max_extensions):
                        Ts = _compose(T0, 2.0 * scale * omega, 2.0 * scale * t, center)
                        Xs, Ns, rs, _ = evaluate(Ts, 0, m)
                        es = _cost(rs, v, sigma, loss_id, c)
                        if not es < e1:
                            break
                        scale *= 2.0
                        T, X, Nrm, r, e1 = Ts, Xs, Ns, rs, es
                    delta = scale * delta
                    extended += scale > 1.0
                prev_delta = delta
                # RMS displacement of the points by this step, mm.
                motion = float(np.sqrt(delta @ delta))
                accepted += 1
                step_ok = True
                break
            lam *= 4.0
            rejected += 1
            e1 = e0
        history.append((e0, e1))
        sizes.append(m)
        log.debug(
            "iteration %d: m %d sigma %.4g cost %.6g -> %.6g lambda %.2g accepted %s step %.3g",
            *(iterations, m, sigma, e0, e1, lam, step_ok, float(np.linalg.norm(delta))),
        )
        if m == n_all:
            if tiny or (step_ok and small):
                stop = StopReason.CONVERGED
                break
            if not step_ok:
                stop = StopReason.NO_PROGRESS
                break
            continue
        # Subset phase: grow while the pose moves; once it has settled on the
        # largest subset, finish on every point (one or two cheap steps that
        # bring in the full data's statistics).
        # Settled on this subset only once the scale has settled too: a scale
        # still shrinking re-weights the points and moves the optimum.
        settled = (tiny or small) and (
            max(_robust_scale(r, V[:m], min_scale_mm), motion) >= 0.9 * sigma
        )
        if settled:
            m2 = n_all if m >= cap else cap
        elif tiny or small:
            continue
        elif not step_ok:
            # No lower cost on a small subset: more points smooth the cost.
            m2 = n_all if m >= cap else min(cap, 2 * m)
        elif m < cap:
            m2 = min(cap, 2 * m)
        else:
            continue
        # Only the new points are queried, at the current pose.
        X2, N2, r2, d2 = evaluate(T, m, m2)
        V[m:m2] *= np.abs(d2) <= max_distance_mm
        X = np.concatenate([X, X2])
        Nrm = np.concatenate([Nrm, N2])
        r = np.concatenate([r, r2])
        m = m2
        lam = max(lam, 1e-6)

    # Final evaluation on every point at the final pose.
    if m < n_all:
        X2, N2, r2, d2 = evaluate(T, m, n_all)
        V[m:] *= np.abs(d2) <= max_distance_mm
        X = np.concatenate([X, X2])
        Nrm = np.concatenate([Nrm, N2])
        r = np.concatenate([r, r2])
    sigma = min(sigma, _robust_scale(r, V, min_scale_mm))
    w = _irls_weights(r, V, sigma, loss_id, c)
    inl = (V > 0) & (np.abs(r) <= _INLIER_SIGMAS * sigma)
    n_inl = int(inl.sum())
    if n_inl < min_points:
        raise InsufficientOverlap(f"only {n_inl} of {n_all} points fit the CAD after registration")
    rms = float(np.sqrt(np.mean(r[inl] ** 2)))
    if not (stop is StopReason.CONVERGED and tiny and m == n_all):
        # The last normal matrix was built at another pose or on a subset.
        center, L = _weighted_centroid(X, V)
        L = max(L, 1.0)
        H, _, _ = _normal_equations(X, Nrm, r, V, sigma, loss_id, c, center, L)
    eig, vec = np.linalg.eigh(H)
    eig = np.maximum(eig, 0.0)
    degenerate = vec[:, eig < _DEGENERATE_REL_EIG * max(float(eig[-1]), 1e-300)].T.copy()

    weights_out = np.empty(n_all)
    weights_out[perm] = w
    resid_out = np.empty(n_all)
    resid_out[perm] = r
    converged = stop is StopReason.CONVERGED
    log.debug(
        "register: %s after %d iterations (%d accepted, %d rejected, %d extended), "
        "rms %.4f mm, inliers %.3f",
        stop.value,
        iterations,
        accepted,
        rejected,
        extended,
        rms,
        n_inl / n_all,
    )
    return Registration(
        transform=T,
        rms_mm=rms,
        inlier_fraction=n_inl / n_all,
        iterations=iterations,
        converged=converged,
        stop_reason=stop,
        weights=weights_out,
        residuals=resid_out,
        scale_mm=float(sigma),
        cost_history=np.asarray(history, dtype=np.float64).reshape(-1, 2),
        subset_sizes=np.asarray(sizes, dtype=np.int64),
        observability=eig,
        degenerate_directions=degenerate,
        loss=loss,
        accepted_steps=accepted,
        rejected_steps=rejected,
    )
