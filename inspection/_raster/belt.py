"""The belt as a camera sees it: its albedo texture, and its static shading per camera."""

from __future__ import annotations

import math

from numba import njit

from .._jit import NO_RUNTIME
from .flash import pixel_slide, shadow_bias
from .zbuffer import NEAR_MM


@njit(cache=True, nogil=True, inline="always")
def belt_albedo(x, y, tex, texel_mm, belt_half_width, floor_albedo):  # pragma: no cover
    """Belt albedo at rig (x, y): periodic texture along x, dark floor beyond the belt."""
    if abs(y) > belt_half_width:
        return floor_albedo
    Ty, Tx = tex.shape
    u = x / texel_mm
    u = u - math.floor(u / Tx) * Tx  # wrap: the belt is an endless loop
    v = min(max((y + belt_half_width) / texel_mm, 0.0), Ty - 1.0)
    j = int(u)
    i = min(int(v), Ty - 2)
    fu = u - j
    fv = v - i
    j1 = j + 1 if j + 1 < Tx else 0
    return (1.0 - fv) * ((1.0 - fu) * tex[i, j] + fu * tex[i, j1]) + fv * (
        (1.0 - fu) * tex[i + 1, j] + fu * tex[i + 1, j1]
    )


@njit(cache=True, nogil=True, **NO_RUNTIME)
def belt_static(  # pragma: no cover - compiled
    rays,
    Rcr,
    C,
    Rp,
    tp,
    kproj,
    pattern,
    P,
    power,
    r0,
    tex,
    texel_mm,
    belt_half_width,
    floor_albedo,
    samples,
    belt_irr,
    belt_q,
    belt_alb,
):
    """What a camera sees of the empty belt, computed once per rig.

    Writes, per pixel: ``belt_irr`` (H, W) float32, the patterned irradiance
    times the cosine (before shadows); ``belt_q`` (H, W, 4) float32, the slide
    position (u, v), depth from the projector (mm) and shadow bias (mm) of the
    belt point; ``belt_alb`` (H, W) float32, the belt's albedo there (belt at
    rest). The formulas are those of :func:`shade_scene`, ``samples`` too.
    """
    H, W = belt_irr.shape
    ncx = Rcr[2, 0]
    ncy = Rcr[2, 1]
    ncz = Rcr[2, 2]
    ndc = -C[2]
    for i in range(H):
        for j in range(W):
            xn = rays[i, j, 0]
            yn = rays[i, j, 1]
            den_c = ncx * xn + ncy * yn + ncz
            z = ndc / den_c if den_c != 0.0 else -1.0
            belt_irr[i, j] = 0.0
            belt_q[i, j, 0] = -1.0
            belt_q[i, j, 1] = -1.0
            belt_q[i, j, 2] = 0.0
            belt_q[i, j, 3] = 0.0
            belt_alb[i, j] = 0.0
            if z <= 0.0:
                continue
            xc = xn * z
            yc = yn * z
            X0 = Rcr[0, 0] * xc + Rcr[0, 1] * yc + Rcr[0, 2] * z + C[0]
            X1 = Rcr[1, 0] * xc + Rcr[1, 1] * yc + Rcr[1, 2] * z + C[1]
            belt_alb[i, j] = belt_albedo(X0, X1, tex, texel_mm, belt_half_width, floor_albedo)
            lx = P[0] - X0
            ly = P[1] - X1
            lz = P[2]
            dist = math.sqrt(lx * lx + ly * ly + lz * lz)
            cos_l = lz / dist
            if cos_l <= 0.0:
                continue
            qx = Rp[0, 0] * X0 + Rp[0, 1] * X1 + tp[0]
            qy = Rp[1, 0] * X0 + Rp[1, 1] * X1 + tp[1]
            qz = Rp[2, 0] * X0 + Rp[2, 1] * X1 + tp[2]
            if qz <= NEAR_MM:
                continue
            up = kproj[0] * qx / qz + kproj[1] * qy / qz + kproj[2]
            vp = kproj[3] * qy / qz + kproj[4]
            slide = pixel_slide(
                pattern, rays, i, j, up, vp, (ncx, ncy, ncz, ndc), Rcr, C, Rp, tp, kproj, samples
            )
            falloff = (r0 / dist) * (r0 / dist)
            belt_irr[i, j] = power * falloff * slide * cos_l
            belt_q[i, j, 0] = up
            belt_q[i, j, 1] = vp
            belt_q[i, j, 2] = qz
            belt_q[i, j, 3] = shadow_bias(qz, kproj[0], cos_l)
