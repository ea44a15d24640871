"""numba kernels of the rig simulator: z-buffer rasteriser and per-pixel shading.

The renderer works in two steps per camera, so that lens distortion is exact
and triangle edges stay straight where they are straight:

1. :func:`rasterize` draws the mesh into an *ideal* (undistorted pinhole)
   buffer that stores, per ideal pixel, the depth and the index of the
   nearest face (a classic z-buffer; 1/z is interpolated, since it is the
   quantity that is linear in screen space).
2. :func:`shade_scene` visits every *real* (distorted) pixel, takes its exact
   viewing ray (precomputed by undistortion), looks up the face seen along
   that ray in the ideal buffer, and intersects the ray with that face's
   plane. Geometry is therefore exact to floating point inside faces; only
   which face a pixel sees is decided at the resolution of the buffer.

The projector's shadow map is the same rasteriser run from the projector.

The kernels are serial and release the GIL: :mod:`inspection.simulate` runs
the cameras in parallel Python threads, which is safe under every numba
threading layer (numba's own ``parallel=True`` under the "workqueue" layer
aborts the process when two threads launch kernels at once).

Internal module: callers are trusted (shapes and dtypes are checked in
:mod:`inspection.simulate`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Fast-math without "nnan"/"ninf": infinities mark "no surface" in the kernels.
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}

NEAR_MM = 1.0
"""Faces with a vertex closer than this to the image plane are skipped."""


@njit(cache=True, nogil=True)
def rasterize(sx, sy, sz, faces, zbuf, fbuf):  # pragma: no cover - compiled
    """Z-buffer rasterisation of triangles.

    Parameters
    ----------
    sx, sy : (V,) float64
        Vertex positions in buffer pixels (pixel centres at integers).
    sz : (V,) float64, mm
        Vertex depth along the optical axis.
    faces : (F, 3) int64
    zbuf : (H, W) float32, mm
        Depth buffer, initialised to +inf; updated in place.
    fbuf : (H, W) int32
        Face index buffer, initialised to -1; updated in place.
    """
    H, W = zbuf.shape
    for f in range(faces.shape[0]):
        a = faces[f, 0]
        b = faces[f, 1]
        c = faces[f, 2]
        za = sz[a]
        zb = sz[b]
        zc = sz[c]
        if za < NEAR_MM or zb < NEAR_MM or zc < NEAR_MM:
            continue
        x0 = sx[a]
        y0 = sy[a]
        x1 = sx[b]
        y1 = sy[b]
        x2 = sx[c]
        y2 = sy[c]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        xmin = max(int(math.ceil(min(x0, min(x1, x2)))), 0)
        xmax = min(int(math.floor(max(x0, max(x1, x2)))), W - 1)
        ymin = max(int(math.ceil(min(y0, min(y1, y2)))), 0)
        ymax = min(int(math.floor(max(y0, max(y1, y2)))), H - 1)
        if xmin > xmax or ymin > ymax:
            continue
        inv = 1.0 / area
        iz0 = 1.0 / za
        iz1 = 1.0 / zb
        iz2 = 1.0 / zc
        # Barycentric weights are affine in (x, y): step them incrementally.
        # w0 = ((x1 - x)(y2 - y) - (x2 - x)(y1 - y)) / area, likewise w1.
        dw0dx = (y1 - y2) * inv
        dw1dx = (y2 - y0) * inv
        for y in range(ymin, ymax + 1):
            w0 = ((x1 - xmin) * (y2 - y) - (x2 - xmin) * (y1 - y)) * inv
            w1 = ((x2 - xmin) * (y0 - y) - (x0 - xmin) * (y2 - y)) * inv
            for x in range(xmin, xmax + 1):
                w2 = 1.0 - w0 - w1
                if w0 >= -1e-9 and w1 >= -1e-9 and w2 >= -1e-9:
                    z = 1.0 / (w0 * iz0 + w1 * iz1 + w2 * iz2)
                    if z < zbuf[y, x]:
                        zbuf[y, x] = z
                        fbuf[y, x] = f
                w0 += dw0dx
                w1 += dw1dx


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
def _pixel_slide(
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
def _inside(sx, sy, faces, f, pu, pv):  # pragma: no cover - compiled
    """Is the point (pu, pv) inside projected face f (either winding, 1e-9 tolerance)?"""
    a = faces[f, 0]
    b = faces[f, 1]
    c = faces[f, 2]
    x0 = sx[a]
    y0 = sy[a]
    x1 = sx[b]
    y1 = sy[b]
    x2 = sx[c]
    y2 = sy[c]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    if area == 0.0:
        return False
    w0 = ((x1 - pu) * (y2 - pv) - (x2 - pu) * (y1 - pv)) / area
    w1 = ((x2 - pu) * (y0 - pv) - (x0 - pu) * (y2 - pv)) / area
    return w0 >= -1e-9 and w1 >= -1e-9 and 1.0 - w0 - w1 >= -1e-9


@njit(cache=True, nogil=True, inline="always")
def _shadow(smap_z, smap_f, up, vp, qz, f, bias):  # pragma: no cover - compiled
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
def _bias(qz, fpx, cos_l):  # pragma: no cover - compiled
    """Shadow-map depth bias, mm: grows with the slope seen from the projector (acne otherwise)."""
    tan_l = math.sqrt(max(1.0 - cos_l * cos_l, 0.0)) / max(cos_l, 0.05)
    return 0.3 + 1.5 * (qz / fpx) * min(tan_l, 10.0)


@njit(cache=True, nogil=True, inline="always")
def _belt_albedo(x, y, tex, texel_mm, belt_half_width, floor_albedo):  # pragma: no cover
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
        samples x samples samples (see :func:`_pixel_slide`); 1: the centre only.
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
            if f < 0 or not _inside(sx, sy, faces, f, pu, pv):
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
                        if g != f0 and g != f and _inside(sx, sy, faces, g, pu, pv):
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
                    irr *= _shadow(
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
                    a = _belt_albedo(
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
                    slide = _pixel_slide(
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
                        lit = _shadow(smap_z, smap_f, up, vp, qz, f, _bias(qz, fpx, cos_l))
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
                a = _belt_albedo(
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
                        value = _belt_albedo(
                            X0 + belt_shift_mm, X1, tex, texel_mm, belt_half_width, floor_albedo
                        )
                    acc += value
            out[i, j] = irradiance * acc * inv_n * gain[i, j]


@njit(cache=True, nogil=True, inline="always")
def _splitmix64(x):  # pragma: no cover - compiled
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@njit(cache=True, nogil=True)
def sensor_noise(img, key, shot, read2, out):  # pragma: no cover - compiled
    """Add shot and read noise, clip and quantise to 8 bits.

    The noise is a counter-based generator (splitmix64 of the key and the
    pixel index), so every pixel's noise depends only on the
    seed and its position: deterministic whatever the number of threads.

    Parameters
    ----------
    img : (H, W) float32
        Noise-free signal in DN.
    key : uint64
        Derived from the seed and the camera.
    shot : float
        Shot-noise variance per DN of signal.
    read2 : float
        Read-noise variance, DN^2.
    out : (H, W) uint8
        Written.
    """
    H, W = img.shape
    for i in range(H):
        for j in range(W):
            s = img[i, j]
            if s < 0.0:
                s = 0.0
            var = s * shot + read2
            if var > 0.0:
                # Irwin-Hall: the sum of four 16-bit uniforms from one hash,
                # centred and scaled to unit variance (a Gaussian to within
                # 1 % out to 3 sigma; sensor noise needs no better).
                h = _splitmix64(key ^ np.uint64(i * W + j))
                acc = 0.0
                for _ in range(4):
                    acc += float(h & np.uint64(0xFFFF))
                    h = h >> np.uint64(16)
                g = (acc * (1.0 / 65536.0) - 2.0) * 1.7320508075688772
                s += math.sqrt(var) * g
            s = math.floor(s + 0.5)
            if s < 0.0:
                s = 0.0
            elif s > 255.0:
                s = 255.0
            out[i, j] = np.uint8(s)


@njit(cache=True, nogil=True)
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
            belt_alb[i, j] = _belt_albedo(X0, X1, tex, texel_mm, belt_half_width, floor_albedo)
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
            slide = _pixel_slide(
                pattern, rays, i, j, up, vp, (ncx, ncy, ncz, ndc), Rcr, C, Rp, tp, kproj, samples
            )
            falloff = (r0 / dist) * (r0 / dist)
            belt_irr[i, j] = power * falloff * slide * cos_l
            belt_q[i, j, 0] = up
            belt_q[i, j, 1] = vp
            belt_q[i, j, 2] = qz
            belt_q[i, j, 3] = _bias(qz, kproj[0], cos_l)
