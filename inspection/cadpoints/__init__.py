"""The comparison-point path: the part measured at its comparison points alone.

Instead of a full cloud, each comparison point is measured by local
photogrammetry around it (:mod:`.local`), with the CAD at the part's pose
shaping the matching windows through perspective maps
(:mod:`inspection.perspective`); :mod:`.params` holds the settings.
"""

from __future__ import annotations

from .local import LocalModel, PairLook, PointMeasurement, measure_points
from .params import LocalParams

__all__ = ["LocalModel", "LocalParams", "PairLook", "PointMeasurement", "measure_points"]
