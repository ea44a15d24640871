"""What the flash puts on a surface point: the slide over a pixel's footprint, and its shadow."""

from __future__ import annotations

import math

from numba import njit

from .zbuffer import NEAR_MM


@njit(cache=True, nogil=True, inline="always")
def _bilinear(img, u, v):  # pragma: no cover - compiled
    """Bilinear sample of a 2-D float array at (u, v) (x, y), 0 outside."""
    H, W = img.shape
    if not (u >= 0.0 and v >= 0.0 and u <= W - 1.0 and v <= H - 1.0):
        return 0.0
    j = min(int(u), W - 2)
    i = min(int(v), H - 2)
    fu = u - j
    fv = v - i
    return (1.0 - fv) * ((1.0 - fu) * img[i, j] + fu * img[i, j + 1]) + fv * (
        (1.0 - fu) * img[i + 1, j] + fu * img[i + 1, j + 1]
    )


@njit(cache=True, nogil=True, inline="always")
def _slide_uv(xn, yn, pl, Rcr, C, Rp, tp, kproj):  # pragma: no cover - compiled
    """Slide position (u, v) of the point where the ray (xn, yn, 1) of a camera
    meets the plane pl = (nx, ny, nz, d), n . X = d in the camera frame;
    (-1, -1) when it does not."""
    den = pl[0] * xn + pl[1] * yn + pl[2]
    if abs(den) < 1e-12:
        return -1.0, -1.0
    z = pl[3] / den
    xc = xn * z
    yc = yn * z
    X0 = Rcr[0, 0] * xc + Rcr[0, 1] * yc + Rcr[0, 2] * z + C[0]
    X1 = Rcr[1, 0] * xc + Rcr[1, 1] * yc + Rcr[1, 2] * z + C[1]
    X2 = Rcr[2, 0] * xc + Rcr[2, 1] * yc + Rcr[2, 2] * z + C[2]
    qx = Rp[0, 0] * X0 + Rp[0, 1] * X1 + Rp[0, 2] * X2 + tp[0]
    qy = Rp[1, 0] * X0 + Rp[1, 1] * X1 + Rp[1, 2] * X2 + tp[1]
    qz = Rp[2, 0] * X0 + Rp[2, 1] * X1 + Rp[2, 2] * X2 + tp[2]
    if qz <= NEAR_MM:
        return -1.0, -1.0
    return kproj[0] * qx / qz + kproj[1] * qy / qz + kproj[2], kproj[3] * qy / qz + kproj[4]


@njit(cache=True, nogil=True, inline="always")
def pixel_slide(
    pattern, rays, i, j, up, vp, pl, Rcr, C, Rp, tp, kproj, samples
):  # pragma: no cover - compiled
    """The slide's mean over the footprint of real pixel (i, j) on the plane
    pl (see :func:`_slide_uv`): ``samples`` x ``samples`` bilinear samples on
    a regular grid over the pixel, placed through the footprint's Jacobian
    (the slide position of the pixel's neighbours on the same plane). (up, vp)
    is the slide position of the pixel's centre. ``samples`` 1: the centre only."""
    if samples <= 1:
        return _bilinear(pattern, up, vp)
    H = rays.shape[0]
    W = rays.shape[1]
    j0 = max(j - 1, 0)
    j1 = min(j + 1, W - 1)
    i0 = max(i - 1, 0)
    i1 = min(i + 1, H - 1)
    sj = 1.0 / (j1 - j0)
    si = 1.0 / (i1 - i0)
    # The rays one pixel along the row and one down the column.
    xj = rays[i, j, 0] + (rays[i, j1, 0] - rays[i, j0, 0]) * sj
    yj = rays[i, j, 1] + (rays[i, j1, 1] - rays[i, j0, 1]) * sj
    xi = rays[i, j, 0] + (rays[i1, j, 0] - rays[i0, j, 0]) * si
    yi = rays[i, j, 1] + (rays[i1, j, 1] - rays[i0, j, 1]) * si
    uj, vj = _slide_uv(xj, yj, pl, Rcr, C, Rp, tp, kproj)
    ui, vi = _slide_uv(xi, yi, pl, Rcr, C, Rp, tp, kproj)
    if uj < 0.0 or ui < 0.0:
        return _bilinear(pattern, up, vp)
    duj = uj - up
    dvj = vj - vp
    dui = ui - up
    dvi = vi - vp
    total = 0.0
    for a in range(samples):
        oa = (a + 0.5) / samples - 0.5
        for b in range(samples):
            ob = (b + 0.5) / samples - 0.5
            total += _bilinear(pattern, up + ob * duj + oa * dui, vp + ob * dvj + oa * dvi)
    return total / (samples * samples)


@njit(cache=True, nogil=True, inline="always")
def lit_fraction(smap_z, smap_f, up, vp, qz, f, bias):  # pragma: no cover - compiled
    """Fraction of the projector's light reaching a point (percentage-closer filtering).

    The four shadow-map texels around the point's slide position (up, vp) each
    vote lit when they see nothing, the point's own face f, or a surface no
    nearer to the projector than the point's depth qz minus ``bias``; the votes
    are weighted bilinearly, so shadow edges are soft like a real flash's.
    """
    Hs, Ws = smap_z.shape
    j0 = int(math.floor(up))
    i0 = int(math.floor(vp))
    fu = up - j0
    fv = vp - i0
    lit = 0.0
    for di in range(2):
        for dj in range(2):
            ii = min(max(i0 + di, 0), Hs - 1)
            jj = min(max(j0 + dj, 0), Ws - 1)
            sf = smap_f[ii, jj]
            if sf < 0 or (f >= 0 and sf == f) or qz <= smap_z[ii, jj] + bias:
                lit += (fu if dj == 1 else 1.0 - fu) * (fv if di == 1 else 1.0 - fv)
    return lit


@njit(cache=True, nogil=True, inline="always")
def shadow_bias(qz, fpx, cos_l):  # pragma: no cover - compiled
    """Shadow-map depth bias, mm: grows with the slope seen from the projector (acne otherwise)."""
    tan_l = math.sqrt(max(1.0 - cos_l * cos_l, 0.0)) / max(cos_l, 0.05)
    return 0.3 + 1.5 * (qz / fpx) * min(tan_l, 10.0)
