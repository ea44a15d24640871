"""Numba kernels of :mod:`inspection.grid`: exact point-to-triangle, the grid build and query.

Internal: the public entry points in :mod:`inspection.grid` validate their
inputs; these kernels trust their callers. All kernels are compiled with
``cache=True``, so a process pays the compile time (a few seconds) once per
machine and later only loads them (see :func:`inspection.grid.warmup`).

Conventions
-----------
tri : (F, 3, 3) float64, mm
    The triangles' corners a, b, c.
Region codes returned by :func:`closest_on_triangle`: 0 interior,
1, 2, 3 the corners a, b, c, and 4, 5, 6 the edges ab, bc, ca (edge e of a
face joins its corners e and (e + 1) % 3).
Faces are numbered in the tree's own (spatial) order; ``face_id`` maps that
number to the CAD model's face index, which is what the queries return.
Cell codes of the fine grid: ``>= 0`` a face that is closest to all eight
corners of the cell, ``-1`` unknown (a corner lies outside the computed band:
use the exact slow path), ``<= -2`` mixed: the cell is split in eight
subcells of half its edge, whose codes are ``subcells[8 * (-code - 2) + s]``
(``s = 4 sx + 2 sy + sz``, the half the point lies in along each axis).
Subcell codes read like cell codes, except that a mixed one, ``<= -2``,
indexes a list of candidate faces: ``mixed_faces[mixed_ptr[m]:mixed_ptr[m + 1]]``
with ``m = -code - 2`` (the distinct faces closest to the subcell's corners).
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

REGION_INTERIOR = 0
CELL_UNKNOWN = -1
# ``out_face`` of a query the fast path leaves to the slow one.
FACE_SLOW = -1

_MAX_WALK = 32
# A single-face cell code carries this bit when the foot point of every point
# of the cell lies inside the face (checked at the eight corners: the foot is
# an affine function of the point, the cell convex).
INTERIOR_FLAG = 1 << 30
FACE_MASK = INTERIOR_FLAG - 1
_MAX_PLANE_STEPS = 6
# Queries per chunk of the fast path's passes: the chunk's cells and face
# records stay in the first-level caches between the passes.
QUERY_CHUNK = 64

# Layout of a face record, one row of the (F, HOT_WIDTH) 4-byte array the
# queries read (as float32, and as int32 for the integer columns): 128
# bytes, two cache lines per face. Line 0 holds what the plane test needs
# (most queries read nothing else), line 1 the corners and the
# neighbourhood for the exact test and the walk. Geometry is stored
# relative to the face's home point (origin + home * home_step, the home
# packed in HOT_HOME as three HOME_BITS-bit integers, corner a within a
# few block edges of it): p - home is taken in float64, so the float32
# values (relative error 6e-8) place planes and corners to nanometres.
HOT_WIDTH = 32
# Line 0: unit normal n (3), n.(a - home); U (3), U.(a - home); V (3),
# V.(a - home) (U, V: the dual basis of the edges ab, ac in the plane).
HOT_N, HOT_U, HOT_V = 0, 4, 8
HOT_HOME = 12  # int32: home x | y << HOME_BITS | z << 2 * HOME_BITS
HOT_SMOOTH = 13  # int32 (3): the face across edge e where it is smooth, else -1
# Line 1: a - home (3), b - a (3), c - a (3).
HOT_A, HOT_AB, HOT_AC = 16, 19, 22
HOT_ADJ = 25  # int32 (3): the face across edge e, or -1
HOT_VERT = 28  # int32 (3): the vertex index of corner e
# int32: for each edge e, bits 2e..2e+1: the corner of the face g across
# edge e opposite their shared edge (3: unknown); bits 6+2e..7+2e: the side
# of this face's plane g lies on (ACROSS_ABOVE, ACROSS_BELOW, or 0).
HOT_ACROSS = 31
ACROSS_ABOVE = 1
ACROSS_BELOW = 2
HOME_BITS = 10
HOME_MASK = (1 << HOME_BITS) - 1


@intrinsic
def prefetch(typingctx, arr, index):
    """Ask the CPU to start loading the cache line of ``arr[index]``.

    ``index`` is an integer (1-D arrays) or a tuple of integers. A hint only
    (LLVM's ``llvm.prefetch``): it never faults, changes no result and does
    not wait, so one loop can start many loads at once; an out-of-range
    index is allowed.
    """
    if not isinstance(arr, types.Array):
        return None
    if isinstance(index, types.Integer):
        if arr.ndim != 1:
            return None
    elif not (
        isinstance(index, types.BaseTuple)
        and len(index) == arr.ndim
        and all(isinstance(t, types.Integer) for t in index)
    ):
        return None
    sig = types.void(arr, index)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def,unused-ignore]
        aryty, idxty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        if isinstance(idxty, types.Integer):
            idx = [context.cast(builder, args[1], idxty, types.intp)]
        else:
            idx = [
                context.cast(builder, builder.extract_value(args[1], k), t, types.intp)
                for k, t in enumerate(idxty)
            ]
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, idx, wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        # read, high temporal locality, data cache
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True)
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
def _closest_any(px, py, pz, hot, hot_i, f, origin, home_step, tri, exact):
    """Closest point on face f: float64 ``tri`` when ``exact``, else its face record."""
    if exact:
        return closest_on_triangle(px, py, pz, tri, f)
    return closest_on_hot(px, py, pz, hot, hot_i, f, origin, home_step)


@njit(cache=True, inline="always")
def _face_normal(hot, f, fnorm, exact):
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


@njit(cache=True, inline="always")
def _closer_across(px, py, pz, f, fd, qx, qy, qz, d2, hot, hot_i, origin, home_step):
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
        if g < 0 or hot_i[f, HOT_SMOOTH + e] >= 0 or _behind(across, e, fd):
            continue
        hit, d, u, v = _hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
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


@njit(cache=True)
def _walk_and_finish(
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
                fd = _hot_distance(px, py, pz, hot, hot_i, f, origin, home_step)
                bf, bx, by, bz, b2, br = _closer_across(
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
                rx, ry, rz, e2, rg = _closest_any(
                    px, py, pz, hot, hot_i, g, origin, home_step, tri, exact
                )
                if e2 < b2 * (1.0 - 1e-12) - 1e-18:
                    bf, bx, by, bz, b2, br = g, rx, ry, rz, e2, rg
            if bf != f:
                f, qx, qy, qz, d2, region = bf, bx, by, bz, b2, br
                moved = True
        elif region >= 4:
            g = int(hot_i[f, HOT_ADJ + region - 4])
            if g >= 0 and g != f:
                rx, ry, rz, e2, rg = _closest_any(
                    px, py, pz, hot, hot_i, g, origin, home_step, tri, exact
                )
                if e2 < d2 * (1.0 - 1e-12) - 1e-18:
                    f, qx, qy, qz, d2, region = g, rx, ry, rz, e2, rg
                    moved = True
        else:
            v = hot_i[f, HOT_VERT + region - 1]
            bf, bx, by, bz, b2, br = f, qx, qy, qz, d2, region
            if not exact:
                # Start the loads of the faces around the corner first.
                for k in range(vf_ptr[v], vf_ptr[v + 1]):
                    prefetch(hot, (vf_idx[k], HOT_N))
                    prefetch(hot, (vf_idx[k], HOT_A))
            for k in range(vf_ptr[v], vf_ptr[v + 1]):
                g = int(vf_idx[k])
                if g == f:
                    continue
                rx, ry, rz, e2, rg = _closest_any(
                    px, py, pz, hot, hot_i, g, origin, home_step, tri, exact
                )
                if e2 < b2 * (1.0 - 1e-12) - 1e-18:
                    bf, bx, by, bz, b2, br = g, rx, ry, rz, e2, rg
            if bf != f:
                f, qx, qy, qz, d2, region = bf, bx, by, bz, b2, br
                moved = True
        if not moved:
            break
    fx, fy, fz = _face_normal(hot, f, fnorm, exact)
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


@njit(cache=True)
def _plane_foot(px, py, pz, plane, f):
    """Signed plane distance and barycentric (u, v) of p's foot on face f; hit if inside."""
    d = px * plane[f, 0] + py * plane[f, 1] + pz * plane[f, 2] - plane[f, 3]
    u = px * plane[f, 4] + py * plane[f, 5] + pz * plane[f, 6] - plane[f, 7]
    v = px * plane[f, 8] + py * plane[f, 9] + pz * plane[f, 10] - plane[f, 11]
    return (u >= 0.0 and v >= 0.0 and u + v <= 1.0), d, u, v


@njit(cache=True)
def _shift_of(block):
    shift = 0
    while (1 << shift) < block:
        shift += 1
    return shift


@njit(cache=True, inline="always")
def _hot_foot(px, py, pz, hot, hot_i, f, origin, home_step):
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
def _hot_distance(px, py, pz, hot, hot_i, f, origin, home_step):
    """Signed distance of p to face f's plane, from its hot record."""
    ox, oy, oz = _home(hot_i, f, origin, home_step)
    qx, qy, qz = px - ox, py - oy, pz - oz
    return qx * hot[f, 0] + qy * hot[f, 1] + qz * hot[f, 2] - hot[f, 3]


@njit(cache=True, inline="always")
def _exit_edge(u, v):
    """The edge opposite the most negative barycentric coordinate of a foot point."""
    la = 1.0 - u - v
    if la <= u and la <= v:
        return 1
    if u <= v:
        return 2
    return 0


@njit(cache=True, inline="always")
def _write_foot(i, px, py, pz, d, f, hot, face_id, out_pts, out_nrm, out_dist, out_face):
    """Row i of the outputs for a foot point inside face f at plane distance d.

    d is measured with the record's float32 normal, whose length is 1 to
    within 1e-7: both are rescaled so that the normal is a unit vector and
    the point lies exactly d away.
    """
    nx, ny, nz = np.float64(hot[f, 0]), np.float64(hot[f, 1]), np.float64(hot[f, 2])
    s = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz, d = nx * s, ny * s, nz * s, d * s
    out_pts[i, 0] = px - d * nx
    out_pts[i, 1] = py - d * ny
    out_pts[i, 2] = pz - d * nz
    out_nrm[i, 0] = nx
    out_nrm[i, 1] = ny
    out_nrm[i, 2] = nz
    out_dist[i] = d
    out_face[i] = face_id[f]


@njit(cache=True, inline="always")
def _behind(across, e, d):
    """Whether the face across edge e lies wholly on the other side of this
    face's plane than a point at signed plane distance d (then it is no
    closer to it than the plane)."""
    side = (across >> (6 + 2 * e)) & 3
    return (side == ACROSS_BELOW and d > 0.0) or (side == ACROSS_ABOVE and d < 0.0)


@njit(cache=True, inline="always")
def _sharp_prefetch(hot, hot_i, f, d):
    """Start the loads of the planes of the faces across f's sharp edges that
    a point at plane distance d may be closer to."""
    across = hot_i[f, HOT_ACROSS]
    for e in range(3):
        g = int(hot_i[f, HOT_ADJ + e])
        if g >= 0 and hot_i[f, HOT_SMOOTH + e] < 0 and not _behind(across, e, d):
            prefetch(hot, (g, HOT_N))


@njit(cache=True, parallel=True)
def query_grid(
    points,
    origin,
    inv_h,
    block,
    dims,
    coarse,
    cells,
    subcells,
    mixed_ptr,
    mixed_faces,
    hot,
    hot_i,
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
    n_slow,
):
    """Fast path: cell lookup, plane tests on the cell's face(s), local walk.

    A cell with one face first tries the face's plane: when the foot point
    falls inside the triangle (barycentric test with the dual basis of the
    face's hot record) it is the closest point on that face and the answer
    costs a dozen multiply-adds; a foot outside steps across the smooth edge
    it left by. Cells with a candidate list bound their candidates by their
    planes first. Where no plane foot decides, the exact point-to-triangle
    test on the record's corners and the walk of :func:`_walk_and_finish` do.
    All of it reads the float32 face records: exact to a few nanometres.
    A query in a mixed cell reads the code of its subcell first (one more
    pass, for those queries only), which most often names a single face.

    Points whose cell is unknown or outside the grid get
    ``out_face = FACE_SLOW`` and their other outputs untouched;
    ``n_slow[c]`` counts them per chunk of QUERY_CHUNK rows.
    """
    n = points.shape[0]
    nby, nbz = dims[1], dims[2]
    # block is a power of two: shifts and masks instead of integer division.
    shift = _shift_of(block)
    mask = block - 1
    limx = float(dims[0] * block)
    limy = float(dims[1] * block)
    limz = float(dims[2] * block)
    for c in prange(n_slow.shape[0]):
        j0 = c * QUERY_CHUNK
        j1 = min(n, j0 + QUERY_CHUNK)
        # Memory, not arithmetic, sets the pace: each pass issues loads that
        # do not depend on one another, so their cache misses overlap, and
        # the next pass finds the lines in cache. Pass 1 reads the chunk's
        # cell codes (and those of the subcells of mixed cells), pass 2
        # prefetches the hot records they name, pass 3 answers every query
        # it can and prefetches the record of the face a walk steps to (or
        # of the faces across the sharp edges of a subcell's face or of a
        # list's best candidate), passes 4 and 5 finish those.
        cell = np.empty(QUERY_CHUNK, dtype=np.int64)
        sub = np.empty(QUERY_CHUNK, dtype=np.int64)
        for i in range(j0, j1):
            gx = (points[i, 0] - origin[0]) * inv_h
            gy = (points[i, 1] - origin[1]) * inv_h
            gz = (points[i, 2] - origin[2]) * inv_h
            k = -1
            sub[i - j0] = 0
            # Also keeps far points from overflowing the integer conversion.
            if 0.0 <= gx < limx and 0.0 <= gy < limy and 0.0 <= gz < limz:
                ix, iy, iz = int(gx), int(gy), int(gz)
                b = coarse[((ix >> shift) * nby + (iy >> shift)) * nbz + (iz >> shift)]
                if b >= 0:
                    local = ((((ix & mask) << shift) + (iy & mask)) << shift) + (iz & mask)
                    k = (np.int64(b) << (3 * shift)) + local
                    prefetch(cells, k)
                # The half-cell the point lies in, should its cell be mixed
                # (doubling is exact, so these agree with ix, iy, iz).
                sub[i - j0] = (
                    ((int(gx * 2.0) & 1) << 2) | ((int(gy * 2.0) & 1) << 1) | (int(gz * 2.0) & 1)
                )
            cell[i - j0] = k
        codes = np.empty(QUERY_CHUNK, dtype=np.int32)
        n_mixed = 0
        for j in range(j1 - j0):
            k = cell[j]
            code = cells[k] if k >= 0 else CELL_UNKNOWN
            if code < CELL_UNKNOWN:
                # A mixed cell: its code names eight subcells; the one
                # holding the point has its own code, read in the next pass.
                s = (np.int64(-code - 2) << 3) + sub[j]
                prefetch(subcells, s)
                cell[j] = s
                n_mixed += 1
            codes[j] = code
        # A subcell storing one face takes the path of a one-face cell when
        # marked safe (INTERIOR_FLAG, see mark_safe_subcells); otherwise it
        # also checks the face's sharp neighbours (passes 3 and 5), marked
        # by sub[j] = -1.
        if n_mixed:
            for j in range(j1 - j0):
                if codes[j] < CELL_UNKNOWN:
                    code = subcells[cell[j]]
                    if code < CELL_UNKNOWN:
                        prefetch(mixed_ptr, -code - 2)
                    elif code >= 0:
                        if code & INTERIOR_FLAG:
                            code = code & FACE_MASK
                        else:
                            sub[j] = -1
                    codes[j] = code
        for j in range(j1 - j0):
            code = codes[j]
            if code >= 0:
                prefetch(hot, (code & FACE_MASK, HOT_N))
                prefetch(face_id, code & FACE_MASK)
                if sub[j] < 0:
                    prefetch(hot, (code & FACE_MASK, HOT_A))
            elif code != CELL_UNKNOWN:
                m = -code - 2
                for k in range(mixed_ptr[m], mixed_ptr[m + 1]):
                    # Both lines: candidates often need the exact test.
                    g = mixed_faces[k]
                    prefetch(hot, (g, HOT_N))
                    prefetch(hot, (g, HOT_A))
                    prefetch(face_id, g)
        wait_i = np.empty(QUERY_CHUNK, dtype=np.int64)
        wait_f = np.empty(QUERY_CHUNK, dtype=np.int64)
        wait_g = np.empty(QUERY_CHUNK, dtype=np.int64)
        wait_one = np.empty(QUERY_CHUNK, dtype=np.bool_)
        n_wait = 0
        edge_i = np.empty(QUERY_CHUNK, dtype=np.int64)
        edge_f = np.empty(QUERY_CHUNK, dtype=np.int64)
        edge_d = np.empty(QUERY_CHUNK)
        n_edge = 0
        slow = 0
        for i in range(j0, j1):
            code = codes[i - j0]
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            if code == CELL_UNKNOWN:
                out_face[i] = FACE_SLOW
                slow += 1
            elif code >= 0:
                f = int(code & FACE_MASK)
                if code & INTERIOR_FLAG:
                    # Every point of this cell has its foot inside face f:
                    # the plane gives the answer without any test.
                    d = _hot_distance(px, py, pz, hot, hot_i, f, origin, home_step)
                    _write_foot(
                        i, px, py, pz, d, f, hot, face_id, out_pts, out_nrm, out_dist, out_face
                    )
                    continue
                one = sub[i - j0] < 0
                hit, d, u, v = _hot_foot(px, py, pz, hot, hot_i, f, origin, home_step)
                if hit:
                    if one:
                        # A subcell of a mixed cell storing one face: its
                        # corners all have f closest among the cell's
                        # candidates, but a face across one of f's sharp
                        # edges may still be closer inside it (on the
                        # concave side, or a narrow face along the edge,
                        # closest at no corner). As in a candidate list, a
                        # foot inside f is checked across those edges, in
                        # pass 5, once their records have been fetched.
                        _sharp_prefetch(hot, hot_i, f, d)
                        edge_i[n_edge] = i
                        edge_f[n_edge] = f
                        edge_d[n_edge] = d
                        n_edge += 1
                        continue
                    _write_foot(
                        i, px, py, pz, d, f, hot, face_id, out_pts, out_nrm, out_dist, out_face
                    )
                    continue
                # The foot left the triangle: step across the edge it left
                # by, if that edge is smooth (a patch where plane feet are
                # the exact answer); pass 4 tests the neighbour.
                g = int(hot_i[f, HOT_SMOOTH + _exit_edge(u, v)])
                if g >= 0:
                    prefetch(hot, (g, HOT_N))
                    wait_i[n_wait] = i
                    wait_f[n_wait] = f
                    wait_g[n_wait] = g
                    wait_one[n_wait] = one
                    n_wait += 1
                    continue
                _exact_from(
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
                )
            else:
                f, fd, region = _mixed_best(
                    px, py, pz, code, mixed_ptr, mixed_faces, hot, hot_i, origin, home_step
                )
                if region == REGION_INTERIOR:
                    # A foot inside f: pass 5 looks across f's sharp edges.
                    _sharp_prefetch(hot, hot_i, f, fd)
                    edge_d[n_edge] = fd
                else:
                    # On an edge or corner of f: pass 5 walks from f.
                    edge_d[n_edge] = np.nan
                edge_i[n_edge] = i
                edge_f[n_edge] = f
                n_edge += 1
        for w in range(n_wait):
            i = wait_i[w]
            f = wait_f[w]
            g = wait_g[w]
            prev = f
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            hit, d, u, v = _hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
            for _ in range(_MAX_PLANE_STEPS - 1):
                if hit:
                    break
                nxt = int(hot_i[g, HOT_SMOOTH + _exit_edge(u, v)])
                if nxt < 0 or nxt == prev:
                    break
                prev = g
                g = nxt
                hit, d, u, v = _hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
            if hit and wait_one[w]:
                _sharp_prefetch(hot, hot_i, g, d)
                edge_i[n_edge] = i
                edge_f[n_edge] = g
                edge_d[n_edge] = d
                n_edge += 1
            elif hit:
                _write_foot(i, px, py, pz, d, g, hot, face_id, out_pts, out_nrm, out_dist, out_face)
            else:
                _exact_from(
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
                )
        for w in range(n_edge):
            i = edge_i[w]
            f = edge_f[w]
            d = edge_d[w]
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            if np.isnan(d):
                # A list's best candidate, closest on an edge or corner.
                qx, qy, qz, d2, region = closest_on_hot(
                    px, py, pz, hot, hot_i, f, origin, home_step
                )
            else:
                # A foot inside f (at plane distance d): a closer face can
                # only lie across one of f's edges (see _closer_across).
                g, qx, qy, qz, d2, region = _closer_across(
                    px,
                    py,
                    pz,
                    f,
                    d,
                    px - d * hot[f, 0],
                    py - d * hot[f, 1],
                    pz - d * hot[f, 2],
                    d * d,
                    hot,
                    hot_i,
                    origin,
                    home_step,
                )
                if g < 0:
                    _write_foot(
                        i, px, py, pz, d, f, hot, face_id, out_pts, out_nrm, out_dist, out_face
                    )
                    continue
                f = g
            _walk_and_finish(
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
        n_slow[c] = slow


@njit(cache=True)
def _exact_from(
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
    _walk_and_finish(
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


@njit(cache=True, inline="always")
def _mixed_best(px, py, pz, code, mixed_ptr, mixed_faces, hot, hot_i, origin, home_step):
    """The closest of the candidates of a list cell (code <= -2).

    Returns (f, fd, region): the face, its signed plane distance (when the
    foot lies inside it, region 0), and the region of its closest point (see
    :func:`closest_on_triangle`).
    """
    m = -code - 2
    k0, k1 = mixed_ptr[m], mixed_ptr[m + 1]
    # First the candidates' planes: a foot inside its triangle is that
    # face's distance, and |plane distance| bounds every other face's
    # distance from below, so most candidates never need the full
    # point-to-triangle test.
    f = -1
    d2 = np.inf
    fd = 0.0
    near_g, near2, near_u, near_v = -1, np.inf, 0.0, 0.0
    for k in range(k0, k1):
        g = int(mixed_faces[k])
        hit, d, u, v = _hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
        if hit and d * d < d2:
            f, d2, fd = g, d * d, d
        elif not hit and f < 0 and d * d < near2:
            near_g, near2, near_u, near_v = g, d * d, u, v
    if f < 0:
        # No candidate's plane foot lies inside it: the closest face is
        # often none of them (one closest at no corner of the subcell).
        # Step from the candidate nearest by its plane across the smooth
        # edges its foot leaves by, as a one-face cell does; a plane foot
        # inside a face gives a first answer that bounds the exact tests.
        g, prev, u, v = near_g, -1, near_u, near_v
        for _ in range(_MAX_PLANE_STEPS):
            nxt = int(hot_i[g, HOT_SMOOTH + _exit_edge(u, v)])
            if nxt < 0 or nxt == prev:
                break
            prev, g = g, nxt
            hit, d, u, v = _hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
            if hit:
                f, d2, fd = g, d * d, d
                break
    region = REGION_INTERIOR
    for k in range(k0, k1):
        g = int(mixed_faces[k])
        hit, d, u, v = _hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
        if hit or d * d >= d2:
            continue
        _, _, _, e2, rg = closest_on_hot(px, py, pz, hot, hot_i, g, origin, home_step)
        if e2 < d2:
            f, d2, region = g, e2, rg
            if rg == REGION_INTERIOR:
                # The plane test and the triangle test round differently and
                # can disagree within nanometres of an edge: keep fd this face's.
                fd = d
    return f, fd, region


@njit(cache=True)
def face_block_ranges(lo, hi, origin, block_mm, dims):
    """Per face, the inclusive block index range its expanded box overlaps: (F, 6) int64."""
    nf = lo.shape[0]
    out = np.empty((nf, 6), dtype=np.int64)
    for f in range(nf):
        for a in range(3):
            b0 = int(np.floor((lo[f, a] - origin[a]) / block_mm))
            b1 = int(np.floor((hi[f, a] - origin[a]) / block_mm))
            out[f, a] = min(max(b0, 0), dims[a] - 1)
            out[f, 3 + a] = min(max(b1, 0), dims[a] - 1)
    return out


@njit(cache=True)
def block_face_lists(ranges, dims):
    """Mark active blocks and list, per active block, the faces whose box overlaps it.

    Returns (coarse (nbx*nby*nbz,) int32 block ids or -1, block_coords (B, 3)
    int64, ptr (B+1,) int64, face_idx (P,) int32), blocks in raster order.
    """
    nbx, nby, nbz = dims[0], dims[1], dims[2]
    count = np.zeros(nbx * nby * nbz, dtype=np.int64)
    nf = ranges.shape[0]
    for f in range(nf):
        for bx in range(ranges[f, 0], ranges[f, 3] + 1):
            for by in range(ranges[f, 1], ranges[f, 4] + 1):
                for bz in range(ranges[f, 2], ranges[f, 5] + 1):
                    count[(bx * nby + by) * nbz + bz] += 1
    coarse = np.full(nbx * nby * nbz, -1, dtype=np.int32)
    nb = 0
    for k in range(count.shape[0]):
        if count[k] > 0:
            coarse[k] = nb
            nb += 1
    coords = np.empty((nb, 3), dtype=np.int64)
    ptr = np.zeros(nb + 1, dtype=np.int64)
    for k in range(count.shape[0]):
        b = coarse[k]
        if b >= 0:
            coords[b, 0] = k // (nby * nbz)
            coords[b, 1] = (k // nbz) % nby
            coords[b, 2] = k % nbz
            ptr[b + 1] = count[k]
    for b in range(nb):
        ptr[b + 1] += ptr[b]
    fill = ptr[:-1].copy()
    face_idx = np.empty(ptr[nb], dtype=np.int32)
    for f in range(nf):
        for bx in range(ranges[f, 0], ranges[f, 3] + 1):
            for by in range(ranges[f, 1], ranges[f, 4] + 1):
                for bz in range(ranges[f, 2], ranges[f, 5] + 1):
                    b = coarse[(bx * nby + by) * nbz + bz]
                    face_idx[fill[b]] = f
                    fill[b] += 1
    return coarse, coords, ptr, face_idx


@njit(cache=True, parallel=True)
def block_nodes(
    b0, b1, coords, ptr, face_idx, lo, hi, centre, radius, tri, origin, h, block, reach2
):
    """Closest face of every node of blocks b0..b1-1, or -1 beyond sqrt(reach2).

    Each block owns (block+1)^3 nodes, so the eight corners of each of its
    cells are local. Faces come from the block's list; nodes outside a face's
    expanded box or provably farther than the current best (bounding sphere)
    are skipped before the exact test.
    """
    nn = block + 1
    out = np.empty((b1 - b0, nn * nn * nn), dtype=np.int32)
    for bb in prange(b1 - b0):
        b = b0 + bb
        ox = origin[0] + coords[b, 0] * block * h
        oy = origin[1] + coords[b, 1] * block * h
        oz = origin[2] + coords[b, 2] * block * h
        best = np.full(nn * nn * nn, reach2)
        bf = np.full(nn * nn * nn, -1, dtype=np.int32)
        for k in range(ptr[b], ptr[b + 1]):
            f = int(face_idx[k])
            i0 = max(0, int(np.ceil((lo[f, 0] - ox) / h)))
            i1 = min(block, int(np.floor((hi[f, 0] - ox) / h)))
            j0 = max(0, int(np.ceil((lo[f, 1] - oy) / h)))
            j1 = min(block, int(np.floor((hi[f, 1] - oy) / h)))
            k0 = max(0, int(np.ceil((lo[f, 2] - oz) / h)))
            k1 = min(block, int(np.floor((hi[f, 2] - oz) / h)))
            scx, scy, scz, sr = centre[f, 0], centre[f, 1], centre[f, 2], radius[f]
            for i in range(i0, i1 + 1):
                px = ox + i * h
                for j in range(j0, j1 + 1):
                    py = oy + j * h
                    for l in range(k0, k1 + 1):
                        pz = oz + l * h
                        node = (i * nn + j) * nn + l
                        dx, dy, dz = px - scx, py - scy, pz - scz
                        ds = np.sqrt(dx * dx + dy * dy + dz * dz) - sr
                        if ds > 0.0 and ds * ds >= best[node]:
                            continue
                        e2 = closest_on_triangle(px, py, pz, tri, f)[3]
                        if e2 < best[node]:
                            best[node] = e2
                            bf[node] = f
        out[bb] = bf
    return out


@njit(cache=True)
def _share_vertex(faces, f, g):
    for a in range(3):
        for b in range(3):
            if faces[f, a] == faces[g, b]:
                return True
    return False


@njit(cache=True)
def _single(f, x0, y0, z0, h, plane):
    """Code of a cell stored as face f, with INTERIOR_FLAG when all its corners' feet are inside."""
    margin = 1e-9
    for dx in range(2):
        for dy in range(2):
            for dz in range(2):
                hit, d, u, v = _plane_foot(x0 + dx * h, y0 + dy * h, z0 + dz * h, plane, f)
                if not (u >= margin and v >= margin and u + v <= 1.0 - margin):
                    return f
    return f | INTERIOR_FLAG


@njit(cache=True)
def cells_from_nodes(
    nodes,
    b0,
    coords,
    origin,
    h,
    block,
    tri,
    plane,
    faces,
    face_normals,
    cos_smooth,
    cells_out,
    mixed_base,
):
    """Cell codes of a chunk of blocks from their node faces, plus the mixed lists.

    A cell whose corners all have one closest face stores it. A cell whose
    corner faces all touch the one closest to the cell centre, at a dihedral
    angle below arccos(cos_smooth), also stores that one face: on such a
    smooth patch the walk reaches the foot point's face, and where two faces'
    regions overlap (the concave side) the distances differ by at most about
    distance * angle^2. Any other cell stores its distinct corner faces
    (centre's closest first) as a candidate list.

    Returns (mixed_count (M,) int64, mixed_faces (P,) int32) of the chunk's
    mixed cells in order; their codes are ``-(mixed_base + m) - 2``.
    """
    nn = block + 1
    nb = nodes.shape[0]
    b3 = block * block * block
    counts = np.zeros(nb * b3, dtype=np.int64)
    buf = np.empty(nb * b3 * 8, dtype=np.int32)
    nm = 0
    nbuf = 0
    corner = np.empty(8, dtype=np.int64)
    uniq = np.empty(8, dtype=np.int64)
    for b in range(nb):
        ox = origin[0] + coords[b0 + b, 0] * block * h
        oy = origin[1] + coords[b0 + b, 1] * block * h
        oz = origin[2] + coords[b0 + b, 2] * block * h
        for lx in range(block):
            for ly in range(block):
                for lz in range(block):
                    c = 0
                    unknown = False
                    for dx in range(2):
                        for dy in range(2):
                            for dz in range(2):
                                v = nodes[b, ((lx + dx) * nn + ly + dy) * nn + lz + dz]
                                if v < 0:
                                    unknown = True
                                corner[c] = v
                                c += 1
                    cell = b * b3 + (lx * block + ly) * block + lz
                    if unknown:
                        cells_out[cell] = -1
                        continue
                    nu = 0
                    for c in range(8):
                        seen = False
                        for q in range(nu):
                            if uniq[q] == corner[c]:
                                seen = True
                        if not seen:
                            uniq[nu] = corner[c]
                            nu += 1
                    if nu == 1:
                        cells_out[cell] = _single(
                            uniq[0], ox + lx * h, oy + ly * h, oz + lz * h, h, plane
                        )
                        continue
                    cx = ox + (lx + 0.5) * h
                    cy = oy + (ly + 0.5) * h
                    cz = oz + (lz + 0.5) * h
                    best = np.inf
                    r = 0
                    for q in range(nu):
                        e2 = closest_on_triangle(cx, cy, cz, tri, uniq[q])[3]
                        if e2 < best:
                            best = e2
                            r = q
                    rep = uniq[r]
                    uniq[r] = uniq[0]
                    uniq[0] = rep
                    smooth = True
                    for q in range(1, nu):
                        g = uniq[q]
                        cosang = (
                            face_normals[g, 0] * face_normals[rep, 0]
                            + face_normals[g, 1] * face_normals[rep, 1]
                            + face_normals[g, 2] * face_normals[rep, 2]
                        )
                        if cosang < cos_smooth or not _share_vertex(faces, g, rep):
                            smooth = False
                            break
                    if smooth:
                        cells_out[cell] = _single(
                            rep, ox + lx * h, oy + ly * h, oz + lz * h, h, plane
                        )
                        continue
                    for q in range(nu):
                        buf[nbuf] = uniq[q]
                        nbuf += 1
                    counts[nm] = nu
                    cells_out[cell] = -(mixed_base + nm) - 2
                    nm += 1
    return counts[:nm].copy(), buf[:nbuf].copy()


@njit(cache=True)
def _never_closer(f, g, k, x0, y0, z0, h, plane):
    """Whether face g is nowhere in the cube [x0, x0 + h]^3 closer than face f,
    given that every point of the cube has its foot inside f (so its distance
    to f is its plane distance) and that g meets f along the edge of g
    opposite its corner k.

    Either every corner's foot on g's plane lies beyond that shared edge
    only (barycentric coordinate k negative, the other two not): then g's
    closest point lies on the shared edge, at least as far as f's plane.
    Or every corner's foot lies inside g, on one side of each plane, with
    |d_g| >= |d_f|: the difference is affine on the cube, so it holds
    inside too. Both regions are convex: the corners decide.
    """
    beyond = True
    inside = True
    sf = 0.0
    sg = 0.0
    for dx in range(2):
        for dy in range(2):
            for dz in range(2):
                px, py, pz = x0 + dx * h, y0 + dy * h, z0 + dz * h
                hit_f, df, uf, vf = _plane_foot(px, py, pz, plane, f)
                hit, dg, u, v = _plane_foot(px, py, pz, plane, g)
                lam0 = 1.0 - u - v
                lk = lam0 if k == 0 else (u if k == 1 else v)
                others_ok = (
                    (lam0 >= 0.0 or k == 0) and (u >= 0.0 or k == 1) and (v >= 0.0 or k == 2)
                )
                if not (lk < 0.0 and others_ok):
                    beyond = False
                if not (hit and abs(dg) >= abs(df)):
                    inside = False
                if dx == 0 and dy == 0 and dz == 0:
                    sf, sg = df, dg
                elif df * sf <= 0.0 or dg * sg <= 0.0:
                    inside = False
    return beyond or inside


@njit(cache=True)
def _all_behind(f, across, e, x0, y0, z0, h, plane):
    """Whether every point of the cube [x0, x0 + h]^3 has the face across
    edge e of f behind f's plane (:func:`_behind`; the plane distance is
    affine, so the corners decide)."""
    for dx in range(2):
        for dy in range(2):
            for dz in range(2):
                hit, d, u, v = _plane_foot(x0 + dx * h, y0 + dy * h, z0 + dz * h, plane, f)
                if not _behind(across, e, d):
                    return False
    return True


@njit(cache=True)
def mark_safe_subcells(codes, ijk, origin, h, plane, face_adj, smooth_adj, across):
    """Recode the one-face subcells: INTERIOR_FLAG now marks those where no
    face across a sharp edge of their face f can be closer to a point whose
    foot lies inside f.

    ``codes`` (8 M,) are the subcell codes of the mixed cells with corner
    ``origin + ijk[m] * 2 h`` (h the subcell edge), as cells_from_nodes gave
    them (INTERIOR_FLAG: every foot inside f). A sharp neighbour is harmless
    when it lies behind f's plane for every point of the subcell
    (:func:`_all_behind`, a convex edge), or when every foot lies inside f
    and :func:`_never_closer` holds. Queries in a marked subcell take the
    one-face path of a cell; the others also look across f's sharp edges.
    """
    for m in range(ijk.shape[0]):
        for s in range(8):
            code = codes[8 * m + s]
            if code < 0:
                continue
            interior = (code & INTERIOR_FLAG) != 0
            f = code & FACE_MASK
            x0 = origin[0] + (2 * ijk[m, 0] + (s >> 2)) * h
            y0 = origin[1] + (2 * ijk[m, 1] + ((s >> 1) & 1)) * h
            z0 = origin[2] + (2 * ijk[m, 2] + (s & 1)) * h
            safe = True
            for e in range(3):
                g = face_adj[f, e]
                if g < 0 or smooth_adj[f, e] >= 0:
                    continue
                if _all_behind(f, across[f], e, x0, y0, z0, h, plane):
                    continue
                k = (across[f] >> (2 * e)) & 3
                if not interior or k == 3 or not _never_closer(f, g, k, x0, y0, z0, h, plane):
                    safe = False
                    break
            codes[8 * m + s] = f | INTERIOR_FLAG if safe else f


# ---------------------------------------------------------------------------
# Bounding volume hierarchy over the faces: the exact slow path.
_LEAF = 8


@njit(cache=True)
def bvh_build(tri):
    """A binary AABB tree over the faces, split at the median centroid of the longest axis.

    Returns (order (F,) int32 faces in leaf order, lo (N, 3), hi (N, 3) node
    boxes, child (N, 2) int32 children or -1 for a leaf, span (N, 2) int32
    leaf face range [start, end) into ``order``); node 0 is the root.
    """
    nf = tri.shape[0]
    cen = np.empty((nf, 3))
    for f in range(nf):
        for a in range(3):
            cen[f, a] = (tri[f, 0, a] + tri[f, 1, a] + tri[f, 2, a]) / 3.0
    order = np.arange(nf).astype(np.int32)
    cap = 2 * nf + 1  # a binary tree with at most nf leaves
    lo = np.empty((cap, 3))
    hi = np.empty((cap, 3))
    child = np.full((cap, 2), -1, dtype=np.int32)
    span = np.zeros((cap, 2), dtype=np.int32)
    stack = np.empty(cap, dtype=np.int64)
    n_nodes = 1
    span[0, 0], span[0, 1] = 0, nf
    top = 0
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        s, e = span[node, 0], span[node, 1]
        for a in range(3):
            lo[node, a] = np.inf
            hi[node, a] = -np.inf
        for k in range(s, e):
            f = order[k]
            for c in range(3):
                for a in range(3):
                    x = tri[f, c, a]
                    if x < lo[node, a]:
                        lo[node, a] = x
                    if x > hi[node, a]:
                        hi[node, a] = x
        if e - s <= _LEAF:
            continue
        cmin = np.full(3, np.inf)
        cmax = np.full(3, -np.inf)
        for k in range(s, e):
            for a in range(3):
                x = cen[order[k], a]
                cmin[a] = min(cmin[a], x)
                cmax[a] = max(cmax[a], x)
        axis = int(np.argmax(cmax - cmin))
        keys = np.empty(e - s)
        for k in range(s, e):
            keys[k - s] = cen[order[k], axis]
        perm = np.argsort(keys)
        seg = order[s:e].copy()
        for k in range(e - s):
            order[s + k] = seg[perm[k]]
        mid = (s + e) // 2
        left, right = n_nodes, n_nodes + 1
        n_nodes += 2
        span[left, 0], span[left, 1] = s, mid
        span[right, 0], span[right, 1] = mid, e
        child[node, 0], child[node, 1] = left, right
        stack[top] = left
        stack[top + 1] = right
        top += 2
    return (
        order,
        lo[:n_nodes].copy(),
        hi[:n_nodes].copy(),
        child[:n_nodes].copy(),
        span[:n_nodes].copy(),
    )


@njit(cache=True, inline="always")
def _box_d2(px, py, pz, lo, hi, node):
    dx = max(lo[node, 0] - px, 0.0, px - hi[node, 0])
    dy = max(lo[node, 1] - py, 0.0, py - hi[node, 1])
    dz = max(lo[node, 2] - pz, 0.0, pz - hi[node, 2])
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, parallel=True)
def query_bvh(
    points,
    rows,
    order,
    lo,
    hi,
    child,
    span,
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
    """Exact closest face of points[rows[j]] by depth-first search, nearer child first,
    pruning boxes farther than the best face so far; written to row rows[j]."""
    for j in prange(rows.shape[0]):
        i = rows[j]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        stack = np.empty(128, dtype=np.int32)
        stack[0] = 0
        top = 1
        f = -1
        qx = qy = qz = 0.0
        d2 = np.inf
        region = 0
        while top > 0:
            top -= 1
            node = stack[top]
            if _box_d2(px, py, pz, lo, hi, node) >= d2:
                continue
            c0 = child[node, 0]
            if c0 < 0:
                for k in range(span[node, 0], span[node, 1]):
                    g = int(order[k])
                    # The distance to a face's plane bounds the distance to
                    # the face from below: a few multiply-adds spare most
                    # faces of a leaf the full test.
                    dp = (
                        (px - tri[g, 0, 0]) * fnorm[g, 0]
                        + (py - tri[g, 0, 1]) * fnorm[g, 1]
                        + (pz - tri[g, 0, 2]) * fnorm[g, 2]
                    )
                    if dp * dp >= d2:
                        continue
                    rx, ry, rz, e2, rg = closest_on_triangle(px, py, pz, tri, g)
                    if e2 < d2:
                        f, qx, qy, qz, d2, region = g, rx, ry, rz, e2, rg
                continue
            c1 = child[node, 1]
            a0 = _box_d2(px, py, pz, lo, hi, c0)
            a1 = _box_d2(px, py, pz, lo, hi, c1)
            if a0 <= a1:
                stack[top] = c1
                stack[top + 1] = c0
            else:
                stack[top] = c0
                stack[top + 1] = c1
            top += 2
        _walk_and_finish(
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
            True,
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
