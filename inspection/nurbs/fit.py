"""Fitting a NURBS curve to points by orthogonal distance (degree and knots fixed).

The unknowns are the control points ``P`` (n, 3), the weights ``w`` (n,) and
one foot-point parameter ``t_i`` per data point ``x_i``; the cost is

    f = 1/2 sum_i |C(t_i) - x_i|^2 + lambda_s/2 |D2 P|^2 + lambda_w/2 |w - 1|^2,

with ``D2`` the second differences of the control points (a smoothness
penalty that keeps spans with few points tame) and the weights pulled
towards one (a NURBS curve does not change when all its weights are scaled
alike: without the penalty the normal equations are singular).

The residual ``r_i = C(t_i) - x_i`` depends on its own ``t_i`` alone, so the
Jacobian is ``[J_t | J_y]`` with ``J_t`` block diagonal (one 3 x 1 block
``C'(t_i)`` per point) and ``J_y`` dense in ``y = (P, w)``. The normal matrix
of a Gauss-Newton step is then

    [ D    B ]      D = diag(|C'(t_i)|^2)        (m x m, diagonal)
    [ B^T  E ]      B = J_t^T J_y,  E = J_y^T J_y + regularisation.

The methods (``method=``):

- ``"normal"``: Gauss-Newton on the normal equations, assembled from the
  dense Jacobian and solved as one ``(m + 4n)``-square system;
- ``"split"``: Gauss-Newton with the splitting of variables: the diagonal
  block is eliminated (the Schur complement ``E - B^T D^-1 B``, a 4n-square
  system), then ``dt = -D^-1 (g_t + B dy)``. Same steps, less work;
- ``"vp-gn"``: variable projection: the model is linear in ``P``, so for
  given ``(t, w)`` the best ``P`` is a linear least-squares solution, and
  the reduced cost ``phi(t, w) = min_P f`` is minimised by Gauss-Newton
  (Kaufman's approximation: the split step's ``(t, w)`` part at the optimal
  ``P``, after which ``P`` is solved for again);
- ``"vp-newton"``: variable projection with Newton's method on ``phi``: the
  exact Hessian of ``f`` (with the residuals' second derivatives) reduced
  over ``P`` by the same elimination.

The regularisation of the steps is Marquardt's: the system's diagonal is
scaled by ``1 + mu``, ``mu`` shrinking after an accepted step and growing
until the step lowers the cost (and, for Newton's indefinite Hessian, until
the damped matrix is positive definite). A step is accepted only if it lowers
the cost, with the parameters clipped to the domain and the weights positive;
a fit stops when the relative decrease of the cost falls below ``tolerance``
(converged), when no step lowers the cost at any damping (a stationary point,
also converged), or after ``max_iterations``. Near the minimum the foot
points and the control points slide along the curve together, a
reparametrisation that barely changes the curve's shape: fits take many
iterations to settle (``bench/bench_nurbs.py`` counts them).

The first and last points keep their parameters at the domain's ends:
otherwise the curve's ends can slide along their own tangents with the foot
points near them at almost no cost, a near-null direction of the normal
matrix.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import scipy.linalg

from ..errors import InvalidInput
from .basis import basis_table
from .curve import Curve
from .knots import FloatArray, check_degree, check_knots, check_params, check_weights, domain

Method = Literal["normal", "split", "vp-gn", "vp-newton"]
METHODS: tuple[str, ...] = ("normal", "split", "vp-gn", "vp-newton")
StopReason = Literal["converged", "max_iterations", "no_descent"]
# Marquardt damping: its start, the value below which it is dropped, and the
# tries per iteration (each multiplying it by 4) before a fit gives up.
_MU_START = 1e-3
_MU_MIN = 1e-9
_MAX_TRIES = 40


@dataclass(frozen=True)
class CurveFit:
    """The result of :func:`fit_curve`.

    ``curve`` the fitted curve; ``params`` (m,) the foot-point parameters;
    ``distances`` (m,) mm, |C(t_i) - x_i|; ``rms_mm`` their root mean square;
    ``cost`` the final value of the regularised cost; ``cost_history`` one
    value per accepted iterate, starting with the initial one.
    """

    curve: Curve
    params: FloatArray
    distances: FloatArray
    rms_mm: float
    cost: float
    iterations: int
    converged: bool
    stop_reason: StopReason
    method: str
    cost_history: tuple[float, ...]


@dataclass
class _Problem:
    degree: int
    knots: FloatArray
    x: FloatArray  # (m, 3) data points
    smoothing: float
    weight_penalty: float
    d2tD2: FloatArray  # (n, n)

    @property
    def n(self) -> int:
        return self.knots.shape[0] - self.degree - 1

    def basis(self, t: FloatArray, nd: int) -> FloatArray:
        """Dense non-rational basis and derivatives (nd+1, m, n) at t."""
        spans, table = basis_table(self.degree, self.knots, self.n - 1, t, nd)
        out = np.zeros((nd + 1, t.shape[0], self.n))
        cols = spans[:, None] - self.degree + np.arange(self.degree + 1)[None]
        rows = np.arange(t.shape[0])[:, None]
        for k in range(nd + 1):
            out[k, rows, cols] = table[:, k, :]
        return out

    def cost(self, r: FloatArray, P: FloatArray, w: FloatArray) -> float:
        smooth = self.smoothing * np.trace(P.T @ self.d2tD2 @ P)
        return 0.5 * float(np.sum(r * r) + smooth + self.weight_penalty * np.sum((w - 1) ** 2))

    def best_control_points(self, N: FloatArray, w: FloatArray) -> FloatArray:
        """The P minimising f for fixed t and w (the linear part of the model)."""
        R = N * w / (N @ w)[:, None]
        A = R.T @ R + self.smoothing * self.d2tD2
        return np.asarray(scipy.linalg.solve(A, R.T @ self.x, assume_a="pos"))


@dataclass
class _State:
    t: FloatArray
    P: FloatArray
    w: FloatArray
    N: FloatArray  # (3, m, n): basis, first and second derivative at t
    C: FloatArray  # (3, m, 3): point, first and second derivative
    r: FloatArray
    cost: float


def _state(prob: _Problem, t: FloatArray, P: FloatArray, w: FloatArray, nd: int) -> _State:
    N = prob.basis(t, nd)
    W = N @ w  # (nd+1, m): W, W', W''
    A = N @ (P * w[:, None])  # (nd+1, m, 3)
    C = np.empty_like(A)
    C[0] = A[0] / W[0][:, None]
    C[1] = (A[1] - W[1][:, None] * C[0]) / W[0][:, None]
    if nd >= 2:
        C[2] = (A[2] - 2 * W[1][:, None] * C[1] - W[2][:, None] * C[0]) / W[0][:, None]
    r = C[0] - prob.x
    return _State(t, P, w, N, C, r, prob.cost(r, P, w))


def _jacobian(s: _State) -> tuple[FloatArray, FloatArray, FloatArray]:
    """J_t (m, 3), J_P as the rational basis R (m, n), J_w (m, 3, n)."""
    N, W = s.N[0], s.N[0] @ s.w
    R = N * s.w / W[:, None]
    # dC_i/dw_k = N_k (P_k - C_i) / W
    Jw = (N / W[:, None])[:, None, :] * (s.P.T[None, :, :] - s.C[0][:, :, None])
    return s.C[1], R, Jw


def _gradient_and_blocks(
    prob: _Problem, s: _State
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Gauss-Newton blocks: g_t (m,), g_y (4n,), D (m,), B (m, 4n), E (4n, 4n).

    ``y`` is ordered as P (component-major: all x, then y, then z) and w.
    """
    m, n = s.t.shape[0], prob.n
    Jt, R, Jw = _jacobian(s)
    r = s.r
    g_t = np.einsum("ic,ic->i", Jt, r)
    g_P = (R.T @ r).T.ravel() + prob.smoothing * (prob.d2tD2 @ s.P).T.ravel()
    g_w = np.einsum("icl,ic->l", Jw, r) + prob.weight_penalty * (s.w - 1)
    D = np.einsum("ic,ic->i", Jt, Jt)
    B = np.empty((m, 4 * n))
    for c in range(3):
        B[:, c * n : (c + 1) * n] = Jt[:, c : c + 1] * R
    B[:, 3 * n :] = np.einsum("ic,icl->il", Jt, Jw)
    E = np.zeros((4 * n, 4 * n))
    RtR = R.T @ R + prob.smoothing * prob.d2tD2
    for c in range(3):
        E[c * n : (c + 1) * n, c * n : (c + 1) * n] = RtR
        E[c * n : (c + 1) * n, 3 * n :] = R.T @ Jw[:, c, :]
        E[3 * n :, c * n : (c + 1) * n] = E[c * n : (c + 1) * n, 3 * n :].T
    E[3 * n :, 3 * n :] = np.einsum("ick,icl->kl", Jw, Jw) + prob.weight_penalty * np.eye(n)
    return g_t, np.r_[g_P, g_w], D, B, E


def _second_order(prob: _Problem, s: _State, D: FloatArray, B: FloatArray, E: FloatArray) -> None:
    """Adds the residuals' second-derivative terms sum_i r_i . d2C_i to the blocks
    (in place), turning the Gauss-Newton matrix into the exact Hessian of f."""
    n = prob.n
    N0, N1 = s.N[0], s.N[1]
    W, W1 = N0 @ s.w, N1 @ s.w
    C0, C1, C2 = s.C
    r = s.r
    R = N0 * s.w / W[:, None]
    # t t: r . C''
    D += np.einsum("ic,ic->i", r, C2)
    # t P: dR_k/dt = (N'_k w_k - R_k W') / W
    R1 = (N1 * s.w - R * W1[:, None]) / W[:, None]
    for c in range(3):
        B[:, c * n : (c + 1) * n] += r[:, c : c + 1] * R1
    # t w: d2C/dt dw_k = N'_k (P_k - C)/W - N_k C'/W - N_k (P_k - C) W'/W^2
    PmC = s.P.T[None, :, :] - C0[:, :, None]  # (m, 3, n)
    rPmC = np.einsum("ic,ick->ik", r, PmC)
    rC1 = np.einsum("ic,ic->i", r, C1)
    B[:, 3 * n :] += (N1 * rPmC - N0 * rC1[:, None] - N0 * rPmC * W1[:, None] / W[:, None]) / W[
        :, None
    ]
    # P w: dR_k/dw_l = delta_kl N_k / W - R_k N_l / W
    for c in range(3):
        block = -(R * r[:, c : c + 1]).T @ (N0 / W[:, None])
        block += np.diag((N0 * r[:, c : c + 1] / W[:, None]).sum(0))
        E[c * n : (c + 1) * n, 3 * n :] += block
        E[3 * n :, c * n : (c + 1) * n] += block.T
    # w w: -N_k N_l ((P_l - C) + (P_k - C)) / W^2
    a = N0 / W[:, None]
    ww = -(a * rPmC).T @ a
    E[3 * n :, 3 * n :] += ww + ww.T


def fit_curve(
    points: Any,
    degree: int,
    knots: Any,
    *,
    method: Method = "split",
    smoothing: float = 1e-6,
    weight_penalty: float = 1e-4,
    max_iterations: int = 1000,
    tolerance: float = 1e-10,
    params: Any = None,
    weights: Any = None,
) -> CurveFit:
    """Fit a NURBS curve of the given degree and knots to points by orthogonal distance.

    Parameters
    ----------
    points : (m, 3) float64, mm, ordered along the curve
    degree : int >= 1
    knots : (n + degree + 1,) float64, the knot vector of n control points
    method : "normal", "split", "vp-gn" or "vp-newton" (see the module)
    smoothing : lambda_s >= 0 of the control points' second differences
    weight_penalty : lambda_w > 0 pulling the weights towards one
    max_iterations : int >= 1
    tolerance : relative decrease of the cost below which the fit has converged
    params : (m,) initial foot-point parameters; chord length by default. The
        first and last points keep theirs (the curve's ends are tied to them).
    weights : (n,) initial weights; ones by default

    Returns
    -------
    CurveFit
    """
    x = np.array(points, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or not np.all(np.isfinite(x)):
        raise InvalidInput(f"points must be a finite (m, 3) array, got shape {x.shape}")
    if method not in METHODS:
        raise InvalidInput(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if not (smoothing >= 0 and weight_penalty > 0 and tolerance > 0):
        raise InvalidInput("smoothing must be >= 0, weight_penalty and tolerance > 0")
    if (
        not isinstance(max_iterations, int)
        or isinstance(max_iterations, bool)
        or max_iterations < 1
    ):
        raise InvalidInput(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
    p = check_degree(degree, "degree")
    k = np.array(knots, dtype=np.float64)
    n = k.shape[0] - p - 1 if k.ndim == 1 else -1
    k = check_knots(k, p, n, "knots")
    if x.shape[0] < n:
        raise InvalidInput(f"{n} control points need at least {n} points, got {x.shape[0]}")
    lo, hi = domain(k, p)
    if params is None:
        chord = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(x, axis=0), axis=1))]
        if chord[-1] <= 0:
            raise InvalidInput("points must not all coincide")
        t = lo + (hi - lo) * chord / chord[-1]
    else:
        t = check_params(params, (lo, hi), "params")
        if t.shape[0] != x.shape[0]:
            raise InvalidInput("params must have one value per point")
    w = check_weights(weights, (n,))
    d2 = np.diff(np.eye(n), 2, axis=0)
    prob = _Problem(p, k, x, float(smoothing), float(weight_penalty), d2.T @ d2)

    projected = method in ("vp-gn", "vp-newton")
    nd = 2 if method == "vp-newton" else 1
    P = prob.best_control_points(prob.basis(t, 0)[0], w)
    s = _state(prob, t, P, w, nd)
    history = [s.cost]
    stop: StopReason = "max_iterations"
    iterations = 0
    mu = _MU_START
    while iterations < max_iterations:
        iterations += 1
        system = _system(prob, s, method, (lo, hi))
        accepted = None
        for _ in range(_MAX_TRIES):
            step = _solve(system, mu, n)
            if step is not None:
                trial = _trial(prob, s, step, projected, nd, (lo, hi))
                if trial is not None and trial.cost < s.cost:
                    accepted = trial
                    break
            mu = max(4.0 * mu, _MU_MIN)
        if accepted is None:
            stop = "no_descent"
            break
        mu = mu / 3.0 if mu / 3.0 >= _MU_MIN else 0.0
        decrease = (s.cost - accepted.cost) / max(s.cost, 1e-300)
        s = accepted
        history.append(s.cost)
        if decrease < tolerance:
            stop = "converged"
            break
    # With no descent left, a fit at a stationary point has converged too.
    converged = stop == "converged" or (stop == "no_descent" and len(history) > 1)
    distances = np.linalg.norm(s.r, axis=1)
    return CurveFit(
        curve=Curve(p, k, s.P, s.w),
        params=s.t,
        distances=distances,
        rms_mm=float(np.sqrt(np.mean(distances**2))),
        cost=s.cost,
        iterations=iterations,
        converged=converged,
        stop_reason=stop,
        method=method,
        cost_history=tuple(history),
    )


@dataclass
class _System:
    """One iterate's linear system: the blocks of the split, or (normal) the
    assembled matrix and gradient over the free variables."""

    g_t: FloatArray
    g_y: FloatArray
    D: FloatArray
    B: FloatArray
    E: FloatArray
    free: npt.NDArray[np.bool_]
    H: FloatArray | None = None
    g: FloatArray | None = None


def _system(prob: _Problem, s: _State, method: str, dom: tuple[float, float]) -> _System:
    """The Gauss-Newton (or, for vp-newton, Newton) system at ``s``.

    The first and last points keep the ends of the domain: otherwise the
    curve's ends could slide along their own tangents with the foot points
    near them at almost no cost (a near-null direction of the normal
    matrix, which made Gauss-Newton's steps overshoot by the domain's
    length). A foot point elsewhere at an end of the domain whose gradient
    pushes it outwards is held there (an active bound), so that clipping
    cannot turn the step into an ascent.
    """
    g_t, g_y, D, B, E = _gradient_and_blocks(prob, s)
    free = ~(((s.t <= dom[0]) & (g_t > 0)) | ((s.t >= dom[1]) & (g_t < 0)))
    free[[0, -1]] = False
    if method == "vp-newton":
        _second_order(prob, s, D, B, E)
    system = _System(g_t, g_y, D, B, E, free)
    if method == "normal":
        system.H, system.g = _normal_equations(prob, s, free)
    return system


def _normal_equations(
    prob: _Problem, s: _State, free: npt.NDArray[np.bool_]
) -> tuple[FloatArray, FloatArray]:
    """J^T J + regularisation and the gradient, assembled from the dense
    Jacobian (rows: point and coordinate; columns: the free t, then P, w)."""
    n = prob.n
    Jt, R, Jw = _jacobian(s)
    idx = np.flatnonzero(free)
    mf = idx.shape[0]
    m = s.t.shape[0]
    J3 = np.zeros((m, 3, mf + 4 * n))
    for c in range(3):
        J3[idx, c, np.arange(mf)] = Jt[idx, c]
        J3[:, c, mf + c * n : mf + (c + 1) * n] = R
    J3[:, :, mf + 3 * n :] = Jw
    J = J3.reshape(3 * m, mf + 4 * n)
    H = J.T @ J
    g = J.T @ s.r.ravel()
    for c in range(3):
        sl = slice(mf + c * n, mf + (c + 1) * n)
        H[sl, sl] += prob.smoothing * prob.d2tD2
    H[mf + 3 * n :, mf + 3 * n :] += prob.weight_penalty * np.eye(n)
    g[mf : mf + 3 * n] += prob.smoothing * (prob.d2tD2 @ s.P).T.ravel()
    g[mf + 3 * n :] += prob.weight_penalty * (s.w - 1)
    return H, g


def _solve(system: _System, mu: float, n: int) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """(dt, dP, dw) of the system damped by Marquardt's ``mu |diag|``; None when
    the damped matrix is not positive definite."""
    free = system.free
    if system.H is not None and system.g is not None:
        H = system.H.copy()
        H[np.diag_indices_from(H)] += mu * np.abs(np.diag(H))
        try:
            cf = scipy.linalg.cho_factor(H)
        except np.linalg.LinAlgError:
            return None
        step = scipy.linalg.cho_solve(cf, -system.g)
        mf = int(free.sum())
        dt = np.zeros(free.shape[0])
        dt[free] = step[:mf]
        dy = step[mf:]
    else:
        D = system.D[free]
        D = D + mu * np.abs(D)
        if np.any(D <= 0):
            return None
        B, g = system.B[free], system.g_t[free]
        E = system.E + mu * np.diag(np.abs(np.diag(system.E)))
        # The splitting: eliminate the diagonal block, solve the Schur
        # complement for (P, w), then each foot point on its own.
        BtDinv = B.T / D
        try:
            cf = scipy.linalg.cho_factor(E - BtDinv @ B)
        except np.linalg.LinAlgError:
            return None
        dy = scipy.linalg.cho_solve(cf, -(system.g_y - BtDinv @ g))
        dt = np.zeros(free.shape[0])
        dt[free] = -(g + B @ dy) / D
    return dt, dy[: 3 * n].reshape(3, n).T, dy[3 * n :]


def _trial(
    prob: _Problem,
    s: _State,
    step: tuple[FloatArray, FloatArray, FloatArray],
    projected: bool,
    nd: int,
    dom: tuple[float, float],
) -> _State | None:
    """The iterate after ``step`` (t clipped to the domain; with variable
    projection P solved for again), or None if a weight would not stay positive."""
    dt, dP, dw = step
    w = s.w + dw
    if not np.all(w > 0):
        return None
    t = np.clip(s.t + dt, *dom)
    P = prob.best_control_points(prob.basis(t, 0)[0], w) if projected else s.P + dP
    return _state(prob, t, P, w, nd)


@dataclass(frozen=True)
class CurveDeviation:
    """The deviation of a measured curve from its nominal, along the nominal.

    ``params`` (k,) the nominal's parameters sampled; ``points`` (k, 3) mm the
    nominal's points there; ``vectors`` (k, 3) mm from each to the closest
    point of the measured curve; ``distances`` (k,) mm their lengths.
    """

    params: FloatArray
    points: FloatArray
    vectors: FloatArray
    distances: FloatArray


def deviation_along(
    measured: Curve,
    nominal: Curve,
    samples: int = 200,
    *,
    span: tuple[float, float] | None = None,
) -> CurveDeviation:
    """The deviation of a fitted, measured curve (a trim edge, a character
    line) from its nominal, at ``samples`` parameters evenly spread over the
    nominal's domain (or ``span`` of it): each nominal point's vector to its
    closest point on the measured curve.

    Parameters
    ----------
    measured : Curve, e.g. ``fit_curve(...).curve`` of the measured edge points
    nominal : Curve, the design's edge
    samples : int >= 2
    span : (lo, hi), optional, the nominal's parameters where the edge was
        measured (within its domain, lo < hi); default its whole domain
    """
    if not isinstance(samples, int) or isinstance(samples, bool) or samples < 2:
        raise InvalidInput(f"samples must be an integer >= 2, got {samples!r}")
    lo, hi = nominal.domain if span is None else (float(span[0]), float(span[1]))
    if not (nominal.domain[0] <= lo < hi <= nominal.domain[1]):
        raise InvalidInput(
            f"span must lie within the nominal's domain {nominal.domain}, got {span}"
        )
    t = np.linspace(lo, hi, samples)
    pts = nominal.evaluate(t)
    # Start each foot at the nearest of dense samples of the measured curve.
    dense = np.linspace(*measured.domain, 20 * samples + 1)
    cloud = measured.evaluate(dense)
    nearest = np.array([int(np.argmin(np.sum((cloud - p) ** 2, axis=1))) for p in pts])
    feet = measured.evaluate(measured.project(pts, dense[nearest]))
    vectors = feet - pts
    return CurveDeviation(t, pts, vectors, np.linalg.norm(vectors, axis=1))
