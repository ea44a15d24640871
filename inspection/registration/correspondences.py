"""What each measured point is matched to on the CAD at a pose: closest face, residual, gradient.

A fresh match queries the CAD tree. A small step can instead be evaluated
against each point's last closest face (its plane, while the foot point stays
inside the triangle): only the few points whose foot leaves that face's
interior, or that cross its plane, are queried again. The distance to one
face is at least the distance to the surface, so such a cost bounds the true
one from above, and a step it accepts lowers the true cost too (the classic
ICP argument).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from .._faces import face_planes
from ..arrays import Points, Scalars, Transform, Vectors
from ..errors import InvalidInput
from ..protocols import ClosestPointQuery, ClosestWithinQuery, Triangles
from .kernels import distance_residuals, face_residuals, plane_residuals, transform_points


@dataclass(frozen=True, eq=False)
class CadFaces:
    """The CAD's faces as a fit uses them beside the tree: their planes and bounding box.

    Build it once per CAD (:meth:`of`) and pass it to every fit against that
    CAD's tree.

    Attributes
    ----------
    planes : (F, 12) float64
        Rows ``[n, n.a, U, U.a, V, V.a]`` of each face
        (:func:`inspection._faces.face_planes`), in the numbering of the
        tree's answers' ``face``.
    bounds : (2, 3) float64, mm, CAD frame
        Bounding box of the vertices, min row then max row.
    """

    planes: np.ndarray
    bounds: np.ndarray

    @classmethod
    def of(cls, mesh: Triangles) -> CadFaces:
        """The faces of ``mesh`` (a ``CadModel`` or a ``GridTree``: the same CAD numbering).

        Raises
        ------
        InvalidInput
            Vertices, faces or normals of the wrong shape.
        """
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
        normals = np.asarray(mesh.face_normals, dtype=np.float64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
            raise InvalidInput(f"vertices must have shape (V, 3), got {vertices.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3 or normals.shape != faces.shape:
            raise InvalidInput(
                f"faces and face_normals must have shape (F, 3), got {faces.shape} and "
                f"{normals.shape}"
            )
        planes = face_planes(vertices[faces], normals)
        bounds = np.stack([vertices.min(axis=0), vertices.max(axis=0)])
        planes.setflags(write=False)
        bounds.setflags(write=False)
        return cls(planes, bounds)


class Matches(NamedTuple):
    """A subset's points at one pose and what they are matched to.

    Attributes
    ----------
    points : (m, 3) float64, mm, CAD frame
        The points at the pose.
    gradients : (m, 3) float64
        Gradient of each residual with respect to the point (the face normal
        on a face; towards the edge or corner beyond it otherwise).
    residuals : (m,) float64, mm
    normals : (m, 3) float64
        Normal of each point's closest face (the view rule).
    faces : (m,) int64
        Each point's closest face.
    """

    points: Points
    gradients: Vectors
    residuals: Scalars
    normals: Vectors
    faces: np.ndarray


def closest(
    tree: ClosestPointQuery, X: Points, within_mm: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closest points, face normals, signed distances and faces of ``X`` on ``tree``;
    with ``within_mm``, points farther off may come back beyond reach (face -1,
    distance ``+inf``, NaN point and normal) where the tree can spare their search
    (a :class:`~inspection.protocols.ClosestWithinQuery`)."""
    # One numba thread for the tree's parallel kernels: these queries are
    # small, and on a loaded machine a parallel launch waits for a second core
    # longer than the query takes. The answer does not depend on the thread count.
    if within_mm is not None and isinstance(tree, ClosestWithinQuery):
        run = functools.partial(tree.query_within, X, within_mm)
    else:
        run = functools.partial(tree.query, X)
    threads = numba.get_num_threads()
    if threads == 1:
        cl = run()
    else:
        numba.set_num_threads(1)
        try:
            cl = run()
        finally:
            numba.set_num_threads(threads)
    Q = np.ascontiguousarray(cl.points, dtype=np.float64)
    N = np.ascontiguousarray(cl.normals, dtype=np.float64)
    d = np.asarray(cl.distances, dtype=np.float64)
    f = np.asarray(cl.face, dtype=np.int64)
    return Q, N, d, f


def residuals_at(
    tree: ClosestPointQuery, T: Transform, P: Points, distance: bool
) -> tuple[Scalars, Scalars]:
    """Residuals and signed distances of the points ``P`` (data frame) at the pose ``T``."""
    X = transform_points(T[:3, :3].copy(), T[:3, 3].copy(), P)
    Q, N, d, _ = closest(tree, X)
    if distance:
        # The signed distance is the residual (distance_residuals copies it
        # and adds the gradients, which no caller of this needs).
        return d, d
    return plane_residuals(X, Q, N), d


def match(
    tree: ClosestPointQuery, T: Transform, P: Points, distance: bool
) -> tuple[Matches, Scalars]:
    """Fresh matches of the points ``P`` (data frame) at the pose ``T``, and their
    signed distances."""
    X = transform_points(T[:3, :3].copy(), T[:3, 3].copy(), P)
    Q, N, d, f = closest(tree, X)
    if distance:
        r, U = distance_residuals(X, Q, N, d)
        return Matches(X, U, r, N, f), d
    return Matches(X, N, plane_residuals(X, Q, N), N, f), d


def match_kept_faces(
    tree: ClosestPointQuery,
    T: Transform,
    P: Points,
    last: Matches,
    planes: np.ndarray,
    distance: bool,
) -> Matches:
    """Matches of ``P`` at ``T`` against each point's face in ``last`` (an upper
    bound of the true cost, no query), with a fresh query for the points whose
    foot left that face or that crossed its plane."""
    X = transform_points(T[:3, :3].copy(), T[:3, 3].copy(), P)
    r, U, again = face_residuals(X, last.faces, planes, last.residuals, distance)
    idx = np.flatnonzero(again)
    if len(idx) == 0:
        return Matches(X, U, r, last.normals, last.faces)
    Xi = np.ascontiguousarray(X[idx])
    Q, N, d, f = closest(tree, Xi)
    if distance:
        ri, Ui = distance_residuals(Xi, Q, N, d)
    else:
        ri, Ui = plane_residuals(Xi, Q, N), N
    r[idx] = ri
    U[idx] = Ui
    normals, faces = last.normals.copy(), last.faces.copy()
    normals[idx] = N
    faces[idx] = f
    return Matches(X, U, r, normals, faces)


def concatenated(a: Matches, b: Matches) -> Matches:
    """The matches of ``a``'s points followed by ``b``'s."""
    return Matches(*(np.concatenate([x, y]) for x, y in zip(a, b, strict=True)))
