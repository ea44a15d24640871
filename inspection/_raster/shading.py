"""The radiance of every real pixel: the part and belt under the flash, or a calibration board."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .._jit import NO_RUNTIME
from .belt import belt_albedo
from .flash import _bilinear, lit_fraction, pixel_slide, shadow_bias
from .zbuffer import NEAR_MM, in_face

# Fast-math without "nnan"/"ninf": infinities mark "no surface" in the kernels.
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


# A pixel whose 3 x 3 neighbourhood in the buffer spans more depth than this (mm) straddles
# an occluding outline (a flange over the belt, a wall over the floor), not a sloped face.
_DEPTH_JUMP_MM = 5.0


@njit(cache=True, nogil=True, inline="always")
def _depth_on_face(sx, sy, faces, planes, g, pu, pv, xn, yn):  # pragma: no cover - compiled
    """Depth (camera z, mm) where the ray (xn, yn, 1) meets face g, inf when the ray's
    point (pu, pv) of the ideal buffer lies outside the face or the face is behind."""
    if not in_face(sx, sy, faces, g, pu, pv):
        return np.inf
    den = planes[g, 0] * xn + planes[g, 1] * yn + planes[g, 2]
    z = planes[g, 3] / den if abs(den) > 1e-12 else np.inf
    return z if z > 0.0 else np.inf


_WALK_STEPS = 64


@njit(cache=True, nogil=True, inline="always")
def _walk(sx, sy, faces, neighbours, g, pu, pv):  # pragma: no cover - compiled
    """The face holding the point (pu, pv) of the ideal buffer, found by walking from face
    g across the edge the point lies beyond, at most :data:`_WALK_STEPS` faces; -1 when
    the walk leaves the mesh (the point is off the part) or runs out of steps."""
    for _ in range(_WALK_STEPS):
        if g < 0:
            return -1
        a = faces[g, 0]
        b = faces[g, 1]
        c = faces[g, 2]
        area = (sx[b] - sx[a]) * (sy[c] - sy[a]) - (sx[c] - sx[a]) * (sy[b] - sy[a])
        if area == 0.0:
            return -1
        w0 = ((sx[b] - pu) * (sy[c] - pv) - (sx[c] - pu) * (sy[b] - pv)) / area
        w1 = ((sx[c] - pu) * (sy[a] - pv) - (sx[a] - pu) * (sy[c] - pv)) / area
        w2 = 1.0 - w0 - w1
        if w0 >= -1e-9 and w1 >= -1e-9 and w2 >= -1e-9:
            return g
        # Across the edge facing the most negative weight's vertex: neighbours' slots are
        # the edges (v0 v1), (v1 v2), (v2 v0).
        if w0 <= w1 and w0 <= w2:
            g = neighbours[g, 1]
        elif w1 <= w2:
            g = neighbours[g, 2]
        else:
            g = neighbours[g, 0]
    return -1


@njit(cache=True, nogil=True, inline="always")
def face_on_ray(
    fbuf, sx, sy, faces, planes, neighbours, bi, bj, pu, pv, xn, yn
):  # pragma: no cover - compiled
    """The face a ray meets first, -1 for none (the belt or the floor beyond it).

    The buffer's cell (bi, bj) nearest the ray's point (pu, pv) is right inside
    faces; near edges the exact point-in-triangle test decides among the faces
    of the 3 x 3 cells around, the nearest along the ray winning. Inside a
    surface, a ray no face of those cells holds (on a shared edge, where every
    test fails by rounding, or next to a face thinner than a pixel) takes the
    nearest cell's face: no gap, and a point within a pixel. By the outline,
    where some cells see nothing, that would be the belt: a face smaller than
    a pixel, or thin (a sliver along a hole's rim), may hold no cell's centre,
    and a strip of them may lie between two columns of centres, so such faces
    are found by walking across the mesh's edges from the faces around
    towards the point.

    Also returns whether no cell of the 3 x 3 around holds a face (the belt
    or the floor all round: no walk can start, and the pixel is on no outline).
    """
    Hb, Wb = fbuf.shape
    f0 = -1
    if bi >= 0 and bi < Hb and bj >= 0 and bj < Wb:
        f0 = fbuf[bi, bj]
    if f0 >= 0 and in_face(sx, sy, faces, f0, pu, pv):
        return f0, False
    found = -1
    best = np.inf
    edge = False
    clear = True
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
            clear = False
            if g != f0 and g != found:
                z = _depth_on_face(sx, sy, faces, planes, g, pu, pv, xn, yn)
                if z < best:
                    best = z
                    found = g
    if found >= 0:
        return found, False
    if not edge:
        return f0, False
    if clear:
        return -1, True
    for di in range(-1, 2):
        for dj in range(-1, 2):
            ii = bi + di
            jj = bj + dj
            if ii < 0 or ii >= Hb or jj < 0 or jj >= Wb:
                continue
            g = _walk(sx, sy, faces, neighbours, fbuf[ii, jj], pu, pv)
            if g >= 0 and g != found:
                z = _depth_on_face(sx, sy, faces, planes, g, pu, pv, xn, yn)
                if z < best:
                    best = z
                    found = g
    return found, False


@njit(cache=True, nogil=True, inline="always")
def _ray_jacobian(rays, i, j):  # pragma: no cover - compiled
    """How the normalised ray of pixel (i, j) moves per pixel along u and v: the local
    Jacobian of the undistortion map, by central differences (one-sided at the border).
    Sub-pixel rays from it, to first order, err by ~1e-7 px over a pixel."""
    H, W = rays.shape[0], rays.shape[1]
    jl = max(j - 1, 0)
    jr = min(j + 1, W - 1)
    it = max(i - 1, 0)
    ib = min(i + 1, H - 1)
    dxu = (rays[i, jr, 0] - rays[i, jl, 0]) / (jr - jl)
    dyu = (rays[i, jr, 1] - rays[i, jl, 1]) / (jr - jl)
    dxv = (rays[ib, j, 0] - rays[it, j, 0]) / (ib - it)
    dyv = (rays[ib, j, 1] - rays[it, j, 1]) / (ib - it)
    return dxu, dyu, dxv, dyv


@njit(cache=True, nogil=True, inline="always")
def _on_outline(fbuf, zbuf, bi, bj):  # pragma: no cover - compiled
    """Does the pixel at buffer cell (bi, bj) straddle the part's outline: part and
    no part, or depths far apart, among the 3 x 3 cells around?"""
    Hb, Wb = fbuf.shape
    part = False
    air = False
    zmin = np.inf
    zmax = -np.inf
    for di in range(-1, 2):
        for dj in range(-1, 2):
            ii = bi + di
            jj = bj + dj
            if ii < 0 or ii >= Hb or jj < 0 or jj >= Wb or fbuf[ii, jj] < 0:
                air = True
                continue
            part = True
            z = zbuf[ii, jj]
            zmin = min(zmin, z)
            zmax = max(zmax, z)
    return part and (air or zmax - zmin > _DEPTH_JUMP_MM)


@njit(cache=True, nogil=True, inline="always")
def _belt_radiance(
    i, j, xn, yn, z, Rcr, C, smap_z, smap_f, ambient, tex, texel_mm,
    belt_shift_mm, belt_half_width, floor_albedo, belt_irr, belt_q, belt_alb,
):  # pragma: no cover - compiled  # fmt: skip
    """Radiance of the belt seen by real pixel (i, j) along its ray (xn, yn) at depth z
    (0 where the ray misses it), and the patterned irradiance there: everything but the
    part's shadow is static per camera and precomputed (:func:`belt_static`)."""
    if not (z < np.inf):
        return 0.0, 0.0
    irr = belt_irr[i, j]
    if irr > 0.0:
        irr *= lit_fraction(
            smap_z, smap_f, belt_q[i, j, 0], belt_q[i, j, 1], belt_q[i, j, 2], -1, belt_q[i, j, 3]
        )
    if belt_shift_mm == 0.0:
        a = belt_alb[i, j]
    else:
        xc = xn * z
        yc = yn * z
        X0 = Rcr[0, 0] * xc + Rcr[0, 1] * yc + Rcr[0, 2] * z + C[0]
        X1 = Rcr[1, 0] * xc + Rcr[1, 1] * yc + Rcr[1, 2] * z + C[1]
        a = belt_albedo(X0 + belt_shift_mm, X1, tex, texel_mm, belt_half_width, floor_albedo)
    return a * (ambient + irr), irr


@njit(cache=True, nogil=True, inline="always")
def _belt_ray_radiance(
    xn, yn, Rcr, C, Rp, tp, kproj, pattern, smap_z, smap_f, P, power, r0, ambient, tex,
    texel_mm, belt_shift_mm, belt_half_width, floor_albedo,
):  # pragma: no cover - compiled  # fmt: skip
    """Radiance of the belt along one ray (xn, yn) of a camera (0 where the ray misses it),
    computed as :func:`belt_static` and :func:`_belt_radiance` do for a pixel's centre, with
    the slide taken at the ray's point: one of the rays an outline pixel is sampled with."""
    den_c = Rcr[2, 0] * xn + Rcr[2, 1] * yn + Rcr[2, 2]
    z = -C[2] / den_c if den_c != 0.0 else -1.0
    if z <= 0.0:
        return 0.0
    xc = xn * z
    yc = yn * z
    X0 = Rcr[0, 0] * xc + Rcr[0, 1] * yc + Rcr[0, 2] * z + C[0]
    X1 = Rcr[1, 0] * xc + Rcr[1, 1] * yc + Rcr[1, 2] * z + C[1]
    a = belt_albedo(X0 + belt_shift_mm, X1, tex, texel_mm, belt_half_width, floor_albedo)
    lx = P[0] - X0
    ly = P[1] - X1
    lz = P[2]
    dist = math.sqrt(lx * lx + ly * ly + lz * lz)
    cos_l = lz / dist
    irr = 0.0
    if cos_l > 0.0:
        qx = Rp[0, 0] * X0 + Rp[0, 1] * X1 + tp[0]
        qy = Rp[1, 0] * X0 + Rp[1, 1] * X1 + tp[1]
        qz = Rp[2, 0] * X0 + Rp[2, 1] * X1 + tp[2]
        if qz > NEAR_MM:
            up = kproj[0] * qx / qz + kproj[1] * qy / qz + kproj[2]
            vp = kproj[3] * qy / qz + kproj[4]
            slide = _bilinear(pattern, up, vp)
            if slide > 0.0:
                lit = lit_fraction(smap_z, smap_f, up, vp, qz, -1, shadow_bias(qz, kproj[0], cos_l))
                irr = power * (r0 / dist) * (r0 / dist) * slide * cos_l * lit
    return a * (ambient + irr)


@njit(cache=True, nogil=True, inline="always")
def _part_radiance(
    f, i, j, xn, yn, z, samples, rays, planes, normals_rig, Rcr, C, Rp, tp, kproj, pattern,
    smap_z, smap_f, P, power, r0, ambient, albedo, ks_sharp, n_sharp, ks_broad, n_broad,
    dirt_c, dirt_r, dirt_k,
):  # pragma: no cover - compiled  # fmt: skip
    """Radiance of face f where the ray (xn, yn) of real pixel (i, j) meets it at depth z,
    the slide averaged over the pixel's footprint with ``samples`` per axis (1: at the ray);
    also the rig-frame point and the patterned irradiance there."""
    xc = xn * z
    yc = yn * z
    X0 = Rcr[0, 0] * xc + Rcr[0, 1] * yc + Rcr[0, 2] * z + C[0]
    X1 = Rcr[1, 0] * xc + Rcr[1, 1] * yc + Rcr[1, 2] * z + C[1]
    X2 = Rcr[2, 0] * xc + Rcr[2, 1] * yc + Rcr[2, 2] * z + C[2]
    # View direction (to the camera) and the surface normal facing it.
    vx = C[0] - X0
    vy = C[1] - X1
    vz = C[2] - X2
    vn = math.sqrt(vx * vx + vy * vy + vz * vz)
    vx /= vn
    vy /= vn
    vz /= vn
    nx = normals_rig[f, 0]
    ny = normals_rig[f, 1]
    nz = normals_rig[f, 2]
    if nx * vx + ny * vy + nz * vz < 0.0:  # two-sided: open meshes too
        nx = -nx
        ny = -ny
        nz = -nz
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
                pattern, rays, i, j, up, vp, (planes[f, 0], planes[f, 1], planes[f, 2],
                planes[f, 3]), Rcr, C, Rp, tp, kproj, samples,
            )  # fmt: skip
            if slide > 0.0:
                lit = lit_fraction(smap_z, smap_f, up, vp, qz, f, shadow_bias(qz, kproj[0], cos_l))
                falloff = (r0 / dist) * (r0 / dist)
                light = power * falloff * lit
                irr = light * slide
    keep = 1.0
    for k in range(dirt_r.shape[0]):
        dx = X0 - dirt_c[k, 0]
        dy = X1 - dirt_c[k, 1]
        dz = X2 - dirt_c[k, 2]
        d2 = dx * dx + dy * dy + dz * dz
        r2 = dirt_r[k] * dirt_r[k]
        if d2 < r2:
            s = 1.0 - d2 / r2
            keep *= 1.0 - (1.0 - dirt_k[k]) * s * s * (3.0 - 2.0 * s)
    radiance = albedo * keep * (ambient + irr * cos_l)
    if light > 0.0:
        hx = lx + vx
        hy = ly + vy
        hz = lz + vz
        hn = math.sqrt(hx * hx + hy * hy + hz * hz)
        nh = (nx * hx + ny * hy + nz * hz) / hn
        if nh > 0.0:
            # Blinn-Phong: the sharp lobe is the flash's mirror image (the unpatterned lamp
            # aperture), dirt is matte. nh^n = exp(n ln nh); skipped where it is < 1e-7.
            lnh = math.log(nh)
            spec = 0.0
            if n_broad * lnh > -16.0:
                spec += ks_broad * math.exp(n_broad * lnh)
            if n_sharp * lnh > -16.0:
                spec += ks_sharp * math.exp(n_sharp * lnh)
            radiance += light * keep * spec
    return radiance, X0, X1, X2, irr


@njit(cache=True, nogil=True, fastmath=_FAST, **NO_RUNTIME)
def shade_scene(  # pragma: no cover - compiled
    rays,
    kcam,
    ox,
    oy,
    fbuf,
    zbuf,
    sx,
    sy,
    faces,
    neighbours,
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
    edge_samples,
    out,
    points,
    flags,
    want_truth,
):
    """Radiance of every real pixel of one camera, under the pattern flash.

    A pixel collects the light over its whole area. Inside a face that is the
    pattern averaged over the pixel's footprint (``samples``); where the
    pixel straddles the part's outline (a hole's rim, the part's edge against
    the belt, a flange over the floor) it is ``edge_samples`` x
    ``edge_samples`` rays through the pixel, each finding its own face (or
    the belt) and shaded on its own, averaged: the outline falls between
    pixels' centres as it does on a sensor, not on whole pixels.

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
    zbuf : (Hb, Wb) float32, mm
        Depth per ideal pixel (inf: no face).
    sx, sy : (V,) float64; faces : (F, 3) int64
        The projected vertices in buffer pixels, and the faces (for the exact
        point-in-triangle test at edges).
    neighbours : (F, 3) int64
        Per face, the faces across its three edges (-1: none).
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
    edge_samples : int
        Rays per axis through a pixel on the outline (1: its centre decides).
    out : (H, W) float32
        Irradiance of the sensor in DN before noise (written).
    points : (H, W, 3) float32
        Rig-frame point seen by each pixel's centre (written when want_truth).
    flags : (H, W) uint8
        Bit 0: part, bit 1: lit by the projector, at the pixel's centre
        (written when want_truth).
    """
    H, W = out.shape
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
    inv_e = 1.0 / (edge_samples * edge_samples)
    for i in range(H):
        for j in range(W):
            xn = rays[i, j, 0]
            yn = rays[i, j, 1]
            pu = fx * xn + sk * yn + cx - ox
            pv = fy * yn + cy - oy
            bj = int(math.floor(pu + 0.5))
            bi = int(math.floor(pv + 0.5))
            f, clear = face_on_ray(fbuf, sx, sy, faces, planes, neighbours, bi, bj, pu, pv, xn, yn)
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
                value, irr = _belt_radiance(
                    i, j, xn, yn, zc, Rcr, C, smap_z, smap_f, ambient, tex, texel_mm,
                    belt_shift_mm, belt_half_width, floor_albedo, belt_irr, belt_q, belt_alb,
                )  # fmt: skip
                if want_truth:
                    xc = xn * z
                    yc = yn * z
                    points[i, j, 0] = Rcr[0, 0] * xc + Rcr[0, 1] * yc + Rcr[0, 2] * z + C[0]
                    points[i, j, 1] = Rcr[1, 0] * xc + Rcr[1, 1] * yc + Rcr[1, 2] * z + C[1]
                    points[i, j, 2] = 0.0
                    flags[i, j] = 2 if irr > 0.0 else 0
            else:
                value, X0, X1, X2, irr = _part_radiance(
                    f, i, j, xn, yn, z, samples, rays, planes, normals_rig, Rcr, C, Rp, tp,
                    kproj, pattern, smap_z, smap_f, P, power, r0, ambient, albedo, ks_sharp,
                    n_sharp, ks_broad, n_broad, dirt_c, dirt_r, dirt_k,
                )  # fmt: skip
                if want_truth:
                    points[i, j, 0] = X0
                    points[i, j, 1] = X1
                    points[i, j, 2] = X2
                    flags[i, j] = 3 if irr > 0.0 else 1
            if edge_samples > 1 and not clear and _on_outline(fbuf, zbuf, bi, bj):
                # The pixel's own rays, spread over its area.
                dxu, dyu, dxv, dyv = _ray_jacobian(rays, i, j)
                acc = 0.0
                for si in range(edge_samples):
                    dv = (si + 0.5) / edge_samples - 0.5
                    for sj in range(edge_samples):
                        du = (sj + 0.5) / edge_samples - 0.5
                        xs = xn + du * dxu + dv * dxv
                        ys = yn + du * dyu + dv * dyv
                        qu = fx * xs + sk * ys + cx - ox
                        qv = fy * ys + cy - oy
                        g, _ = face_on_ray(
                            fbuf, sx, sy, faces, planes, neighbours,
                            int(math.floor(qv + 0.5)), int(math.floor(qu + 0.5)), qu, qv, xs, ys,
                        )  # fmt: skip
                        zs = np.inf
                        if g >= 0:
                            den = planes[g, 0] * xs + planes[g, 1] * ys + planes[g, 2]
                            zs = planes[g, 3] / den if abs(den) > 1e-12 else -1.0
                            den_c = ncx * xs + ncy * ys + ncz
                            zcs = ndc / den_c if den_c != 0.0 else np.inf
                            if zcs <= 0.0:
                                zcs = np.inf
                            if not (zs > 0.0 and zs <= zcs + 1e-3):
                                g = -1
                        if g < 0:
                            acc += _belt_ray_radiance(
                                xs, ys, Rcr, C, Rp, tp, kproj, pattern, smap_z, smap_f, P,
                                power, r0, ambient, tex, texel_mm, belt_shift_mm,
                                belt_half_width, floor_albedo,
                            )  # fmt: skip
                        else:
                            r, _, _, _, _ = _part_radiance(
                                g, i, j, xs, ys, zs, 1, rays, planes, normals_rig, Rcr, C, Rp,
                                tp, kproj, pattern, smap_z, smap_f, P, power, r0, ambient,
                                albedo, ks_sharp, n_sharp, ks_broad, n_broad, dirt_c, dirt_r,
                                dirt_k,
                            )  # fmt: skip
                            acc += r
                value = acc * inv_e
            out[i, j] = value * gain[i, j]


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
            dxu, dyu, dxv, dyv = _ray_jacobian(rays, i, j)
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
