"""A measured edge (a trim edge, a character line) as a smooth curve, and its deviation.

The points a check finds on a part's edge are scattered along it, in no
order and with noise. :func:`fit_edge` orders them along the nominal (the
design's edge), fits a NURBS curve to them by orthogonal distance
(:func:`.fit.fit_curve`, knots evenly spread over the measured span) and
gives the deviation of the fitted curve from the nominal along the part of
it that was measured (:func:`.fit.deviation_along`): the smooth curve is
the edge's shape, the noise of the single points left out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InvalidInput
from .curve import Curve
from .fit import CurveDeviation, CurveFit, Method, deviation_along, fit_curve
from .knots import FloatArray

# Samples of the nominal that start each point's projection onto it.
_START_SAMPLES = 2000


@dataclass(frozen=True)
class EdgeFit:
    """A measured edge fitted as a curve, and its deviation from the nominal.

    Attributes
    ----------
    fit : CurveFit, of the points in their order along the nominal
    order : (m,) int64, the indices of the input points in that order
    nominal_params : (m,) float64, each ordered point's foot parameter on the nominal
    deviation : CurveDeviation, along the nominal over the measured span
        (its ``vectors`` from the nominal to the fitted curve, mm)
    max_mm, rms_mm : float, of ``deviation.distances``
    """

    fit: CurveFit
    order: np.ndarray
    nominal_params: FloatArray
    deviation: CurveDeviation
    max_mm: float
    rms_mm: float


def fit_edge(
    points: Any,
    nominal: Curve,
    *,
    spans: int = 8,
    degree: int = 3,
    method: Method = "vp-gn",
    samples: int = 200,
    smoothing: float = 1e-6,
    max_iterations: int = 1000,
    tolerance: float = 1e-10,
) -> EdgeFit:
    """Fit measured edge points with a smooth curve and measure it against the nominal.

    Parameters
    ----------
    points : (m, 3) float64, mm, CAD frame, in any order; m >= spans + degree
    nominal : Curve, the design's edge, CAD frame
    spans : int >= 1, knot spans of the fitted curve (its control points:
        ``spans + degree``): fewer follow the edge more smoothly
    degree : int >= 1
    method : a method of :func:`.fit.fit_curve`; variable projection with
        Gauss-Newton is the fastest of them
    samples : int >= 2, nominal parameters the deviation is given at
    smoothing : the fit's penalty on the control points' second differences
    max_iterations, tolerance : the fit's (:func:`.fit.fit_curve`): a looser
        tolerance stops it once the curve's shape has settled, before the
        foot points have finished sliding along it

    Returns
    -------
    EdgeFit

    Raises
    ------
    InvalidInput
        Points of the wrong shape or not finite, too few for the curve,
        or all at one place along the nominal.
    """
    x = np.array(points, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or not np.all(np.isfinite(x)):
        raise InvalidInput(f"points must be a finite (m, 3) array, got shape {x.shape}")
    if not isinstance(nominal, Curve):
        raise InvalidInput(f"nominal must be a Curve, got {type(nominal).__name__}")
    for name, value, least in (("spans", spans, 1), ("degree", degree, 1), ("samples", samples, 2)):
        if not isinstance(value, int) or isinstance(value, bool) or value < least:
            raise InvalidInput(f"{name} must be an integer >= {least}, got {value!r}")
    n = spans + degree
    if x.shape[0] < n:
        raise InvalidInput(
            f"a curve of {n} control points needs at least {n} points, got {x.shape[0]}"
        )
    # Order the points by their foot parameters on the nominal.
    dense = np.linspace(*nominal.domain, _START_SAMPLES)
    cloud = nominal.evaluate(dense)
    nearest = np.argmin(((x[:, None, :] - cloud[None, :, :]) ** 2).sum(-1), axis=1)
    t_nom = nominal.project(x, dense[nearest])
    order = np.argsort(t_nom, kind="stable")
    t_sorted = t_nom[order]
    lo, hi = float(t_sorted[0]), float(t_sorted[-1])
    if not hi > lo:
        raise InvalidInput("the points lie at one place along the nominal edge")
    knots = np.r_[np.zeros(degree + 1), np.linspace(0.0, 1.0, spans + 1)[1:-1], np.ones(degree + 1)]
    # The nominal's parameters, mapped onto the fit's domain, start the foot points.
    start = (t_sorted - lo) / (hi - lo)
    fit = fit_curve(
        x[order], degree, knots, method=method, params=start, smoothing=smoothing,
        max_iterations=max_iterations, tolerance=tolerance,
    )  # fmt: skip
    deviation = deviation_along(fit.curve, nominal, samples=samples, span=(lo, hi))
    d = deviation.distances
    return EdgeFit(
        fit=fit,
        order=order,
        nominal_params=t_sorted,
        deviation=deviation,
        max_mm=float(d.max()),
        rms_mm=float(np.sqrt(np.mean(d**2))),
    )
