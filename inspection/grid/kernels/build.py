"""The grid build's kernels: faces near each block, closest face per node, cell codes.

Called by :mod:`inspection.grid.build`, which holds the order of the stages.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..._jit import NO_RUNTIME
from .face import FOOT_STEPS, behind, closest_on_triangle, exit_edge, plane_foot
from .layout import FACE_MASK, INTERIOR_FLAG


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


_SHARP_CROSSINGS = 4


@njit(cache=True, parallel=True)
def subcell_nodes(b0, b1, ijk, origin, h, ptr, faces, tri, plane, face_adj, smooth_adj, reach2):
    """Closest face of the 27 nodes of the subcells of mixed cells b0..b1-1.

    Mixed cell m has its corner at ``origin + ijk[m] * 2 h`` (h the subcell
    edge) and its candidates at ``faces[ptr[m]:ptr[m + 1]]``, the faces closest
    to its corners. A node takes the closest of them, or a face of their smooth
    patches that is closer: where a candidate's plane is nearer than the best
    so far but the node's foot on it lies beyond the triangle, the foot is
    followed across the patch's smooth edges to the face that holds it.
    Inside a thin plate by an edge, a node closest to the face across the
    edge thus gets that side's face rather than a farther one of the near
    side, which would drop the other side from its subcells' lists. Then,
    as a query does, the best face's neighbours across sharp edges are
    tried, while one is closer. Nodes beyond sqrt(reach2) of every
    candidate get -1, as in :func:`block_nodes`.
    """
    out = np.empty((b1 - b0, 27), dtype=np.int32)
    for mm in prange(b1 - b0):
        m = b0 + mm
        ox = origin[0] + ijk[m, 0] * 2 * h
        oy = origin[1] + ijk[m, 1] * 2 * h
        oz = origin[2] + ijk[m, 2] * 2 * h
        for node in range(27):
            px = ox + (node // 9) * h
            py = oy + ((node // 3) % 3) * h
            pz = oz + (node % 3) * h
            best = reach2
            bf = -1
            for k in range(ptr[m], ptr[m + 1]):
                g = int(faces[k])
                e2 = closest_on_triangle(px, py, pz, tri, g)[3]
                if e2 < best:
                    best, bf = e2, g
            for k in range(ptr[m], ptr[m + 1]):
                g = int(faces[k])
                hit, d, u, v = plane_foot(px, py, pz, plane, g)
                if hit or d * d >= best:
                    continue
                prev = -1
                for _ in range(FOOT_STEPS):
                    nxt = int(smooth_adj[g, exit_edge(u, v)])
                    if nxt < 0 or nxt == prev:
                        break
                    prev, g = g, nxt
                    hit, d, u, v = plane_foot(px, py, pz, plane, g)
                    if hit:
                        break
                if hit and d * d < best:
                    e2 = closest_on_triangle(px, py, pz, tri, g)[3]
                    if e2 < best:
                        best, bf = e2, g
            # Across the best face's sharp edges, as a query looks: inside a
            # thin wall the end face is closest in its middle and at none of
            # the cell's corners. Each crossing turns by a sharp angle, so a
            # few suffice.
            for _ in range(_SHARP_CROSSINGS):
                nb = -1
                for e in range(3):
                    g = int(face_adj[bf, e]) if bf >= 0 else -1
                    if g < 0 or smooth_adj[bf, e] >= 0:
                        continue
                    e2 = closest_on_triangle(px, py, pz, tri, g)[3]
                    if e2 < best:
                        best, nb = e2, g
                if nb < 0:
                    break
                bf = nb
            out[mm, node] = bf
    return out


@njit(cache=True, **NO_RUNTIME)
def _share_vertex(faces, f, g):
    for a in range(3):
        for b in range(3):
            if faces[f, a] == faces[g, b]:
                return True
    return False


@njit(cache=True, **NO_RUNTIME)
def _single(f, x0, y0, z0, h, plane):
    """Code of a cell stored as face f, with INTERIOR_FLAG when all its corners' feet are inside."""
    margin = 1e-9
    for dx in range(2):
        for dy in range(2):
            for dz in range(2):
                hit, d, u, v = plane_foot(x0 + dx * h, y0 + dy * h, z0 + dz * h, plane, f)
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


@njit(cache=True, **NO_RUNTIME)
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
                hit_f, df, uf, vf = plane_foot(px, py, pz, plane, f)
                hit, dg, u, v = plane_foot(px, py, pz, plane, g)
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


@njit(cache=True, **NO_RUNTIME)
def _all_behind(f, across, e, x0, y0, z0, h, plane):
    """Whether every point of the cube [x0, x0 + h]^3 has the face across
    edge e of f behind f's plane (:func:`behind`; the plane distance is
    affine, so the corners decide)."""
    for dx in range(2):
        for dy in range(2):
            for dz in range(2):
                hit, d, u, v = plane_foot(x0 + dx * h, y0 + dy * h, z0 + dz * h, plane, f)
                if not behind(across, e, d):
                    return False
    return True


@njit(cache=True, **NO_RUNTIME)
def mark_safe_subcells(codes, ijk, origin, h, plane, face_adj, smooth_adj, across):
    """Recode the one-face subcells: INTERIOR_FLAG now marks those where every
    foot lies inside their face f and no face across a sharp edge of f can be
    closer. A foot that may leave f takes the query to a neighbour of f,
    whose own sharp edges (by a thin plate's edge, the other side's faces)
    this test does not see: such a subcell is never marked.

    ``codes`` (8 M,) are the subcell codes of the mixed cells with corner
    ``origin + ijk[m] * 2 h`` (h the subcell edge), as cells_from_nodes gave
    them (INTERIOR_FLAG: every foot inside f). A sharp neighbour is harmless
    when it lies behind f's plane for every point of the subcell
    (:func:`_all_behind`, a convex edge), or when :func:`_never_closer`
    holds. Queries in a marked subcell take the one-face path of a cell; the
    others also look across the sharp edges of the face they end on.
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
            safe = interior
            for e in range(3):
                if not safe:
                    break
                g = face_adj[f, e]
                if g < 0 or smooth_adj[f, e] >= 0:
                    continue
                if _all_behind(f, across[f], e, x0, y0, z0, h, plane):
                    continue
                k = (across[f] >> (2 * e)) & 3
                if k == 3 or not _never_closer(f, g, k, x0, y0, z0, h, plane):
                    safe = False
            codes[8 * m + s] = f | INTERIOR_FLAG if safe else f
