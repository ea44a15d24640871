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
use the exact slow path), ``<= -2`` mixed: ``-code - 2`` indexes a list of
candidate faces (the distinct faces closest to the corners).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

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

# Layout of a face record, one row of the (F, REC_WIDTH) float64 array the
# queries read: everything a query needs of one face in three adjacent cache
# lines (rows are 192 bytes, 64-byte aligned), instead of one line or two in
# each of several arrays.
REC_WIDTH = 24
REC_TRI = 12  # corners a, b, c (9 values); columns 0..11 are the plane row
REC_SMOOTH = 21  # smooth_adj of the three edges, as floats (-1.0: none)


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
def closest_on_record(px, py, pz, rec, f):
    """:func:`closest_on_triangle` with the corners read from face record f (see REC_*)."""
    return _closest(
        px,
        py,
        pz,
        rec[f, REC_TRI],
        rec[f, REC_TRI + 1],
        rec[f, REC_TRI + 2],
        rec[f, REC_TRI + 3],
        rec[f, REC_TRI + 4],
        rec[f, REC_TRI + 5],
        rec[f, REC_TRI + 6],
        rec[f, REC_TRI + 7],
        rec[f, REC_TRI + 8],
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
    rec,
    faces,
    face_adj,
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
    correct side.
    """
    for _ in range(_MAX_WALK):
        moved = False
        if region == 0:
            # A foot inside f is a local minimum of the distance to f alone;
            # on the concave side of a bend a neighbour tilted towards p can
            # still be closer, so look across the three edges too.
            bf, bx, by, bz, b2, br = f, qx, qy, qz, d2, region
            for e in range(3):
                g = int(face_adj[f, e])
                if g < 0:
                    continue
                rx, ry, rz, e2, rg = closest_on_record(px, py, pz, rec, g)
                if e2 < b2 * (1.0 - 1e-12) - 1e-18:
                    bf, bx, by, bz, b2, br = g, rx, ry, rz, e2, rg
            if bf != f:
                f, qx, qy, qz, d2, region = bf, bx, by, bz, b2, br
                moved = True
        elif region >= 4:
            g = int(face_adj[f, region - 4])
            if g >= 0 and g != f:
                rx, ry, rz, e2, rg = closest_on_record(px, py, pz, rec, g)
                if e2 < d2 * (1.0 - 1e-12) - 1e-18:
                    f, qx, qy, qz, d2, region = g, rx, ry, rz, e2, rg
                    moved = True
        else:
            v = faces[f, region - 1]
            bf, bx, by, bz, b2, br = f, qx, qy, qz, d2, region
            for k in range(vf_ptr[v], vf_ptr[v + 1]):
                g = int(vf_idx[k])
                if g == f:
                    continue
                rx, ry, rz, e2, rg = closest_on_record(px, py, pz, rec, g)
                if e2 < b2 * (1.0 - 1e-12) - 1e-18:
                    bf, bx, by, bz, b2, br = g, rx, ry, rz, e2, rg
            if bf != f:
                f, qx, qy, qz, d2, region = bf, bx, by, bz, b2, br
                moved = True
        if not moved:
            break
    if region == 0:
        nx, ny, nz = rec[f, 0], rec[f, 1], rec[f, 2]
    elif region >= 4:
        e = region - 4
        nx, ny, nz = edge_pn[f, e, 0], edge_pn[f, e, 1], edge_pn[f, e, 2]
    else:
        v = faces[f, region - 1]
        nx, ny, nz = vert_pn[v, 0], vert_pn[v, 1], vert_pn[v, 2]
    s = (px - qx) * nx + (py - qy) * ny + (pz - qz) * nz
    d = np.sqrt(d2)
    out_pts[i, 0] = qx
    out_pts[i, 1] = qy
    out_pts[i, 2] = qz
    out_nrm[i, 0] = rec[f, 0]
    out_nrm[i, 1] = rec[f, 1]
    out_nrm[i, 2] = rec[f, 2]
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


@njit(cache=True)
def block_order(points, origin, inv_h, block, dims, coarse, n_blocks):
    """Query rows grouped by fine block (a stable counting sort): (N,) int64.

    Queries arrive in any order; visiting them block by block makes the
    reads of the cell codes and of the faces they name local, where a random
    order would miss the cache on nearly every one. Points outside the fine
    blocks come last.
    """
    n = points.shape[0]
    shift = _shift_of(block)
    nby, nbz = dims[1], dims[2]
    limx = float(dims[0] * block)
    limy = float(dims[1] * block)
    limz = float(dims[2] * block)
    key = np.empty(n, dtype=np.int32)
    start = np.zeros(n_blocks + 2, dtype=np.int64)
    for i in range(n):
        gx = (points[i, 0] - origin[0]) * inv_h
        gy = (points[i, 1] - origin[1]) * inv_h
        gz = (points[i, 2] - origin[2]) * inv_h
        b = n_blocks
        if 0.0 <= gx < limx and 0.0 <= gy < limy and 0.0 <= gz < limz:
            c = coarse[((int(gx) >> shift) * nby + (int(gy) >> shift)) * nbz + (int(gz) >> shift)]
            if c >= 0:
                b = c
        key[i] = b
        start[b + 1] += 1
    for b in range(n_blocks + 1):
        start[b + 1] += start[b]
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        b = key[i]
        order[start[b]] = i
        start[b] += 1
    return order


@njit(cache=True, parallel=True)
def query_grid(
    order,
    points,
    origin,
    inv_h,
    block,
    dims,
    coarse,
    cells,
    mixed_ptr,
    mixed_faces,
    rec,
    faces,
    face_adj,
    vf_ptr,
    vf_idx,
    edge_pn,
    vert_pn,
    face_id,
    out_pts,
    out_nrm,
    out_dist,
    out_face,
    sink,
):
    """Fast path: cell lookup, exact distance to the cell's face(s), local walk.

    A cell with one face first tries the face's plane: when the foot point
    falls inside the triangle (barycentric test with the precomputed dual
    basis in the face record ``rec``) it is the exact closest point on that face and the
    answer costs a dozen multiply-adds. Otherwise, and for cells with a
    candidate list, the exact point-to-triangle test and the walk decide.
    Points whose cell is unknown or outside the grid get
    ``out_face = FACE_SLOW`` and their other outputs untouched.
    """
    n = points.shape[0]
    nby, nbz = dims[1], dims[2]
    # block is a power of two: shifts and masks instead of integer division.
    shift = _shift_of(block)
    mask = block - 1
    limx = float(dims[0] * block)
    limy = float(dims[1] * block)
    limz = float(dims[2] * block)
    for c in prange(sink.shape[0]):
        j0 = c * QUERY_CHUNK
        j1 = min(n, j0 + QUERY_CHUNK)
        # Pass 1 reads the chunk's cell codes, pass 2 touches the face
        # records they name (every candidate's in a mixed cell). The loads of
        # a pass do not depend on one another, so the memory system serves
        # many at once; pass 3 then finds them in cache instead of waiting
        # for each in turn.
        codes = np.empty(QUERY_CHUNK, dtype=np.int32)
        acc = 0.0
        for j in range(j0, j1):
            i = order[j]
            gx = (points[i, 0] - origin[0]) * inv_h
            gy = (points[i, 1] - origin[1]) * inv_h
            gz = (points[i, 2] - origin[2]) * inv_h
            code = CELL_UNKNOWN
            # Also keeps far points from overflowing the integer conversion.
            if 0.0 <= gx < limx and 0.0 <= gy < limy and 0.0 <= gz < limz:
                ix, iy, iz = int(gx), int(gy), int(gz)
                b = coarse[((ix >> shift) * nby + (iy >> shift)) * nbz + (iz >> shift)]
                if b >= 0:
                    local = ((((ix & mask) << shift) + (iy & mask)) << shift) + (iz & mask)
                    code = cells[(np.int64(b) << (3 * shift)) + local]
            codes[j - j0] = code
        for j in range(j1 - j0):
            code = codes[j]
            if code >= 0:
                f = int(code & FACE_MASK)
                acc += rec[f, 3] + rec[f, 11]
            elif code != CELL_UNKNOWN:
                m = -code - 2
                for k in range(mixed_ptr[m], mixed_ptr[m + 1]):
                    g = int(mixed_faces[k])
                    acc += rec[g, 3] + rec[g, 11]
        # Kept so that the compiler cannot drop the touches.
        sink[c] = acc
        for j in range(j0, j1):
            _query_one(
                order[j],
                codes[j - j0],
                points,
                mixed_ptr,
                mixed_faces,
                rec,
                faces,
                face_adj,
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
def _query_one(
    i,
    code,
    points,
    mixed_ptr,
    mixed_faces,
    rec,
    faces,
    face_adj,
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
    """Row i of the fast path, given the code of its cell (see :func:`query_grid`)."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    if code == CELL_UNKNOWN:
        out_face[i] = FACE_SLOW
        return
    if code >= 0:
        f = int(code & FACE_MASK)
        if code & INTERIOR_FLAG:
            # Every point of this cell has its foot inside face f: the
            # plane gives the answer without any test.
            nx, ny, nz = rec[f, 0], rec[f, 1], rec[f, 2]
            d = px * nx + py * ny + pz * nz - rec[f, 3]
            out_pts[i, 0] = px - d * nx
            out_pts[i, 1] = py - d * ny
            out_pts[i, 2] = pz - d * nz
            out_nrm[i, 0] = nx
            out_nrm[i, 1] = ny
            out_nrm[i, 2] = nz
            out_dist[i] = d
            out_face[i] = face_id[f]
            return
        hit, d, u, v = _plane_foot(px, py, pz, rec, f)
        g = f
        prev = -1
        for _ in range(_MAX_PLANE_STEPS):
            if hit:
                break
            # The foot left the triangle: step across the edge opposite
            # the most negative barycentric coordinate, if that edge is
            # smooth (a patch where plane feet are the exact answer).
            la = 1.0 - u - v
            if la <= u and la <= v:
                e = 1
            elif u <= v:
                e = 2
            else:
                e = 0
            nxt = int(rec[g, REC_SMOOTH + e])
            if nxt < 0 or nxt == prev:
                break
            prev = g
            g = nxt
            hit, d, u, v = _plane_foot(px, py, pz, rec, g)
        if hit:
            f = g
        if hit:
            nx, ny, nz = rec[f, 0], rec[f, 1], rec[f, 2]
            out_pts[i, 0] = px - d * nx
            out_pts[i, 1] = py - d * ny
            out_pts[i, 2] = pz - d * nz
            out_nrm[i, 0] = nx
            out_nrm[i, 1] = ny
            out_nrm[i, 2] = nz
            out_dist[i] = d
            out_face[i] = face_id[f]
            return
        qx, qy, qz, d2, region = closest_on_record(px, py, pz, rec, f)
    else:
        m = -code - 2
        k0, k1 = mixed_ptr[m], mixed_ptr[m + 1]
        # First the candidates' planes: a foot inside its triangle is
        # that face's exact distance, and |plane distance| bounds every
        # other face's distance from below, so most candidates never
        # need the full point-to-triangle test.
        f = -1
        d2 = np.inf
        fd = 0.0
        for k in range(k0, k1):
            g = int(mixed_faces[k])
            hit, d, u, v = _plane_foot(px, py, pz, rec, g)
            if hit and d * d < d2:
                f, d2, fd = g, d * d, d
        region = 0
        qx = qy = qz = 0.0
        if f >= 0:
            qx = px - fd * rec[f, 0]
            qy = py - fd * rec[f, 1]
            qz = pz - fd * rec[f, 2]
        for k in range(k0, k1):
            g = int(mixed_faces[k])
            hit, d, u, v = _plane_foot(px, py, pz, rec, g)
            if hit or d * d >= d2:
                continue
            rx, ry, rz, e2, rg = closest_on_record(px, py, pz, rec, g)
            if e2 < d2:
                f, qx, qy, qz, d2, region = g, rx, ry, rz, e2, rg
        if region == 0:
            # A foot inside f: a closer face can only lie across one of
            # f's edges. Across a smooth edge it would be closer by at
            # most distance * angle^2 (the single-face cells' bound), so
            # only sharp edges are looked across, each first bounded by
            # its plane.
            g_best = -1
            for e in range(3):
                g = int(face_adj[f, e])
                if g < 0 or rec[f, REC_SMOOTH + e] >= 0.0:
                    continue
                hit, d, u, v = _plane_foot(px, py, pz, rec, g)
                if d * d >= d2:
                    continue
                rx, ry, rz, e2, rg = closest_on_record(px, py, pz, rec, g)
                if e2 < d2:
                    g_best, qx, qy, qz, d2, region = g, rx, ry, rz, e2, rg
            if g_best < 0:
                nx, ny, nz = rec[f, 0], rec[f, 1], rec[f, 2]
                out_pts[i, 0] = qx
                out_pts[i, 1] = qy
                out_pts[i, 2] = qz
                out_nrm[i, 0] = nx
                out_nrm[i, 1] = ny
                out_nrm[i, 2] = nz
                out_dist[i] = fd
                out_face[i] = face_id[f]
                return
            f = g_best
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
        rec,
        faces,
        face_adj,
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
    rec,
    faces,
    face_adj,
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
                    rx, ry, rz, e2, rg = closest_on_record(px, py, pz, rec, g)
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
            rec,
            faces,
            face_adj,
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
