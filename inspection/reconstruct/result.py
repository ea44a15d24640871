"""What a reconstruction returns: the cloud in the rig frame and the report of its stages.

A :class:`Cloud` is plain data: the points, one weight per point, the pair
that measured it and a :class:`ReconstructionReport` of counts per pair and
flags per frame. What the matching found, which a later pass over the same
frames starts from, is not part of it: :meth:`Reconstructor.match
<inspection.reconstruct.Reconstructor.match>` hands it out separately, as a
:class:`~inspection.reconstruct.Matching`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ..arrays import Points, Scalars

FLAG_TOO_DARK = "too_dark"
FLAG_SATURATED = "saturated"
FLAG_LOW_TEXTURE = "low_texture"
FLAG_EMPTY = "empty"
FLAG_PAIR_SKIPPED = "pair_skipped"


@dataclass(frozen=True)
class PairReport:
    """Counts of one stereo pair through the stages of :func:`reconstruct`.

    Attributes
    ----------
    pair : str
        "left-right" camera indices.
    coarse : int
        Full-resolution pixels with a coarse (SGBM) disparity.
    foreground : int
        Of those, pixels above the belt (the part's region).
    refined : int
        Pixels that passed refinement (score, shift, convergence).
    in_volume : int
        Triangulated points inside the measurement volume, above ``z_min_mm``.
    confirmed, unconfirmed, dropped : int
        Cross-pair check: seen by the other pair consistently, not seen by it,
        dropped as inconsistent.
    disparity_range : (float, float)
        Disparities searched (full-resolution pixels).
    skipped : str
        Why the pair was not used ("" when it was).
    """

    pair: str
    coarse: int = 0
    foreground: int = 0
    refined: int = 0
    in_volume: int = 0
    confirmed: int = 0
    unconfirmed: int = 0
    dropped: int = 0
    disparity_range: tuple[float, float] = (0.0, 0.0)
    skipped: str = ""


@dataclass(frozen=True)
class ReconstructionReport:
    """What happened in :func:`reconstruct`.

    Attributes
    ----------
    flags : tuple of str
        Sorted, e.g. ``"too_dark"``, ``"saturated"``, ``"low_texture"``,
        ``"empty"``, ``"pair_skipped"``.
    frame_flags : tuple of tuple of str
        Per camera, the flags of its frame.
    pairs : tuple of PairReport
    points : int
        Points in the cloud.
    timings_ms : dict of str to float
        Wall time per stage.
    """

    flags: tuple[str, ...]
    frame_flags: tuple[tuple[str, ...], ...]
    pairs: tuple[PairReport, ...]
    points: int
    timings_ms: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready summary."""
        return {
            "flags": list(self.flags),
            "frame_flags": [list(f) for f in self.frame_flags],
            "pairs": [vars(p) | {"disparity_range": list(p.disparity_range)} for p in self.pairs],
            "points": self.points,
            "timings_ms": dict(self.timings_ms),
        }


@dataclass(frozen=True, eq=False)
class Cloud:
    """A reconstructed point cloud in the rig frame.

    Attributes
    ----------
    points : (N, 3) float64, mm, rig frame
    weights : (N,) float64 in [0, 1]
        Per-point quality: match score times cross-pair confirmation.
    pair : (N,) int8
        Index of the pair that measured each point, into
        ``Reconstructor.pairs + Reconstructor.guide_pairs`` (the rig's stereo
        pairs, then its ring pairs when they are used).
    report : ReconstructionReport
    rig_id : str
        Calibration id of the rig used.
    """

    points: Points
    weights: Scalars
    pair: npt.NDArray[np.int8]
    report: ReconstructionReport
    rig_id: str = ""

    def __len__(self) -> int:
        return len(self.points)

    @property
    def empty(self) -> bool:
        return len(self.points) == 0


__all__ = [
    "FLAG_EMPTY",
    "FLAG_LOW_TEXTURE",
    "FLAG_PAIR_SKIPPED",
    "FLAG_SATURATED",
    "FLAG_TOO_DARK",
    "Cloud",
    "PairReport",
    "ReconstructionReport",
]
