"""NURBS geometry: rational B-spline curves and surfaces, and fitting curves to points.

- :class:`Surface`: points and first derivatives at arbitrary parameters
  (:meth:`Surface.evaluate`) and on regular parameter grids
  (:meth:`Surface.evaluate_grid`, the basis computed once per grid line);
  :func:`evaluation_flops` counts the arithmetic of both ways.
- :class:`Curve`: points and derivatives up to the second, foot points.
- :func:`fit_curve`: a curve's control points and weights (degree and knots
  fixed) fitted to points by orthogonal distance.

Modules: :mod:`.basis` (the B-spline basis kernels), :mod:`.kernels` (the
compiled evaluation), :mod:`.knots` (input checks), :mod:`.surface`,
:mod:`.curve`, :mod:`.flops`, :mod:`.fit`.
"""

from __future__ import annotations

from .curve import Curve
from .fit import METHODS, CurveFit, fit_curve
from .flops import EvaluationFlops, basis_flops, evaluation_flops
from .surface import Surface

__all__ = [
    "METHODS",
    "Curve",
    "CurveFit",
    "EvaluationFlops",
    "Surface",
    "basis_flops",
    "evaluation_flops",
    "fit_curve",
]
