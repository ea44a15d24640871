"""Compiled evaluation of rational curves and surfaces, point by point and on grids.

A NURBS surface is evaluated in homogeneous coordinates: with the weighted
control points ``Pw = (w P, w)`` the numerator and denominator
``A(u, v) = sum_k sum_l N_k(u) M_l(v) Pw_kl`` are a plain tensor-product
B-spline, and the point and its first derivatives follow by the quotient rule
(The NURBS Book, eq. 4.19):

    S = A / w,    S_u = (A_u - w_u S) / w,    S_v = (A_v - w_v S) / w.

Two ways of evaluating many parameters share the same basis kernel
(:func:`.basis.ders_basis`) and the same rational step:

- :func:`surface_points`: each parameter pair on its own: two span searches,
  two basis evaluations and the full ``(p+1) x (q+1)`` contraction per point;
- :func:`surface_grid`: a regular grid ``us x vs``: the basis of every grid
  line is computed once (:func:`.basis.basis_table`), and along a grid row
  ``u = us[i]`` the contraction over ``k`` is done once per control column,
  ``Q_l = sum_k N_k(u) Pw_kl``, leaving ``q + 1`` terms per grid point.

Their operation counts are in :mod:`.flops`. The kernels run on one thread
(no ``prange``): callers may evaluate from several threads of their own.
Callers are trusted: shapes, knots and parameters are checked by the classes.
"""

from __future__ import annotations

import numpy as np
from numba import njit

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


@njit(cache=True, nogil=True, fastmath=True)
def surface_points(p, q, knots_u, knots_v, pw, us, vs, nd, pts, d_du, d_dv):  # pragma: no cover
    """Points (and with ``nd = 1`` first derivatives) at the parameter pairs
    ``(us[i], vs[i])``, each computed from scratch."""
    nu = pw.shape[0] - 1
    nv = pw.shape[1] - 1
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
        su = find_span(nu, p, us[i], knots_u)
        ders_basis(su, us[i], p, knots_u, nd, ndu_u, left_u, right_u, a_u, bu)
        sv = find_span(nv, q, vs[i], knots_v)
        ders_basis(sv, vs[i], q, knots_v, nd, ndu_v, left_v, right_v, a_v, bv)
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
def surface_grid(p, q, knots_u, knots_v, pw, us, vs, nd, pts, d_du, d_dv):  # pragma: no cover
    """Points (and with ``nd = 1`` first derivatives) on the grid ``us x vs``;
    outputs are (len(us) * len(vs), 3), row ``i * len(vs) + j`` for
    ``(us[i], vs[j])``."""
    nu = pw.shape[0] - 1
    nv = pw.shape[1] - 1
    ncol = nv + 1
    spans_u, table_u = basis_table(p, knots_u, nu, us, nd)
    spans_v, table_v = basis_table(q, knots_v, nv, vs, nd)
    # The row's contraction over k, per control column: Q (value) and R (u-derivative).
    rq = np.empty((ncol, 4))
    rr = np.empty((ncol, 4))
    m = vs.shape[0]
    for i in range(us.shape[0]):
        su = spans_u[i]
        for c in range(ncol):
            t0 = t1 = t2 = t3 = 0.0
            s0 = s1 = s2 = s3 = 0.0
            for k in range(p + 1):
                row = su - p + k
                b = table_u[i, 0, k]
                t0 += b * pw[row, c, 0]
                t1 += b * pw[row, c, 1]
                t2 += b * pw[row, c, 2]
                t3 += b * pw[row, c, 3]
                if nd:
                    b = table_u[i, 1, k]
                    s0 += b * pw[row, c, 0]
                    s1 += b * pw[row, c, 1]
                    s2 += b * pw[row, c, 2]
                    s3 += b * pw[row, c, 3]
            rq[c, 0] = t0
            rq[c, 1] = t1
            rq[c, 2] = t2
            rq[c, 3] = t3
            rr[c, 0] = s0
            rr[c, 1] = s1
            rr[c, 2] = s2
            rr[c, 3] = s3
        base = i * m
        for j in range(m):
            sv = spans_v[j]
            c0 = c1 = c2 = c3 = 0.0
            u0 = u1 = u2 = u3 = 0.0
            v0 = v1 = v2 = v3 = 0.0
            for l in range(q + 1):
                c = sv - q + l
                b = table_v[j, 0, l]
                c0 += b * rq[c, 0]
                c1 += b * rq[c, 1]
                c2 += b * rq[c, 2]
                c3 += b * rq[c, 3]
                if nd:
                    u0 += b * rr[c, 0]
                    u1 += b * rr[c, 1]
                    u2 += b * rr[c, 2]
                    u3 += b * rr[c, 3]
                    b = table_v[j, 1, l]
                    v0 += b * rq[c, 0]
                    v1 += b * rq[c, 1]
                    v2 += b * rq[c, 2]
                    v3 += b * rq[c, 3]
            x, y, z, inv = _rational(c0, c1, c2, c3, pts, base + j)
            if nd:
                _rational_derivative(u0, u1, u2, u3, x, y, z, inv, d_du, base + j)
                _rational_derivative(v0, v1, v2, v3, x, y, z, inv, d_dv, base + j)


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
