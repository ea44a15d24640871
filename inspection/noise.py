"""How noisy a cloud is on its own, without any CAD: the spread about local planes.

A fit's residual means little alone: 0.03 mm is a match on a cloud with
0.03 mm of noise, 3 mm is not a match on any cloud the rig makes. Comparing
the residual with the cloud's own noise tells the two apart.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .errors import InvalidInput
from .validate import validate_points

__all__ = ["surface_noise_mm"]


def surface_noise_mm(
    points: np.ndarray, *, neighbours: int = 16, samples: int = 2000, seed: int = 0
) -> float:
    """The cloud's noise along the surface normal, estimated from local plane fits.

    For ``samples`` seeded points, the ``neighbours`` nearest points are
    fitted with a plane (their covariance's smallest eigenvalue is the
    residual variance); the median over the samples of the residual's
    standard deviation, corrected for the plane's three fitted parameters
    (``k / (k - 3)``), is returned. The median keeps edges and corners,
    where a plane does not fit, from inflating it.

    Parameters
    ----------
    points : (N, 3) float64, mm
    neighbours : int
        Points per local plane (>= 5).
    samples : int
        Local planes fitted (all points when fewer).
    seed : int

    Returns
    -------
    float, mm

    Raises
    ------
    InvalidInput
        Fewer points than ``neighbours``, or bad parameters.
    """
    pts = validate_points(points)
    if neighbours < 5:
        raise InvalidInput(f"neighbours must be at least 5, got {neighbours}")
    if samples < 1:
        raise InvalidInput(f"samples must be positive, got {samples}")
    if len(pts) < neighbours:
        raise InvalidInput(f"{len(pts)} points are too few for planes of {neighbours} neighbours")
    rng = np.random.default_rng(seed)
    centre = pts[rng.choice(len(pts), size=min(samples, len(pts)), replace=False)]
    _, idx = cKDTree(pts).query(centre, k=neighbours)
    local = pts[idx]
    local = local - local.mean(axis=1, keepdims=True)
    cov = np.einsum("sni,snj->sij", local, local) / neighbours
    smallest = np.linalg.eigvalsh(cov)[:, 0]
    sigma = np.sqrt(np.maximum(smallest, 0.0) * neighbours / (neighbours - 3))
    return float(np.median(sigma))
