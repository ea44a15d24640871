"""Checks of degrees, knot vectors, weights and parameters at the public entry points.

A knot vector of a degree-``p`` basis over ``n + 1`` control points has
``n + p + 2`` non-decreasing finite knots; its parameter domain is
``[knots[p], knots[n + 1]]``, the interval on which the ``p + 1`` non-zero
functions sum to one. A *clamped* vector repeats its end knots ``p + 1``
times, so that the curve starts and ends at its end control points; an
*unclamped* one does not, and its domain is then smaller than the knots'
range. Both are accepted. An interior knot repeated more than ``p`` times
would split the curve in two, and is refused.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import InvalidInput

FloatArray = npt.NDArray[np.float64]


def check_degree(degree: Any, name: str) -> int:
    """The degree as an int >= 1, or InvalidInput."""
    if isinstance(degree, bool) or not isinstance(degree, int | np.integer) or degree < 1:
        raise InvalidInput(f"{name} must be an integer >= 1, got {degree!r}")
    return int(degree)


def check_knots(knots: Any, degree: int, n_ctrl: int, name: str) -> FloatArray:
    """A validated float64 copy of a knot vector for ``n_ctrl`` control points."""
    k = np.array(knots, dtype=np.float64)
    if k.ndim != 1:
        raise InvalidInput(f"{name} must be a 1-D sequence, got shape {k.shape}")
    if n_ctrl < degree + 1:
        raise InvalidInput(
            f"a degree-{degree} basis needs at least {degree + 1} control points, got {n_ctrl}"
        )
    want = n_ctrl + degree + 1
    if k.shape[0] != want:
        raise InvalidInput(
            f"{name} must have n_control + degree + 1 = {n_ctrl} + {degree} + 1 = {want} knots,"
            f" got {k.shape[0]}"
        )
    if not np.all(np.isfinite(k)):
        raise InvalidInput(f"{name} must be finite")
    if np.any(np.diff(k) < 0):
        raise InvalidInput(f"{name} must be non-decreasing")
    lo, hi = k[degree], k[n_ctrl]
    if not lo < hi:
        raise InvalidInput(
            f"{name} leaves an empty parameter domain [knots[{degree}], knots[{n_ctrl}]]"
            f" = [{lo}, {hi}]"
        )
    interior = k[degree + 1 : n_ctrl]
    if interior.size:
        _, counts = np.unique(interior, return_counts=True)
        if counts.max() > degree:
            raise InvalidInput(
                f"{name} repeats an interior knot {counts.max()} times, more than the degree"
                f" {degree}: the curve would fall apart there"
            )
    return k


def domain(knots: FloatArray, degree: int) -> tuple[float, float]:
    """The parameter domain ``[knots[p], knots[n + 1]]``."""
    n_ctrl = knots.shape[0] - degree - 1
    return float(knots[degree]), float(knots[n_ctrl])


def check_weights(weights: Any, shape: tuple[int, ...]) -> FloatArray:
    """Finite, strictly positive weights of the given shape (all ones for None)."""
    if weights is None:
        return np.ones(shape)
    w = np.array(weights, dtype=np.float64)
    if w.shape != shape:
        raise InvalidInput(f"weights must have shape {shape}, got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise InvalidInput("weights must be finite and strictly positive")
    return w


def check_params(values: Any, dom: tuple[float, float], name: str) -> FloatArray:
    """A contiguous 1-D float64 copy of parameters inside the domain."""
    t = np.atleast_1d(np.array(values, dtype=np.float64))
    if t.ndim != 1:
        raise InvalidInput(f"{name} must be a scalar or a 1-D array, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InvalidInput(f"{name} must be finite")
    if t.size and (t.min() < dom[0] or t.max() > dom[1]):
        raise InvalidInput(
            f"{name} must lie in the parameter domain [{dom[0]}, {dom[1]}],"
            f" got [{t.min()}, {t.max()}]"
        )
    return np.ascontiguousarray(t)


def check_derivatives(derivatives: Any, highest: int) -> int:
    """The derivative order as an int in [0, highest]."""
    ok = isinstance(derivatives, int | np.integer) and not isinstance(derivatives, bool)
    if not ok or not 0 <= derivatives <= highest:
        raise InvalidInput(f"derivatives must be one of 0..{highest}, got {derivatives!r}")
    return int(derivatives)
