"""In-line shape inspection: the computation.

Reconstruct a point cloud from the rig's frames, align it to the part's CAD
model through a precomputed closest-point grid, and measure deviations.
Pure computation: numpy, scipy, numba, OpenCV, trimesh. Units are millimetres.
"""

from __future__ import annotations

from .cad import CadModel, CadReport, load_cad
from .errors import (
    CadLoadError,
    CalibrationError,
    InspectionError,
    InsufficientOverlap,
    InvalidInput,
    ReconstructionError,
    TreeMismatch,
)

__all__ = [
    "CadLoadError",
    "CadModel",
    "CadReport",
    "CalibrationError",
    "InspectionError",
    "InsufficientOverlap",
    "InvalidInput",
    "ReconstructionError",
    "TreeMismatch",
    "load_cad",
]
