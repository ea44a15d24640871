"""The exception tree of the inspection computation.

::

    InspectionError
     ├── InvalidInput (also ValueError)      bad arrays, shapes, parameters
     ├── CadLoadError                        a CAD file that cannot be read
     ├── TreeMismatch                        a saved tree for another CAD / build / format
     ├── InsufficientOverlap                 too few points near the CAD to fit
     └── CalibrationError                    board images that cannot give a rig

Non-convergence of an optimisation is data (``converged``, ``stop_reason``),
never an exception.
"""

from __future__ import annotations


class InspectionError(Exception):
    """Base of every error raised by :mod:`inspection`."""


class InvalidInput(InspectionError, ValueError):
    """An argument has the wrong shape, dtype, range or content."""


class CadLoadError(InspectionError):
    """A CAD file could not be turned into a usable triangle mesh."""


class TreeMismatch(InspectionError):
    """A saved closest-point tree does not belong to the given CAD, build or format."""


class InsufficientOverlap(InspectionError):
    """Too few measured points lie near the CAD surface to fit or measure."""


class CalibrationError(InspectionError):
    """The calibration images cannot be turned into a calibrated rig."""
