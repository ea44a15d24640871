"""Floating-point operation counts of the two ways of evaluating a surface on a grid.

The counts follow the loops of :mod:`.basis` and :mod:`.kernels` one for one
(an addition, a multiplication, a division or a negation is one operation;
span searches are comparisons and are not counted), so that the bench can
set the measured speed-up beside the arithmetic one.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import InvalidInput
from .kernels import GRID_TERMS
from .knots import check_degree, check_derivatives


def basis_flops(degree: int, derivatives: int) -> int:
    """Operations of one call of :func:`.basis.ders_basis`."""
    p = check_degree(degree, "degree")
    nd = min(check_derivatives(derivatives, 2), p)
    # The triangle (A2.2): left and right, then per (j, r) one knot sum, one
    # division and three operations of the recursion.
    total = sum(2 + 5 * j for j in range(1, p + 1))
    for r in range(p + 1):
        for k in range(1, nd + 1):
            rk, pk = r - k, p - k
            if r >= k:
                total += 2
            j1 = 1 if rk >= -1 else -rk
            j2 = k - 1 if r - 1 <= pk else p - r
            total += 4 * max(0, j2 - j1 + 1)
            if r <= pk:
                total += 4
    # The factor p! / (p - k)! of each derivative row.
    return total + nd * (p + 1)


def _rational_flops(nd: int) -> int:
    # One reciprocal and three products; per derivative three (sub, mul, mul).
    return 4 + 2 * 9 * nd


@dataclass(frozen=True)
class EvaluationFlops:
    """Operation counts of evaluating an ``m x k`` parameter grid.

    ``per_point``: every point on its own (:func:`.kernels.surface_points`);
    ``grid``: the basis once per grid line, the row contraction once per
    control column, and per grid point ``max(q + 1, GRID_TERMS)`` terms of
    each homogeneous sum (:func:`.kernels.surface_grid`: a degree below 3
    runs the four-term loop with zero terms).
    """

    per_point: int
    grid: int

    @property
    def ratio(self) -> float:
        return self.per_point / self.grid


def evaluation_flops(
    degree_u: int, degree_v: int, m: int, k: int, n_ctrl_v: int, derivatives: int = 1
) -> EvaluationFlops:
    """Operation counts of points (and first derivatives) on an ``m x k`` grid.

    Parameters
    ----------
    degree_u, degree_v : the degrees ``p`` and ``q``
    m, k : the grid's sizes along u and v
    n_ctrl_v : control points along v (the columns of the row contraction)
    derivatives : 0 (points) or 1 (points and first derivatives)
    """
    p = check_degree(degree_u, "degree_u")
    q = check_degree(degree_v, "degree_v")
    nd = check_derivatives(derivatives, 1)
    if min(m, k, n_ctrl_v) < 1:
        raise InvalidInput("grid sizes and the number of control columns must be >= 1")
    rational = _rational_flops(nd)
    # Per point: both bases, then per row k the contraction over l (4
    # homogeneous coordinates, a multiply-add each, twice with the
    # v-derivative) and its share of the value and the derivatives.
    point = (
        basis_flops(p, nd)
        + basis_flops(q, nd)
        + (p + 1) * ((q + 1) * 8 * (1 + nd) + 8 * (1 + 2 * nd))
        + rational
    )
    per_point = m * k * point
    terms = max(q + 1, GRID_TERMS)
    grid = (
        m * basis_flops(p, nd)
        + k * basis_flops(q, nd)
        + m * n_ctrl_v * (p + 1) * 8 * (1 + nd)
        + m * k * (terms * 8 * (1 + 2 * nd) + rational)
    )
    return EvaluationFlops(per_point=per_point, grid=grid)
