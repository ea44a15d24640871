"""Array aliases used across :mod:`inspection`, with their shapes.

Units are millimetres, transforms are 4x4 homogeneous float64 matrices named by
their frames (``T_cad_rig`` maps rig-frame points into the CAD frame).
"""

from __future__ import annotations

from typing import Any, TypeAlias

import numpy as np
import numpy.typing as npt

from .errors import InvalidInput

Points: TypeAlias = npt.NDArray[np.float64]
"""(N, 3) float64, mm."""

Vectors: TypeAlias = npt.NDArray[np.float64]
"""(N, 3) float64, unit length."""

Scalars: TypeAlias = npt.NDArray[np.float64]
"""(N,) float64."""

Indices: TypeAlias = npt.NDArray[np.int64]
"""(N,) int64."""

Faces: TypeAlias = npt.NDArray[np.int64]
"""(F, 3) int64 vertex indices."""

Transform: TypeAlias = npt.NDArray[np.float64]
"""(4, 4) float64 homogeneous rigid transform."""

Image: TypeAlias = npt.NDArray[np.uint8]
"""(H, W) uint8 grey image."""


def mesh_arrays(mesh: Any) -> tuple[Points, Faces]:
    """The checked vertices (V, 3) and faces (F, 3) of anything that has them (a trimesh
    mesh, a CadModel): finite vertices, faces that index them.

    Raises
    ------
    InvalidInput
        No vertices or faces, wrong shapes, non-finite vertices, faces out of range.
    """
    try:
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
    except AttributeError as exc:
        raise InvalidInput(f"mesh must have vertices and faces, got {type(mesh).__name__}") from exc
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
        raise InvalidInput(f"mesh vertices must have shape (V >= 3, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise InvalidInput(f"mesh faces must have shape (F >= 1, 3), got {faces.shape}")
    if not np.all(np.isfinite(vertices)):
        raise InvalidInput("mesh vertices must be finite")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InvalidInput("mesh faces index vertices that do not exist")
    return vertices, np.ascontiguousarray(faces)
