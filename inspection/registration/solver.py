"""The fine registration, stage by stage: robust ICP by IRLS in a Levenberg-Marquardt trust region.

The fit finds ``T_cad_data``, the rigid transform that maps the measured
points (data frame, e.g. the rig) into the CAD frame, by minimising a robust
cost of the residuals (:mod:`.kernels`): by default the signed distance of
``T p_i`` to the CAD surface, whose gradient is the face normal where the
closest point lies inside a face (there it equals the point-to-plane
residual) and points towards the edge or corner beyond it otherwise, so that
points overhanging a border pull the part back.

The stages, as :func:`register` runs them:

1. *A seeded subset.* The points are shuffled once (seeded); every subset is
   a prefix of the next, so growing one queries only the new points. A
   closest-point query costs far more than anything else per point: the fit
   is arranged to query few points, few times.
2. *The robust scale*, graduated: it starts wide (the 90th percentile of the
   first residuals) and narrows 4 times each time the pose settles at it
   (graduated non-convexity), so that points misfit by the start offset pull
   the part into place before the scale narrows to the noise (1.4826 x the
   median absolute residual) and would reject them. It never grows between
   iterations on one subset, so the cost never rises there.
3. *One damped Gauss-Newton step* on the IRLS surrogate per iteration: the
   6x6 normal equations ``(H + lambda D) delta = -g`` give a small twist
   ``delta = (omega L, t)`` about the centroid of the points. The step is
   accepted only if the true cost at the new pose is lower; otherwise
   ``lambda`` grows and the step is retried (a trust region). The gain ratio
   ``actual / predicted`` reduction steers ``lambda`` (Madsen, Nielsen &
   Tingleff, "Methods for non-linear least squares problems", 2004, eq.
   3.13-3.14). When steps keep the same direction (sliding along a weakly
   constrained direction, where Gauss-Newton converges linearly), the rest of
   the geometric series of steps (Aitken's extrapolation) and longer steps
   are tried, each kept only if it lowers the cost. Past the first subset, a
   step that moves the points by less than 0.02 mm is evaluated against each
   point's last closest face (:mod:`.correspondences`).
4. *Settled?* A step below a quarter of the pose's statistical uncertainty
   on the subset ends a stage (a fixed absolute step size would either waste
   queries or stop short on a subset with a looser tolerance); before the
   last subset, so does a step that lowers the cost by less than the subset's
   noise can tell apart (1 % of sigma^2 / n), since damped steps would
   otherwise crawl along a direction the subset leaves loose. Then the scale
   narrows, or the subset grows ``subset_growth`` times (to the last one
   when that would leave out fewer points than it holds), up to
   ``max_subset``; a pose those points do not pin down to
   ``uncertainty_mm`` continues on every point. On the last subset, a fit
   that no damped step moves has converged if its Gauss-Newton step lies
   within the pose's own uncertainty (the cost is rough at that scale), and
   made no progress otherwise.
5. *The result*: every point's residual and weight at the final pose (one
   query of the points the fit did not use), the observability and the
   covariance of the pose.
6. *The escape* along a rotation the fit leaves free (:mod:`.escape`).

``cost_history`` keeps, per iteration, the cost before and after its step:
within an iteration it never rises; across iterations it never rises while
the subset stays the same (when it grows, the mean is over more points and
the scale is estimated afresh).

Determinism: the subsets come from a seeded generator and every reduction
runs in a fixed order in single-threaded kernels, so the same input gives a
bit-identical result.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..arrays import Points, Scalars, Transform
from ..errors import InsufficientOverlap, InvalidInput
from ..protocols import ClosestPointQuery, Triangles
from ..validate import validate_points, validate_transform
from .correspondences import (
    CadFaces,
    Matches,
    concatenated,
    match,
    match_kept_faces,
    residuals_at,
)
from .escape import escape_free_rotation
from .kernels import (
    LOSSES,
    compose,
    cost_normal_equations,
    irls_weights,
    lm_step,
    median_abs,
    opposed_fraction,
    partial_shuffle,
    robust_cost,
    trace_inverse,
    transform_points,
    turned_away,
    weighted_centroid,
)
from .params import RegisterParams
from .result import INLIER_SIGMAS, Registration, StopReason

log = logging.getLogger(__name__)

# Residuals used to estimate the robust scale.
_SCALE_SAMPLE = 4096
# MAD to standard deviation for Gaussian noise.
_MAD_TO_SIGMA = 1.482602218505602
# Relative eigenvalue of the normalised normal matrix below which a direction
# of motion counts as unconstrained by the data.
_DEGENERATE_REL_EIG = 1e-3
# ... and below which the data do not resolve it at all (rounding of an exact zero).
UNRESOLVED_REL_EIG = 1e-9
# Graduated scale: it starts at this quantile of the first |residuals| and
# narrows by this factor each time the pose settles at it ...
_GNC_QUANTILE = 0.9
_GNC_FACTOR = 4.0
# ... once a step lowers the cost by less than this fraction, or moves the
# points by less than this fraction of the scale.
_GNC_GAIN = 1e-3
_GNC_STEP = 1e-3
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
# A damped step within this fraction of its length of one the cost just
# rejected is taken as rejected too, without evaluating it.
_SAME_STEP = 1e-3
# Steps moving the points by less than this (RMS, mm) are evaluated against
# each point's last closest face rather than with a fresh query.
_FIXED_FACE_STEP_MM = 0.02
# A cloud whose sampled points lie this rarely near the CAD cannot fit.
_MIN_NEAR_FRACTION = 0.05
_BOX_SAMPLE = 1024


def register(
    tree: ClosestPointQuery,
    points: Points,
    params: RegisterParams | None = None,
    *,
    init: Transform | None = None,
    weights: Scalars | None = None,
    faces: CadFaces | None = None,
    **keywords: Any,
) -> Registration:
    """Fit measured points to the CAD with robust point-to-surface ICP.

    Parameters
    ----------
    tree : ClosestPointQuery
        The CAD's closest-point structure (``GridTree``), CAD frame, mm.
    points : (N, 3) float64, mm, data frame
        Measured points (e.g. the reconstructed cloud in the rig frame).
    params : RegisterParams, optional
        How to fit; default ``RegisterParams()``.
    init : (4, 4) float64, optional
        Initial ``T_cad_data``; identity when omitted.
    weights : (N,) float64, optional
        Per-point input weights >= 0 (reconstruction quality); 1 when omitted.
    faces : CadFaces, optional
        The CAD's face planes and bounding box (``CadFaces.of(cad)``): small
        steps are evaluated against each point's last face, and a cloud far
        outside the box is refused before any query. Build it once to fit
        many clouds against one CAD; when omitted it is built from ``tree``
        for this fit if the tree has triangles (a ``GridTree`` has).
    **keywords
        Fields of :class:`RegisterParams` (``register(tree, points,
        loss="l2")``), replacing those of ``params``.

    Returns
    -------
    Registration

    Raises
    ------
    InvalidInput
        Bad shapes, non-finite values, a non-rigid ``init``, negative
        weights, bad parameters.
    InsufficientOverlap
        Fewer than ``min_points`` points near the CAD at the start, or fewer
        than ``min_points`` inliers at the end.
    """
    p = params if params is not None else RegisterParams()
    if not isinstance(p, RegisterParams):
        raise InvalidInput(f"params must be RegisterParams, got {type(p).__name__}")
    if keywords:
        p = dataclasses.replace(p, **keywords)
    if not isinstance(tree, ClosestPointQuery):
        raise InvalidInput("tree must answer closest-point queries (have a .query(points) method)")
    P_in = validate_points(points, min_points=max(int(p.min_points), 6))
    T = np.eye(4) if init is None else validate_transform(init)
    v_in = _input_weights(weights, len(P_in))
    if faces is None and isinstance(tree, Triangles):
        faces = CadFaces.of(tree)

    # 1. The seeded subset, matched at the initial pose.
    fit = _first_subset(tree, P_in, v_in, T, p, faces)

    # 2.-4. IRLS iterations under a trust region, on growing subsets.
    for _ in range(p.max_iterations):
        fit.iterations += 1
        _update_scale(fit)
        e0, g = _normal_equations(fit)
        step = _trust_region_step(fit, e0, g)
        fit.history.append((e0, step.e1))
        fit.sizes.append(fit.m)
        _log_iteration(fit, e0, step)
        if not _settled(fit, e0, step):
            continue
        if _view_rule_stuck(fit, step):
            # No step lowers the cost with back faces ruled out, or only
            # crawling ones do: points that would cross onto one jump to the
            # loss's plateau, which can block every step (a part far off in
            # its plane). Go on without the rule; it only ever lowers the
            # cost (a plateau is the most a point can cost), so the cost
            # still never rises.
            fit.view_active = False
            fit.lam = 1e-4
            continue
        if fit.gnc > 0.0:
            # Settled at this scale: narrow it.
            fit.gnc = fit.gnc / _GNC_FACTOR
            continue
        if step.accepted and _scale_still_shrinking(fit):
            continue
        if _loosely_constrained(fit):
            _use_every_point(fit)
        if fit.m < fit.cap:
            _grow_subset(fit)
            continue
        settled = step.tiny or step.accepted or _at_minimum(fit, g)
        fit.stop = StopReason.CONVERGED if settled else StopReason.NO_PROGRESS
        break

    # 5. Every point's figures at the final pose, and the pose's observability.
    result, misfit = _result(fit, P_in)

    # 6. A rotation the points leave free is scanned, and fitted again from
    #    its best angles.
    if p.escape_deg is not None:
        no_escape = dataclasses.replace(p, escape_deg=None)
        result = escape_free_rotation(
            tree,
            result,
            fit.P,
            fit.V[: fit.cap],
            fit.H,
            fit.center,
            fit.L,
            misfit,
            p.escape_deg,
            lambda T_start: register(
                tree, points, no_escape, init=T_start, weights=weights, faces=faces
            ),
        )
    return result


# --------------------------------------------------------------------------- state


@dataclass
class _Fit:
    """The state of one fit as its stages pass it on."""

    tree: ClosestPointQuery
    p: RegisterParams
    planes: np.ndarray | None
    view: np.ndarray | None
    loss_id: int
    c: float
    P_in: Points
    perm: np.ndarray
    # The points the fit may use (a prefix of the permutation: ``cap`` of
    # them), and every point's input weight in permuted order, set to 0 for
    # points gated out as far.
    P: Points
    V: Scalars
    cap: int
    m: int
    T: Transform
    match: Matches
    gnc: float
    sigma: float = np.inf
    lam: float = 1e-4
    # Robust scale of the current residuals; < 0 when stale.
    mad: float = -1.0
    view_active: bool = False
    prev_delta: np.ndarray = field(default_factory=lambda: np.zeros(6))
    H: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    # Whether H was built at the current pose on the current subset.
    H_current: bool = False
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    L: float = 1.0
    iterations: int = 0
    accepted: int = 0
    rejected: int = 0
    extended: int = 0
    history: list[tuple[float, float]] = field(default_factory=list)
    sizes: list[int] = field(default_factory=list)
    stop: StopReason = StopReason.MAX_ITERATIONS

    # The input weights' sum over the subset, for the subset of ``_vsum_m`` points.
    _vsum: float = 0.0
    _vsum_m: int = -1

    @property
    def distance(self) -> bool:
        return self.p.residual == "distance"

    @property
    def weight_sum(self) -> float:
        """The sum of the input weights of the current subset. The weights of
        a subset's points are set (gated) before it is used and never change
        after, so the sum is taken once per subset, not once per iteration."""
        if self._vsum_m != self.m:
            self._vsum = float(self.V[: self.m].sum())
            self._vsum_m = self.m
        return self._vsum

    def for_cost(self, r: np.ndarray, normals: np.ndarray, T: Transform) -> np.ndarray:
        """The residuals for the cost: a point whose closest face is turned
        away from the sensor (more than 120 degrees from ``view_direction``)
        cannot have been measured on it; it counts as an outlier (the loss's
        plateau, no pull) rather than pulling the part onto a back face."""
        if self.view is None or not self.view_active:
            return r
        return turned_away(r, normals, T[:3, :3] @ self.view, _BACK_FACE_COS, _FAR_MM)

    def trial(self, T: Transform, step_mm: float) -> Matches:
        """The subset's matches at a trial pose ``T``, reached from the current
        one by a step moving the points by ``step_mm`` (RMS): past the coarse
        stage a small step keeps each point's closest face (an upper bound of
        the true cost); otherwise a fresh query. (In the coarse stage the kept
        faces would save few queries and cost accuracy.)"""
        if (
            self.planes is not None
            and self.gnc == 0.0
            and self.m > self.p.initial_subset
            and step_mm < _FIXED_FACE_STEP_MM
        ):
            return match_kept_faces(
                self.tree, T, self.P[: self.m], self.match, self.planes, self.distance
            )
        return match(self.tree, T, self.P[: self.m], self.distance)[0]


@dataclass(frozen=True)
class _Step:
    """What one iteration's trust-region loop did."""

    accepted: bool
    tiny: bool
    small: bool
    e1: float
    delta: np.ndarray


# --------------------------------------------------------------------------- stages


def _input_weights(weights: Scalars | None, n: int) -> Scalars:
    if weights is None:
        return np.ones(n)
    v = np.asarray(weights, dtype=np.float64)
    if v.shape != (n,):
        raise InvalidInput(f"weights must have shape ({n},), got {v.shape}")
    if not np.isfinite(v).all() or (v < 0).any():
        raise InvalidInput("weights must be finite and >= 0")
    if not (v > 0).any():
        raise InvalidInput("all weights are zero")
    return v


def _first_subset(
    tree: ClosestPointQuery,
    P_in: Points,
    v_in: Scalars,
    T: Transform,
    p: RegisterParams,
    faces: CadFaces | None,
) -> _Fit:
    """1. The seeded permutation, the first subset matched at ``T``, and the
    graduated scale's start.

    Raises InsufficientOverlap when too few of the points lie near the CAD
    (its bounding box first, before any query: far queries are the slow ones).
    """
    n_all = len(P_in)
    min_points = max(int(p.min_points), 6)
    cap = n_all if p.max_subset is None else min(n_all, int(p.max_subset))
    perm = partial_shuffle(n_all, cap, np.uint64(p.seed % (1 << 63)))
    # Only the points the fit can use are gathered (np.take gathers rows
    # several times faster than fancy indexing).
    P = np.take(P_in, perm[:cap], axis=0)
    V = np.take(v_in, perm)
    m = min(p.initial_subset, cap)

    if faces is not None:
        b = faces.bounds
        k0 = min(cap, _BOX_SAMPLE)
        X0 = transform_points(T[:3, :3].copy(), T[:3, 3].copy(), P[:k0])
        gap = np.linalg.norm(np.maximum(np.maximum(b[0] - X0, X0 - b[1]), 0.0), axis=1)
        inside = int(np.sum((gap <= p.max_distance_mm) & (V[:k0] > 0)))
        if inside < min(min_points, k0) or inside < _MIN_NEAR_FRACTION * k0:
            raise InsufficientOverlap(
                f"only {inside} of {k0} sampled points lie within {p.max_distance_mm} mm "
                "of the CAD's bounding box at the initial pose"
            )

    first, d = match(tree, T, P[:m], p.residual == "distance")
    V[:m] *= np.abs(d) <= p.max_distance_mm
    near = int((V[:m] > 0).sum())
    if near < min(min_points, m) or near < _MIN_NEAR_FRACTION * m:
        raise InsufficientOverlap(
            f"only {near} of {m} sampled points lie within {p.max_distance_mm} mm of the CAD "
            "at the initial pose"
        )

    # The graduated scale starts wide enough that nearly every point near the
    # CAD pulls (the residuals of a misplaced part are misfit, not outliers).
    gnc = 0.0
    if p.graduated and p.loss != "l2":
        a0 = np.abs(first.residuals[V[:m] > 0])
        gnc = float(np.quantile(a0, _GNC_QUANTILE)) if len(a0) else 0.0
    view = None if p.view_direction is None else np.asarray(p.view_direction, dtype=np.float64)
    loss_id, c = LOSSES[p.loss]
    return _Fit(
        tree=tree,
        p=p,
        planes=None if faces is None else faces.planes,
        view=view,
        loss_id=loss_id,
        c=c,
        P_in=P_in,
        perm=perm,
        P=P,
        V=V,
        cap=cap,
        m=m,
        T=T,
        match=first,
        gnc=gnc,
        view_active=view is not None,
    )


def _update_scale(fit: _Fit) -> None:
    """2. The robust scale of this iteration: the residuals' MAD, or the
    graduated scale while it is wider. It never grows: with sigma^2
    rho(r/sigma) non-decreasing in sigma, a smaller scale cannot raise the
    cost of the accepted pose."""
    if fit.mad < 0.0:  # the residuals changed since the last estimate
        fit.mad = _robust_scale(fit.match.residuals, fit.V[: fit.m], fit.p.min_scale_mm)
    if fit.gnc <= fit.mad:
        fit.gnc = 0.0
    fit.sigma = min(fit.sigma, max(fit.mad, fit.gnc))


def _normal_equations(fit: _Fit) -> tuple[float, np.ndarray]:
    """The cost ``e0`` at the current pose and the IRLS normal equations (H
    into ``fit.H``, g returned), about the subset's centroid."""
    v = fit.V[: fit.m]
    mt = fit.match
    center, L = weighted_centroid(mt.points, v)
    fit.center, fit.L = center, max(L, 1.0)
    e0, fit.H, g = cost_normal_equations(
        mt.points,
        mt.gradients,
        fit.for_cost(mt.residuals, mt.normals, fit.T),
        v,
        fit.sigma,
        fit.loss_id,
        fit.c,
        fit.center,
        fit.L,
    )
    fit.H_current = True
    return e0, g


def _tolerances(fit: _Fit) -> tuple[float, float]:
    """Steps below these (rad, mm) end the stage: a graduating scale needs the
    pose settled only to a fraction of itself; a smaller subset or the last
    only to a quarter of what the noise leaves uncertain on its points."""
    p = fit.p
    if fit.gnc > 0.0:
        return np.inf, _GNC_STEP * fit.gnc
    # A step well below the pose's statistical uncertainty on these points
    # (noise x sqrt(trace H^-1 / n), the RMS displacement it causes) changes
    # nothing that matters: up to 10 times the given tolerances, a quarter of
    # that uncertainty ends the stage.
    f = p.subset_tolerance_factor if fit.m < fit.cap else 1.0
    f = max(f, min(10.0, 0.25 * _uncertainty(fit.H, fit.sigma, fit.weight_sum) / p.tolerance_mm))
    return f * p.tolerance_rad, f * p.tolerance_mm


def _trust_region_step(fit: _Fit, e0: float, g: np.ndarray) -> _Step:
    """3. One Levenberg-Marquardt iteration: damped steps are tried until one
    lowers the true cost (fresh matches at the new pose), ``lambda`` growing
    after each rejection; an accepted step may be extended."""
    tol_rad, tol_mm = _tolerances(fit)
    v = fit.V[: fit.m]
    H, L, center = fit.H, fit.L, fit.center
    small = False
    delta = np.zeros(6)
    rejected: np.ndarray | None = None
    for _trial in range(fit.p.max_rejections + 1):
        # Predicted reduction of the quadratic IRLS model (a lower bound of
        # the true reduction where the linearisation holds).
        delta, pred, ok = lm_step(H, g, fit.lam)
        if not ok:
            fit.lam *= 4.0
            fit.rejected += 1
            continue
        omega, t = delta[:3] / L, delta[3:]
        if fit.gnc > 0.0:
            # Graduating: the RMS displacement of the points by the step.
            small = float(np.sqrt(delta @ delta)) < tol_mm
        else:
            small = float(np.sqrt(omega @ omega)) < tol_rad and float(np.sqrt(t @ t)) < tol_mm
        if pred <= 1e-15 * max(e0, 1e-300) or (small and fit.lam <= 1e-3):
            return _Step(accepted=False, tiny=True, small=small, e1=e0, delta=delta)
        if rejected is not None and _same_step(delta, rejected):
            # While lambda is small against diag(H) the damped step barely
            # changes: it would be rejected again, and its query is spared.
            fit.lam *= 4.0
            fit.rejected += 1
            continue
        T1 = compose(fit.T, omega, t, center)
        m1 = fit.trial(T1, float(np.sqrt(delta @ delta)))
        e1 = robust_cost(
            fit.for_cost(m1.residuals, m1.normals, T1), v, fit.sigma, fit.loss_id, fit.c
        )
        if e1 < e0:
            # Gain ratio rho = actual / predicted (Madsen et al. eq. 3.14):
            # a good model lets the region grow, a poor one shrinks it.
            ratio = (e0 - e1) / pred
            if ratio > 0.75:
                fit.lam = max(fit.lam / 3.0, 1e-9)
            elif ratio < 0.25:
                fit.lam *= 2.0
            T0 = fit.T
            fit.T, fit.match = T1, m1
            fit.H_current = False
            delta, e1 = _extend(fit, T0, delta, omega, t, e1)
            fit.prev_delta = delta
            fit.mad = -1.0
            fit.accepted += 1
            return _Step(accepted=True, tiny=False, small=small, e1=e1, delta=delta)
        fit.lam *= 4.0
        fit.rejected += 1
        rejected = delta
    return _Step(accepted=False, tiny=False, small=small, e1=e0, delta=delta)


def _same_step(delta: np.ndarray, rejected: np.ndarray) -> bool:
    """Whether ``delta`` is the rejected step to within ``_SAME_STEP`` of its length."""
    d = delta - rejected
    return float(d @ d) <= _SAME_STEP * _SAME_STEP * float(rejected @ rejected)


def _extend(
    fit: _Fit, T0: Transform, delta: np.ndarray, omega: np.ndarray, t: np.ndarray, e1: float
) -> tuple[np.ndarray, float]:
    """An accepted step, extended along its direction while the cost falls.

    Sliding along a weakly constrained direction, Gauss-Newton overestimates
    the curvature (a point overhanging an edge by less than the noise pulls
    less than its linearised residual says), so steps repeat in the same
    direction, each a fraction q of the last: linear convergence. The rest of
    that geometric series is q / (1 - q) of this step (Aitken's
    extrapolation); then doublings. Each longer step is kept only if the cost
    falls. Returns the step taken and its cost.
    """
    prev = fit.prev_delta
    dn = float(np.sqrt(delta @ delta))
    pn = float(np.sqrt(prev @ prev))
    if not (dn > 0.0 and pn > 0.0 and delta @ prev > 0.8 * dn * pn):
        return delta, e1
    v = fit.V[: fit.m]
    q = min(float(delta @ prev) / (pn * pn), 0.95)
    factors = [1.0 / (1.0 - q)] if q < 0.5 * (1.0 + 1.0 / 1.5) else []
    factors = [f for f in factors if f >= 1.5]
    scale = 1.0
    for f in factors + [2.0] * fit.p.max_extensions:
        s_ = scale * f
        Ts = compose(T0, s_ * omega, s_ * t, fit.center)
        ms = fit.trial(Ts, s_ * dn)
        es = robust_cost(
            fit.for_cost(ms.residuals, ms.normals, Ts), v, fit.sigma, fit.loss_id, fit.c
        )
        if not es < e1:
            if scale == 1.0 and f != 2.0:
                continue  # the extrapolation overshot: try doublings
            break
        scale = s_
        fit.T, fit.match, e1 = Ts, ms, es
    fit.extended += scale > 1.0
    return scale * delta, e1


def _settled(fit: _Fit, e0: float, step: _Step) -> bool:
    """4. Whether the pose has settled at this scale on this subset."""
    # A short step says so only if it was not damped.
    settled = step.tiny or (step.accepted and step.small and fit.lam <= 1e-3) or not step.accepted
    if fit.gnc > 0.0 and step.accepted and e0 - step.e1 < _GNC_GAIN * e0:
        # Sliding along a weakly constrained direction converges linearly:
        # short steps do not mean the pose has settled at this scale, a cost
        # that no longer falls does.
        settled = True
    if (
        fit.gnc == 0.0
        and fit.m < fit.cap
        and step.accepted
        and e0 - step.e1 < _SUBSET_GAIN * fit.sigma * fit.sigma / max(fit.weight_sum, 1.0)
    ):
        settled = True
    return settled


def _at_minimum(fit: _Fit, g: np.ndarray) -> bool:
    """Whether the pose is at the model's minimum to within what the points can tell,
    so that a cost no damped step lowered is rough there (points trading faces under
    so small a step), not far from its minimum."""
    return gauss_newton_step_within_noise(fit.H, g, fit.sigma, fit.weight_sum, fit.p.tolerance_mm)


def gauss_newton_step_within_noise(
    H: np.ndarray, g: np.ndarray, sigma: float, vs: float, tolerance_mm: float
) -> bool:
    """Whether the undamped (Gauss-Newton) step ``H delta = -g`` is shorter than the
    tolerance, or no longer than the noise typically displaces the pose, measured in
    the metric of the pose's own covariance ``sigma^2 H^-1 / vs`` (``H`` normalised
    by the weight total ``vs``): its squared Mahalanobis length at most the six
    parameters' expected chi-square. The metric matters: a step along a
    well-constrained direction is measured against that direction's small
    uncertainty, not against the uncertainty of the loosest one. A pose with a
    direction the points do not constrain has no minimum to speak of."""
    if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
        return False
    eig = np.linalg.eigvalsh(H)
    if eig[0] < _DEGENERATE_REL_EIG * max(float(eig[-1]), 1e-300):
        return False
    delta, _, ok = lm_step(H, g, 0.0)
    if not ok or not np.all(np.isfinite(delta)):
        return False
    # delta's rotation part is scaled by the points' reach: |delta| is the RMS displacement.
    if float(np.sqrt(delta @ delta)) <= tolerance_mm:
        return True
    if not (sigma > 0.0 and vs > 0.0):
        return False
    return float(delta @ H @ delta) * vs / (sigma * sigma) <= len(delta)


def _view_rule_stuck(fit: _Fit, step: _Step) -> bool:
    """Whether the view rule blocks the fit: no step lowers the cost under it,
    or only heavily damped ones."""
    return fit.view_active and (
        (not step.accepted and not step.tiny) or fit.lam > _VIEW_STUCK_LAMBDA
    )


def _scale_still_shrinking(fit: _Fit) -> bool:
    """A scale still shrinking re-weights the points and moves the optimum:
    the pose has settled only once the scale has too."""
    fit.mad = _robust_scale(fit.match.residuals, fit.V[: fit.m], fit.p.min_scale_mm)
    return fit.mad < 0.9 * fit.sigma


def _loosely_constrained(fit: _Fit) -> bool:
    """Whether the pose, converged on ``max_subset`` points, rests on too few
    of them: the noise leaves it more uncertain than ``uncertainty_mm``."""
    return bool(
        fit.m == fit.cap < len(fit.P_in)
        and fit.p.uncertainty_mm is not None
        and _uncertainty(fit.H, fit.sigma, fit.weight_sum) > fit.p.uncertainty_mm
    )


def _use_every_point(fit: _Fit) -> None:
    fit.cap = len(fit.P_in)
    fit.P = np.concatenate([fit.P, np.take(fit.P_in, fit.perm[fit.m :], axis=0)])


def _grow_subset(fit: _Fit) -> None:
    """The next subset: only the new points are queried, at the current pose.
    A new cost on more points: the trust region starts afresh, and the scale
    is estimated afresh on them (the smallest of many noisy estimates on few
    points would be biased low). A subset that would leave out fewer points than it
    holds is skipped for all of them: its iterations would cost nearly as much as
    the last subset's and settle nearly the same pose."""
    m, m2 = fit.m, min(fit.cap, fit.p.subset_growth * fit.m)
    if fit.cap - m2 < m2:
        m2 = fit.cap
    new, d = match(fit.tree, fit.T, fit.P[m:m2], fit.distance)
    fit.V[m:m2] *= np.abs(d) <= fit.p.max_distance_mm
    fit.match = concatenated(fit.match, new)
    fit.m = m2
    fit.mad = -1.0
    fit.lam = 1e-4
    fit.sigma = np.inf
    fit.H_current = False


def _result(fit: _Fit, P_in: Points) -> tuple[Registration, float]:
    """5. The registration at the final pose, and the fraction of the last
    subset's points it leaves misfit (for the escape)."""
    p = fit.p
    m, v, mt = fit.m, fit.V[: fit.m], fit.match
    # The final scale, from every point of the last subset: the weights of
    # all points use it, and any prefix of a few thousand would make them
    # depend, by a few per cent, on which points the subset drew.
    sigma = _robust_scale(mt.residuals, v, p.min_scale_mm, m)
    inl = (v > 0) & (np.abs(mt.residuals) <= INLIER_SIGMAS * sigma)
    n_inl = int(inl.sum())
    if n_inl < min(max(int(p.min_points), 6), m):
        raise InsufficientOverlap(f"only {n_inl} of {m} points fit the CAD after registration")
    if not fit.H_current:
        # The last normal matrix was built at another pose or on fewer points.
        center, L = weighted_centroid(mt.points, v)
        fit.center, fit.L = center, max(L, 1.0)
        _, fit.H, _ = cost_normal_equations(
            mt.points,
            mt.gradients,
            fit.for_cost(mt.residuals, mt.normals, fit.T),
            v,
            sigma,
            fit.loss_id,
            fit.c,
            fit.center,
            fit.L,
        )
    eig, vec = np.linalg.eigh(fit.H)
    eig = np.maximum(eig, 0.0)
    free = eig < _DEGENERATE_REL_EIG * max(float(eig[-1]), 1e-300)
    degenerate = vec[:, free].T.copy()
    # Gauss-Newton's covariance of the twist: sigma^2 (sum w J J^T)^-1, and H
    # is that sum divided by the weight total.
    # A weak direction counts with its small eigenvalue (a large variance);
    # only a direction the data do not resolve at all is left out.
    vs = max(float(np.sum(v[v > 0])), 1e-300)
    unresolved = eig <= UNRESOLVED_REL_EIG * max(float(eig[-1]), 1e-300)
    inv_eig = np.where(unresolved, 0.0, 1.0 / np.where(unresolved, 1.0, eig))
    covariance = (vec * inv_eig) @ vec.T * (float(sigma) ** 2 / vs)
    T = _orthonormalised(fit.T)
    weights, residuals, rms, inlier_fraction = _every_point(fit, P_in, T, float(sigma))

    log.debug(
        "register: %s after %d iterations (%d accepted, %d rejected, %d extended) on %d points",
        fit.stop.value,
        fit.iterations,
        fit.accepted,
        fit.rejected,
        fit.extended,
        m,
    )
    result = Registration(
        transform=T,
        iterations=fit.iterations,
        converged=fit.stop is StopReason.CONVERGED,
        stop_reason=fit.stop,
        rms_mm=rms,
        inlier_fraction=inlier_fraction,
        weights=weights,
        residuals=residuals,
        scale_mm=float(sigma),
        cost_history=np.asarray(fit.history, dtype=np.float64).reshape(-1, 2),
        subset_sizes=np.asarray(fit.sizes, dtype=np.int64),
        observability=eig,
        degenerate_directions=degenerate,
        pose_center=np.asarray(fit.center, dtype=np.float64).copy(),
        pose_radius_mm=float(fit.L),
        pose_covariance=covariance,
        loss=p.loss,
        accepted_steps=fit.accepted,
        rejected_steps=fit.rejected,
        opposed_fraction=opposed_fraction(mt.normals, np.where(inl, v, 0.0)),
    )
    misfit = 1.0 - n_inl / max(int(np.sum(v > 0)), 1)
    return result, misfit


def _every_point(
    fit: _Fit, P_in: Points, T: Transform, sigma: float
) -> tuple[Scalars, Scalars, float, float]:
    """Weights, residuals (input order, read-only), RMS of the inliers and
    inlier fraction of every input point at the final pose ``T``: the points
    the fit did not use are queried once, and gated by ``max_distance_mm``."""
    m, n = fit.m, len(fit.perm)
    V = fit.V.copy()
    r = np.empty(n)
    r[:m] = fit.match.residuals
    if m < n:
        r_rest, d_rest = residuals_at(
            fit.tree, T, np.take(P_in, fit.perm[m:n], axis=0), fit.distance
        )
        V[m:] *= np.abs(d_rest) <= fit.p.max_distance_mm
        r[m:] = r_rest
    w = irls_weights(r, V, sigma, fit.loss_id, fit.c)
    inl = (V > 0) & (np.abs(r) <= INLIER_SIGMAS * sigma)
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("nan")
    weights = np.empty(n)
    weights[fit.perm] = w
    residuals = np.empty(n)
    residuals[fit.perm] = r
    weights.flags.writeable = False
    residuals.flags.writeable = False
    return weights, residuals, rms, float(inl.sum()) / n


def _log_iteration(fit: _Fit, e0: float, step: _Step) -> None:
    if log.isEnabledFor(logging.DEBUG):
        log.debug(
            "iteration %d: m %d sigma %.4g gnc %.4g cost %.6g -> %.6g lambda %.2g "
            "accepted %s step %.3g",
            fit.iterations,
            fit.m,
            fit.sigma,
            fit.gnc,
            e0,
            step.e1,
            fit.lam,
            step.accepted,
            float(np.linalg.norm(step.delta)),
        )


# --------------------------------------------------------------------------- numbers


def _robust_scale(r: np.ndarray, v: np.ndarray, floor: float, sample: int = _SCALE_SAMPLE) -> float:
    """1.4826 x the median absolute residual (the MAD of a zero-centred
    residual), at least ``floor``. The points are in random order: a prefix
    is a random sample, and a few thousand residuals give the median to ~2 %."""
    return max(_MAD_TO_SIGMA * median_abs(r, v, min(len(r), sample)), floor)


def _uncertainty(H: np.ndarray, sigma: float, vs: float) -> float:
    """RMS displacement, mm, that the noise ``sigma`` leaves in the pose fitted
    to points whose input weights sum to ``vs``, from the normal matrix ``H``
    (normalised by that sum): ``sigma sqrt(trace(H^-1) / vs)``."""
    tr = trace_inverse(H)
    if not np.isfinite(tr) or tr <= 0.0 or vs <= 0.0:
        return 0.0
    return sigma * float(np.sqrt(tr / vs))


def _orthonormalised(T: Transform) -> Transform:
    """``T`` with its rotation made orthonormal to the last bit (a few dozen
    compositions leave it off by ~1e-15)."""
    out = T.copy()
    U, _, Vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = U @ Vt
    return out
