"""NURBS faces as a CAD model: their tessellation for the grid tree, and exact closest points.

:func:`tessellate` samples a (trimmed) face on a regular parameter grid with
the grid evaluation and splits every grid cell inside the trim into two
triangles, keeping the ``(u, v)`` of every triangle's corners;
:func:`tessellate_faces` does so for all the faces of a part, each on a grid
of about ``cell_mm``. The grid tree is built on that mesh as on any CAD
(:meth:`inspection.GridTree.build`); :class:`ExactTree` answers a query with
the tree and then refines each closest point on the exact surface of the
face its triangle belongs to (:func:`.closest.closest_points`), starting
from the parameters of the tessellation's closest point (interpolated in its
triangle). A deviation is then measured to the design, not to the chords of
its tessellation; a mesh-only CAD keeps its plain tree.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..cad import CadModel
from ..errors import InvalidInput
from ..grid import Closest, GridTree
from .closest import Trim, closest_points
from .knots import FloatArray
from .surface import Surface


@dataclass(frozen=True, eq=False)
class NurbsModel:
    """Trimmed NURBS faces and their tessellation.

    Attributes
    ----------
    surfaces : tuple of Surface, one per face
    trims : tuple of Trim or None, one per face
    cad : CadModel, the tessellation (triangles oriented along S_u x S_v)
    triangle_face : (F,) int64, the face each triangle of ``cad`` samples
    corner_params : (F, 3, 2) float64, the (u, v) of each triangle's corners
    """

    surfaces: tuple[Surface, ...]
    trims: tuple[Trim | None, ...]
    cad: CadModel
    triangle_face: np.ndarray
    corner_params: FloatArray

    def faces_hash(self) -> str:
        """SHA-256 (hex) of the faces: degrees, knots, weighted control points
        and trim polygons, little-endian float64, in face order (the source of
        the tessellation, whatever its sampling)."""
        h = hashlib.sha256()
        for surface, trim in zip(self.surfaces, self.trims, strict=True):
            h.update(np.array([surface.degree_u, surface.degree_v], dtype="<i8").tobytes())
            for a in (surface.knots_u, surface.knots_v, surface.homogeneous):
                h.update(np.array(a.shape, dtype="<i8").tobytes())
                h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
            loops = () if trim is None else (trim.polygon, *trim.holes)
            h.update(np.array([len(loops)], dtype="<i8").tobytes())
            for loop in loops:
                h.update(np.array(loop.shape, dtype="<i8").tobytes())
                h.update(np.ascontiguousarray(loop, dtype="<f8").tobytes())
        return h.hexdigest()


def _grid_triangles(
    surface: Surface, m: int, k: int, trim: Trim | None
) -> tuple[FloatArray, np.ndarray, FloatArray]:
    """Vertices (m k, 3), triangles (t, 3) and the vertices' (u, v) (m k, 2)."""
    if min(m, k) < 2:
        raise InvalidInput(f"a tessellation needs at least 2 x 2 grid lines, got {m} x {k}")
    us = np.linspace(*surface.domain_u, m)
    vs = np.linspace(*surface.domain_v, k)
    vertices = surface.evaluate_grid(us, vs).reshape(-1, 3)
    uv = np.stack(np.meshgrid(us, vs, indexing="ij"), axis=-1).reshape(-1, 2)
    idx = np.arange(m * k).reshape(m, k)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    if trim is not None:
        trim.check_within(surface)
        inside = trim.contains(uv)
        keep = inside[a] & inside[b] & inside[c] & inside[d]
        a, b, c, d = a[keep], b[keep], c[keep], d[keep]
        if a.size == 0:
            raise InvalidInput("no grid cell of the tessellation lies inside the trim")
    # Counter-clockwise in (u, v), so the triangles' normals follow S_u x S_v.
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]), uv


def _model(
    surfaces: Sequence[Surface],
    trims: Sequence[Trim | None],
    grids: Sequence[tuple[int, int]],
    name: str,
) -> NurbsModel:
    vertices, triangles, corner_uv, owner = [], [], [], []
    offset = 0
    for f, (surface, trim, (m, k)) in enumerate(zip(surfaces, trims, grids, strict=True)):
        v, t, uv = _grid_triangles(surface, m, k, trim)
        vertices.append(v)
        triangles.append(t + offset)
        corner_uv.append(uv[t])
        owner.append(np.full(t.shape[0], f, dtype=np.int64))
        offset += v.shape[0]
    all_v = np.concatenate(vertices)
    all_t = np.concatenate(triangles)
    cad = CadModel.from_arrays(all_v, all_t, name=name, source=f"<nurbs {name}>")
    # The model merges vertices (faces share their edges) and may drop
    # degenerate triangles, keeping the others' order and corner order: find
    # each of its triangles among ours by its centroid.
    ours = all_v[all_t].mean(axis=1)
    dist, j = cKDTree(ours).query(cad.vertices[cad.faces].mean(axis=1))
    if dist.max() > 1e-9 * max(1.0, float(np.abs(all_v).max())):
        raise InvalidInput("the tessellation's triangles could not be matched to their faces")
    corner = np.ascontiguousarray(np.concatenate(corner_uv)[j])
    face_of = np.concatenate(owner)[j]
    for arr in (corner, face_of):
        arr.setflags(write=False)
    return NurbsModel(tuple(surfaces), tuple(trims), cad, face_of, corner)


def tessellate(
    surface: Surface, m: int, k: int, *, trim: Trim | None = None, name: str = "nurbs"
) -> NurbsModel:
    """One face sampled on an ``m x k`` regular parameter grid, as triangles.

    Grid cells with a corner outside the trim are left out, so the
    tessellation stays on the face.

    Parameters
    ----------
    surface : Surface
    m, k : int >= 2, grid lines along u and v
    trim : Trim, optional
    name : str, the CAD model's name
    """
    return _model([surface], [trim], [(m, k)], name)


def tessellate_faces(
    faces: Sequence[tuple[Surface, Trim | None]], *, cell_mm: float = 5.0, name: str = "nurbs"
) -> NurbsModel:
    """All the faces of a part (as :func:`.step.read_step_faces` gives them),
    each on a regular parameter grid of cells of about ``cell_mm``.

    A face's grid has as many cells along u as its control net is long along
    u (the longest row of the net, an upper bound of the surface's length),
    divided by ``cell_mm``; likewise along v.
    """
    if not (math.isfinite(cell_mm) and cell_mm > 0):
        raise InvalidInput(f"cell_mm must be a positive number, got {cell_mm!r}")
    if not faces:
        raise InvalidInput("no faces to tessellate")
    grids = []
    for surface, _ in faces:
        cp = surface.control_points
        along_u = np.linalg.norm(np.diff(cp, axis=0), axis=-1).sum(axis=0).max()
        along_v = np.linalg.norm(np.diff(cp, axis=1), axis=-1).sum(axis=1).max()
        grids.append(
            (max(2, math.ceil(along_u / cell_mm) + 1), max(2, math.ceil(along_v / cell_mm) + 1))
        )
    return _model([f[0] for f in faces], [f[1] for f in faces], grids, name)


class ExactTree:
    """Closest points on NURBS faces: the grid tree's, refined on the exact surfaces.

    Answers :meth:`query` like a :class:`inspection.GridTree` (so that
    :func:`inspection.deviations` takes it), with the tree's ``face`` kept.
    """

    def __init__(self, tree: GridTree, model: NurbsModel) -> None:
        if tree.cad_hash != model.cad.hash:
            raise InvalidInput("the tree was not built on this model's tessellation")
        self.tree = tree
        self.model = model

    def query(self, points: np.ndarray) -> Closest:
        """Closest points on the exact (trimmed) faces.

        Parameters
        ----------
        points : (N, 3) float64, mm, CAD frame

        Returns
        -------
        Closest, with ``points``, ``normals`` and signed ``distances`` of the
        exact surfaces and the tessellation's closest ``face`` (triangle).
        """
        x = np.asarray(points, dtype=np.float64)
        coarse = self.tree.query(x)
        cad = self.model.cad
        corners = cad.vertices[cad.faces[coarse.face]]
        start = np.einsum(
            "ij,ijk->ik",
            _barycentric(coarse.points, corners),
            self.model.corner_params[coarse.face],
        )
        out_pts = np.empty_like(x)
        out_nrm = np.empty_like(x)
        out_dist = np.empty(x.shape[0])
        owner = self.model.triangle_face[coarse.face]
        for f in np.unique(owner):
            rows = np.flatnonzero(owner == f)
            exact = closest_points(
                self.model.surfaces[f], x[rows], start[rows], trim=self.model.trims[f]
            )
            out_pts[rows], out_nrm[rows], out_dist[rows] = (
                exact.points, exact.normals, exact.distances,
            )  # fmt: skip
        return Closest(points=out_pts, normals=out_nrm, distances=out_dist, face=coarse.face)


def _barycentric(p: FloatArray, tri: FloatArray) -> FloatArray:
    """(n, 3) barycentric coordinates of points p (n, 3) in triangles (n, 3, 3)."""
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    q = p - tri[:, 0]
    d11 = np.einsum("ij,ij->i", e1, e1)
    d12 = np.einsum("ij,ij->i", e1, e2)
    d22 = np.einsum("ij,ij->i", e2, e2)
    q1 = np.einsum("ij,ij->i", q, e1)
    q2 = np.einsum("ij,ij->i", q, e2)
    det = d11 * d22 - d12 * d12
    b1 = (d22 * q1 - d12 * q2) / det
    b2 = (d11 * q2 - d12 * q1) / det
    return np.stack([1 - b1 - b2, b1, b2], axis=1)
