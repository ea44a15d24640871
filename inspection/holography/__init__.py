"""The second sensor: single-shot dual-wavelength digital holography against the CAD.

One image of a small-field head holds two off-axis holograms (two lasers,
each with its own reference wave). Their phase difference measures height in
intervals of half the synthetic wavelength; the CAD at the part's pose
predicts that phase, so the measurement needs no spatial unwrapping across
the CAD's steps, and regions deviating by more than a quarter of the
synthetic wavelength are found and flagged rather than unwrapped wrongly.

- :mod:`.head`: the head's optics, reference waves and noise model;
- :mod:`.parts`, :mod:`.depth`, :mod:`.simulate`: test parts, the CAD under
  the head, the hologram simulator;
- :mod:`.spectrum`, :mod:`.propagate`, :mod:`.correlation`: lobes, angular
  spectrum refocusing, speckle displacements with a peak quality;
- :mod:`.lobecut`: each lobe's cut centred by the speckle displacements it leaves;
- :mod:`.calibration`: both lobes and the phase difference from a plate;
- :mod:`.gradient`: the unwrapped gradient field from speckle displacements,
  and the coarse pose against the CAD (tilts from it, the shift from the steps);
- :mod:`.unwrap`, :mod:`.shape`: the CAD-based unwrapping and the shape.
"""

from __future__ import annotations

from .calibration import CalibrateParams, HoloCalibration, LobeCalibration, calibrate_head
from .correlation import Displacement, correlate
from .depth import DepthMap, depth_map
from .gradient import (
    CoarsePose,
    GradientField,
    align_to_cad,
    coarse_pose,
    gradient_field,
    step_shift,
)
from .head import HoloHead, HoloNoise, ReferenceWave, describe
from .lobecut import LobeCut, minimise_cut
from .parts import Dent, dent_map, stepped_plate
from .propagate import propagate
from .shape import FlaggedRegion, HoloShape, ShapeParams, measure_shape
from .simulate import HoloTruth, simulate_hologram
from .spectrum import Lobe, find_lobes, lobe_field, spectrum
from .unwrap import Orders, orders, wrap

__all__ = [
    "CalibrateParams",
    "CoarsePose",
    "DepthMap",
    "Dent",
    "Displacement",
    "FlaggedRegion",
    "GradientField",
    "HoloCalibration",
    "HoloHead",
    "HoloNoise",
    "HoloShape",
    "HoloTruth",
    "Lobe",
    "LobeCalibration",
    "LobeCut",
    "Orders",
    "ReferenceWave",
    "ShapeParams",
    "align_to_cad",
    "calibrate_head",
    "coarse_pose",
    "correlate",
    "dent_map",
    "depth_map",
    "describe",
    "find_lobes",
    "gradient_field",
    "lobe_field",
    "measure_shape",
    "minimise_cut",
    "orders",
    "propagate",
    "simulate_hologram",
    "spectrum",
    "step_shift",
    "stepped_plate",
    "wrap",
]
