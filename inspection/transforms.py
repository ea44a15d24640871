"""Rigid transforms applied to points: the one place ``points @ R.T + t`` is written."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .arrays import Points, Transform


def apply(T: Transform, points: npt.ArrayLike) -> Points:
    """Map points through a rigid transform.

    Parameters
    ----------
    T : (4, 4) float64
        ``T_b_a``: maps frame-a points into frame b.
    points : (N, 3) float64, mm, frame a

    Returns
    -------
    (N, 3) float64, mm, frame b
        ``points @ T[:3, :3].T + T[:3, 3]``: the same floating-point operations
        wherever a transform is applied, so results agree bit for bit.
    """
    T = np.asarray(T)
    return np.asarray(points) @ T[:3, :3].T + T[:3, 3]
