"""What one measured part comes back as: its verdict, fit, deviations and passes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..alignment.rps import RpsAlignment
from ..cadpoints import PointMeasurement
from ..deviations import Deviations, Verdict
from ..registration import Registration
from ..transforms import apply
from .params import Frame


@dataclass(frozen=True, eq=False)
class Pass:
    """One matching pass: its cloud and the fit made to it.

    Attributes
    ----------
    name : str
        ``first``, ``guided`` or ``bends``.
    points : (N, 3) float64, mm, rig frame
    weights : (N,) float64
        Per-point quality of the reconstruction.
    fit : Registration or None
        The fit to this pass's cloud (None: not fitted, or the fit failed).
    """

    name: str
    points: np.ndarray = field(repr=False)
    weights: np.ndarray = field(repr=False)
    fit: Registration | None = field(default=None, repr=False)


@dataclass(frozen=True)
class FitQuality:
    """What the final fit says of itself.

    Attributes
    ----------
    converged : bool
    stop_reason : str
    iterations : int
    observability : float
        Smallest over largest eigenvalue of the fit's normal matrix (1: as
        well constrained in every direction; 0: a free direction).
    weak_directions : tuple of str
        The directions the data leave free, named in the CAD frame
        ("translation along x", "rotation about z", or a sum of them).
    ambiguous : bool or None
        The global search found another pose fitting almost as well (None:
        no global search ran).
    runner_up_score : float or None
        The best other pose's score over the chosen one's (1: fits as well).
    """

    converged: bool
    stop_reason: str
    iterations: int
    observability: float
    weak_directions: tuple[str, ...]
    ambiguous: bool | None = None
    runner_up_score: float | None = None


@dataclass(frozen=True, eq=False)
class Measurement:
    """One measured part.

    Attributes
    ----------
    verdict : Verdict or None
        ``pass``, ``fail`` or ``not_measurable``; None when the part could
        not be measured at all (see ``reason``).
    reason : str or None
        Why the verdict is not ``pass`` (the points that failed or could not
        be judged), why there is none, and any note of the fit.
    frame : {"rig", "cad", "data"}
        The frame the measured points were given in.
    transform : (4, 4) float64 or None
        ``T_cad_<frame>``: maps the measured points into the CAD frame.
    registration : Registration or None
        The final fit.
    quality : FitQuality or None
    deviations : Deviations or None
        Per point and at the comparison points (each comparison entry as
        judged against the pose's uncertainty); its ``verdict`` is the
        part's. On the comparison-point path, its ``distances`` are the
        windows' deviations and its ``defects`` None: the surface between
        the points was not checked.
    points : (N, 3) float64, mm
        The cloud that was measured, in ``frame`` (the last pass's).
    passes : tuple of Pass
        Each matching pass's cloud and fit, in order (frames only).
    timings_ms : dict of str to float
        Per stage: ``reconstruct``, ``guide``, ``align``, ``deviations``, ``total``.
    rps : RpsAlignment or None
        The datum alignment, where the part has one: ``transform`` is then its
        pose, ``registration`` the best fit it started from, and each datum's
        residual is in it.
    cpu_ms : dict of str to float
        The same stages' CPU time, ms: the whole process's, every thread (the
        reconstruction's pool included), so the sequence's own in a process
        that does nothing else.
    path : {"cloud", "comparison_points"}
        Which path measured the part.
    local : tuple of PointMeasurement
        The comparison-point path's measurement of each point (its
        uncertainty, the pairs that saw it); empty on the cloud path.
    maps : dict of str to (H, W) float64
        What a sensor measures on its own pixel grid, NaN where not measured:
        the holographic head's ``phase`` (the wrapped phase difference, rad)
        and ``deviation`` (of each measured pixel from the CAD, mm). Empty for
        the flash rig, whose cloud has no pixel grid.
    """

    verdict: Verdict | None
    reason: str | None
    frame: Frame
    transform: np.ndarray | None = field(default=None, repr=False)
    registration: Registration | None = field(default=None, repr=False)
    quality: FitQuality | None = None
    deviations: Deviations | None = field(default=None, repr=False)
    points: np.ndarray = field(default_factory=lambda: np.empty((0, 3)), repr=False)
    passes: tuple[Pass, ...] = field(default=(), repr=False)
    timings_ms: dict[str, float] = field(default_factory=dict)
    cpu_ms: dict[str, float] = field(default_factory=dict)
    path: str = "cloud"
    local: tuple[PointMeasurement, ...] = field(default=(), repr=False)
    maps: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    rps: RpsAlignment | None = field(default=None, repr=False)

    def points_cad(self) -> np.ndarray | None:
        """``points`` mapped into the CAD frame (None without a transform)."""
        if self.transform is None:
            return None
        return apply(self.transform, self.points)
