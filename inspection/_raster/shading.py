"""The radiance of every real pixel: the part and belt under the flash, or a calibration board."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .belt import belt_albedo
from .flash import lit_fraction, pixel_slide, shadow_bias
from .zbuffer import NEAR_MM, in_face

# Fast-math without "nnan"/"ninf": infinities mark "no surface" in the kernels.
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True, nogil=True, fastmath=_FAST)
def shade_scene(  # pragma: no cover - compiled
    rays,
    kcam,
    ox,
    oy,
    fbuf,
    sx,
    sy,
    faces,
    planes,
    normals_rig,
    Rcr,
    C,
    Rp,
    tp,
    kproj,
    pattern,
    smap_z,
    smap_f,
    P,
    power,
    r0,
    ambient,
    albedo,
    ks_sharp,
    n_sharp,
    ks_broad,
    n_broad,
    dirt_c,
    dirt_r,
    dirt_k,
    tex,
    texel_mm,
    belt_shift_mm,
    belt_half_width,
    floor_albedo,
    belt_irr,
    belt_q,
    belt_alb,
    gain,
    samples,
    out,
    points,
    flags,
    want_truth,
):
    """Radiance of every real pixel of one camera, under the pattern flash.

    Parameters
    ----------
    rays : (H, W, 2) float64
        Ideal normalised coordinates (x/z, y/z) of each real pixel's ray.
    kcam : (5,) float64
        fx, skew, cx, fy, cy of the camera (the ideal buffer uses the same K).
    ox, oy : int
        Offset of the ideal buffer: buffer pixel (i, j) is ideal pixel (j + ox, i + oy).
    fbuf : (Hb, Wb) int32
        Face index per ideal pixel (-1: no face).
    sx, sy : (V,) float64; faces : (F, 3) int64
        The projected vertices in buffer pixels, and the faces (for the exact
        point-in-triangle test at edges).
    planes : (F, 4) float64
        Face planes in the camera frame: n . X = d, as (nx, ny, nz, d).
    normals_rig : (F, 3) float64
        Unit face normals in the rig frame.
    Rcr : (3, 3) float64
        Rotation camera -> rig (R.T).
    C : (3,) float64, mm
        Camera centre in the rig frame.
    Rp, tp : (3, 3), (3,) float64
        Projector pose rig -> projector.
    kproj : (5,) float64
        fx, skew, cx, fy, cy of the projector.
    pattern : (Hp, Wp) float32
        Slide intensity in [0, 1].
    smap_z : (Hp, Wp) float32, mm; smap_f : (Hp, Wp) int32
        Shadow map (depth and face) rendered from the projector.
    P : (3,) float64, mm
        Projector centre (the light source) in the rig frame.
    power, r0, ambient : float
        Flash irradiance at distance r0 (inverse-square fall-off), and the
        ambient irradiance (stray light in the housing).
    albedo, ks_sharp, n_sharp, ks_broad, n_broad : float
        Part reflectance: Lambert albedo plus two Blinn-Phong lobes (a sharp
        mirror-like one that saturates, a broad sheen).
    dirt_c : (D, 3) float64; dirt_r : (D,) float64; dirt_k : (D,) float64
        Dirt spots on the part (rig frame): centre, radius (mm), remaining
        reflectance factor at the centre.
    tex : (Ty, Tx) float32
        Belt albedo texture, texel_mm per texel, periodic along x.
    belt_shift_mm, belt_half_width, floor_albedo : float
    belt_irr, belt_q, belt_alb
        The static part of the belt's shading, from :func:`belt_static`.
    gain : (H, W) float32
        Exposure times vignetting per pixel (radiance -> DN).
    samples : int
        The slide is averaged over each pixel's footprint on the part with
        samples x samples samples (see :func:`pixel_slide`); 1: the centre only.
    out : (H, W) float32
        Irradiance of the sensor in DN before noise (written).
    points : (H, W, 3) float32
        Rig-frame point seen by each pixel (written when want_truth).
    flags : (H, W) uint8
        Bit 0: part, bit 1: lit by the projector (written when want_truth).
    """
    H, W = out.shape
    Hb, Wb = fbuf.shape
    fx = kcam[0]
    sk = kcam[1]
    cx = kcam[2]
    fy = kcam[3]
    cy = kcam[4]
    # The belt plane z = 0 in the camera frame: n_c = Rcr^T e_z, d_c = -e_z . C.
    ncx = Rcr[2, 0]
    ncy = Rcr[2, 1]
    ncz = Rcr[2, 2]
    ndc = -C[2]
    Hs, Ws = smap_z.shape
    fpx = kproj[0]
    nd = dirt_r.shape[0]
    for i in range(H):
        for j in range(W):
            xn = rays[i, j, 0]
            yn = rays[i, j, 1]
            u = fx * xn + sk * yn + cx
            v = fy * yn + cy
            bj = int(math.floor(u - ox + 0.5))
            bi = int(math.floor(v - oy + 0.5))
            # Which face does the ray hit? The buffer's nearest pixel is right
            # inside faces; near edges the exact point-in-triangle test in the
            # ideal image decides among the faces of the 3 x 3 neighbourhood.
            pu = u - ox
            pv = v - oy
            f = -1
            if bi >= 0 and bi < Hb and bj >= 0 and bj < Wb:
                f = fbuf[bi, bj]
            if f < 0 or not in_face(sx, sy, faces, f, pu, pv):
                f0 = f
                f = -1
                best = np.inf
                edge = False
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        ii = bi + di
                        jj = bj + dj
                        if ii < 0 or ii >= Hb or jj < 0 or jj >= Wb:
                            edge = True
                            continue
                        g = fbuf[ii, jj]
                        if g < 0:
                            edge = True
                            continue
                        if g != f0 and g != f and in_face(sx, sy, faces, g, pu, pv):
                            den = planes[g, 0] * xn + planes[g, 1] * yn + planes[g, 2]
                            zg = planes[g, 3] / den if abs(den) > 1e-12 else np.inf
                            if zg > 0.0 and zg < best:
                                best = zg
                                f = g
                if f < 0 and not edge:
                    f = f0  # inside a surface, on a shared edge: no gap
            den_c = ncx * xn + ncy * yn + ncz
            zc = ndc / den_c if den_c != 0.0 else np.inf
            if zc <= 0.0:
                zc = np.inf
            z = zc
            if f >= 0:
                den = planes[f, 0] * xn + planes[f, 1] * yn + planes[f, 2]
                zf = planes[f, 3] / den if abs(den) > 1e-12 else -1.0
                if zf > 0.0 and zf <= zc + 1e-3:  # a face lying on the belt wins the tie
                    z = zf
                else:
                    f = -1
            if not (z < np.inf):
                out[i, j] = 0.0
                continue
            if f < 0:
                # The belt: everything but the part's shadow is static per
                # camera and precomputed (belt_static).
                irr = belt_irr[i, j]
                if irr > 0.0:
                    irr *= lit_fraction(
                        smap_z,
                        smap_f,
                        belt_q[i, j, 0],
                        belt_q[i, j, 1],
                        belt_q[i, j, 2],
                        -1,
                        belt_q[i, j, 3],
                    )
                xc = xn * z
                yc = yn * z
                X0 = Rcr[0, 0] * xc + Rcr[0, 1] * yc + Rcr[0, 2] * z + C[0]
                X1 = Rcr[1, 0] * xc + Rcr[1, 1] * yc + Rcr[1, 2] * z + C[1]
                if belt_shift_mm == 0.0:
                    a = belt_alb[i, j]
                else:
                    a = belt_albedo(
                        X0 + belt_shift_mm, X1, tex, texel_mm, belt_half_width, floor_albedo
                    )
                out[i, j] = a * (ambient + irr) * gain[i, j]
                if want_truth:
                    points[i, j, 0] = X0
                    points[i, j, 1] = X1
                    points[i, j, 2] = 0.0
                    flags[i, j] = 2 if irr > 0.0 else 0
                continue
            xc = xn * z
            yc = yn * z
            X0 = Rcr[0, 0] * xc + Rcr[0, 1] * yc + Rcr[0, 2] * z + C[0]
            X1 = Rcr[1, 0] * xc + Rcr[1, 1] * yc + Rcr[1, 2] * z + C[1]
            X2 = Rcr[2, 0] * xc + Rcr[2, 1] * yc + Rcr[2, 2] * z + C[2]
            if f < 0:
                X2 = 0.0  # exactly on the belt
            # View direction (to the camera) and the surface normal facing it.
            vx = C[0] - X0
            vy = C[1] - X1
            vz = C[2] - X2
            vn = math.sqrt(vx * vx + vy * vy + vz * vz)
            vx /= vn
            vy /= vn
            vz /= vn
            if f >= 0:
                nx = normals_rig[f, 0]
                ny = normals_rig[f, 1]
                nz = normals_rig[f, 2]
                if nx * vx + ny * vy + nz * vz < 0.0:  # two-sided: open meshes too
                    nx = -nx
                    ny = -ny
                    nz = -nz
            else:
                nx = 0.0
                ny = 0.0
                nz = 1.0
            # Light: the projector is a point source with a patterned slide.
            lx = P[0] - X0
            ly = P[1] - X1
            lz = P[2] - X2
            dist = math.sqrt(lx * lx + ly * ly + lz * lz)
            lx /= dist
            ly /= dist
            lz /= dist
            cos_l = nx * lx + ny * ly + nz * lz
            irr = 0.0
            light = 0.0
            if cos_l > 0.0:
                qx = Rp[0, 0] * X0 + Rp[0, 1] * X1 + Rp[0, 2] * X2 + tp[0]
                qy = Rp[1, 0] * X0 + Rp[1, 1] * X1 + Rp[1, 2] * X2 + tp[1]
                qz = Rp[2, 0] * X0 + Rp[2, 1] * X1 + Rp[2, 2] * X2 + tp[2]
                if qz > NEAR_MM:
                    up = kproj[0] * qx / qz + kproj[1] * qy / qz + kproj[2]
                    vp = kproj[3] * qy / qz + kproj[4]
                    slide = pixel_slide(
                        pattern,
                        rays,
                        i,
                        j,
                        up,
                        vp,
                        (planes[f, 0], planes[f, 1], planes[f, 2], planes[f, 3]),
                        Rcr,
                        C,
                        Rp,
                        tp,
                        kproj,
                        samples,
                    )
                    if slide > 0.0:
                        lit = lit_fraction(
                            smap_z, smap_f, up, vp, qz, f, shadow_bias(qz, fpx, cos_l)
                        )
                        falloff = (r0 / dist) * (r0 / dist)
                        light = power * falloff * lit
                        irr = light * slide
            if f >= 0:
                a = albedo
                keep = 1.0
                for k in range(nd):
                    dx = X0 - dirt_c[k, 0]
                    dy = X1 - dirt_c[k, 1]
                    dz = X2 - dirt_c[k, 2]
                    d2 = dx * dx + dy * dy + dz * dz
                    r2 = dirt_r[k] * dirt_r[k]
                    if d2 < r2:
                        s = 1.0 - d2 / r2
                        keep *= 1.0 - (1.0 - dirt_k[k]) * s * s * (3.0 - 2.0 * s)
                radiance = a * keep * (ambient + irr * cos_l)
                if light > 0.0:
                    hx = lx + vx
                    hy = ly + vy
                    hz = lz + vz
                    hn = math.sqrt(hx * hx + hy * hy + hz * hz)
                    nh = (nx * hx + ny * hy + nz * hz) / hn
                    if nh > 0.0:
                        # Blinn-Phong: the sharp lobe is the flash's mirror
                        # image (the unpatterned lamp aperture), dirt is matte.
                        # nh^n = exp(n ln nh); skipped where it is < 1e-7.
                        lnh = math.log(nh)
                        spec = 0.0
                        if n_broad * lnh > -16.0:
                            spec += ks_broad * math.exp(n_broad * lnh)
                        if n_sharp * lnh > -16.0:
                            spec += ks_sharp * math.exp(n_sharp * lnh)
                        radiance += light * keep * spec
            else:
                a = belt_albedo(
                    X0 + belt_shift_mm, X1, tex, texel_mm, belt_half_width, floor_albedo
                )
                radiance = a * (ambient + irr * cos_l)
            out[i, j] = radiance * gain[i, j]
            if want_truth:
                points[i, j, 0] = X0
                points[i, j, 1] = X1
                points[i, j, 2] = X2
                fl = 0
                if f >= 0:
                    fl |= 1
                if irr > 0.0:
                    fl |= 2
                flags[i, j] = fl


@njit(cache=True, nogil=True, fastmath=_FAST)
def shade_board(  # pragma: no cover - compiled
    rays,
    Rbc,
    tbc,
    plane,
    board_tex,
    tex_ppm,
    tex_origin,
    board_lo,
    board_hi,
    Rcr,
    C,
    tex,
    texel_mm,
    belt_shift_mm,
    belt_half_width,
    floor_albedo,
    irradiance,
    ss,
    gain,
    out,
):
    """Radiance of a flat printed board (and the belt behind it), supersampled.

    Parameters
    ----------
    rays : (H, W, 2) float64
        Ideal normalised coordinates of each real pixel's ray.
    Rbc, tbc : (3, 3), (3,) float64
        Camera -> board transform: X_board = Rbc @ X_cam + tbc.
    plane : (4,) float64
        Board plane in the camera frame (n, d) with n . X = d.
    board_tex : (Ht, Wt) uint8
        The printed board image; texel (col, row) centre at board coordinates
        ((col + 0.5) / tex_ppm - tex_origin[0], (row + 0.5) / tex_ppm - tex_origin[1]).
    tex_ppm : float
        Texels per mm.
    tex_origin : (2,) float64, mm
    board_lo, board_hi : (2,) float64, mm
        Extent of the physical board in board coordinates.
    Rcr, C : camera -> rig rotation and centre (for the belt behind).
    tex, texel_mm, belt_shift_mm, belt_half_width, floor_albedo
        The belt (see :func:`shade_scene`).
    irradiance : float
        Diffuse illumination of the calibration scene.
    ss : int
        Supersampling per axis (ss * ss rays per pixel, box filter: the
        pixel's area integral, which keeps corner positions unbiased).
    gain : (H, W) float32
        Exposure times vignetting per pixel.
    out : (H, W) float32
        Sensor irradiance in DN before noise (written).
    """
    H, W = out.shape
    ncx = Rcr[2, 0]
    ncy = Rcr[2, 1]
    ncz = Rcr[2, 2]
    ndc = -C[2]
    Ht, Wt = board_tex.shape
    inv_n = 1.0 / (ss * ss)
    for i in range(H):
        for j in range(W):
            # Local Jacobian of the undistortion map: sub-pixel rays by a
            # first-order expansion (errors ~1e-7 px over a pixel).
            jl = max(j - 1, 0)
            jr = min(j + 1, W - 1)
            it = max(i - 1, 0)
            ib = min(i + 1, H - 1)
            dxu = (rays[i, jr, 0] - rays[i, jl, 0]) / (jr - jl)
            dyu = (rays[i, jr, 1] - rays[i, jl, 1]) / (jr - jl)
            dxv = (rays[ib, j, 0] - rays[it, j, 0]) / (ib - it)
            dyv = (rays[ib, j, 1] - rays[it, j, 1]) / (ib - it)
            acc = 0.0
            for si in range(ss):
                dv = (si + 0.5) / ss - 0.5
                for sj in range(ss):
                    du = (sj + 0.5) / ss - 0.5
                    xn = rays[i, j, 0] + du * dxu + dv * dxv
                    yn = rays[i, j, 1] + du * dyu + dv * dyv
                    den_c = ncx * xn + ncy * yn + ncz
                    zc = ndc / den_c if den_c != 0.0 else np.inf
                    if zc <= 0.0:
                        zc = np.inf
                    den = plane[0] * xn + plane[1] * yn + plane[2]
                    zb = plane[3] / den if abs(den) > 1e-12 else -1.0
                    value = 0.0
                    hit = False
                    if zb > 0.0 and zb <= zc + 1e-3:  # a board lying on the belt wins the tie
                        xc = xn * zb
                        yc = yn * zb
                        bx = Rbc[0, 0] * xc + Rbc[0, 1] * yc + Rbc[0, 2] * zb + tbc[0]
                        by = Rbc[1, 0] * xc + Rbc[1, 1] * yc + Rbc[1, 2] * zb + tbc[1]
                        if (
                            bx >= board_lo[0]
                            and bx <= board_hi[0]
                            and by >= board_lo[1]
                            and by <= board_hi[1]
                        ):
                            hit = True
                            tu = (bx + tex_origin[0]) * tex_ppm - 0.5
                            tv = (by + tex_origin[1]) * tex_ppm - 0.5
                            if tu < 0.0 or tv < 0.0 or tu > Wt - 1.0 or tv > Ht - 1.0:
                                g = 255.0  # the white rim of the board
                            else:
                                jj = min(int(tu), Wt - 2)
                                ii = min(int(tv), Ht - 2)
                                fu = tu - jj
                                fv = tv - ii
                                g = (1.0 - fv) * (
                                    (1.0 - fu) * board_tex[ii, jj] + fu * board_tex[ii, jj + 1]
                                ) + fv * (
                                    (1.0 - fu) * board_tex[ii + 1, jj]
                                    + fu * board_tex[ii + 1, jj + 1]
                                )
                            # Printed matte board: black ink 0.05, white paper 0.85.
                            value = 0.05 + 0.80 * g / 255.0
                    if not hit and zc < np.inf:
                        xc = xn * zc
                        yc = yn * zc
                        X0 = Rcr[0, 0] * xc + Rcr[0, 1] * yc + Rcr[0, 2] * zc + C[0]
                        X1 = Rcr[1, 0] * xc + Rcr[1, 1] * yc + Rcr[1, 2] * zc + C[1]
                        value = belt_albedo(
                            X0 + belt_shift_mm, X1, tex, texel_mm, belt_half_width, floor_albedo
                        )
                    acc += value
            out[i, j] = irradiance * acc * inv_n * gain[i, j]
