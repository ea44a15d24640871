"""Small dense linear algebra for the compiled kernels (callers are trusted)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def cholesky_solve(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """Solve ``A x = b`` for a small symmetric positive definite ``A``
    (Cholesky, fixed order); ``ok`` False when ``A`` is not positive definite."""
    n = A.shape[0]
    Lc = np.zeros((n, n))
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= Lc[j, k] * Lc[j, k]
        if not s > 0.0:
            return np.zeros(n), False
        d = np.sqrt(s)
        Lc[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= Lc[i, k] * Lc[j, k]
            Lc[i, j] = s / d
    y = np.empty(n)
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= Lc[i, k] * y[k]
        y[i] = s / Lc[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= Lc[k, i] * x[k]
        x[i] = s / Lc[i, i]
    return x, True
