"""The CAD mesh as the grid kernels read it: adjacency, pseudo-normals, planes, BVH, face records.

Faces are in the tree's own spatial order; ``face_id`` maps them back to the
CAD model's numbering.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .._faces import face_planes
from ..arrays import Faces, Points, Vectors
from .kernels.bvh import bvh_build
from .kernels.layout import (
    HOME_BITS,
    HOME_MASK,
    HOT_A,
    HOT_AB,
    HOT_AC,
    HOT_ACROSS,
    HOT_ADJ,
    HOT_HOME,
    HOT_N,
    HOT_SMOOTH,
    HOT_U,
    HOT_V,
    HOT_VERT,
    HOT_WIDTH,
)

# Adjacent faces meeting at less than this dihedral angle count as one smooth
# patch, whose cells store a single face. Where their regions overlap (the
# concave side) picking the wrong one errs by at most distance * angle^2.
COS_SMOOTH = math.cos(0.02)


@dataclass(frozen=True)
class Mesh:
    """Per-face and per-vertex arrays the kernels read (all C-contiguous)."""

    vertices: Points
    faces: Faces
    face_normals: Vectors
    tri: np.ndarray  # (F, 3, 3) float64
    plane: np.ndarray  # (F, 12) float64: corner a, unit normal, dual basis U, V of the edges
    face_adj: np.ndarray  # (F, 3) int32: face across edge e, or -1
    smooth_adj: np.ndarray  # (F, 3) int32: face_adj where the dihedral angle is small, else -1
    vf_ptr: np.ndarray  # (V+1,) int64
    vf_idx: np.ndarray  # (sum,) int32: faces around each vertex
    edge_pn: np.ndarray  # (F, 3, 3) float64: pseudo-normal of edge e of face f
    vert_pn: np.ndarray  # (V, 3) float64: angle-weighted vertex pseudo-normal
    bvh_order: np.ndarray  # (F,) int32: faces in leaf order
    bvh_lo: np.ndarray  # (N, 3) float64: node boxes
    bvh_hi: np.ndarray  # (N, 3) float64
    bvh_child: np.ndarray  # (N, 2) int32: children, -1 for a leaf
    bvh_span: np.ndarray  # (N, 2) int32: a leaf's [start, end) in bvh_order
    face_id: np.ndarray  # (F,) int64: the CAD face index of each (spatially ordered) face


def mesh_arrays(
    vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray, face_id: np.ndarray
) -> Mesh:
    """Adjacency and pseudo-normals of a triangle mesh whose face i is the CAD's face_id[i]."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    fn = np.ascontiguousarray(face_normals, dtype=np.float64)
    nf, nv = len(f), len(v)
    tri = np.ascontiguousarray(v[f])

    # Edge e of face i joins corners e and e+1; faces sharing an undirected
    # edge are neighbours (on a non-manifold edge, the next one in sort order).
    a = f[:, [0, 1, 2]].ravel()
    b = f[:, [1, 2, 0]].ravel()
    key = np.minimum(a, b) * np.int64(nv) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    adj_flat = np.full(3 * nf, -1, dtype=np.int64)
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    group_len = np.diff(np.r_[start, len(ks)])
    group_of = np.repeat(np.arange(len(start)), group_len)
    pos = np.arange(len(ks)) - start[group_of]
    nxt = np.where(pos + 1 < group_len[group_of], np.arange(len(ks)) + 1, start[group_of])
    multi = group_len[group_of] > 1
    adj_flat[order[multi]] = order[nxt[multi]] // 3
    face_adj = adj_flat.reshape(nf, 3).astype(np.int32)

    # Edge pseudo-normal: sum of the two face normals (one on a border edge).
    other = np.where(face_adj >= 0, face_adj, np.arange(nf)[:, None])
    epn = fn[:, None, :] + fn[other]
    epn /= np.maximum(np.linalg.norm(epn, axis=2, keepdims=True), 1e-300)
    # Opposite normals (a folded sheet) sum to zero: fall back to the face's own.
    flat = np.linalg.norm(fn[:, None, :] + fn[other], axis=2) < 1e-9
    epn[flat] = np.broadcast_to(fn[:, None, :], epn.shape)[flat]

    # Vertex pseudo-normal: normals weighted by the corner angles.
    angles = np.empty((nf, 3))
    for c in range(3):
        e1 = tri[:, (c + 1) % 3] - tri[:, c]
        e2 = tri[:, (c + 2) % 3] - tri[:, c]
        cosang = (e1 * e2).sum(axis=1) / np.maximum(
            np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-300
        )
        angles[:, c] = np.arccos(np.clip(cosang, -1.0, 1.0))
    vpn = np.zeros((nv, 3))
    for c in range(3):
        np.add.at(vpn, f[:, c], fn * angles[:, c : c + 1])
    vpn /= np.maximum(np.linalg.norm(vpn, axis=1, keepdims=True), 1e-300)

    # Faces around each vertex (CSR).
    flat_v = f.ravel()
    vorder = np.argsort(flat_v, kind="stable")
    vf_idx = (vorder // 3).astype(np.int32)
    vf_ptr = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat_v, minlength=nv), out=vf_ptr[1:])

    plane = face_planes(tri, fn)
    bvh = bvh_build(tri)
    smooth_adj = _smooth_adjacency(face_adj, fn)
    mesh = Mesh(
        vertices=v,
        faces=f,
        face_normals=fn,
        tri=tri,
        plane=plane,
        face_adj=face_adj,
        smooth_adj=smooth_adj,
        vf_ptr=vf_ptr,
        vf_idx=vf_idx,
        edge_pn=np.ascontiguousarray(epn),
        vert_pn=vpn,
        bvh_order=bvh[0],
        bvh_lo=bvh[1],
        bvh_hi=bvh[2],
        bvh_child=bvh[3],
        bvh_span=bvh[4],
        face_id=np.ascontiguousarray(face_id, dtype=np.int64),
    )
    for arr in (
        mesh.face_id,
        v,
        f,
        fn,
        tri,
        plane,
        face_adj,
        smooth_adj,
        vf_ptr,
        vf_idx,
        mesh.edge_pn,
        vpn,
        *bvh,
    ):
        arr.setflags(write=False)
    return mesh


def mesh_from_saved(a: dict[str, np.ndarray]) -> Mesh:
    """The mesh of a saved tree's (read-only) arrays; the triangles are recomputed."""
    vertices, faces = a["vertices"], a["faces"]
    tri = np.ascontiguousarray(vertices[faces])
    tri.setflags(write=False)
    return Mesh(
        vertices=vertices,
        faces=faces,
        face_normals=a["face_normals"],
        tri=tri,
        plane=a["plane"],
        smooth_adj=a["smooth_adj"],
        face_adj=a["face_adj"],
        vf_ptr=a["vf_ptr"],
        vf_idx=a["vf_idx"],
        edge_pn=a["edge_pn"],
        vert_pn=a["vert_pn"],
        bvh_order=a["bvh_order"],
        bvh_lo=a["bvh_lo"],
        bvh_hi=a["bvh_hi"],
        bvh_child=a["bvh_child"],
        bvh_span=a["bvh_span"],
        face_id=a["face_id"],
    )


def _smooth_adjacency(face_adj: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(F, 3) int32: the face across each edge where the dihedral angle is below the
    smooth-patch limit, else -1. The query walks plane feet only across these."""
    other = np.where(face_adj >= 0, face_adj, 0)
    cos = np.einsum("fk,fek->fe", normals, normals[other])
    return np.ascontiguousarray(
        np.where((face_adj >= 0) & (cos >= COS_SMOOTH), face_adj, -1)
    ).astype(np.int32)


def hot_records(
    mesh: Mesh, origin: np.ndarray, dims: np.ndarray, block_mm: float
) -> tuple[float, np.ndarray, np.ndarray]:
    """The face records every query reads (see :mod:`.kernels.layout`), 128 bytes per face.

    Each face gets a home point on a lattice of step ``home_step`` (a block
    edge, or a few on a model wider than 2^HOME_BITS blocks) at most one
    step per axis below its corner a, and its plane rows, corners and
    neighbours relative to that point in float32. Queries take ``p - home``
    in float64, so the float32 rounding (relative 6e-8) moves planes and
    corners by about 6e-8 times their distance from the home point: a few
    nanometres near the face, 0.02 um 300 mm along a long triangle.

    Returns
    -------
    home_step : float, mm
    hot : (F, HOT_WIDTH) float32, rows 64-byte aligned
    hot_i : (F, HOT_WIDTH) int32, the same memory (the integer columns)
    """
    k = max(1, math.ceil(int(dims.max()) / (1 << HOME_BITS)))
    home_step = float(block_mm * k)
    tri, plane = mesh.tri, mesh.plane
    nf = len(tri)
    home = np.clip(np.floor((tri[:, 0] - origin) / home_step), 0, HOME_MASK).astype(np.int64)
    # The same float64 operations as the kernels' (origin + home * step).
    rel = tri[:, 0] - (origin + home.astype(np.float64) * home_step)
    raw = np.empty(nf * HOT_WIDTH + 16, dtype=np.float32)
    skip = (-raw.ctypes.data % 64) // 4
    hot = raw[skip : skip + nf * HOT_WIDTH].reshape(nf, HOT_WIDTH)
    hot_i = hot.view(np.int32)
    for col in (HOT_N, HOT_U, HOT_V):
        axis = plane[:, col : col + 3].astype(np.float32)
        hot[:, col : col + 3] = axis
        # The offset for the stored (rounded) axis, so that the float32
        # plane still passes through corner a.
        hot[:, col + 3] = (axis.astype(np.float64) * rel).sum(axis=1)
    hot_i[:, HOT_HOME] = (
        home[:, 0] | (home[:, 1] << HOME_BITS) | (home[:, 2] << (2 * HOME_BITS))
    ).astype(np.int32)
    hot_i[:, HOT_SMOOTH : HOT_SMOOTH + 3] = mesh.smooth_adj
    hot[:, HOT_A : HOT_A + 3] = rel
    hot[:, HOT_AB : HOT_AB + 3] = tri[:, 1] - tri[:, 0]
    hot[:, HOT_AC : HOT_AC + 3] = tri[:, 2] - tri[:, 0]
    hot_i[:, HOT_ADJ : HOT_ADJ + 3] = mesh.face_adj
    hot_i[:, HOT_VERT : HOT_VERT + 3] = mesh.faces
    hot_i[:, HOT_ACROSS] = across_codes(mesh)
    hot.setflags(write=False)
    hot_i.setflags(write=False)
    return home_step, hot, hot_i


def across_codes(mesh: Mesh) -> np.ndarray:
    """Per face f and edge e, what a query needs to know of the face g across
    it (see ``HOT_ACROSS``): bits 2e..2e+1 the corner of g opposite their
    shared edge (3: g's adjacency does not name f back, or no g), bits
    6+2e..7+2e the side of f's plane g lies on (1 above, 2 below, 0 on
    it or unknown). (F,) int32."""
    face_adj, faces = mesh.face_adj, mesh.faces
    nf = len(face_adj)
    out = np.zeros(nf, dtype=np.int32)
    rows = np.arange(nf)
    for e in range(3):
        g = face_adj[:, e]
        has = g >= 0
        gg = np.where(has, g, 0)
        back = face_adj[gg] == rows[:, None]
        k = np.full(nf, 3, dtype=np.int32)
        for e2 in range(3):
            k = np.where(has & back[:, e2] & (k == 3), (e2 + 2) % 3, k)
        # g's corner off the shared edge against f's plane: the whole of g
        # lies on that side.
        far = mesh.vertices[faces[gg, np.minimum(k, 2)]]
        h = np.einsum("ij,ij->i", far - mesh.tri[:, 0], mesh.face_normals)
        side = np.where(h > 1e-9, 1, np.where(h < -1e-9, 2, 0)).astype(np.int32)
        side[~has | (k == 3)] = 0
        out |= (k << (2 * e)) | (side << (6 + 2 * e))
    return out
