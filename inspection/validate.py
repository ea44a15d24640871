"""Checks of the arrays and transforms given to the public entry points."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .arrays import Points, Transform
from .errors import InvalidInput


def validate_points(points: object, *, name: str = "points", min_points: int = 1) -> Points:
    """(N, 3) finite float64 array, a C-contiguous copy-free view where possible."""
    try:
        p = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{name} must be an (N, 3) array of numbers: {exc}") from exc
    if p.ndim != 2 or p.shape[1] != 3:
        raise InvalidInput(f"{name} must have shape (N, 3), got {p.shape}")
    if len(p) < min_points:
        raise InvalidInput(f"{name} needs at least {min_points} points, got {len(p)}")
    if not np.isfinite(p).all():
        bad = int((~np.isfinite(p)).any(axis=1).sum())
        raise InvalidInput(f"{name}: {bad} points have non-finite coordinates (NaN or inf)")
    return np.ascontiguousarray(p)


def validate_view(view_direction: npt.ArrayLike | None, loss: str) -> np.ndarray | None:
    """``view_direction`` as a unit 3-vector (None stays None), checked
    against the loss it is used with (see :func:`inspection.register`): a
    point the sensor cannot see counts as an outlier, which needs a loss
    with a plateau.

    Raises
    ------
    InvalidInput
        Not a finite non-zero 3-vector, or a loss without a plateau.
    """
    if view_direction is None:
        return None
    view = np.asarray(view_direction, dtype=np.float64)
    if view.shape != (3,) or not np.isfinite(view).all() or not np.linalg.norm(view) > 0:
        raise InvalidInput(f"view_direction must be a finite non-zero 3-vector, got {view!r}")
    if loss not in ("tukey", "welsch"):
        raise InvalidInput(
            "view_direction needs a loss with a plateau (tukey or welsch), got " + repr(loss)
        )
    return view / np.linalg.norm(view)


def validate_transform(T: object, *, name: str = "init") -> Transform:
    """A finite rigid (4, 4) transform: orthonormal rotation, det +1, last row 0 0 0 1."""
    try:
        M = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{name} must be a (4, 4) array: {exc}") from exc
    if M.shape != (4, 4):
        raise InvalidInput(f"{name} must have shape (4, 4), got {M.shape}")
    if not np.isfinite(M).all():
        raise InvalidInput(f"{name} has non-finite entries")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InvalidInput(
            f"{name} is not a rigid transform (rotation not orthonormal with det +1)"
        )
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-12):
        raise InvalidInput(f"{name}: last row must be 0 0 0 1, got {M[3]}")
    return M.copy()
