"""Validators of the rig's inputs: finite matrices of a shape, rotations, point and pixel arrays."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from ..arrays import Points
from ..errors import InvalidInput


def as_matrix(value: Any, shape: tuple[int, ...], what: str) -> npt.NDArray[np.float64]:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{what} must be numeric with shape {shape}") from exc
    if arr.shape != shape:
        raise InvalidInput(f"{what} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInput(f"{what} must be finite")
    arr.setflags(write=False)
    return arr


def check_points(points: Any) -> Points:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInput(f"points must have shape (N, 3), got {arr.shape}")
    return arr


def check_pixels(pixels: Any) -> npt.NDArray[np.float64]:
    arr = np.asarray(pixels, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InvalidInput(f"pixels must have shape (N, 2), got {arr.shape}")
    return arr


def rotation_ok(R: npt.NDArray[np.float64], what: str) -> None:
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0.0:
        raise InvalidInput(f"{what} must be a rotation matrix (orthonormal, det +1)")
