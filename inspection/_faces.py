"""Per-face plane data shared by the CAD tree and the registration."""

from __future__ import annotations

import numpy as np


def face_planes(tri: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(F, 12) float64 rows [n, n.a, U, U.a, V, V.a] of each face.

    Parameters
    ----------
    tri : (F, 3, 3) float64, mm
        Corners a, b, c of each face.
    normals : (F, 3) float64
        Unit normal of each face.

    n is the unit normal, U and V the dual basis of the edges ab and ac (both
    in the plane), so for a point p: d = p.n - n.a is its signed plane
    distance and u = p.U - U.a, v = p.V - V.a the barycentric coordinates of
    its foot point. The normal comes first so a query that needs only the
    plane reads one cache line. A degenerate face gets U = V = 0.
    """
    a = tri[:, 0]
    e1 = tri[:, 1] - a
    e2 = tri[:, 2] - a
    g11 = (e1 * e1).sum(axis=1)
    g12 = (e1 * e2).sum(axis=1)
    g22 = (e2 * e2).sum(axis=1)
    det = g11 * g22 - g12 * g12
    det = np.where(det > 0, det, np.inf)
    U = (g22[:, None] * e1 - g12[:, None] * e2) / det[:, None]
    V = (g11[:, None] * e2 - g12[:, None] * e1) / det[:, None]

    def dot(x: np.ndarray) -> np.ndarray:
        return (x * a).sum(axis=1, keepdims=True)

    rows = [normals, dot(normals), U, dot(U), V, dot(V)]
    return np.ascontiguousarray(np.concatenate(rows, axis=1))
