"""In-line shape inspection: the computation.

Reconstruct a point cloud from the rig's frames, align it to the part's CAD
model through a precomputed closest-point grid, and measure deviations: the
whole sequence is :func:`measure_frames` (or :func:`measure_cloud`) against a
:class:`PartModel`.
Pure computation: numpy, scipy, numba, OpenCV, trimesh. Units are millimetres;
transforms are 4x4 float64 arrays named by their frames (``T_cad_rig`` maps
rig-frame points into the CAD frame).
"""

from __future__ import annotations

# First: it points numba's cache before any module below defines a cached kernel.
from . import _kernel_cache  # noqa: F401
from .alignment import Alignment, align
from .cad import CadModel, CadReport, load_cad
from .calibration import Calibration, calibrate
from .deviations import ComparisonPoint, Deviations, deviations
from .errors import (
    CadLoadError,
    CalibrationError,
    InspectionError,
    InsufficientOverlap,
    InvalidInput,
    TreeMismatch,
)
from .grid import Closest, GridTree, warmup
from .measure import (
    FitQuality,
    Measurement,
    MeasureParams,
    PartModel,
    Pass,
    measure_cloud,
    measure_frames,
)
from .panel import PanelSpec, sheet_metal_panel
from .reconstruct import Cloud, Guide, Prior, Reconstructor, ReconstructParams, reconstruct
from .registration import CadFaces, RegisterParams, Registration, StopReason, register
from .rig import Camera, Conveyor, Projector, Rig, belt_pose
from .simulate import RenderOptions, Simulator, simulate, simulate_board
from .surface import SurfaceDefect, SurfaceModel, SurfaceParams

__all__ = [
    "Alignment",
    "CadLoadError",
    "CadFaces",
    "CadModel",
    "CadReport",
    "CalibrationError",
    "Calibration",
    "Camera",
    "Closest",
    "Cloud",
    "ComparisonPoint",
    "Conveyor",
    "Deviations",
    "FitQuality",
    "GridTree",
    "Guide",
    "InspectionError",
    "InsufficientOverlap",
    "InvalidInput",
    "MeasureParams",
    "Measurement",
    "PanelSpec",
    "PartModel",
    "Pass",
    "Prior",
    "Projector",
    "ReconstructParams",
    "RegisterParams",
    "Reconstructor",
    "Registration",
    "RenderOptions",
    "Rig",
    "Simulator",
    "StopReason",
    "SurfaceDefect",
    "SurfaceModel",
    "SurfaceParams",
    "TreeMismatch",
    "align",
    "belt_pose",
    "calibrate",
    "deviations",
    "load_cad",
    "measure_cloud",
    "measure_frames",
    "reconstruct",
    "register",
    "sheet_metal_panel",
    "simulate",
    "simulate_board",
    "warmup",
]
