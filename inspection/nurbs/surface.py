"""Rational B-spline (NURBS) surfaces: points and first derivatives, per point and on grids."""

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


class Surface:
    """A NURBS surface of degrees ``(p, q)``.

    Parameters
    ----------
    degree_u, degree_v : int >= 1
    knots_u : (nu + p + 1,) float64, non-decreasing (clamped or not)
    knots_v : (nv + q + 1,) float64
    control_points : (nu, nv, 3) float64, mm
    weights : (nu, nv) float64 > 0, or None for a non-rational surface

    The arrays are copied and made read-only; the weighted control points
    ``Pw = (w P, w)`` the kernels read are formed once here.
    """

    def __init__(
        self,
        degree_u: int,
        degree_v: int,
        knots_u: Any,
        knots_v: Any,
        control_points: Any,
        weights: Any = None,
    ) -> None:
        self.degree_u = check_degree(degree_u, "degree_u")
        self.degree_v = check_degree(degree_v, "degree_v")
        cp = np.array(control_points, dtype=np.float64)
        if cp.ndim != 3 or cp.shape[2] != 3:
            raise InvalidInput(f"control_points must have shape (nu, nv, 3), got {cp.shape}")
        if not np.all(np.isfinite(cp)):
            raise InvalidInput("control_points must be finite")
        nu, nv = cp.shape[:2]
        self.knots_u = check_knots(knots_u, self.degree_u, nu, "knots_u")
        self.knots_v = check_knots(knots_v, self.degree_v, nv, "knots_v")
        self.control_points = cp
        self.weights = check_weights(weights, (nu, nv))
        pw = np.empty((nu, nv, 4))
        pw[..., :3] = cp * self.weights[..., None]
        pw[..., 3] = self.weights
        self._pw = pw
        for a in (self.knots_u, self.knots_v, self.control_points, self.weights, self._pw):
            a.setflags(write=False)
        self.domain_u = domain(self.knots_u, self.degree_u)
        self.domain_v = domain(self.knots_v, self.degree_v)

    @property
    def homogeneous(self) -> FloatArray:
        """(nu, nv, 4) float64: the weighted control points ``(w P, w)`` (read-only)."""
        return self._pw

    @property
    def shape(self) -> tuple[int, int]:
        """The number of control points (nu, nv)."""
        return self.control_points.shape[0], self.control_points.shape[1]

    @overload
    def evaluate(self, u: Any, v: Any, derivatives: Literal[0] = 0) -> FloatArray: ...

    @overload
    def evaluate(
        self, u: Any, v: Any, derivatives: Literal[1]
    ) -> tuple[FloatArray, FloatArray, FloatArray]: ...

    @overload
    def evaluate(self, u: Any, v: Any, derivatives: Literal[2]) -> tuple[FloatArray, ...]: ...

    def evaluate(self, u: Any, v: Any, derivatives: int = 0) -> FloatArray | tuple[FloatArray, ...]:
        """Points at the parameter pairs ``(u[i], v[i])``.

        Parameters
        ----------
        u, v : (n,) float64 in ``domain_u`` and ``domain_v`` (or scalars)
        derivatives : 0, 1 or 2

        Returns
        -------
        points : (n, 3) float64, mm; with ``derivatives=1`` the tuple
        ``(points, d_du, d_dv)`` of (n, 3) arrays (mm per unit parameter);
        with ``derivatives=2`` also ``d_duu, d_duv, d_dvv``.
        """
        nd = check_derivatives(derivatives, 2)
        us = check_params(u, self.domain_u, "u")
        vs = check_params(v, self.domain_v, "v")
        if us.shape != vs.shape:
            raise InvalidInput(f"u and v must have the same length, got {us.size} and {vs.size}")
        n = us.shape[0]
        if nd == 2:
            out = np.empty((6, n, 3))
            kernels.surface_points2(
                self.degree_u, self.degree_v, self.knots_u, self.knots_v, self._pw, us, vs, out
            )
            return tuple(out)
        pts = np.empty((n, 3))
        d_du = np.empty((n if nd else 0, 3))
        d_dv = np.empty((n if nd else 0, 3))
        kernels.surface_points(
            self.degree_u, self.degree_v, self.knots_u, self.knots_v, self._pw,
            us, vs, nd, pts, d_du, d_dv,
        )  # fmt: skip
        return (pts, d_du, d_dv) if nd else pts

    @overload
    def evaluate_grid(self, us: Any, vs: Any, derivatives: Literal[0] = 0) -> FloatArray: ...

    @overload
    def evaluate_grid(
        self, us: Any, vs: Any, derivatives: Literal[1]
    ) -> tuple[FloatArray, FloatArray, FloatArray]: ...

    def evaluate_grid(
        self, us: Any, vs: Any, derivatives: int = 0
    ) -> FloatArray | tuple[FloatArray, FloatArray, FloatArray]:
        """Points on the regular grid ``us x vs``, the basis computed once per grid line.

        Parameters
        ----------
        us : (m,) float64 in ``domain_u``
        vs : (k,) float64 in ``domain_v``
        derivatives : 0 or 1

        Returns
        -------
        points : (m, k, 3) float64, mm, ``points[i, j] = S(us[i], vs[j])``; with
        ``derivatives=1`` the tuple ``(points, d_du, d_dv)`` of (m, k, 3) arrays.
        """
        nd = check_derivatives(derivatives, 1)
        gu = check_params(us, self.domain_u, "us")
        gv = check_params(vs, self.domain_v, "vs")
        m, k = gu.shape[0], gv.shape[0]
        pts = np.empty((m * k, 3))
        d_du = np.empty((m * k if nd else 0, 3))
        d_dv = np.empty((m * k if nd else 0, 3))
        kernels.surface_grid(
            self.degree_u, self.degree_v, self.knots_u, self.knots_v, self._pw,
            gu, gv, nd, pts, d_du, d_dv,
        )  # fmt: skip
        if nd:
            return pts.reshape(m, k, 3), d_du.reshape(m, k, 3), d_dv.reshape(m, k, 3)
        return pts.reshape(m, k, 3)
