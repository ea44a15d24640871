"""Compiled evaluation of rational curves and surfaces, point by point and on grids.

A NURBS surface is evaluated in homogeneous coordinates: with the weighted
control points ``Pw = (w P, w)`` the numerator and denominator
``A(u, v) = sum_k sum_l N_k(u) M_l(v) Pw_kl`` are a plain tensor-product
B-spline, and the point and its first derivatives follow by the quotient rule
(The NURBS Book, eq. 4.19):

    S = A / w,    S_u = (A_u - w_u S) / w,    S_v = (A_v - w_v S) / w.

Two ways of evaluating many parameters share the same basis kernel
(:func:`.basis.ders_basis`) and the same quotient rule:

- :func:`surface_points`: each parameter pair on its own: two span searches,
  two basis evaluations and the full ``(p+1) x (q+1)`` contraction per point;
- :func:`surface_grid`: a regular grid ``us x vs``: the basis of every grid
  line is computed once (:func:`.basis.basis_table`), and along a grid row
  ``u = us[i]`` the contraction over ``k`` is done once per control column,
  ``Q_l = sum_k N_k(u) Pw_kl`` and ``R_l = sum_k N'_k(u) Pw_kl``. The grid
  points of the row on one v-span then read the same ``q + 1`` columns: that
  ``(q+1) x 8`` block times the run's v-basis gives A and A_u, the block's Q
  half times the v-basis' derivative gives A_v, ``q + 1`` terms per sum and
  point, and the quotient rule forms ``1 / w`` and S once for both
  derivatives.

Their operation counts are in :mod:`.flops`. The kernels run on one thread
(no ``prange``): callers may evaluate from several threads of their own.
Callers are trusted: shapes, knots and parameters are checked by the classes.
"""

from __future__ import annotations

import numpy as np
from numba import njit, uint64

from .basis import basis_table, ders_basis, find_span


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _rational(a0, a1, a2, w, out, i):  # pragma: no cover
    """Row ``i`` of ``out`` = the point of homogeneous coordinates (a0, a1, a2, w);
    returns (x, y, z, 1 / w) for the derivatives' quotient rule."""
    inv = 1.0 / w
    x = a0 * inv
    y = a1 * inv
    z = a2 * inv
    out[i, 0] = x
    out[i, 1] = y
    out[i, 2] = z
    return x, y, z, inv


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _rational_derivative(b0, b1, b2, bw, x, y, z, inv, out, i):  # pragma: no cover
    """Row ``i`` of ``out`` = (B - b_w S) / w, the first derivative of a rational point."""
    out[i, 0] = (b0 - bw * x) * inv
    out[i, 1] = (b1 - bw * y) * inv
    out[i, 2] = (b2 - bw * z) * inv


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _surface_point(
    p, q, knots_u, knots_v, pw, u, v, nd, ndu_u, left_u, right_u, a_u, bu,
    ndu_v, left_v, right_v, a_v, bv, pts, d_du, d_dv, i,
):  # pragma: no cover  # fmt: skip
    """Row ``i`` of the outputs: the point (and first derivatives) at (u, v)."""
    su = find_span(pw.shape[0] - 1, p, u, knots_u)
    ders_basis(su, u, p, knots_u, nd, ndu_u, left_u, right_u, a_u, bu)
    sv = find_span(pw.shape[1] - 1, q, v, knots_v)
    ders_basis(sv, v, q, knots_v, nd, ndu_v, left_v, right_v, a_v, bv)
    c0 = c1 = c2 = c3 = 0.0
    u0 = u1 = u2 = u3 = 0.0
    v0 = v1 = v2 = v3 = 0.0
    for k in range(p + 1):
        # A4.3: the row's contraction over l first, then its share of
        # the sum over k (and of the u-derivative with N'_k).
        t0 = t1 = t2 = t3 = 0.0
        s0 = s1 = s2 = s3 = 0.0
        row = su - p + k
        for l in range(q + 1):
            c = sv - q + l
            b = bv[0, l]
            t0 += b * pw[row, c, 0]
            t1 += b * pw[row, c, 1]
            t2 += b * pw[row, c, 2]
            t3 += b * pw[row, c, 3]
            if nd:
                b = bv[1, l]
                s0 += b * pw[row, c, 0]
                s1 += b * pw[row, c, 1]
                s2 += b * pw[row, c, 2]
                s3 += b * pw[row, c, 3]
        b = bu[0, k]
        c0 += b * t0
        c1 += b * t1
        c2 += b * t2
        c3 += b * t3
        if nd:
            b = bu[1, k]
            u0 += b * t0
            u1 += b * t1
            u2 += b * t2
            u3 += b * t3
            b = bu[0, k]
            v0 += b * s0
            v1 += b * s1
            v2 += b * s2
            v3 += b * s3
    x, y, z, inv = _rational(c0, c1, c2, c3, pts, i)
    if nd:
        _rational_derivative(u0, u1, u2, u3, x, y, z, inv, d_du, i)
        _rational_derivative(v0, v1, v2, v3, x, y, z, inv, d_dv, i)


@njit(cache=True, nogil=True, fastmath=True)
def surface_points(p, q, knots_u, knots_v, pw, us, vs, nd, pts, d_du, d_dv):  # pragma: no cover
    """Points (and with ``nd = 1`` first derivatives) at the parameter pairs
    ``(us[i], vs[i])``, each computed from scratch."""
    ndu_u = np.empty((p + 1, p + 1))
    left_u = np.empty(p + 1)
    right_u = np.empty(p + 1)
    a_u = np.empty((2, p + 1))
    ndu_v = np.empty((q + 1, q + 1))
    left_v = np.empty(q + 1)
    right_v = np.empty(q + 1)
    a_v = np.empty((2, q + 1))
    bu = np.empty((nd + 1, p + 1))
    bv = np.empty((nd + 1, q + 1))
    for i in range(us.shape[0]):
        _surface_point(
            p, q, knots_u, knots_v, pw, us[i], vs[i], nd, ndu_u, left_u, right_u, a_u, bu,
            ndu_v, left_v, right_v, a_v, bv, pts, d_du, d_dv, i,
        )  # fmt: skip


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _surface_point2(
    p, q, knots_u, knots_v, pw, u, v, ndu_u, left_u, right_u, a_u, bu,
    ndu_v, left_v, right_v, a_v, bv, out, h,
):  # pragma: no cover  # fmt: skip
    """``out`` (6, 3): S, S_u, S_v, S_uu, S_uv, S_vv at (u, v) (NURBS Book eq.
    4.20: the quotient rule applied twice); ``h`` (6, 4) scratch for the
    homogeneous sums A, A_u, A_v, A_uu, A_uv, A_vv."""
    su = find_span(pw.shape[0] - 1, p, u, knots_u)
    ders_basis(su, u, p, knots_u, 2, ndu_u, left_u, right_u, a_u, bu)
    sv = find_span(pw.shape[1] - 1, q, v, knots_v)
    ders_basis(sv, v, q, knots_v, 2, ndu_v, left_v, right_v, a_v, bv)
    for r in range(6):
        for c in range(4):
            h[r, c] = 0.0
    for k in range(p + 1):
        row = su - p + k
        for l in range(q + 1):
            col = sv - q + l
            for c in range(4):
                w = pw[row, col, c]
                h[0, c] += bu[0, k] * bv[0, l] * w
                h[1, c] += bu[1, k] * bv[0, l] * w
                h[2, c] += bu[0, k] * bv[1, l] * w
                h[3, c] += bu[2, k] * bv[0, l] * w
                h[4, c] += bu[1, k] * bv[1, l] * w
                h[5, c] += bu[0, k] * bv[2, l] * w
    inv = 1.0 / h[0, 3]
    for c in range(3):
        s0 = h[0, c] * inv
        s_u = (h[1, c] - h[1, 3] * s0) * inv
        s_v = (h[2, c] - h[2, 3] * s0) * inv
        out[0, c] = s0
        out[1, c] = s_u
        out[2, c] = s_v
        out[3, c] = (h[3, c] - 2.0 * h[1, 3] * s_u - h[3, 3] * s0) * inv
        out[4, c] = (h[4, c] - h[1, 3] * s_v - h[2, 3] * s_u - h[4, 3] * s0) * inv
        out[5, c] = (h[5, c] - 2.0 * h[2, 3] * s_v - h[5, 3] * s0) * inv


@njit(cache=True, nogil=True, fastmath=True)
def surface_points2(p, q, knots_u, knots_v, pw, us, vs, out):  # pragma: no cover
    """``out[k]`` (n, 3): S, S_u, S_v, S_uu, S_uv, S_vv at ``(us[i], vs[i])``."""
    ndu_u = np.empty((p + 1, p + 1))
    left_u = np.empty(p + 1)
    right_u = np.empty(p + 1)
    a_u = np.empty((2, p + 1))
    ndu_v = np.empty((q + 1, q + 1))
    left_v = np.empty(q + 1)
    right_v = np.empty(q + 1)
    a_v = np.empty((2, q + 1))
    bu = np.empty((3, p + 1))
    bv = np.empty((3, q + 1))
    one = np.empty((6, 3))
    h = np.empty((6, 4))
    for i in range(us.shape[0]):
        _surface_point2(
            p, q, knots_u, knots_v, pw, us[i], vs[i], ndu_u, left_u, right_u, a_u, bu,
            ndu_v, left_v, right_v, a_v, bv, one, h,
        )  # fmt: skip
        for k in range(6):
            for c in range(3):
                out[k, i, c] = one[k, c]


@njit(cache=True, nogil=True, fastmath=True)
def closest_newton(
    p, q, knots_u, knots_v, pw, x, uv, lo_u, hi_u, lo_v, hi_v, tol, max_steps, converged,
    pts, d_du, d_dv,
):  # pragma: no cover  # fmt: skip
    """Newton on (u, v) for the foot point of every ``x[i]`` from ``uv[i]``
    (updated in place), minimising |S - x|^2 / 2; steps clipped to the domain.
    Where the Hessian is not positive definite (far from the foot point, on
    the concave side) the step is Gauss-Newton's. ``converged[i]`` when a step
    would move the point by less than ``tol`` (mm), which is then not taken,
    so that ``pts``, ``d_du`` and ``d_dv`` are the surface's at ``uv``."""
    ndu_u = np.empty((p + 1, p + 1))
    left_u = np.empty(p + 1)
    right_u = np.empty(p + 1)
    a_u = np.empty((2, p + 1))
    ndu_v = np.empty((q + 1, q + 1))
    left_v = np.empty(q + 1)
    right_v = np.empty(q + 1)
    a_v = np.empty((2, q + 1))
    bu = np.empty((3, p + 1))
    bv = np.empty((3, q + 1))
    d = np.empty((6, 3))
    h = np.empty((6, 4))
    for i in range(x.shape[0]):
        u = uv[i, 0]
        v = uv[i, 1]
        converged[i] = False
        for step in range(max_steps + 1):
            _surface_point2(
                p, q, knots_u, knots_v, pw, u, v, ndu_u, left_u, right_u, a_u, bu,
                ndu_v, left_v, right_v, a_v, bv, d, h,
            )  # fmt: skip
            a11 = a12 = a22 = b1 = b2 = 0.0
            r11 = r12 = r22 = 0.0
            for c in range(3):
                r = d[0, c] - x[i, c]
                a11 += d[1, c] * d[1, c]
                a12 += d[1, c] * d[2, c]
                a22 += d[2, c] * d[2, c]
                b1 -= d[1, c] * r
                b2 -= d[2, c] * r
                r11 += r * d[3, c]
                r12 += r * d[4, c]
                r22 += r * d[5, c]
            h11, h12, h22 = a11 + r11, a12 + r12, a22 + r22
            det = h11 * h22 - h12 * h12
            if h11 > 0 and det > 1e-12 * h11 * h22:
                du = (h22 * b1 - h12 * b2) / det
                dv = (h11 * b2 - h12 * b1) / det
            else:
                det = a11 * a22 - a12 * a12
                if det > 1e-12 * a11 * a22:
                    du = (a22 * b1 - a12 * b2) / det
                    dv = (a11 * b2 - a12 * b1) / det
                else:
                    # A degenerate point (a collapsed edge): a gradient step.
                    du = b1 / max(a11, 1e-300)
                    dv = b2 / max(a22, 1e-300)
            du = min(max(u + du, lo_u), hi_u) - u
            dv = min(max(v + dv, lo_v), hi_v) - v
            moved = 0.0
            for c in range(3):
                m = d[1, c] * du + d[2, c] * dv
                moved += m * m
            if moved < tol * tol:
                converged[i] = True
                break
            if step == max_steps:
                break  # out of steps: the outputs stay at the last point evaluated
            u += du
            v += dv
        for c in range(3):
            pts[i, c] = d[0, c]
            d_du[i, c] = d[1, c]
            d_dv[i, c] = d[2, c]
        uv[i, 0] = u
        uv[i, 1] = v


# A run of grid points along a row that share their v-span reads the same
# control columns: with a fixed count of terms per point the contraction's loop
# has a length known when compiling and is unrolled (degree_v <= 3, the missing
# terms padded with zeros); higher degrees take a loop of q + 1 terms.
GRID_TERMS = 4

# The grid kernels index with unsigned integers: numba wraps a negative signed
# index around, and that branch in every access keeps the compiler from
# treating a run's reads as contiguous. Their division cannot raise
# (error_model="numpy"): the weights are positive, so the denominator is too,
# and the loop carries no exception branch.


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy", inline="always")
def _run_points(terms, w, bv, j0, j1, base, pf):  # pragma: no cover
    """Points of the grid points ``j0 <= j < j1`` of a row: ``w`` (terms, 8)
    holds the run's control columns contracted over u, ``bv`` (2, terms, k)
    the v-basis along the row; ``pf`` is the flat output, from ``base``."""
    for j in range(j0, j1):
        a0 = a1 = a2 = a3 = 0.0
        for l in range(uint64(terms)):
            b = bv[0, l, j]
            a0 += b * w[l, 0]
            a1 += b * w[l, 1]
            a2 += b * w[l, 2]
            a3 += b * w[l, 3]
        inv = 1.0 / a3
        o = base + uint64(3) * j
        pf[o] = a0 * inv
        pf[o + uint64(1)] = a1 * inv
        pf[o + uint64(2)] = a2 * inv


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy", inline="always")
def _run_derivatives(terms, w, bv, j0, j1, base, pf, uf, vf):  # pragma: no cover
    """As :func:`_run_points`, with the first derivatives: ``w[:, 4:]`` holds
    the columns contracted with the u-basis' derivative, ``bv[1]`` the
    v-basis' derivative. The homogeneous sums A, A_u, A_v are formed once and
    the quotient rule reuses S and 1 / w for both derivatives."""
    for j in range(j0, j1):
        a0 = a1 = a2 = a3 = 0.0
        u0 = u1 = u2 = u3 = 0.0
        v0 = v1 = v2 = v3 = 0.0
        for l in range(uint64(terms)):
            b = bv[0, l, j]
            d = bv[1, l, j]
            a0 += b * w[l, 0]
            a1 += b * w[l, 1]
            a2 += b * w[l, 2]
            a3 += b * w[l, 3]
            u0 += b * w[l, 4]
            u1 += b * w[l, 5]
            u2 += b * w[l, 6]
            u3 += b * w[l, 7]
            v0 += d * w[l, 0]
            v1 += d * w[l, 1]
            v2 += d * w[l, 2]
            v3 += d * w[l, 3]
        inv = 1.0 / a3
        x = a0 * inv
        y = a1 * inv
        z = a2 * inv
        o = base + uint64(3) * j
        pf[o] = x
        pf[o + uint64(1)] = y
        pf[o + uint64(2)] = z
        uf[o] = (u0 - u3 * x) * inv
        uf[o + uint64(1)] = (u1 - u3 * y) * inv
        uf[o + uint64(2)] = (u2 - u3 * z) * inv
        vf[o] = (v0 - v3 * x) * inv
        vf[o + uint64(1)] = (v1 - v3 * y) * inv
        vf[o + uint64(2)] = (v2 - v3 * z) * inv


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy", inline="always")
def _grid(terms, p, q, knots_u, knots_v, pw, us, vs, nd, pts, d_du, d_dv):  # pragma: no cover
    """:func:`surface_grid` with ``terms >= q + 1`` terms per grid point."""
    ncol = pw.shape[1]
    m = us.shape[0]
    k = vs.shape[0]
    spans_u, table_u = basis_table(p, knots_u, pw.shape[0] - 1, us, nd)
    spans_v, table_v = basis_table(q, knots_v, ncol - 1, vs, nd)
    # The v-basis transposed, so that a run reads each term's values contiguously.
    bv = np.zeros((2, terms, k))
    for j in range(k):
        for d in range(nd + 1):
            for l in range(q + 1):
                bv[d, l, j] = table_v[j, d, l]
    # Runs of consecutive grid points on one v-span (one per span for sorted vs).
    starts = np.empty(k + 1, dtype=np.uint64)
    runs = 0
    for j in range(k):
        if j == 0 or spans_v[j] != spans_v[j - 1]:
            starts[runs] = j
            runs += 1
    starts[runs] = k
    width = 4 * (nd + 1)
    # Per control column, the row's contraction over u: Q = sum_k N_k(u) Pw_k
    # (and R with N'_k), then the run's q + 1 columns of it, zero-padded.
    rq = np.empty((ncol, 8))
    w = np.zeros((terms, 8))
    pf = pts.reshape(-1)
    uf = d_du.reshape(-1)
    vf = d_dv.reshape(-1)
    for i in range(m):
        su = spans_u[i]
        for c in range(ncol):
            for h in range(width):
                d = h // 4
                acc = 0.0
                for kk in range(p + 1):
                    acc += table_u[i, d, kk] * pw[su - p + kk, c, h % 4]
                rq[c, h] = acc
        base = uint64(3 * i * k)
        for r in range(runs):
            j0 = starts[r]
            first = spans_v[j0] - q
            for l in range(q + 1):
                for h in range(width):
                    w[l, h] = rq[first + l, h]
            if nd:
                _run_derivatives(terms, w, bv, j0, starts[r + 1], base, pf, uf, vf)
            else:
                _run_points(terms, w, bv, j0, starts[r + 1], base, pf)


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def surface_grid(p, q, knots_u, knots_v, pw, us, vs, nd, pts, d_du, d_dv):  # pragma: no cover
    """Points (and with ``nd = 1`` first derivatives) on the grid ``us x vs``;
    outputs are (len(us) * len(vs), 3), row ``i * len(vs) + j`` for
    ``(us[i], vs[j])``."""
    if q < GRID_TERMS:
        _grid(GRID_TERMS, p, q, knots_u, knots_v, pw, us, vs, nd, pts, d_du, d_dv)
    else:
        _grid(q + 1, p, q, knots_u, knots_v, pw, us, vs, nd, pts, d_du, d_dv)


@njit(cache=True, nogil=True, fastmath=True)
def curve_points(p, knots, pw, ts, nd, out):  # pragma: no cover
    """Points and derivatives up to order ``nd <= 2`` of a rational curve:
    ``out[k]`` (len(ts), 3) is the k-th derivative at ``ts``."""
    n = pw.shape[0] - 1
    ndu = np.empty((p + 1, p + 1))
    left = np.empty(p + 1)
    right = np.empty(p + 1)
    a = np.empty((2, p + 1))
    basis = np.empty((nd + 1, p + 1))
    h = np.empty((nd + 1, 4))
    for i in range(ts.shape[0]):
        s = find_span(n, p, ts[i], knots)
        ders_basis(s, ts[i], p, knots, nd, ndu, left, right, a, basis)
        for k in range(nd + 1):
            for c in range(4):
                acc = 0.0
                for j in range(p + 1):
                    acc += basis[k, j] * pw[s - p + j, c]
                h[k, c] = acc
        # The quotient rule of eq. 4.8: C^(k) = (A^(k) - sum_j binom(k, j) w^(j) C^(k-j)) / w.
        inv = 1.0 / h[0, 3]
        for c in range(3):
            x = h[0, c] * inv
            out[0, i, c] = x
            if nd >= 1:
                d1 = (h[1, c] - h[1, 3] * x) * inv
                out[1, i, c] = d1
                if nd >= 2:
                    out[2, i, c] = (h[2, c] - 2.0 * h[1, 3] * d1 - h[2, 3] * x) * inv
