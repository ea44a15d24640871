"""Rotations and rigid transforms of the rig frame: look-at, belt poses, Rodrigues, Kabsch."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from ..arrays import Transform
from ..errors import InvalidInput
from .checks import check_points


def look_at(
    centre: npt.ArrayLike, target: npt.ArrayLike, right: npt.ArrayLike = (1.0, 0.0, 0.0)
) -> npt.NDArray[np.float64]:
    """Rotation rig -> camera for a camera at ``centre`` looking at ``target``.

    Parameters
    ----------
    centre, target : (3,) float64, mm, rig frame
    right : (3,) float64
        Direction in the rig frame that the image x axis should follow as
        closely as possible.

    Returns
    -------
    R : (3, 3) float64
        Rows are the camera axes (x right, y down, z forward) in the rig frame.
    """
    c = np.asarray(centre, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - c
    z /= np.linalg.norm(z)
    x = np.asarray(right, dtype=np.float64)
    x = x - z * (x @ z)
    norm = np.linalg.norm(x)
    if norm < 1e-9:
        raise InvalidInput("look_at: 'right' is parallel to the viewing direction")
    x /= norm
    y = np.cross(z, x)
    return np.stack([x, y, z])


def belt_pose(x_mm: float, y_mm: float, yaw_deg: float, z_mm: float = 0.0) -> Transform:
    """Pose of a part on the belt: turned by ``yaw_deg`` about the rig's vertical
    (z), then moved to (``x_mm``, ``y_mm``, ``z_mm``).

    Returns
    -------
    T_rig_part : (4, 4) float64
        Maps part-frame points into the rig frame; a part resting on its own
        z = 0 plane lies on the belt for ``z_mm`` = 0.
    """
    if not np.isfinite([x_mm, y_mm, yaw_deg, z_mm]).all():
        raise InvalidInput("belt_pose needs finite x_mm, y_mm, yaw_deg and z_mm")
    a = np.deg2rad(yaw_deg)
    c, s = np.cos(a), np.sin(a)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x_mm, y_mm, z_mm)
    return T


def rotvec_matrix(rotvec: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Rodrigues: rotation vector (3,) rad -> (3, 3) rotation."""
    theta = float(np.linalg.norm(rotvec))
    if theta < 1e-15:
        return np.eye(3)
    k = rotvec / theta
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * Kx + (1.0 - math.cos(theta)) * (Kx @ Kx)


def rigid_align(src: npt.ArrayLike, dst: npt.ArrayLike) -> Transform:
    """Least-squares rigid transform (Kabsch) mapping ``src`` points onto ``dst``.

    Parameters
    ----------
    src, dst : (N, 3) float64, mm, N >= 3, not collinear

    Returns
    -------
    (4, 4) float64
        ``T`` with ``dst ≈ T[:3, :3] @ src + T[:3, 3]``.
    """
    a = check_points(src)
    b = check_points(dst)
    if a.shape != b.shape or len(a) < 3:
        raise InvalidInput("rigid_align needs two (N, 3) arrays of equal N >= 3")
    ca = a.mean(axis=0)
    cb = b.mean(axis=0)
    H = (a - ca).T @ (b - cb)
    U, S, Vt = np.linalg.svd(H)
    if S[1] < 1e-9 * max(S[0], 1e-300):
        raise InvalidInput("rigid_align: points are collinear")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cb - R @ ca
    return T
