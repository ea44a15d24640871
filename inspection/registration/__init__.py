"""Robust fine registration of a measured cloud to the CAD: IRLS point-to-surface ICP.

One module per stage of the algorithm: ``params`` (how to fit,
:class:`RegisterParams`), ``correspondences`` (what each point is matched to
at a pose), ``kernels`` (the compiled robust cost, normal equations and damped
step), ``solver`` (:func:`register`, stage by stage), ``escape`` (the scan along
a rotation the fit leaves free) and ``result`` (:class:`Registration`).
"""

from __future__ import annotations

from ..protocols import ClosestLike, ClosestPointQuery, ClosestWithinQuery
from ..validate import validate_points, validate_transform, validate_view
from .correspondences import CadFaces
from .kernels import LOSSES
from .params import RegisterParams
from .result import Registration, StopReason
from .solver import register

__all__ = [
    "LOSSES",
    "CadFaces",
    "ClosestLike",
    "ClosestPointQuery",
    "ClosestWithinQuery",
    "RegisterParams",
    "Registration",
    "StopReason",
    "register",
    "validate_points",
    "validate_transform",
    "validate_view",
]
