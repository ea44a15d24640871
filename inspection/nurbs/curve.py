"""Rational B-spline (NURBS) curves: points and derivatives up to the second."""

from __future__ import annotations

from typing import Any, Literal, overload

import numpy as np

from ..errors import InvalidInput
from . import kernels
from .knots import (
    FloatArray,
    check_degree,
    check_derivatives,
    check_knots,
    check_params,
    check_weights,
    domain,
)


class Curve:
    """A NURBS curve of degree ``p``.

    Parameters
    ----------
    degree : int >= 1
    knots : (n + p + 1,) float64, non-decreasing (clamped or not)
    control_points : (n, 3) float64, mm
    weights : (n,) float64 > 0, or None for a non-rational curve
    """

    def __init__(self, degree: int, knots: Any, control_points: Any, weights: Any = None) -> None:
        self.degree = check_degree(degree, "degree")
        cp = np.array(control_points, dtype=np.float64)
        if cp.ndim != 2 or cp.shape[1] != 3:
            raise InvalidInput(f"control_points must have shape (n, 3), got {cp.shape}")
        if not np.all(np.isfinite(cp)):
            raise InvalidInput("control_points must be finite")
        self.knots = check_knots(knots, self.degree, cp.shape[0], "knots")
        self.control_points = cp
        self.weights = check_weights(weights, (cp.shape[0],))
        pw = np.empty((cp.shape[0], 4))
        pw[:, :3] = cp * self.weights[:, None]
        pw[:, 3] = self.weights
        self._pw = pw
        for a in (self.knots, self.control_points, self.weights, self._pw):
            a.setflags(write=False)
        self.domain = domain(self.knots, self.degree)

    @overload
    def evaluate(self, t: Any, derivatives: Literal[0] = 0) -> FloatArray: ...

    @overload
    def evaluate(self, t: Any, derivatives: Literal[1, 2]) -> tuple[FloatArray, ...]: ...

    def evaluate(self, t: Any, derivatives: int = 0) -> FloatArray | tuple[FloatArray, ...]:
        """Points at the parameters ``t``.

        Parameters
        ----------
        t : (n,) float64 in ``domain`` (or a scalar)
        derivatives : 0, 1 or 2

        Returns
        -------
        points : (n, 3) float64, mm; with ``derivatives=k > 0`` the tuple
        ``(points, d_dt, ...)`` of k + 1 (n, 3) arrays.
        """
        nd = check_derivatives(derivatives, 2)
        ts = check_params(t, self.domain, "t")
        out = np.empty((nd + 1, ts.shape[0], 3))
        kernels.curve_points(self.degree, self.knots, self._pw, ts, nd, out)
        return tuple(out) if nd else out[0]

    def project(self, points: Any, params: Any, *, iterations: int = 20) -> FloatArray:
        """Foot-point parameters of points on the curve, by Newton's method on
        ``(C(t) - x) . C'(t) = 0`` from the given start parameters.

        Parameters
        ----------
        points : (n, 3) float64, mm
        params : (n,) start parameters in ``domain`` (near the foot points)
        iterations : at most this many Newton steps (fewer once no point moves by
            1e-12 mm); a step that would leave the domain stops at its end

        Returns
        -------
        (n,) float64 parameters
        """
        x = np.array(points, dtype=np.float64)
        t = check_params(params, self.domain, "params").copy()
        if x.shape != (t.shape[0], 3):
            raise InvalidInput(f"points must have shape ({t.shape[0]}, 3), got {x.shape}")
        for _ in range(iterations):
            c, d1, d2 = self.evaluate(t, derivatives=2)
            r = c - x
            g = np.einsum("ij,ij->i", r, d1)
            h = np.einsum("ij,ij->i", d1, d1) + np.einsum("ij,ij->i", r, d2)
            # Away from the foot point h can turn negative; a Gauss-Newton
            # step (|C'|^2 alone) still descends there.
            h = np.where(h > 0, h, np.einsum("ij,ij->i", d1, d1))
            new = np.clip(t - g / h, *self.domain)
            moved = np.abs(new - t) * np.linalg.norm(d1, axis=1)
            t = new
            if moved.max(initial=0.0) < 1e-12:
                break
        return t
