"""The interfaces the computation queries the CAD through: closest points and triangles."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from .arrays import Faces, Points, Scalars, Vectors


class ClosestLike(Protocol):
    """What a closest-point query returns (``inspection.grid.Closest`` and friends).

    Attributes
    ----------
    points : (N, 3) float64, mm, CAD frame
        Closest CAD point of each query point.
    normals : (N, 3) float64
        Unit normal of the closest face (outward).
    distances : (N,) float64, mm
        Signed distance, positive on the outer side.
    face : (N,) int64
        Index of the closest face.
    """

    @property
    def points(self) -> Points: ...

    @property
    def normals(self) -> Vectors: ...

    @property
    def distances(self) -> Scalars: ...

    @property
    def face(self) -> np.ndarray: ...


@runtime_checkable
class ClosestPointQuery(Protocol):
    """Anything that answers closest-point queries on the CAD (a ``GridTree``)."""

    def query(self, points: Points) -> ClosestLike:  # pragma: no cover - protocol
        ...


@runtime_checkable
class ClosestWithinQuery(Protocol):
    """A closest-point query that may leave the points beyond a reach unanswered (a
    ``GridTree``): face -1 and an infinite distance for those, every nearer point
    answered as ``query`` answers it."""

    def query_within(
        self, points: Points, within_mm: float
    ) -> ClosestLike:  # pragma: no cover - protocol
        ...


@runtime_checkable
class Triangles(Protocol):
    """A triangle mesh in the CAD's face numbering (a ``CadModel``, a ``GridTree``).

    Attributes
    ----------
    vertices : (V, 3) float64, mm, CAD frame
    faces : (F, 3) int64
        Vertex indices of each face, in the numbering of a query's ``face``.
    face_normals : (F, 3) float64
        Unit outward normal of each face.
    """

    @property
    def vertices(self) -> Points: ...

    @property
    def faces(self) -> Faces: ...

    @property
    def face_normals(self) -> Vectors: ...
