"""Tests of a point against one face: the exact closest point, and the plane and barycentric tests.

Each test reads either the float64 triangles ``tri`` (F, 3, 3) or the
float32 face records ``hot`` / ``hot_i`` (see :mod:`.layout`); region codes
are those of :mod:`.layout`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..._jit import NO_RUNTIME
from .layout import (
    ACROSS_ABOVE,
    ACROSS_BELOW,
    HOME_BITS,
    HOME_MASK,
    HOT_A,
    HOT_AB,
    HOT_AC,
    HOT_HOME,
    HOT_N,
)


@njit(cache=True, **NO_RUNTIME)
def closest_on_triangle(px, py, pz, tri, f):
    """Closest point to p on triangle f of ``tri`` (F, 3, 3).

    Returns (cx, cy, cz, d2, region) with d2 the squared distance.
    """
    return _closest(
        px,
        py,
        pz,
        tri[f, 0, 0],
        tri[f, 0, 1],
        tri[f, 0, 2],
        tri[f, 1, 0],
        tri[f, 1, 1],
        tri[f, 1, 2],
        tri[f, 2, 0],
        tri[f, 2, 1],
        tri[f, 2, 2],
    )


@njit(cache=True, inline="always")
def _closest(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point to p on triangle abc (Ericson, Real-Time Collision Detection, 5.1.5).

    Returns (cx, cy, cz, d2, region) with d2 the squared distance.
    """
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        qx, qy, qz, region = ax, ay, az, 1
    else:
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz, region = bx, by, bz, 2
        else:
            vc = d1 * d4 - d3 * d2
            if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
                v = d1 / (d1 - d3)
                qx, qy, qz, region = ax + v * abx, ay + v * aby, az + v * abz, 4
            else:
                cpx, cpy, cpz = px - cx, py - cy, pz - cz
                d5 = abx * cpx + aby * cpy + abz * cpz
                d6 = acx * cpx + acy * cpy + acz * cpz
                if d6 >= 0.0 and d5 <= d6:
                    qx, qy, qz, region = cx, cy, cz, 3
                else:
                    vb = d5 * d2 - d1 * d6
                    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
                        w = d2 / (d2 - d6)
                        qx, qy, qz, region = ax + w * acx, ay + w * acy, az + w * acz, 6
                    else:
                        va = d3 * d6 - d5 * d4
                        if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
                            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                            qx = bx + w * (cx - bx)
                            qy = by + w * (cy - by)
                            qz = bz + w * (cz - bz)
                            region = 5
                        else:
                            denom = 1.0 / (va + vb + vc)
                            v = vb * denom
                            w = vc * denom
                            qx = ax + abx * v + acx * w
                            qy = ay + aby * v + acy * w
                            qz = az + abz * v + acz * w
                            region = 0
    dx, dy, dz = px - qx, py - qy, pz - qz
    return qx, qy, qz, dx * dx + dy * dy + dz * dz, region


@njit(cache=True, inline="always")
def _home(hot_i, f, origin, home_step):
    """Face f's home point (see HOT_HOME), mm, float64."""
    hm = hot_i[f, HOT_HOME]
    return (
        origin[0] + (hm & HOME_MASK) * home_step,
        origin[1] + ((hm >> HOME_BITS) & HOME_MASK) * home_step,
        origin[2] + ((hm >> (2 * HOME_BITS)) & HOME_MASK) * home_step,
    )


@njit(cache=True, inline="always")
def closest_on_hot(px, py, pz, hot, hot_i, f, origin, home_step):
    """:func:`closest_on_triangle` with the corners read from face record f (see HOT_*).

    The corners are rebuilt in float64 from the home point and the record's
    float32 offsets, so they are the CAD's to about 1e-7 of their distance
    from the home point (nanometres).
    """
    ox, oy, oz = _home(hot_i, f, origin, home_step)
    ax = ox + hot[f, HOT_A]
    ay = oy + hot[f, HOT_A + 1]
    az = oz + hot[f, HOT_A + 2]
    return _closest(
        px,
        py,
        pz,
        ax,
        ay,
        az,
        ax + hot[f, HOT_AB],
        ay + hot[f, HOT_AB + 1],
        az + hot[f, HOT_AB + 2],
        ax + hot[f, HOT_AC],
        ay + hot[f, HOT_AC + 1],
        az + hot[f, HOT_AC + 2],
    )


@njit(cache=True, inline="always")
def closest_any(px, py, pz, hot, hot_i, f, origin, home_step, tri, exact):
    """Closest point on face f: float64 ``tri`` when ``exact``, else its face record."""
    if exact:
        return closest_on_triangle(px, py, pz, tri, f)
    return closest_on_hot(px, py, pz, hot, hot_i, f, origin, home_step)


@njit(cache=True, inline="always")
def face_normal(hot, f, fnorm, exact):
    """Unit normal of face f: float64 ``fnorm`` when ``exact``, else the record's, rescaled."""
    if exact:
        return fnorm[f, 0], fnorm[f, 1], fnorm[f, 2]
    nx, ny, nz = (
        np.float64(hot[f, HOT_N]),
        np.float64(hot[f, HOT_N + 1]),
        np.float64(hot[f, HOT_N + 2]),
    )
    s = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz)
    return nx * s, ny * s, nz * s


# How many smooth edges a plane foot that left a candidate is followed across
# to the face that holds it: a strip of slivers along an edge takes several.
FOOT_STEPS = 16


@njit(cache=True, inline="always")
def exit_edge(u, v):
    """The edge opposite the most negative barycentric coordinate of a foot point."""
    la = 1.0 - u - v
    if la <= u and la <= v:
        return 1
    if u <= v:
        return 2
    return 0


@njit(cache=True, **NO_RUNTIME)
def plane_foot(px, py, pz, plane, f):
    """Signed plane distance and barycentric (u, v) of p's foot on face f; hit if inside."""
    d = px * plane[f, 0] + py * plane[f, 1] + pz * plane[f, 2] - plane[f, 3]
    u = px * plane[f, 4] + py * plane[f, 5] + pz * plane[f, 6] - plane[f, 7]
    v = px * plane[f, 8] + py * plane[f, 9] + pz * plane[f, 10] - plane[f, 11]
    return (u >= 0.0 and v >= 0.0 and u + v <= 1.0), d, u, v


@njit(cache=True, inline="always")
def hot_foot(px, py, pz, hot, hot_i, f, origin, home_step):
    """Plane test of p against face f's hot record: (hit, d, u, v).

    d is p's signed distance to the face's plane, (u, v) the barycentric
    coordinates of its foot point (see HOT_*); hit when the foot lies inside
    the triangle. Computed in float64 from p relative to the face's home
    point, with the record's float32 values.
    """
    ox, oy, oz = _home(hot_i, f, origin, home_step)
    qx, qy, qz = px - ox, py - oy, pz - oz
    d = qx * hot[f, 0] + qy * hot[f, 1] + qz * hot[f, 2] - hot[f, 3]
    u = qx * hot[f, 4] + qy * hot[f, 5] + qz * hot[f, 6] - hot[f, 7]
    v = qx * hot[f, 8] + qy * hot[f, 9] + qz * hot[f, 10] - hot[f, 11]
    return (u >= 0.0 and v >= 0.0 and u + v <= 1.0), d, u, v


@njit(cache=True, inline="always")
def hot_distance(px, py, pz, hot, hot_i, f, origin, home_step):
    """Signed distance of p to face f's plane, from its hot record."""
    ox, oy, oz = _home(hot_i, f, origin, home_step)
    qx, qy, qz = px - ox, py - oy, pz - oz
    return qx * hot[f, 0] + qy * hot[f, 1] + qz * hot[f, 2] - hot[f, 3]


@njit(cache=True, inline="always")
def behind(across, e, d):
    """Whether the face across edge e lies wholly on the other side of this
    face's plane than a point at signed plane distance d (then it is no
    closer to it than the plane)."""
    side = (across >> (6 + 2 * e)) & 3
    return (side == ACROSS_BELOW and d > 0.0) or (side == ACROSS_ABOVE and d < 0.0)
