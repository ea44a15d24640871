"""The fast path of a query: cell lookup, plane tests on the cell's faces, and the walk.

Queries are answered in chunks of :data:`QUERY_CHUNK` whose passes each
issue loads that do not depend on one another, so that their cache misses
overlap (see :mod:`inspection.grid`).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..._jit import NO_RUNTIME
from .face import FOOT_STEPS, behind, closest_on_hot, exit_edge, hot_distance, hot_foot
from .layout import (
    CELL_UNKNOWN,
    FACE_MASK,
    FACE_SLOW,
    HOT_A,
    HOT_ACROSS,
    HOT_ADJ,
    HOT_N,
    HOT_SMOOTH,
    INTERIOR_FLAG,
    REGION_INTERIOR,
)
from .prefetch import prefetch
from .walk import closer_across, exact_from, walk_and_finish

_MAX_PLANE_STEPS = 6
# Queries per chunk of the fast path's passes: the chunk's cells and face
# records stay in the first-level caches between the passes.
QUERY_CHUNK = 64


@njit(cache=True, **NO_RUNTIME)
def _shift_of(block):
    shift = 0
    while (1 << shift) < block:
        shift += 1
    return shift


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
def _sharp_prefetch(hot, hot_i, f, d):
    """Start the loads of the planes of the faces across f's sharp edges that
    a point at plane distance d may be closer to."""
    across = hot_i[f, HOT_ACROSS]
    for e in range(3):
        g = int(hot_i[f, HOT_ADJ + e])
        if g >= 0 and hot_i[f, HOT_SMOOTH + e] < 0 and not behind(across, e, d):
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
    test on the record's corners and the walk of :func:`walk_and_finish` do.
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
        # cell codes (and those of the subcells of mixed cells, then the
        # first entries of their lists), pass 2 prefetches the hot records
        # they name, pass 3 answers every query
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
            # The lists' first entries: the next pass reads them to fetch
            # the candidates' records, and would otherwise wait on each.
            for j in range(j1 - j0):
                code = codes[j]
                if code < CELL_UNKNOWN:
                    prefetch(mixed_faces, mixed_ptr[-code - 2])
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
                    d = hot_distance(px, py, pz, hot, hot_i, f, origin, home_step)
                    _write_foot(
                        i, px, py, pz, d, f, hot, face_id, out_pts, out_nrm, out_dist, out_face
                    )
                    continue
                one = sub[i - j0] < 0
                hit, d, u, v = hot_foot(px, py, pz, hot, hot_i, f, origin, home_step)
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
                g = int(hot_i[f, HOT_SMOOTH + exit_edge(u, v)])
                if g >= 0:
                    prefetch(hot, (g, HOT_N))
                    wait_i[n_wait] = i
                    wait_f[n_wait] = f
                    wait_g[n_wait] = g
                    wait_one[n_wait] = one
                    n_wait += 1
                    continue
                exact_from(
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
            hit, d, u, v = hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
            for _ in range(_MAX_PLANE_STEPS - 1):
                if hit:
                    break
                nxt = int(hot_i[g, HOT_SMOOTH + exit_edge(u, v)])
                if nxt < 0 or nxt == prev:
                    break
                prev = g
                g = nxt
                hit, d, u, v = hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
            if hit and wait_one[w]:
                _sharp_prefetch(hot, hot_i, g, d)
                edge_i[n_edge] = i
                edge_f[n_edge] = g
                edge_d[n_edge] = d
                n_edge += 1
            elif hit:
                _write_foot(i, px, py, pz, d, g, hot, face_id, out_pts, out_nrm, out_dist, out_face)
            else:
                exact_from(
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
                # only lie across one of f's edges (see closer_across).
                g, qx, qy, qz, d2, region = closer_across(
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
        n_slow[c] = slow


@njit(cache=True, inline="always")
def _step_to_foot(px, py, pz, g, u, v, hot, hot_i, origin, home_step):
    """From face g, whose plane foot (barycentric u, v) lies outside it, step
    across the smooth edges the foot leaves by, as a one-face cell does.

    Returns (face, hit, d): the face whose triangle holds its plane foot
    (hit) at signed plane distance d, or hit False where the patch ends first.
    """
    prev = -1
    hit, d = False, 0.0
    for _ in range(FOOT_STEPS):
        nxt = int(hot_i[g, HOT_SMOOTH + exit_edge(u, v)])
        if nxt < 0 or nxt == prev:
            break
        prev, g = g, nxt
        hit, d, u, v = hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
        if hit:
            break
    return g, hit, d


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
        hit, d, u, v = hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
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
        g, hit, d = _step_to_foot(px, py, pz, near_g, near_u, near_v, hot, hot_i, origin, home_step)
        if hit:
            f, d2, fd = g, d * d, d
    region = REGION_INTERIOR
    for k in range(k0, k1):
        g = int(mixed_faces[k])
        hit, d, u, v = hot_foot(px, py, pz, hot, hot_i, g, origin, home_step)
        if hit or d * d >= d2:
            continue
        # A plane nearer than the best so far whose foot lies beyond this
        # candidate: its smooth patch goes on to the foot, where a face
        # closest at no corner of the subcell may beat the best (inside a
        # thin plate by an edge, the other side's plane).
        s, hit, e = _step_to_foot(px, py, pz, g, u, v, hot, hot_i, origin, home_step)
        if hit and e * e < d2:
            f, d2, fd, region = s, e * e, e, REGION_INTERIOR
            continue
        _, _, _, e2, rg = closest_on_hot(px, py, pz, hot, hot_i, g, origin, home_step)
        if e2 < d2:
            f, d2, region = g, e2, rg
            if rg == REGION_INTERIOR:
                # The plane test and the triangle test round differently and
                # can disagree within nanometres of an edge: keep fd this face's.
                fd = d
    return f, fd, region
