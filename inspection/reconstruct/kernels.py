"""The compiled (numba) window fits of the matching, one pixel's window at a time.

Every fit is a Lucas-Kanade (Gauss-Newton) fit of one pixel's window of the
rectified left image against the right image, with a gain and an offset,

    L(x + u, y + v) ≈ g R(x + u - d - w(u, v), y + v) + o,

on images normalised by their local mean and contrast, so that the different
brightness of the metal seen from two sides does not bias the match. The
unknowns ``(d, g, o)`` are found from the normal equations ``J^T J Δ = J^T e``
of the residual ``e = L - g R - o``, with ``∂e/∂d = g ∂R/∂x``; a step of the
disparity is clamped to one pixel, and a fit stops when it moves less than
0.002 px. The kernels differ in the window's warp ``w``:

- :func:`refine_pixels`: a square window, ``w = 0`` (one disparity across it);
- :func:`refine_cyclopean`: a square window centred half-way between the
  views (``L(c + d/2 + u) ≈ g R(c - d/2 + u) + o``), which cancels to first
  order the shift of edges and slopes towards the occluded side;
- :func:`refine_warped`: ``w(u, v) = S(x + u, y + v) - S(x, y)`` for a known
  disparity field ``S`` (the measured one, or the CAD's), so that a window on
  a slope or a bend compares the right image stretched as the surface
  stretches it; samples off the field get no weight;
- :func:`refine_warped_shaded`: the warped window with light that changes
  with the surface across it, ``+ Σ_k c_k (q_k - q_k(centre))`` for the
  quadratic monomials ``q`` of two surface coordinates (five more unknowns,
  solved by Cholesky with a ridge on their diagonal).

**Interpolation.** The right image is sampled between its pixels by the
cubic B-spline through them (its row coefficients: :func:`spline_rows
<inspection.reconstruct.matching.spline_rows>`; four taps, :func:`_bspline`).
Any interpolator smooths the image by an amount that depends on where between
two pixels it samples, and the fit then prefers the disparities whose
fraction the smoothing favours (the "pixel locking" of window matchers). The
cubic B-spline's response varies much less with the fraction than that of
cubic convolution (Catmull-Rom), for the same four taps; its coefficients
cost one recursive filter pass per row.

The kernels run on one thread each (no ``prange``): the reconstructor
matches the pairs on threads of its own, and numba's parallel layer nested
inside Python threads aborts (its workqueue layer). Callers are trusted:
shapes and dtypes are not checked.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .._jit import NO_RUNTIME
from .._linalg import cholesky_solve_into


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _gauss_newton_step(a11, a12, a13, a22, a23, a33, b1, b2, b3):  # pragma: no cover
    """One Gauss-Newton step of the window fits: the symmetric 3x3 system
    A x = b solved by Cramer's rule, its first (disparity) component clamped
    to +-1 px. Returns (ok, x1, x2, x3); ok is False for a singular A."""
    c11 = a22 * a33 - a23 * a23
    c12 = a13 * a23 - a12 * a33
    c13 = a12 * a23 - a13 * a22
    det = a11 * c11 + a12 * c12 + a13 * c13
    if abs(det) < 1e-12:
        return False, 0.0, 0.0, 0.0
    c22 = a11 * a33 - a13 * a13
    c23 = a12 * a13 - a11 * a23
    c33 = a11 * a22 - a12 * a12
    dd = (c11 * b1 + c12 * b2 + c13 * b3) / det
    dg = (c12 * b1 + c22 * b2 + c23 * b3) / det
    do = (c13 * b1 + c23 * b2 + c33 * b3) / det
    if dd > 1.0:
        dd = 1.0
    elif dd < -1.0:
        dd = -1.0
    return True, dd, dg, do


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _bspline(a):  # pragma: no cover
    """Cubic B-spline weights of the coefficients at columns i-1 .. i+2 for a
    sample at i + a (0 <= a < 1), and their derivatives in a."""
    b = 1.0 - a
    a2 = a * a
    a3 = a2 * a
    return (
        b * b * b / 6.0,
        0.5 * a3 - a2 + 2.0 / 3.0,
        -0.5 * a3 + 0.5 * a2 + 0.5 * a + 1.0 / 6.0,
        a3 / 6.0,
        -0.5 * b * b,
        1.5 * a2 - 2.0 * a,
        -1.5 * a2 + a + 0.5,
        0.5 * a2,
    )


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _gain_offset_step(g, o, s1, sw, sg, sww, sgg, sgw, st, stw, stg):  # pragma: no cover
    """The Gauss-Newton step of a window fit in (disparity, gain, offset) from its
    weighted sums (of 1, r, r', r^2, r'^2, r' r, t, t r, t r'), at gain ``g`` and offset
    ``o``: residual e = t - g r - o, J = [-g r', r, 1]. Returns (ok, dd, dg, do)."""
    a11 = g * g * sgg
    a12 = -g * sgw
    a13 = -g * sg
    b1 = -g * (stg - g * sgw - o * sg)
    b2 = stw - g * sww - o * sw
    b3 = st - g * sw - o * s1
    return _gauss_newton_step(a11, a12, a13, sww, sw, s1, b1, b2, b3)


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _ncc(s1, st, sw, stt, sww, stw):  # pragma: no cover
    """Normalised cross-correlation of a window's samples t and r from their weighted
    sums: of the weights, t, r, t^2, r^2 and t r."""
    mt = st / s1
    mw = sw / s1
    ctw = stw / s1 - mt * mw
    ctt = stt / s1 - mt * mt
    cww = sww / s1 - mw * mw
    return ctw / math.sqrt(max(ctt * cww, 1e-12))


@njit(cache=True, nogil=True, inline="always")
def _store(i, ok, d, score, step, out_d, out_score, out_step):  # pragma: no cover
    """Row i of a window fit's outputs: its disparity, score and last step, or
    NaN / -1 / 99 for a fit that failed."""
    if ok:
        out_d[i] = d
        out_score[i] = score
        out_step[i] = step
    else:
        out_d[i] = np.nan
        out_score[i] = -1.0
        out_step[i] = 99.0


@njit(cache=True, nogil=True, fastmath=True)
def refine_pixels(
    left, right, wl, wr, px, py, d0, radius, iterations, out_d, out_score, out_step
):  # pragma: no cover
    """Sub-pixel disparity of each listed pixel: Gauss-Newton on its own window.

    For each pixel the window of the left image is matched against the right
    image shifted by a constant disparity ``d`` (cubic B-spline
    interpolation, see the module notes), with a gain and an offset:
    ``L ≈ g R(x - d) + o``. Three unknowns, normal equations solved in closed
    form; samples are weighted by ``wl`` and ``wr`` (0 where saturated).

    Parameters
    ----------
    left : (H, W) float32
        Locally normalised rectified left image.
    right : (H, W) float32
        The same of the right image, as row B-spline coefficients
        (:func:`.matching.spline_rows`).
    wl, wr : (H, W) float32
        Sample weights (0: saturated or outside).
    px, py : (N,) int64
        Pixels to refine (left image).
    d0 : (N,) float32
        Initial disparities.
    radius : int
        Half window (window = 2 radius + 1).
    iterations : int
    out_d, out_score, out_step : (N,) float32
        Refined disparity, weighted normalised correlation, last step (written).
    """
    H, W = left.shape
    WR = right.shape[1]
    # Flat views read with unsigned indices: numba then checks no index for a
    # negative value, which it does on every read of a row slice's counter too.
    lf = left.ravel()
    wlf = wl.ravel()
    rf = right.ravel()
    wrf = wr.ravel()
    one = np.uint64(1)
    n = px.shape[0]
    for i in range(n):
        x = px[i]
        y = py[i]
        d = float(d0[i])
        g = 1.0
        o = 0.0
        score = -1.0
        step = 99.0
        ok = x - radius >= 0 and x + radius < W and y - radius >= 0 and y + radius < H
        for _ in range(iterations):
            if not ok:
                break
            xr = x - d
            xi = int(math.floor(xr))
            a = xr - xi
            if xi - radius - 1 < 0 or xi + radius + 2 >= W:
                ok = False
                break
            w0, w1, w2, w3, g0, g1, g2, g3 = _bspline(a)
            s1 = 0.0
            sw = 0.0
            sg = 0.0
            sww = 0.0
            sgg = 0.0
            sgw = 0.0
            st = 0.0
            stt = 0.0
            stw = 0.0
            stg = 0.0
            for v in range(-radius, radius + 1):
                yy = y + v
                # The row's first sample in the left image, and its spline's first
                # coefficient in the right one.
                kl = np.uint64(yy * W + x - radius)
                kr = np.uint64(yy * WR + xi - radius - 1)
                for c in range(2 * radius + 1):
                    u = np.uint64(c)
                    # No branch on zero weights: the loop stays vectorisable.
                    wt = wlf[kl + u] * wrf[kr + u + one] * wrf[kr + u + one + one]
                    r0 = rf[kr + u]
                    r1 = rf[kr + u + one]
                    r2 = rf[kr + u + one + one]
                    r3 = rf[kr + u + one + one + one]
                    rv = w0 * r0 + w1 * r1 + w2 * r2 + w3 * r3
                    gv = g0 * r0 + g1 * r1 + g2 * r2 + g3 * r3
                    t = lf[kl + u]
                    s1 += wt
                    sw += wt * rv
                    sg += wt * gv
                    sww += wt * rv * rv
                    sgg += wt * gv * gv
                    sgw += wt * gv * rv
                    st += wt * t
                    stt += wt * t * t
                    stw += wt * t * rv
                    stg += wt * t * gv
            if s1 < 0.5 * (2 * radius + 1) ** 2:
                ok = False
                break
            # Weighted normalised cross-correlation at the current shift.
            score = _ncc(s1, st, sw, stt, sww, stw)
            # Gauss-Newton for (Δ, g, o) with residual e = t - g r - o and
            # d(g r)/dΔ = -g dr/dx (the image moves left when d grows).
            # Normal matrix A = J^T J, J = [-g gv, rv, 1]; rhs b = J^T e.
            ok, dd, dg, do = _gain_offset_step(g, o, s1, sw, sg, sww, sgg, sgw, st, stw, stg)
            if not ok:
                break
            d += dd
            g += dg
            o += do
            step = dd
            if abs(dd) < 0.002:
                break
        _store(i, ok, d, score, step, out_d, out_score, out_step)


@njit(cache=True, nogil=True, fastmath=True)
def refine_cyclopean(
    left, right, wl, wr, cl, cr, py, d0, radius, iterations, out_d, out_score, out_step
):  # pragma: no cover
    """Sub-pixel disparity at points of the cyclopean (mid-baseline) view.

    The window is centred half-way between the two views: the left image is
    sampled at ``c + d/2 + u`` and the right one at ``c - d/2 + u``. Matching
    from one view only (the left window against the shifted right image)
    shifts every depth edge and every slope towards the occluded side (the
    "fattening" of window matchers), and with both pairs' baselines along x
    that shift is the same for the whole cloud, an in-plane bias of the part's
    position; the symmetric window cancels it to first order.

    Model ``L(c + d/2 + u) ≈ g R(c - d/2 + u) + o`` per window, three
    unknowns (d, g, o) by Gauss-Newton, cubic B-spline interpolation of both
    images, samples weighted by ``wl`` and ``wr`` (0 where saturated).

    Parameters
    ----------
    left, right : (H, Wl), (H, Wr) float32
        Locally normalised rectified images (crops), both as row B-spline
        coefficients (:func:`.matching.spline_rows`).
    wl, wr : float32, same shapes
        Sample weights.
    cl, cr : (N,) float64
        Cyclopean x of each point in the left and in the right crop's columns.
    py : (N,) int64
        Row of each point (both crops).
    d0 : (N,) float32
        Initial disparities.
    radius : int
    iterations : int
    out_d, out_score, out_step : (N,) float32
        Refined disparity (NaN: failed), normalised correlation, last step.
    """
    H = left.shape[0]
    Wl = left.shape[1]
    Wr = right.shape[1]
    n = py.shape[0]
    for i in range(n):
        y = py[i]
        d = float(d0[i])
        g = 1.0
        o = 0.0
        score = -1.0
        step = 99.0
        ok = y - radius >= 0 and y + radius < H
        for _ in range(iterations):
            if not ok:
                break
            xl = cl[i] + 0.5 * d
            xr = cr[i] - 0.5 * d
            il = int(math.floor(xl))
            ir = int(math.floor(xr))
            if (
                il - radius - 1 < 0
                or il + radius + 2 >= Wl
                or ir - radius - 1 < 0
                or ir + radius + 2 >= Wr
            ):
                ok = False
                break
            lw0, lw1, lw2, lw3, lg0, lg1, lg2, lg3 = _bspline(xl - il)
            rw0, rw1, rw2, rw3, rg0, rg1, rg2, rg3 = _bspline(xr - ir)
            s1 = 0.0
            sl = 0.0
            sr = 0.0
            sll = 0.0
            srr = 0.0
            slr = 0.0
            # Sums for the normal equations with j = dL/dd + g dR/dd... see below.
            sj = 0.0
            sjj = 0.0
            sjr = 0.0
            sje = 0.0
            sre = 0.0
            se = 0.0
            for v in range(-radius, radius + 1):
                yy = y + v
                for u in range(-radius, radius + 1):
                    xa = il + u
                    xb = ir + u
                    wt = wl[yy, xa] * wl[yy, xa + 1] * wr[yy, xb] * wr[yy, xb + 1]
                    l0 = left[yy, xa - 1]
                    l1 = left[yy, xa]
                    l2 = left[yy, xa + 1]
                    l3 = left[yy, xa + 2]
                    r0 = right[yy, xb - 1]
                    r1 = right[yy, xb]
                    r2 = right[yy, xb + 1]
                    r3 = right[yy, xb + 2]
                    lv = lw0 * l0 + lw1 * l1 + lw2 * l2 + lw3 * l3
                    lgr = lg0 * l0 + lg1 * l1 + lg2 * l2 + lg3 * l3
                    rv = rw0 * r0 + rw1 * r1 + rw2 * r2 + rw3 * r3
                    rgr = rg0 * r0 + rg1 * r1 + rg2 * r2 + rg3 * r3
                    # e = L(c + d/2) - g R(c - d/2) - o;  de/dd = (L' + g R') / 2.
                    e = lv - g * rv - o
                    j = 0.5 * (lgr + g * rgr)
                    s1 += wt
                    sl += wt * lv
                    sr += wt * rv
                    sll += wt * lv * lv
                    srr += wt * rv * rv
                    slr += wt * lv * rv
                    sj += wt * j
                    sjj += wt * j * j
                    sjr += wt * j * rv
                    sje += wt * j * e
                    sre += wt * rv * e
                    se += wt * e
            if s1 < 0.5 * (2 * radius + 1) ** 2:
                ok = False
                break
            ml = sl / s1
            mr = sr / s1
            score = (slr / s1 - ml * mr) / math.sqrt(
                max((sll / s1 - ml * ml) * (srr / s1 - mr * mr), 1e-12)
            )
            # Gauss-Newton on Σ e² in (Δd, Δg, Δo): de = j Δd - r Δg - Δo, so
            # [ Σjj  -Σjr  -Σj ] [Δd]     [ Σje ]
            # [-Σjr   Σrr   Σr ] [Δg] = - [-Σre ]
            # [ -Σj   Σr    Σ1 ] [Δo]     [ -Σe ]
            a11 = sjj
            a12 = -sjr
            a13 = -sj
            a22 = srr
            a23 = sr
            a33 = s1
            b1 = -sje
            b2_ = sre
            b3_ = se
            ok, dd, dg, do = _gauss_newton_step(a11, a12, a13, a22, a23, a33, b1, b2_, b3_)
            if not ok:
                break
            d += dd
            g += dg
            o += do
            step = dd
            if abs(dd) < 0.002:
                break
        _store(i, ok, d, score, step, out_d, out_score, out_step)


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _warped_window(
    left, wl, shape, mask, x, y, radius, s0, base, wlm, tv, rows
):  # pragma: no cover
    """What a warped window's samples keep from one step to the next, in row-major
    order: the right-image column of each sample less the disparity (``base``),
    its left weight (``wlm``: on the field, and unsaturated), its left value
    (``tv``) and its row (``rows``)."""
    w = 2 * radius + 1
    j = 0
    for v in range(-radius, radius + 1):
        yy = y + v
        # Row slices indexed by the loop's own counter: plain loads, where 2-D
        # indexing pays numba's index arithmetic on every read.
        lrow = left[yy, x - radius : x + radius + 1]
        wlrow = wl[yy, x - radius : x + radius + 1]
        srow = shape[yy, x - radius : x + radius + 1]
        mrow = mask[yy, x - radius : x + radius + 1]
        for u in range(w):
            base[j + u] = (x - radius + u) - (srow[u] - s0)
            wlm[j + u] = mrow[u] * wlrow[u]
            tv[j + u] = lrow[u]
            rows[j + u] = yy
        j += w


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _warped_columns(base, d, rows, wr_cols, at, frac, inside):  # pragma: no cover
    """Where each sample reads the right image at disparity ``d``: the flat index
    (into the image raveled) of the spline's second coefficient (``at``, its
    column clamped to the row ``rows`` gives; the row holds ``wr_cols``), the
    fraction between columns (``frac``) and whether the column lies on the row
    (``inside``: 1, or 0 for a clamped one, which then gets no weight). A loop of
    its own, free of the image reads, so that it vectorises."""
    for j in range(base.shape[0]):
        xr = base[j] - d
        xf = math.floor(xr)
        frac[j] = xr - xf
        xb0 = int(xf)
        xb = min(max(xb0, 1), wr_cols - 3)
        # One flat index, unsigned: the reads of the sample loop then cost one
        # address each, with no check for a negative index.
        at[j] = np.uint64(rows[j] * wr_cols + xb)
        inside[j] = 1.0 if xb == xb0 else 0.0


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _warped_sample(right, wr, k, a, inside):  # pragma: no cover
    """The right image's spline (coefficients ``right``, raveled) at the flat index
    ``k`` (uint64) plus the fraction ``a``: its value, its derivative, and the
    sample's weight (the right weights ``wr``, raveled, of the two nearest pixels,
    times ``inside``)."""
    w0, w1, w2, w3, g0, g1, g2, g3 = _bspline(a)
    # Unsigned steps: an int64 would turn the uint64 index into a float.
    one = np.uint64(1)
    r0 = right[k - one]
    r1 = right[k]
    r2 = right[k + one]
    r3 = right[k + one + one]
    rv = w0 * r0 + w1 * r1 + w2 * r2 + w3 * r3
    gv = g0 * r0 + g1 * r1 + g2 * r2 + g3 * r3
    return rv, gv, inside * wr[k] * wr[k + one]


@njit(cache=True, nogil=True, inline="always")
def _warp_centre(shape, mask, x, y, radius):  # pragma: no cover
    """Whether a warped window at (x, y) fits in the crop and is centred on the
    field, and the field's value there (0 off the crop)."""
    H, W = shape.shape
    if not (y - radius >= 0 and y + radius < H and x - radius >= 0 and x + radius < W):
        return False, 0.0
    return mask[y, x] > 0.0, float(shape[y, x])


@njit(cache=True, nogil=True, fastmath=True)
def refine_warped(
    left, right, wl, wr, shape, mask, px, py, d0, radius, iterations, out_d, out_score, out_step
):  # pragma: no cover
    """Sub-pixel disparity with the window warped by a known disparity shape.

    As :func:`refine_pixels`, but the right-image sample of window offset
    (u, v) is taken at ``x + u - d - (S[y + v, x + u] - S[y, x])``: the
    window follows the surface's disparity field ``S`` (a previous estimate),
    so slanted and curved surfaces (walls seen at a grazing angle, bends)
    are compared with the right image stretched as the surface stretches it,
    and only the centre's disparity ``d`` (with gain and offset) is fitted.
    Samples where ``S`` is NaN (not part of the surface: across a depth edge)
    get no weight, so windows do not drag a surface past its outline.

    Parameters
    ----------
    shape : (H, W) float32
        Disparity field of the left crop (px; any finite value where none).
    mask : (H, W) float32
        1 where ``shape`` is known, 0 elsewhere.
    Others as :func:`refine_pixels`.
    """
    wr_cols = right.shape[1]
    rf = right.ravel()
    wf = wr.ravel()
    n = px.shape[0]
    nw = (2 * radius + 1) ** 2
    base = np.empty(nw)
    wlm = np.empty(nw)
    tv = np.empty(nw)
    frac = np.empty(nw)
    inside = np.empty(nw)
    rows = np.empty(nw, np.int64)
    at = np.empty(nw, np.uint64)
    for i in range(n):
        x = px[i]
        y = py[i]
        d = float(d0[i])
        g = 1.0
        o = 0.0
        score = -1.0
        step = 99.0
        ok, s0 = _warp_centre(shape, mask, x, y, radius)
        if ok:
            _warped_window(left, wl, shape, mask, x, y, radius, s0, base, wlm, tv, rows)
        for _ in range(iterations):
            if not ok:
                break
            s1 = 0.0
            sw = 0.0
            sg = 0.0
            sww = 0.0
            sgg = 0.0
            sgw = 0.0
            st = 0.0
            stt = 0.0
            stw = 0.0
            stg = 0.0
            _warped_columns(base, d, rows, wr_cols, at, frac, inside)
            for j in range(nw):
                rv, gv, wrt = _warped_sample(rf, wf, at[j], frac[j], inside[j])
                wt = wlm[j] * wrt
                t = tv[j]
                s1 += wt
                sw += wt * rv
                sg += wt * gv
                sww += wt * rv * rv
                sgg += wt * gv * gv
                sgw += wt * gv * rv
                st += wt * t
                stt += wt * t * t
                stw += wt * t * rv
                stg += wt * t * gv
            if s1 < 0.5 * nw:
                ok = False
                break
            score = _ncc(s1, st, sw, stt, sww, stw)
            ok, dd, dg, do = _gain_offset_step(g, o, s1, sw, sg, sww, sgg, sgw, st, stw, stg)
            if not ok:
                break
            d += dd
            g += dg
            o += do
            step = dd
            if abs(dd) < 0.002:
                break
        _store(i, ok, d, score, step, out_d, out_score, out_step)


# Regressors of :func:`refine_warped_shaded` (the quadratic monomials of two
# surface coordinates), and its unknowns (disparity, gain, offset and their
# coefficients): constants, so that the compiler unrolls the accumulation of
# the normal equations.
SHADE_TERMS = 5
_SHADED_UNKNOWNS = 3 + SHADE_TERMS


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _monomials(u, v, out):  # pragma: no cover
    """The regressors of :func:`refine_warped_shaded` at surface coordinates (u, v)."""
    out[0] = u
    out[1] = v
    out[2] = u * u
    out[3] = u * v
    out[4] = v * v


@njit(cache=True, nogil=True, fastmath=True)
def refine_warped_shaded(
    left,
    right,
    wl,
    wr,
    shape,
    mask,
    su,
    sv,
    ridge,
    px,
    py,
    d0,
    radius,
    iterations,
    out_d,
    out_score,
    out_step,
):  # pragma: no cover
    """:func:`refine_warped` with light that varies with the surface across the window.

    The model is ``L ≈ g R(x') + o + sum_k c_k (q_k - q_k(centre))``: besides
    the gain and offset, an additive term linear in ``SHADE_TERMS``
    regressors, the quadratic monomials ``u, v, u^2, u v, v^2`` of two
    coordinates of the surface known at every pixel (such as its slopes),
    whose coefficients ``c`` are fitted with the disparity: light that is a
    smooth function of the surface's orientation.
    Gauss-Newton on all the unknowns, normal equations solved by Cholesky;
    ``ridge`` times the window's weight is added to the coefficients'
    diagonal, which keeps a regressor that does not vary in the window from
    making the system singular.

    Parameters
    ----------
    su, sv : (H, W) float32
        The surface coordinates ``u`` and ``v`` at every left-crop pixel.
    ridge : float
    Others as :func:`refine_warped`.
    """
    wr_cols = right.shape[1]
    rf = right.ravel()
    wf = wr.ravel()
    n = px.shape[0]
    nw = (2 * radius + 1) ** 2
    nc = _SHADED_UNKNOWNS - 2
    A = np.empty((_SHADED_UNKNOWNS, _SHADED_UNKNOWNS))
    b = np.empty(_SHADED_UNKNOWNS)
    c = np.empty(SHADE_TERMS)
    q0 = np.empty(SHADE_TERMS)
    q = np.empty(SHADE_TERMS)
    sol = np.empty(_SHADED_UNKNOWNS)
    chol = np.empty((_SHADED_UNKNOWNS, _SHADED_UNKNOWNS))
    fwd = np.empty(_SHADED_UNKNOWNS)
    base = np.empty(nw)
    wlm = np.empty(nw)
    tv = np.empty(nw)
    frac = np.empty(nw)
    inside = np.empty(nw)
    rows = np.empty(nw, np.int64)
    at = np.empty(nw, np.uint64)
    # The Jacobian by rows, one column per sample (a sample of weight 0 adds
    # nothing): the normal equations are then contiguous dot products, which
    # vectorise. The rows of the offset and the light (1, and each regressor
    # less the centre's) do not change between a window's steps: ``jc``, and
    # the same times the weights, ``jwc``, remade only when a weight changes.
    jc = np.empty((nc, nw))
    jwc = np.empty((nc, nw))
    j0 = np.empty(nw)
    j1 = np.empty(nw)
    jw0 = np.empty(nw)
    jw1 = np.empty(nw)
    e_ = np.empty(nw)
    w_ = np.empty(nw)
    for i in range(n):
        x = px[i]
        y = py[i]
        d = float(d0[i])
        g = 1.0
        o = 0.0
        c[:] = 0.0
        score = -1.0
        step = 99.0
        ok, s0 = _warp_centre(shape, mask, x, y, radius)
        if ok:
            _warped_window(left, wl, shape, mask, x, y, radius, s0, base, wlm, tv, rows)
            _monomials(su[y, x], sv[y, x], q0)
            j = 0
            for v in range(-radius, radius + 1):
                for u in range(-radius, radius + 1):
                    _monomials(su[y + v, x + u], sv[y + v, x + u], q)
                    jc[0, j] = 1.0
                    for k in range(SHADE_TERMS):
                        jc[1 + k, j] = q[k] - q0[k]
                    j += 1
        for it in range(iterations):
            if not ok:
                break
            s1 = 0.0
            sw = 0.0
            sww = 0.0
            st = 0.0
            stt = 0.0
            stw = 0.0
            # Whether every sample's weight is that of the last step: then so is
            # the block of the normal equations of the offset and the light.
            same = it > 0
            _warped_columns(base, d, rows, wr_cols, at, frac, inside)
            for j in range(nw):
                rv, gv, wrt = _warped_sample(rf, wf, at[j], frac[j], inside[j])
                wt = wlm[j] * wrt
                same = same and w_[j] == wt
                w_[j] = wt
                t = tv[j]
                e = t - g * rv - o
                for k in range(SHADE_TERMS):
                    e -= c[k] * jc[1 + k, j]
                e_[j] = e
                j0[j] = -g * gv
                j1[j] = rv
                jw0[j] = wt * j0[j]
                jw1[j] = wt * rv
                s1 += wt
                sw += wt * rv
                sww += wt * rv * rv
                st += wt * t
                stt += wt * t * t
                stw += wt * t * rv
            if s1 < 0.5 * nw:
                ok = False
                break
            score = _ncc(s1, st, sw, stt, sww, stw)
            if not same:
                for r in range(nc):
                    for j in range(nw):
                        jwc[r, j] = w_[j] * jc[r, j]
            b0 = 0.0
            b1 = 0.0
            a00 = 0.0
            a01 = 0.0
            a11 = 0.0
            for j in range(nw):
                b0 += jw0[j] * e_[j]
                b1 += jw1[j] * e_[j]
                a00 += jw0[j] * j0[j]
                a01 += jw0[j] * j1[j]
                a11 += jw1[j] * j1[j]
            b[0] = b0
            b[1] = b1
            A[0, 0] = a00
            A[0, 1] = a01
            A[1, 0] = a01
            A[1, 1] = a11
            for r in range(nc):
                x0 = 0.0
                x1 = 0.0
                xe = 0.0
                for j in range(nw):
                    x0 += jw0[j] * jc[r, j]
                    x1 += jw1[j] * jc[r, j]
                    xe += jwc[r, j] * e_[j]
                A[0, 2 + r] = x0
                A[2 + r, 0] = x0
                A[1, 2 + r] = x1
                A[2 + r, 1] = x1
                b[2 + r] = xe
            if not same:
                for r in range(nc):
                    for r2 in range(r, nc):
                        acc = 0.0
                        for j in range(nw):
                            acc += jwc[r, j] * jc[r2, j]
                        A[2 + r, 2 + r2] = acc
                        A[2 + r2, 2 + r] = acc
                for k in range(SHADE_TERMS):
                    A[3 + k, 3 + k] += ridge * s1
            ok = cholesky_solve_into(A, b, chol, fwd, sol)
            if not ok:
                break
            dd = min(max(sol[0], -1.0), 1.0)
            d += dd
            g += sol[1]
            o += sol[2]
            for k in range(SHADE_TERMS):
                c[k] += sol[3 + k]
            step = dd
            if abs(dd) < 0.002:
                break
        _store(i, ok, d, score, step, out_d, out_score, out_step)


@njit(cache=True, nogil=True, **NO_RUNTIME)
def field_slopes(field_, out_x, out_y):  # pragma: no cover
    """Derivatives of a disparity field along x and y (px/px, written to ``out_x``,
    ``out_y``): at each pixel, the mean of the differences to both neighbours along
    the axis that are on the field (finite), one-sided at its outline, 0 alone or off
    it. One pass over the field, in float32.

    Parameters
    ----------
    field_ : (H, W) float32
        NaN off the field.
    out_x, out_y : (H, W) float32
    """
    H, W = field_.shape
    for y in range(H):
        for x in range(W):
            f = field_[y, x]
            tx = np.float32(0.0)
            ty = np.float32(0.0)
            cx = 0
            cy = 0
            if not np.isnan(f):
                # The lower neighbour's difference first: the order numpy sums them in.
                if x > 0 and not np.isnan(field_[y, x - 1]):
                    tx += f - field_[y, x - 1]
                    cx += 1
                if x + 1 < W and not np.isnan(field_[y, x + 1]):
                    tx += field_[y, x + 1] - f
                    cx += 1
                if y > 0 and not np.isnan(field_[y - 1, x]):
                    ty += f - field_[y - 1, x]
                    cy += 1
                if y + 1 < H and not np.isnan(field_[y + 1, x]):
                    ty += field_[y + 1, x] - f
                    cy += 1
            out_x[y, x] = tx / np.float32(max(cx, 1))
            out_y[y, x] = ty / np.float32(max(cy, 1))


@njit(cache=True, nogil=True, **NO_RUNTIME)
def normalised(img, mean, sq, out):  # pragma: no cover
    """``(img - mean) / sqrt(max(sq - mean^2, 0) + 4)`` per pixel, into ``out``: an
    image less its local mean over its local standard deviation, from the box means
    of the image (``mean``) and of its square (``sq``), both float32. The variance
    and its root in float32, the rest in the image's type, as numpy computes them."""
    H, W = img.shape
    zero = np.float32(0.0)
    floor = np.float32(4.0)
    for y in range(H):
        for x in range(W):
            m = mean[y, x]
            v = sq[y, x] - m * m
            # np.maximum's rule: a NaN stays.
            if v < zero:
                v = zero
            out[y, x] = (img[y, x] - m) / np.sqrt(v + floor)


@njit(cache=True, nogil=True, **NO_RUNTIME)
def masked_field(field_, out_v, out_mask):  # pragma: no cover
    """A field with holes as the box filters take it, in one pass: ``out_v`` the
    field where finite and 0 elsewhere, ``out_mask`` 1 where finite and 0 elsewhere
    (all (H, W) float32)."""
    H, W = field_.shape
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for y in range(H):
        for x in range(W):
            f = field_[y, x]
            if np.isfinite(f):
                out_v[y, x] = f
                out_mask[y, x] = one
            else:
                out_v[y, x] = zero
                out_mask[y, x] = zero


@njit(cache=True, nogil=True, **NO_RUNTIME)
def masked_mean(num, den, mask, out):  # pragma: no cover
    """``num / max(den, 1)`` where ``mask`` is set and 0 elsewhere, in float32: the mean
    of the field's values a box filter summed (``num``) over the pixels it counted
    (``den``), on the field only."""
    H, W = num.shape
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for y in range(H):
        for x in range(W):
            if mask[y, x] != zero:
                out[y, x] = num[y, x] / max(den[y, x], one)
            else:
                out[y, x] = zero


@njit(cache=True, nogil=True, **NO_RUNTIME)
def uneven_windows(num_w, den_w, field_, px, py, curvature, slope, full, out):  # pragma: no cover
    """Per window centred at ``(px, py)``: whether the field (float32, 0 off it) is far
    from constant over it, from the box sums of the field (``num_w``) and of its mask
    (``den_w``) over the window: its mean off the centre's value by more than
    ``curvature``, a slope along the rows above ``slope``, or fewer than ``full`` of
    its pixels on the field. The thresholds are float32, as the field."""
    W = field_.shape[1]
    one = np.float32(1.0)
    half = np.float32(0.5)
    for i in range(px.shape[0]):
        x = px[i]
        y = py[i]
        cnt = den_w[y, x]
        off = abs(num_w[y, x] / max(cnt, one) - field_[y, x])
        right = field_[y, min(x + 1, W - 1)]
        left = field_[y, max(x - 1, 0)]
        out[i] = off > curvature or abs(right - left) * half > slope or cnt < full


@njit(cache=True, nogil=True, **NO_RUNTIME)
def range_inputs(g, on_part, out_hi, out_lo):  # pragma: no cover
    """A slope as a dilation (``out_hi``) and an erosion (``out_lo``) take it to find
    its range over a window: off the part -1e30 and 1e30, which never win."""
    H, W = g.shape
    low = np.float32(-1e30)
    high = np.float32(1e30)
    for y in range(H):
        for x in range(W):
            if on_part[y, x]:
                out_hi[y, x] = g[y, x]
                out_lo[y, x] = g[y, x]
            else:
                out_hi[y, x] = low
                out_lo[y, x] = high


@njit(cache=True, nogil=True, **NO_RUNTIME)
def mark_wide(hi, lo, limit, out):  # pragma: no cover
    """Set ``out`` where the range ``hi - lo`` exceeds ``limit`` (float32), in place."""
    H, W = hi.shape
    for y in range(H):
        for x in range(W):
            if hi[y, x] - lo[y, x] > limit:
                out[y, x] = True


@njit(cache=True, nogil=True)
def fill_row_gaps(disparity, passes):  # pragma: no cover
    """Fill NaN pixels from their measured row neighbours, in place, ``passes`` times.

    Each pass sets every NaN pixel with a measured left or right neighbour
    to the mean of the measured ones (values of the previous pass), so gaps
    of up to ``2 * passes`` columns between measured pixels close and
    outlines grow by ``passes`` columns.

    Parameters
    ----------
    disparity : (H, W) float32
        NaN where not measured; modified in place.
    passes : int
    """
    H, W = disparity.shape
    prev = np.empty(W, np.float32)
    for _ in range(passes):
        for y in range(H):
            row = disparity[y]
            for x in range(W):
                prev[x] = row[x]
            for x in range(W):
                if not np.isnan(prev[x]):
                    continue
                s = np.float32(0.0)
                c = 0
                if x > 0 and not np.isnan(prev[x - 1]):
                    s += prev[x - 1]
                    c += 1
                if x + 1 < W and not np.isnan(prev[x + 1]):
                    s += prev[x + 1]
                    c += 1
                if c > 0:
                    row[x] = s / np.float32(c)


@njit(cache=True, nogil=True)
def fill_column_gaps(disparity, passes):  # pragma: no cover
    """:func:`fill_row_gaps` along the columns: each pass sets every NaN pixel with a
    measured neighbour above or below to the mean of the measured ones (values of the
    previous pass), in place, ``passes`` times.

    Row by row in memory order (a transposed view's strided walk is an order of
    magnitude slower): the row above is kept as it was before this pass, the row
    below is not yet touched.

    Parameters
    ----------
    disparity : (H, W) float32, C-contiguous
        NaN where not measured; modified in place.
    passes : int
    """
    H, W = disparity.shape
    above = np.full(W, np.nan, np.float32)
    here = np.empty(W, np.float32)
    nowhere = np.full(W, np.nan, np.float32)
    for _ in range(passes):
        above[:] = np.nan
        here[:] = disparity[0]
        for y in range(H):
            row = disparity[y]
            below = disparity[y + 1] if y + 1 < H else nowhere
            for x in range(W):
                if not np.isnan(here[x]):
                    continue
                a = above[x]
                b = below[x]
                if np.isnan(a):
                    if not np.isnan(b):
                        row[x] = b
                elif np.isnan(b):
                    row[x] = a
                else:
                    row[x] = (a + b) / np.float32(2.0)
            above[:] = here
            here[:] = below


@njit(cache=True, nogil=True)
def triangulate_matches(
    x_left,
    rows,
    d_ref,
    score,
    step,
    d_init,
    keep,
    geometry,
    R,
    centre,
    lo,
    hi,
    limits,
    full,
    out_pts,
    out_score,
):  # pragma: no cover
    """The accepted matches of one pair as rig-frame points, and its disparity map.

    A match is accepted with a finite disparity, ``score >= min_score``, within
    ``max_shift_px`` of its start and a last step under ``converged_px``
    (``limits``, in that order, after ``z_min_mm``); its point is kept inside the
    box ``lo``..``hi`` (rig frame) and not below ``z_min_mm``. Every kept match draws its
    disparity into ``full`` (rounded pixel; NaN elsewhere, written by the
    caller), and those with ``keep`` (an empty array: all) give points, written
    to the first rows of ``out_pts`` and ``out_score``.

    Parameters
    ----------
    geometry : (5,) float64
        ``fb, offset_px, f_px, cx_left, cy`` of the rectified pair.
    R, centre : the pair's ``R_rect_rig`` and ``centre_left``.
    limits : (4,) float64
        ``z_min_mm, min_score, max_shift_px, converged_px``.

    Returns
    -------
    (points written, matches accepted)
    """
    fb, offset, f_px, cx, cy = geometry[0], geometry[1], geometry[2], geometry[3], geometry[4]
    z_min = limits[0]
    # The matches' figures are float32: compared in float32, as numpy compares them.
    min_score = np.float32(limits[1])
    max_shift = np.float32(limits[2])
    converged = np.float32(limits[3])
    w_img = full.shape[1]
    use_keep = keep.shape[0] > 0
    n_out = 0
    n_good = 0
    for i in range(x_left.shape[0]):
        di = d_ref[i]
        if not (
            np.isfinite(di)
            and score[i] >= min_score
            and abs(di - d_init[i]) <= max_shift
            and abs(step[i]) < converged
        ):
            continue
        n_good += 1
        d = np.float64(di)
        x = x_left[i]
        y = np.float64(rows[i])
        z = fb / (d - offset)
        qx = (x - cx) * z / f_px
        qy = (y - cy) * z / f_px
        inside = True
        p = np.empty(3)
        for j in range(3):
            p[j] = qx * R[0, j] + qy * R[1, j] + z * R[2, j] + centre[j]
            inside = inside and lo[j] <= p[j] <= hi[j]
        if not (inside and p[2] >= z_min):
            continue
        xi = min(max(int(np.rint(x)), 0), w_img - 1)
        full[rows[i], xi] = d
        if use_keep and not keep[i]:
            continue
        for j in range(3):
            out_pts[n_out, j] = p[j]
        out_score[n_out] = score[i]
        n_out += 1
    return n_out, n_good


__all__ = [
    "SHADE_TERMS",
    "field_slopes",
    "fill_column_gaps",
    "fill_row_gaps",
    "mark_wide",
    "masked_field",
    "masked_mean",
    "normalised",
    "range_inputs",
    "refine_cyclopean",
    "refine_pixels",
    "refine_warped",
    "refine_warped_shaded",
    "triangulate_matches",
    "uneven_windows",
]
