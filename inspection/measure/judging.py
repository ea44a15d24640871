"""How a fit is judged: its quality, the pose's uncertainty at a point, and the verdict's reason."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ..alignment import Alignment
from ..cadpoints import PointMeasurement
from ..deviations import (
    MEASURED_KINDS,
    ComparisonPoint,
    ComparisonResult,
    Deviations,
    FieldSummary,
    Verdict,
    part_verdict,
)
from ..registration import Registration, StopReason
from ..registration.solver import UNRESOLVED_REL_EIG
from .params import MeasureParams
from .result import FitQuality

# The names of the twist's components (omega L, t), in the CAD frame.
_DIRECTION_NAMES = (
    "rotation about x",
    "rotation about y",
    "rotation about z",
    "translation along x",
    "translation along y",
    "translation along z",
)
# A free direction that moves a point along its normal by more than this
# fraction of its own (unit) size leaves the point's deviation undetermined.
_FREE_MOVES = 1e-3
# A reason names this many surface defects (the largest), then counts the rest.
_LISTED_DEFECTS = 3
TWO_SIDED_FRACTION = 0.05
"""A fit with more of its weight than this on faces turned against the rest
(``Registration.opposed_fraction``) has laid the cloud through a thin wall."""


def _fit_problem(fit: Registration, quality: FitQuality, p: MeasureParams) -> str | None:
    """Why the fit cannot be measured from, or None."""
    if not fit.converged:
        return (
            f"the fit did not converge ({fit.stop_reason.value} after {fit.iterations} iterations)"
        )
    if quality.ambiguous and p.ambiguous_is_error:
        return (
            "pose ambiguous: another pose fits almost as well "
            f"(score {quality.runner_up_score:.2f} of the chosen one's)"
        )
    if not fit.inlier_fraction >= p.min_inlier_fraction:
        return (
            f"fit kept {fit.inlier_fraction:.0%} of the points, "
            f"below the {p.min_inlier_fraction:.0%} required"
        )
    # After the points it keeps (a cloud that is not the part at all is told by
    # those) and before its residual, which a fit through a wall also spoils.
    if fit.opposed_fraction > TWO_SIDED_FRACTION:
        return (
            f"the fit lays the cloud through a thin wall: {fit.opposed_fraction:.0%} of it rests "
            "on faces turned against the rest, the far side of the wall; measure it with the "
            "sensor's side known (frame 'rig', or a view direction)"
        )
    if not fit.rms_mm <= p.max_rms_mm:
        return f"fit residual {fit.rms_mm:.3f} mm above the {p.max_rms_mm} mm allowed"
    return None


def fit_quality(fit: Registration, search: Registration | None = None) -> FitQuality:
    """The diagnostics of ``fit``: convergence, observability, free directions, and
    the ambiguity of the global search (``fit`` itself, or ``search`` it started from)."""
    eig = np.asarray(fit.observability, dtype=np.float64)
    ratio = float(eig[0] / eig[-1]) if eig[-1] > 0 else 0.0
    ambiguous = runner_up = None
    found = search if search is not None else fit
    if isinstance(found, Alignment):
        ambiguous = bool(found.ambiguous)
        finalists = [c for c in found.candidates if c.refined]
        if len(finalists) > 1 and finalists[0].score > 0:
            runner_up = float(finalists[1].score / finalists[0].score)
    return FitQuality(
        converged=bool(fit.converged),
        stop_reason=StopReason(fit.stop_reason).value,
        iterations=int(fit.iterations),
        observability=ratio,
        weak_directions=tuple(_direction_name(u) for u in fit.degenerate_directions),
        ambiguous=ambiguous,
        runner_up_score=runner_up,
    )


def _direction_name(u: np.ndarray) -> str:
    a = np.abs(u)
    return " + ".join(_DIRECTION_NAMES[i] for i in np.flatnonzero(a >= 0.5 * a.max()))


def pose_sigma_mm(
    fit: Registration, position: npt.ArrayLike, normal: npt.ArrayLike
) -> tuple[float, tuple[str, ...]]:
    """How far the pose's uncertainty moves a CAD point along a direction (1 sigma, mm).

    The fit's twist ``(omega L, t)`` about ``fit.pose_center`` moves a point
    ``q`` along ``n`` by ``J . x`` with ``J = ((q - c) x n / L, n)``; its
    variance is ``J^T C J`` with ``C = fit.pose_covariance``, in which a weakly
    constrained direction counts with its large variance. A direction the
    data do not resolve at all that moves the point along ``n`` makes it
    infinite.

    Returns
    -------
    sigma_mm : float
        ``inf`` when a free direction moves the point.
    weak : tuple of str
        The names of the weak directions (``fit.degenerate_directions``) that
        move the point along ``n``: free ones when ``sigma_mm`` is infinite.
    """
    q = np.asarray(position, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    L = float(fit.pose_radius_mm)
    J = np.concatenate([np.cross(q - fit.pose_center, n) / L, n])
    eig = np.asarray(fit.observability, dtype=np.float64)
    floor = UNRESOLVED_REL_EIG * max(float(eig[-1]), 1e-300)
    # degenerate_directions are the eigenvectors of the smallest eigenvalues, in order.
    moving = [
        (_direction_name(u), bool(eig[k] <= floor))
        for k, u in enumerate(fit.degenerate_directions)
        if abs(float(J @ u)) > _FREE_MOVES
    ]
    free = tuple(name for name, unresolved in moving if unresolved)
    if free:
        return math.inf, free
    sigma = float(np.sqrt(max(float(J @ fit.pose_covariance @ J), 0.0)))
    return sigma, tuple(name for name, _ in moving)


def _held_to_the_pose(
    devs: Deviations,
    points: Sequence[ComparisonPoint],
    fit: Registration,
    p: MeasureParams,
) -> Deviations:
    """The deviations with every judged point whose deviation the pose leaves
    uncertain (3 sigma along its normal above ``uncertainty_fraction`` of its
    tolerance band) made not measurable, with the reason."""
    by_name = {cp.name: cp for cp in points}
    out: list[ComparisonResult] = []
    for c in devs.comparison:
        if c.verdict is Verdict.NOT_MEASURABLE:
            out.append(c)
            continue
        cp = by_name[c.name]
        sigma, weak = pose_sigma_mm(fit, cp.position, cp.normal)
        allowed = p.local.max_sigma_fraction * (cp.upper_mm - cp.lower_mm)
        if 3.0 * sigma <= allowed:
            out.append(c)
            continue
        if math.isinf(sigma):
            why = f"the fit leaves {', '.join(weak)} free, which moves this point along its normal"
        else:
            why = (
                f"the pose leaves its deviation uncertain by {3 * sigma:.4f} mm (3 sigma), "
                f"over {allowed:.4f} mm allowed"
            )
            if weak:
                why += f": {', '.join(weak)} is only weakly constrained"
        out.append(
            dataclasses.replace(
                c, verdict=Verdict.NOT_MEASURABLE, deviation_mm=math.nan, reason=why
            )
        )
    comparison = tuple(out)
    verdict = part_verdict(comparison, devs.failing_defects)
    return dataclasses.replace(devs, comparison=comparison, verdict=verdict)


def _reason(devs: Deviations, note: str | None) -> str | None:
    """Which points and surface defects made the verdict, and any note of the fit."""
    parts = []
    if devs.verdict is Verdict.FAIL:
        names = [c.name for c in devs.comparison if c.verdict is Verdict.FAIL]
        if names:
            parts.append("out of tolerance at " + ", ".join(names))
        failing = devs.failing_defects
        if failing:
            listed = "; ".join(f.describe() for f in failing[:_LISTED_DEFECTS])
            more = len(failing) - _LISTED_DEFECTS
            parts.append(
                f"{len(failing)} surface defect{'s' if len(failing) > 1 else ''}: {listed}"
                + (f"; and {more} more" if more > 0 else "")
            )
    elif devs.verdict is Verdict.NOT_MEASURABLE:
        why = [
            f"{c.name} ({c.reason})" for c in devs.comparison if c.verdict is Verdict.NOT_MEASURABLE
        ]
        parts.append("not measurable at " + "; ".join(why))
    if note:
        parts.append(note)
    return "; ".join(parts) or None


def judge_points(
    points: Sequence[ComparisonPoint], measured: Sequence[PointMeasurement], p: MeasureParams
) -> Deviations:
    """The comparison-point path's deviations: each point's verdict from its local
    measurement, a point whose own uncertainty (3 sigma) exceeds ``local.max_sigma_fraction``
    of its band not measurable; the surface between the points not checked (``defects``
    None), the field's statistics over the windows' deviations."""
    out: list[ComparisonResult] = []
    for cp, m in zip(points, measured, strict=True):
        need = cp.min_support if cp.min_support is not None else p.min_support
        allowed = p.local.max_sigma_fraction * (cp.upper_mm - cp.lower_mm)
        if cp.kind not in MEASURED_KINDS:
            why: str | None = f"kind {cp.kind!r} is not measured"
        elif not m.measurable:
            why = m.reason
        elif m.support < need:
            why = f"{m.support} windows matched in its support, {need} needed"
        elif 3.0 * m.sigma_mm > allowed:
            why = (
                f"its matching leaves the deviation uncertain by {3 * m.sigma_mm:.4f} mm "
                f"(3 sigma), above {p.local.max_sigma_fraction:.0%} of its tolerance band"
            )
        else:
            why = None
        if why is not None:
            out.append(ComparisonResult(cp.name, math.nan, m.support, Verdict.NOT_MEASURABLE,
                                        cp.lower_mm, cp.upper_mm, math.nan, why))  # fmt: skip
            continue
        ok = cp.lower_mm <= m.deviation_mm <= cp.upper_mm
        out.append(ComparisonResult(cp.name, m.deviation_mm, m.support,
                                    Verdict.PASS if ok else Verdict.FAIL, cp.lower_mm,
                                    cp.upper_mm, m.spread_mm))  # fmt: skip
    windows = [m.deviations for m in measured if m.measurable]
    d = np.concatenate(windows) if windows else np.empty(0)
    return Deviations(
        distances=d,
        inliers=np.ones(len(d), bool),
        comparison=tuple(out),
        summary=FieldSummary.of(d),
        verdict=part_verdict(out),
        defects=None,
        defects_fail=False,
    )
