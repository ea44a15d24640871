"""B-spline basis functions and their derivatives (compiled kernels).

The algorithms of Piegl and Tiller, *The NURBS Book* (2nd ed.): the knot span
by bisection (A2.1) and the non-vanishing basis functions with their
derivatives from the triangular table of the Cox-de Boor recursion (A2.2,
A2.3). A degree-``p`` basis has ``p + 1`` non-zero functions on a span; the
kernels write them into caller-owned arrays, so that a caller evaluating
many parameters allocates its scratch once.

Callers are trusted: knots are validated by :mod:`.knots` before any kernel
sees them.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def find_span(n, p, u, knots):  # pragma: no cover
    """The knot span index ``i`` with ``knots[i] <= u < knots[i + 1]`` (A2.1).

    ``n`` is the index of the last control point; the domain's right end
    ``u == knots[n + 1]`` belongs to the last non-empty span, so that a
    closed parameter interval evaluates everywhere.
    """
    if u >= knots[n + 1]:
        # The last non-empty span (an unclamped or repeated end knot can
        # leave knots[n + 1] == knots[n]).
        i = n
        while i > p and knots[i] == knots[i + 1]:
            i -= 1
        return i
    if u <= knots[p]:
        return p
    low = p
    high = n + 1
    mid = (low + high) // 2
    while u < knots[mid] or u >= knots[mid + 1]:
        if u < knots[mid]:
            high = mid
        else:
            low = mid
        mid = (low + high) // 2
    return mid


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def ders_basis(span, u, p, knots, nd, ndu, left, right, a, out):  # pragma: no cover
    """The ``p + 1`` non-zero basis functions at ``u`` and their derivatives up
    to order ``nd`` (A2.3; ``nd = 0`` is A2.2).

    Scratch: ``ndu`` (p+1, p+1), ``left`` and ``right`` (p+1,), ``a``
    (2, p+1). Output: ``out[k, j]`` is the k-th derivative of the basis
    function ``span - p + j``, for ``k <= nd``.
    """
    # The triangle of A2.2: ndu[j][r] (r < j) holds the knot differences,
    # ndu[r][j] (r <= j) the degree-j functions; each step of the Cox-de Boor
    # recursion splits one function of degree j - 1 between two of degree j.
    ndu[0, 0] = 1.0
    for j in range(1, p + 1):
        left[j] = u - knots[span + 1 - j]
        right[j] = knots[span + j] - u
        saved = 0.0
        for r in range(j):
            ndu[j, r] = right[r + 1] + left[j - r]
            temp = ndu[r, j - 1] / ndu[j, r]
            ndu[r, j] = saved + right[r + 1] * temp
            saved = left[j - r] * temp
        ndu[j, j] = saved
    for j in range(p + 1):
        out[0, j] = ndu[j, p]
    # Derivatives of an order above the degree vanish.
    for k in range(p + 1, nd + 1):
        for j in range(p + 1):
            out[k, j] = 0.0
    nd = min(nd, p)
    if nd == 0:
        return
    # Derivatives (A2.3): the k-th derivative of N_{r,p} is a combination of
    # the degree p - k functions, with the coefficients a_{k,j} built up
    # row by row from the knot differences of the lower triangle.
    for r in range(p + 1):
        s1 = 0
        s2 = 1
        a[0, 0] = 1.0
        for k in range(1, nd + 1):
            d = 0.0
            rk = r - k
            pk = p - k
            if r >= k:
                a[s2, 0] = a[s1, 0] / ndu[pk + 1, rk]
                d = a[s2, 0] * ndu[rk, pk]
            j1 = 1 if rk >= -1 else -rk
            j2 = k - 1 if r - 1 <= pk else p - r
            for j in range(j1, j2 + 1):
                a[s2, j] = (a[s1, j] - a[s1, j - 1]) / ndu[pk + 1, rk + j]
                d += a[s2, j] * ndu[rk + j, pk]
            if r <= pk:
                a[s2, k] = -a[s1, k - 1] / ndu[pk + 1, r]
                d += a[s2, k] * ndu[r, pk]
            out[k, r] = d
            s1, s2 = s2, s1
    factor = float(p)
    for k in range(1, nd + 1):
        for j in range(p + 1):
            out[k, j] *= factor
        factor *= p - k


@njit(cache=True, nogil=True, fastmath=True)
def basis_table(p, knots, n, params, nd):  # pragma: no cover
    """Spans (m,) and basis values with derivatives (m, nd+1, p+1) of every
    parameter: the per-line basis of a grid, computed once per line."""
    m = params.shape[0]
    spans = np.empty(m, dtype=np.int64)
    table = np.empty((m, nd + 1, p + 1))
    ndu = np.empty((p + 1, p + 1))
    left = np.empty(p + 1)
    right = np.empty(p + 1)
    a = np.empty((2, p + 1))
    for i in range(m):
        s = find_span(n, p, params[i], knots)
        spans[i] = s
        ders_basis(s, params[i], p, knots, nd, ndu, left, right, a, table[i])
    return spans, table
