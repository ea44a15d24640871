"""The exact slow path: a bounding volume hierarchy over the faces, searched depth first.

Answers the points the fast path leaves (outside the band, the grid, or a
cell whose corners are not all known), exactly in float64.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .face import closest_on_triangle
from .walk import walk_and_finish

# Faces per leaf at most.
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
    reach2,
):
    """Exact closest face of points[rows[j]] by depth-first search, nearer child first,
    pruning boxes farther than the best face so far; written to row rows[j].

    Only faces nearer than ``sqrt(reach2)`` are searched (``inf``: all): a
    point with none gets ``out_face = -1``, an infinite distance and NaN for
    its point and normal, at the cost of the few boxes within reach.
    """
    for j in prange(rows.shape[0]):
        i = rows[j]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        stack = np.empty(128, dtype=np.int32)
        stack[0] = 0
        top = 1
        f = -1
        qx = qy = qz = 0.0
        d2 = reach2
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
        if f < 0:
            for a in range(3):
                out_pts[i, a] = np.nan
                out_nrm[i, a] = np.nan
            out_dist[i] = np.inf
            out_face[i] = -1
            continue
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
