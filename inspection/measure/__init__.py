"""The measuring sequence from a trigger's frames, or a cloud, to the part's verdict.

``sequence`` reads top to bottom like the algorithm (:func:`measure_frames`,
:func:`measure_cloud`), ``hologram`` is its branch for the holographic head
(:func:`measure_hologram`); ``params`` holds its settings, ``part`` what a part
is measured against, ``result`` what comes back, ``judging`` how a fit and
its points are judged.
"""

from __future__ import annotations

from ..registration import RegisterParams
from .hologram import measure_hologram
from .judging import fit_quality, pose_sigma_mm
from .params import LINE_REGISTER, Frame, MeasureParams, MeasurePath
from .part import PartModel
from .result import FitQuality, Measurement, Pass
from .sequence import (
    MAX_POINTS,
    MIN_POINTS,
    measure_cloud,
    measure_frames,
    subsample,
    validate_cloud,
)

__all__ = [
    "LINE_REGISTER",
    "MAX_POINTS",
    "MIN_POINTS",
    "FitQuality",
    "Frame",
    "MeasurePath",
    "Measurement",
    "MeasureParams",
    "Pass",
    "PartModel",
    "RegisterParams",
    "fit_quality",
    "measure_cloud",
    "measure_frames",
    "measure_hologram",
    "pose_sigma_mm",
    "subsample",
    "validate_cloud",
]
