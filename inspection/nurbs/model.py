"""A NURBS face as a CAD model: its tessellation for the grid tree, and exact closest points.

:func:`tessellate` samples a (trimmed) surface on a regular parameter grid
with the grid evaluation and splits every grid cell inside the trim into two
triangles, keeping each vertex's ``(u, v)``. The grid tree is built on that
mesh as on any CAD (:meth:`inspection.GridTree.build`); :class:`ExactTree`
answers a query with the tree and then refines each closest point on the
exact surface (:func:`.closest.closest_points`), starting from the
parameters of the tessellation's closest point (interpolated in its
triangle). A deviation is then measured to the design, not to the chords of
its tessellation; a mesh-only CAD keeps its plain tree.
"""

from __future__ import annotations

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
class NurbsFace:
    """A trimmed NURBS face and its tessellation.

    Attributes
    ----------
    surface : Surface
    trim : Trim or None
    cad : CadModel, the tessellation (faces oriented along S_u x S_v)
    vertex_params : (V, 2) float64, the (u, v) of each vertex of ``cad``
    """

    surface: Surface
    trim: Trim | None
    cad: CadModel
    vertex_params: FloatArray


def tessellate(
    surface: Surface, m: int, k: int, *, trim: Trim | None = None, name: str = "nurbs"
) -> NurbsFace:
    """The surface sampled on an ``m x k`` regular parameter grid, as triangles.

    Grid cells with a corner outside the trim polygon are left out, so the
    tessellation stays inside the face.

    Parameters
    ----------
    surface : Surface
    m, k : int >= 2, grid lines along u and v
    trim : Trim, optional
    name : str, the CAD model's name
    """
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
    # Counter-clockwise in (u, v), so the faces' normals follow S_u x S_v.
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    cad = CadModel.from_arrays(vertices, faces, name=name, source=f"<nurbs {name}>")
    # The model merges and renumbers vertices: find each one's grid vertex.
    dist, j = cKDTree(vertices).query(cad.vertices)
    if dist.max() > 0 or np.unique(j).size != j.size:
        raise InvalidInput("the surface folds onto itself on this grid: vertices coincide")
    params = np.ascontiguousarray(uv[j])
    params.setflags(write=False)
    return NurbsFace(surface, trim, cad, params)


class ExactTree:
    """Closest points on a NURBS face: the grid tree's, refined on the exact surface.

    Answers :meth:`query` like a :class:`inspection.GridTree` (so that
    :func:`inspection.deviations` takes it), with the tree's ``face`` kept.
    """

    def __init__(self, tree: GridTree, face: NurbsFace) -> None:
        if tree.cad_hash != face.cad.hash:
            raise InvalidInput("the tree was not built on this face's tessellation")
        self.tree = tree
        self.face = face

    def query(self, points: np.ndarray) -> Closest:
        """Closest points on the exact (trimmed) surface.

        Parameters
        ----------
        points : (N, 3) float64, mm, CAD frame

        Returns
        -------
        Closest, with ``points``, ``normals`` and signed ``distances`` of the
        exact surface and the tessellation's closest ``face``.
        """
        coarse = self.tree.query(points)
        tri = self.face.cad.faces[coarse.face]
        corners = self.face.cad.vertices[tri]
        uv = self.face.vertex_params[tri]
        start = np.einsum("ij,ijk->ik", _barycentric(coarse.points, corners), uv)
        exact = closest_points(
            self.face.surface, np.asarray(points, dtype=np.float64), start, trim=self.face.trim
        )
        return Closest(
            points=exact.points,
            normals=exact.normals,
            distances=exact.distances,
            face=coarse.face,
        )


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
