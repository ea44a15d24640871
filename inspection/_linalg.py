"""Small dense linear algebra for the compiled kernels (callers are trusted).

Both functions state ``fastmath=False``. numba compiles a helper once per
signature and process, with the options of the first kernel that calls it
when the helper states none: the window fits (``fastmath=True``) and the
registration (exact arithmetic) call the same solver, so whichever compiled
first would decide the other's rounding, and a fit's last bits would depend
on what ran before it in the process, or in the process that filled the
kernel cache.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, fastmath=False)
def cholesky_solve(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """Solve ``A x = b`` for a small symmetric positive definite ``A``
    (Cholesky, fixed order); ``ok`` False when ``A`` is not positive definite."""
    n = A.shape[0]
    x = np.zeros(n)
    ok = cholesky_solve_into(A, b, np.zeros((n, n)), np.empty(n), x)
    return x, ok


@numba.njit(cache=True, nogil=True, fastmath=False)
def cholesky_solve_into(
    A: np.ndarray, b: np.ndarray, Lc: np.ndarray, y: np.ndarray, x: np.ndarray
) -> bool:
    """:func:`cholesky_solve` into ``x``, with the caller's work arrays ``Lc`` (n, n)
    and ``y`` (n,): no allocation, for kernels that solve once per pixel. Returns
    False (``x`` unspecified) when ``A`` is not positive definite."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= Lc[j, k] * Lc[j, k]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        Lc[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= Lc[i, k] * Lc[j, k]
            Lc[i, j] = s / d
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= Lc[i, k] * y[k]
        y[i] = s / Lc[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= Lc[k, i] * x[k]
        x[i] = s / Lc[i, i]
    return True
