"""The walk from a face to the locally closest one, which writes a query's answer.

Shared by the fast path (:mod:`.query`, on the float32 face records) and
the exact slow path (:mod:`.bvh`, on the float64 triangles).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..._jit import NO_RUNTIME
from .face import (
    behind,
    closest_any,
    closest_on_hot,
    face_normal,
    hot_distance,
    hot_foot,
)
from .layout import HOT_A, HOT_ACROSS, HOT_ADJ, HOT_N, HOT_SMOOTH, HOT_VERT, REGION_INTERIOR
from .prefetch import prefetch

_MAX_WALK = 32


@njit(cache=True, inline="always")
def closer_across(px, py, pz, f, fd, qx, qy, qz, d2, hot, hot_i, origin, home_step):
    """The face across one of f's sharp edges closer to p than f's foot point.

    p's foot lies inside f at signed plane distance fd, at squared distance
    d2 (closest point q). Across a smooth edge a closer face would be closer
    by at most distance * angle^2 (the single-face cells' bound), so only
    sharp edges are looked across, each first bounded by its plane. A face
    g lying wholly on the other side of f's plane (a convex edge) is
    farther than that plane. A foot on g's plane inside g gives g's
    distance; one beyond their shared edge alone puts g's closest point on
    that edge, which is no closer than f's plane (p's foot is inside f):
    neither needs the full point-to-triangle test.

    Returns (g, qx, qy, qz, d2, region): the closest such face and its
    closest point, or g = -1 and the inputs when there is none.
    """
    g_best = -1
    region = REGION_INTERIOR
    across = hot_i[f, HOT_ACROSS]
    for e in range(3):
        g = int(hot_i[f, HOT_ADJ + e])
        if g < 0 or hot_i[f, HOT_SMOOTH + e] >= 0 or behind(across, e, fd):
            continue
        hit, d, u, v = hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
        if d * d >= d2:
            continue
        if hit:
            rx = px - d * hot[g, 0]
            ry = py - d * hot[g, 1]
            rz = pz - d * hot[g, 2]
            e2, rg = d * d, REGION_INTERIOR
        else:
            k = (across >> (2 * e)) & 3
            la = 1.0 - u - v
            if (
                (k == 0 and la < 0.0 and u >= 0.0 and v >= 0.0)
                or (k == 1 and u < 0.0 and la >= 0.0 and v >= 0.0)
                or (k == 2 and v < 0.0 and la >= 0.0 and u >= 0.0)
            ):
                continue
            rx, ry, rz, e2, rg = closest_on_hot(px, py, pz, hot, hot_i, g, origin, home_step)
        if e2 < d2:
            g_best, qx, qy, qz, d2, region = g, rx, ry, rz, e2, rg
    return g_best, qx, qy, qz, d2, region


@njit(cache=True, **NO_RUNTIME)
def walk_and_finish(
    i,
    px,
    py,
    pz,
    f,
    qx,
    qy,
    qz,
    d2,
    region,
    hot,
    hot_i,
    origin,
    home_step,
    tri,
    fnorm,
    exact,
    vf_ptr,
    vf_idx,
    edge_pn,
    vert_pn,
    face_id,
    out_pts,
    out_nrm,
    out_dist,
    out_face,
):
    """Descend from face f to a locally closest face, then write row i of the outputs.

    The walk moves across the edge or around the corner where the current
    closest point lies, or (with the foot inside f) to an edge neighbour,
    while that lowers the distance: on a connected surface it ends on the
    face whose interior (or shared edge or corner) holds the foot point.
    The sign uses the angle-weighted pseudo-normal of the closest feature
    (Baerentzen and Aanaes 2005), so points off edges and corners get the
    correct side. With ``exact`` the faces are the float64 triangles ``tri``
    and normals ``fnorm``, else the float32 face records (nanometres).
    """
    for _ in range(_MAX_WALK):
        moved = False
        if region == 0:
            # A foot inside f is a local minimum of the distance to f alone;
            # on the concave side of a bend a neighbour tilted towards p can
            # still be closer, so look across the edges too.
            bf, bx, by, bz, b2, br = f, qx, qy, qz, d2, region
            if not exact:
                # The face records: across the sharp edges only, each
                # bounded by its plane first (as query_grid's pass 5 does).
                # The float64 path tests all three neighbours exactly.
                fd = hot_distance(px, py, pz, hot, hot_i, f, origin, home_step)
                bf, bx, by, bz, b2, br = closer_across(
                    px, py, pz, f, fd, qx, qy, qz, d2, hot, hot_i, origin, home_step
                )
                if bf < 0:
                    break
                f, qx, qy, qz, d2, region = bf, bx, by, bz, b2, br
                continue
            for e in range(3):
                g = int(hot_i[f, HOT_ADJ + e])
                if g < 0:
                    continue
                rx, ry, rz, e2, rg = closest_any(
                    px, py, pz, hot, hot_i, g, origin, home_step, tri, exact
                )
                if e2 < b2 * (1.0 - 1e-12) - 1e-18:
                    bf, bx, by, bz, b2, br = g, rx, ry, rz, e2, rg
            if bf != f:
                f, qx, qy, qz, d2, region = bf, bx, by, bz, b2, br
                moved = True
        elif region >= 4 and hot_i[f, HOT_ADJ + region - 4] >= 0:
            g = int(hot_i[f, HOT_ADJ + region - 4])
            if g != f:
                rx, ry, rz, e2, rg = closest_any(
                    px, py, pz, hot, hot_i, g, origin, home_step, tri, exact
                )
                if e2 < d2 * (1.0 - 1e-12) - 1e-18:
                    f, qx, qy, qz, d2, region = g, rx, ry, rz, e2, rg
                    moved = True
        else:
            # Around a corner; or, on a boundary edge, around both its
            # corners: past a crack or a T-junction the surface goes on from
            # them, whose faces the edges do not reach.
            if region >= 4:
                c0, n_corners = region - 4, 2
            else:
                c0, n_corners = region - 1, 1
            bf, bx, by, bz, b2, br = f, qx, qy, qz, d2, region
            for c in range(n_corners):
                v = hot_i[f, HOT_VERT + (c0 + c) % 3]
                if not exact:
                    # Start the loads of the faces around the corner first.
                    for k in range(vf_ptr[v], vf_ptr[v + 1]):
                        prefetch(hot, (vf_idx[k], HOT_N))
                        prefetch(hot, (vf_idx[k], HOT_A))
                for k in range(vf_ptr[v], vf_ptr[v + 1]):
                    g = int(vf_idx[k])
                    if g == f:
                        continue
                    rx, ry, rz, e2, rg = closest_any(
                        px, py, pz, hot, hot_i, g, origin, home_step, tri, exact
                    )
                    if e2 < b2 * (1.0 - 1e-12) - 1e-18:
                        bf, bx, by, bz, b2, br = g, rx, ry, rz, e2, rg
            if bf != f:
                f, qx, qy, qz, d2, region = bf, bx, by, bz, b2, br
                moved = True
        if not moved:
            break
    fx, fy, fz = face_normal(hot, f, fnorm, exact)
    if region == 0:
        nx, ny, nz = fx, fy, fz
    elif region >= 4:
        e = region - 4
        nx, ny, nz = edge_pn[f, e, 0], edge_pn[f, e, 1], edge_pn[f, e, 2]
    else:
        v = hot_i[f, HOT_VERT + region - 1]
        nx, ny, nz = vert_pn[v, 0], vert_pn[v, 1], vert_pn[v, 2]
    s = (px - qx) * nx + (py - qy) * ny + (pz - qz) * nz
    d = np.sqrt(d2)
    out_pts[i, 0] = qx
    out_pts[i, 1] = qy
    out_pts[i, 2] = qz
    out_nrm[i, 0] = fx
    out_nrm[i, 1] = fy
    out_nrm[i, 2] = fz
    out_dist[i] = d if s >= 0.0 else -d
    out_face[i] = face_id[f]


@njit(cache=True, **NO_RUNTIME)
def exact_from(
    i,
    px,
    py,
    pz,
    f,
    hot,
    hot_i,
    origin,
    home_step,
    tri,
    fnorm,
    vf_ptr,
    vf_idx,
    edge_pn,
    vert_pn,
    face_id,
    out_pts,
    out_nrm,
    out_dist,
    out_face,
):
    """Row i by the exact point-to-triangle test on face f and the walk from there."""
    qx, qy, qz, d2, region = closest_on_hot(px, py, pz, hot, hot_i, f, origin, home_step)
    walk_and_finish(
        i,
        px,
        py,
        pz,
        f,
        qx,
        qy,
        qz,
        d2,
        region,
        hot,
        hot_i,
        origin,
        home_step,
        tri,
        fnorm,
        False,
        vf_ptr,
        vf_idx,
        edge_pn,
        vert_pn,
        face_id,
        out_pts,
        out_nrm,
        out_dist,
        out_face,
    )
