"""A feature's edge as a smooth curve: its offset from the nominal and its largest deviation.

The single points measured on a trim edge or a character line scatter (the
images' noise, a speckle grain on the edge, the cloud's own noise), while the
edge itself is a smooth curve. :func:`curve_offset` fits the measured points
with a NURBS curve (:func:`inspection.nurbs.fit_edge`: ordered along the
nominal, fitted by orthogonal distance with a smoothness penalty on the
control points), drops the points far off it and fits again, and reads the
fitted curve's deviation from the nominal along the measured span: at each
nominal sample, the signed offset along the edge's normal (in the surface,
across the edge). The edge's place is the mean of that offset over the span's
length; its shape, the largest offset and where along the nominal it lies.
:func:`nominal_curve` makes the nominal a curve from samples of it (the CAD's
boundary near a trim-edge point, the projected line of a character line).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.interpolate import make_lsq_spline

from .arrays import Points, Scalars
from .deviations import robust_location
from .errors import InvalidInput
from .nurbs import Curve, EdgeFit, fit_edge

__all__ = ["CurveParams", "EdgeCurve", "curve_offset", "nominal_curve"]

# The nominal's knot spans: one per this length of edge (a cubic through a
# hole's rim of 5 mm radius then stays within microns of the circle).
_NOMINAL_SPAN_MM = 2.0
_NOMINAL_DEGREE = 3
# The half-normal's median is 0.6745 sigma: sigma from the residuals' median length.
_HALF_NORMAL = 1.0 / 0.6745
_REJECT_ROUNDS = 3
# Samples of a curve that find foot points and folds.
_DENSE = 400
# A floor of the points' scatter for the first rejection (mm).
_MIN_SPREAD_MM = 0.02
# The smoothing of the one-span fit a folded curve is fitted again with.
_STIFF = 1e-2


@dataclass(frozen=True)
class CurveParams:
    """How measured edge points are fitted as a curve.

    Attributes
    ----------
    points_per_span : int
        One knot span per this many points (fewer spans: a smoother curve
        that averages more points per span).
    min_span_mm : float
        No span shorter than this along the measured edge.
    max_spans : int
    degree : int
    smoothing : float
        The fit's penalty on the control points' second differences.
    reject_sigma : float
        Points farther from the fitted curve than this many robust sigmas of
        the residuals are dropped and the curve fitted again.
    samples : int
        Nominal parameters the deviation is read at.
    tolerance : float
        The fit stops when its cost falls by less than this fraction in an
        iteration: the curve's shape has settled long before its foot points
        stop sliding along it.
    max_iterations : int
        A fit still going after this many iterations is not trusted.
    """

    points_per_span: int = 10
    min_span_mm: float = 2.5
    max_spans: int = 8
    degree: int = 3
    smoothing: float = 1e-6
    reject_sigma: float = 3.0
    samples: int = 100
    tolerance: float = 1e-5
    max_iterations: int = 1000


@dataclass(frozen=True)
class EdgeCurve:
    """A measured edge's fitted curve against its nominal, over the measured span.

    Attributes
    ----------
    offset_mm : float
        Mean signed offset of the fitted curve along the edge's normal (positive
        along ``across``), weighted by length along the nominal.
    sigma_mm : float
        1 sigma of ``offset_mm``, from the points' scatter about the curve.
    max_mm : float
        The signed offset of largest magnitude along the span.
    at : (3,) tuple of float, mm, CAD frame
        The nominal point where it lies.
    rms_mm : float
        The points' residual from the fitted curve.
    support : int
        Points the final fit used.
    span_mm : float
        Length of the nominal the readings cover.
    points : (k, 3) float64, mm
        The nominal's samples over the span.
    offsets : (k,) float64, mm
        The fitted curve's signed offset at each.
    edge : EdgeFit
        The final fit.
    """

    offset_mm: float
    sigma_mm: float
    max_mm: float
    at: tuple[float, float, float]
    rms_mm: float
    support: int
    span_mm: float
    points: Points
    offsets: Scalars
    edge: EdgeFit


def nominal_curve(samples: Points) -> Curve:
    """A cubic NURBS curve through samples of a nominal edge, in their order along it.

    The samples are ordered along their principal direction, so the edge may
    bend but must not turn back on itself (a hole's rim: less than half of it).

    Parameters
    ----------
    samples : (K, 3) float64, mm, CAD frame, K >= 4, in any order

    Raises
    ------
    InvalidInput
        Too few distinct samples, or all at one place.
    """
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or not np.all(np.isfinite(x)):
        raise InvalidInput(f"samples must be a finite (K, 3) array, got shape {x.shape}")
    centred = x - x.mean(axis=0)
    if len(x) < _NOMINAL_DEGREE + 1:
        raise InvalidInput(f"a nominal edge needs at least 4 samples, got {len(x)}")
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    x = x[np.argsort(centred @ vt[0], kind="stable")]
    step = np.linalg.norm(np.diff(x, axis=0), axis=1)
    x = x[np.r_[True, step > 1e-9]]
    chord = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(x, axis=0), axis=1))]
    length = float(chord[-1])
    if len(x) < _NOMINAL_DEGREE + 1 or length <= 0:
        raise InvalidInput("the nominal edge's samples lie at one place")
    u = chord / length
    p = _NOMINAL_DEGREE
    # Least squares needs a sample inside every span (Schoenberg-Whitney).
    spans = max(1, min(int(length / _NOMINAL_SPAN_MM), (len(x) - 1) // 2))
    knots = np.r_[np.zeros(p + 1), np.linspace(0.0, 1.0, spans + 1)[1:-1], np.ones(p + 1)]
    spline = make_lsq_spline(u, x, knots, k=p)
    return Curve(p, knots, spline.c)


def curve_offset(
    points: Points,
    nominal: Curve,
    samples: Points,
    across: Points,
    params: CurveParams | None = None,
    *,
    min_support: int = 10,
    read: npt.NDArray[np.bool_] | None = None,
) -> tuple[EdgeCurve | None, str | None]:
    """The fitted curve of measured edge points, against the nominal along its normal.

    Parameters
    ----------
    points : (m, 3) float64, mm, CAD frame, in any order
    nominal : Curve, the design's edge
    samples : (K, 3) float64, mm
        Points of the nominal edge, each with its
    across : (K, 3) float64
        unit normal to the edge in the surface, the direction of a positive
        offset: the deviation at a nominal point is taken along its nearest
        sample's.
    params : CurveParams
    min_support : int
        Points needed (at least the curve's degree + 1); after the outliers
        are dropped, the curve's degree + 1 must be left.
    read : (K,) bool, optional
        The samples the curve is read at: the offset's mean, the largest and
        the span are those of the curve's stretch nearest to them (None: all).
        The points beyond it still shape the curve, so that the stretch read
        need not end where the fit ends, which follows its last points least
        firmly.

    Returns
    -------
    measurement : EdgeCurve or None
    reason : str or None
        Why there is none: too few points, or the fit did not converge.
    """
    p = params if params is not None else CurveParams()
    x = np.asarray(points, dtype=np.float64)
    need = max(min_support, p.degree + 1)
    if len(x) < need:
        return None, f"{len(x)} edge points for the fitted curve, {need} needed"
    # Gross outliers first, by their offsets from the nominal (the single points' robust
    # scatter, which holds an edge's bend too): an orthogonal-distance fit bends, even
    # loops, to reach them.
    dense = np.linspace(*nominal.domain, _DENSE)
    line = nominal.evaluate(dense)
    near = np.argmin(((x[:, None, :] - line[None, :, :]) ** 2).sum(-1), axis=1)
    side = across[np.argmin(((line[near][:, None, :] - samples[None]) ** 2).sum(-1), axis=1)]
    off = np.einsum("ij,ij->i", x - line[near], side)
    loc, spread = robust_location(off)
    x = x[np.abs(off - loc) <= p.reject_sigma * max(spread, _MIN_SPREAD_MM)]
    # The support asked for is of the points found; those left must still carry a curve.
    least = p.degree + 1
    if len(x) < least:
        return None, f"{len(x)} edge points agree with one edge, {least} needed"
    fit, why = _fit(x, nominal, p)
    if fit is None:
        return None, why
    # Drop the points the curve does not explain (a grain's edge, a stray match) and fit
    # again, until none is dropped: an outlier that ends the ordered points holds the
    # curve's end (the fit ties it there), so it only stands out once another is gone.
    for _ in range(_REJECT_ROUNDS):
        scale = _HALF_NORMAL * float(np.median(fit.fit.distances))
        keep = np.ones(len(x), bool)
        keep[fit.order] = fit.fit.distances <= p.reject_sigma * max(scale, 1e-3)
        if keep.all():
            break
        if keep.sum() < least:
            return None, f"{int(keep.sum())} edge points agree with one curve, {least} needed"
        x = x[keep]
        fit, why = _fit(x, nominal, p)
        if fit is None:
            return None, why
    if _folds(fit, nominal):
        # Few, scattered points can hold a loop in a curve of several spans: a single,
        # stiffer span follows the edge's place and its gentle bend, not the loop.
        stiff = dataclasses.replace(p, max_spans=1, smoothing=max(p.smoothing, _STIFF))
        fit, why = _fit(x, nominal, stiff)
        if fit is None:
            return None, why
        if _folds(fit, nominal):
            return None, "the curve fitted to the edge points folds back on itself"
    dev = fit.deviation
    near = np.argmin(((dev.points[:, None, :] - samples[None, :, :]) ** 2).sum(-1), axis=1)
    off = np.einsum("ij,ij->i", dev.vectors, across[near])
    # Length along the nominal per sample, for the mean over the span.
    _, d1 = nominal.evaluate(dev.params, 1)
    w = np.linalg.norm(d1, axis=1) * np.gradient(dev.params)
    at_points = dev.points
    if read is not None:
        inside = np.asarray(read, dtype=bool)[near]
        if not inside.any():
            return None, "the points' curve does not reach the stretch to be measured"
        off, w, at_points = off[inside], w[inside], at_points[inside]
    k = int(np.argmax(np.abs(off)))
    rms = float(fit.fit.rms_mm)
    # The constant offset lies in the curve's span: its mean has the variance of a mean
    # of the points, their scatter counted over the fit's degrees of freedom.
    dof = max(len(x) - len(fit.fit.curve.control_points), 1)
    return (
        EdgeCurve(
            offset_mm=float(np.sum(w * off) / np.sum(w)),
            sigma_mm=rms / math.sqrt(dof),
            max_mm=float(off[k]),
            at=(float(at_points[k, 0]), float(at_points[k, 1]), float(at_points[k, 2])),
            rms_mm=rms,
            support=len(x),
            span_mm=float(np.sum(w)),
            points=at_points,
            offsets=off,
            edge=fit,
        ),
        None,
    )


def _folds(fit: EdgeFit, nominal: Curve) -> bool:
    """Whether the fitted curve turns back along the nominal somewhere (a loop or a fold, which
    an orthogonal-distance fit can settle in): its points, in order, must run along the
    nominal one way."""
    c = fit.fit.curve
    pts = c.evaluate(np.linspace(*c.domain, _DENSE // 2))
    dense = np.linspace(*nominal.domain, _DENSE)
    line = nominal.evaluate(dense)
    t = dense[np.argmin(((pts[:, None, :] - line[None, :, :]) ** 2).sum(-1), axis=1)]
    step = dense[1] - dense[0]
    return bool(np.any(np.diff(t) < -2 * step))


def _fit(x: Points, nominal: Curve, p: CurveParams) -> tuple[EdgeFit | None, str | None]:
    """One fit of the points, its spans chosen from their number and the span they cover."""
    dense = np.linspace(*nominal.domain, _DENSE)
    line = nominal.evaluate(dense)
    t = dense[np.argmin(((x[:, None, :] - line[None, :, :]) ** 2).sum(-1), axis=1)]
    lo, hi = float(t.min()), float(t.max())
    inside = (dense >= lo) & (dense <= hi)
    length = float(np.sum(np.linalg.norm(np.diff(line[inside], axis=0), axis=1)))
    spans = min(len(x) // p.points_per_span, int(length / p.min_span_mm), p.max_spans)
    spans = max(1, min(spans, len(x) - p.degree))
    try:
        fit = fit_edge(
            x, nominal, spans=spans, degree=p.degree, samples=p.samples, smoothing=p.smoothing,
            max_iterations=p.max_iterations, tolerance=p.tolerance,
        )  # fmt: skip
    except InvalidInput as exc:
        return None, f"the edge points give no curve: {exc}"
    if not fit.fit.converged:
        return None, f"the curve fit to the edge points stopped: {fit.fit.stop_reason}"
    return fit, None
