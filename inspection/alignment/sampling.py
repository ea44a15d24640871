"""Points spread uniformly over the area of a part's faces, or of the faces a sensor sees."""

from __future__ import annotations

import numpy as np

from ..arrays import Faces, Points, Transform, Vectors
from ..errors import InvalidInput
from ..transforms import apply

# Faces whose normal makes less than this cosine with "up" are not seen by
# the sensor above (grazing faces give no usable points).
DEFAULT_MIN_COS = 0.1


def sample_facing(
    vertices: Points,
    faces: Faces,
    face_normals: Vectors,
    T_view_cad: Transform,
    n: int,
    *,
    seed: int = 0,
    min_cos: float = DEFAULT_MIN_COS,
    views: Vectors | None = None,
) -> tuple[Points, np.ndarray]:
    """Sample the side of a part that faces a sensor looking down.

    Points are spread uniformly over the area of the faces whose normal,
    turned into the view frame, points up (or towards one of ``views``) by
    more than ``min_cos`` (occlusion is ignored).

    Parameters
    ----------
    vertices : (V, 3) float64, mm, CAD frame
    faces : (F, 3) int64
    face_normals : (F, 3) float64
    T_view_cad : (4, 4) float64
        Pose of the part in the view frame (z up).
    n : int
        Number of points.
    seed : int
    min_cos : float
    views : (K, 3) float64, optional
        Directions from the part towards each of K sensors (the cameras of a
        rig), view frame; a face is sampled when it faces any of them. Up
        (+z) when omitted.

    Returns
    -------
    points : (n, 3) float64, mm, view frame
    face : (n,) int64
        The face each point was sampled from.

    Raises
    ------
    InvalidInput
        No face faces the sensor, or bad ``views``.
    """
    R = np.asarray(T_view_cad, dtype=np.float64)[:3, :3]
    if views is None:
        towards = np.array([[0.0, 0.0, 1.0]])
    else:
        towards = np.asarray(views, dtype=np.float64).reshape(-1, 3)
        norm = np.linalg.norm(towards, axis=1, keepdims=True)
        if not len(towards) or not np.isfinite(towards).all() or (norm < 1e-12).any():
            raise InvalidInput("views must be finite, non-zero 3-vectors")
        towards = towards / norm
    # Each face's largest cosine to a sensor, its normal turned into the view frame.
    facing = (face_normals @ R.T @ towards.T).max(axis=1)
    sel = np.flatnonzero(facing > min_cos)
    if len(sel) == 0:
        raise InvalidInput("no face of the part faces the sensor in this pose")
    pts, f = sample_faces(vertices, faces, sel, n, np.random.default_rng(seed))
    return apply(np.asarray(T_view_cad, dtype=np.float64), pts), f


def sample_faces(
    vertices: Points, faces: Faces, sel: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[Points, np.ndarray]:
    tri = vertices[faces[sel]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    k = rng.choice(len(sel), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[k]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return pts, sel[k]
