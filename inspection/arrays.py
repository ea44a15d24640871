"""Array aliases used across :mod:`inspection`, with their shapes.

Units are millimetres, transforms are 4x4 homogeneous float64 matrices named by
their frames (``T_cad_rig`` maps rig-frame points into the CAD frame).
"""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
import numpy.typing as npt

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
