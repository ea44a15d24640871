"""The escape along a free rotation: scan the turn a fit leaves free, refit from the best angles.

A local fit cannot tell where a rotation that its points do not constrain
should end. A disc whose turn rests on a ring of holes, started further off
than the holes are wide, ends where it happens to stop (flagged degenerate);
a part with a toothed rim ends a few teeth off, constrained there, with a
large share of its points off the CAD. When the fit is flagged degenerate
and its least constrained rotation (with the translation free to follow it)
is weak, or when it leaves more than 10 % of its points misfit, that
rotation is scanned over ``escape_deg`` either way in steps that move the
points by ~2 mm, three times: about the centroid (a disc turns about its
centre), with the shift that follows the turn to first order, and with that
shift then fitted to the points at each angle (a plate that settled turned
in its own plane about a corner comes back only so, and first order is
millimetres off a few degrees from a far corner). Each angle is scored by
the truncated distances of a few thousand points to the CAD (one query
each, three on the last line), and the fit is run again, with everything
else as given, from up to three of the scans' local minima that score 10 %
better than the fit or more (and once more from where it ends, should it
run out of iterations while it still moves). A fit that leaves the points'
truncated cost (three robust scales of the first fit) 10 % lower or more
replaces the first.

The scan is about one axis: a free translation (a plate sliding in its
plane) is left to the ``degenerate`` flag. :func:`~inspection.align`
searches the turn itself, and its final fit runs without the scan.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from ..arrays import Points, Scalars, Transform
from ..errors import InsufficientOverlap
from ..protocols import ClosestPointQuery
from .correspondences import closest
from .kernels import compose, transform_points
from .result import INLIER_SIGMAS, Registration, StopReason

log = logging.getLogger(__name__)

# A rotation whose marginal eigenvalue (translation free) is below this,
# relative to the normal matrix's largest, is scanned ...
_ESCAPE_REL_EIG = 1e-2
# ... as is the least constrained rotation of a fit that leaves more than
# this fraction of its points misfit (beyond three robust scales) ...
_ESCAPE_MISFIT = 0.1
# ... on this many points, scored by their mean squared distance to the CAD
# truncated at this (mm; or 20 robust scales, if more), in steps that move
# the points by about this much at their RMS radius (at most 2 degrees) ...
_ESCAPE_POINTS = 4096
_ESCAPE_TRUNCATION_MM = 2.0
# ... and up to this many of the scan's local minima that score this
# fraction of the fit's score or less are fitted again; one replaces the fit
# when it leaves this fraction of its truncated cost (three robust scales of
# the first fit) or less.
_ESCAPE_STARTS = 3
_ESCAPE_GAIN = 0.9
# Point-to-plane steps that fit the shift at each angle of the last line.
_SHIFT_STEPS = 2


def escape_free_rotation(
    tree: ClosestPointQuery,
    fit: Registration,
    points: Points,
    weights: Scalars,
    H: np.ndarray,
    center: np.ndarray,
    L: float,
    misfit: float,
    escape_deg: float,
    refit: Callable[[Transform], Registration],
) -> Registration:
    """The fit, or a better one found along the rotation it leaves free.

    Parameters
    ----------
    tree : ClosestPointQuery
    fit : Registration
        The fit to escape from.
    points : (n, 3) float64, mm, data frame
        The fit's points in its subset order (a random order), and their
        weights (0: gated out as far); the first few thousand with a positive
        weight are scanned.
    weights : (n,) float64
    H : (6, 6) float64
        The fit's final normal matrix for the twist ``(omega L, t)`` about
        ``center`` (CAD frame, mm), ``L`` mm.
    center : (3,) float64
    L : float
    misfit : float
        Fraction of the fit's points beyond three robust scales.
    escape_deg : float, degrees
        Half the span of the scan.
    refit : callable
        The same fit from another start ``T_cad_data`` (without an escape).

    Returns
    -------
    Registration
        ``fit`` itself when it is constrained and fits, or when no other
        angle fits clearly better.
    """
    misfitting = misfit > _ESCAPE_MISFIT
    if not (fit.degenerate or misfitting):
        return fit
    k = min(len(points), _ESCAPE_POINTS)
    # Every point, not only those that fit here: those would fit here best.
    P = points[:k][weights[:k] > 0]
    span_rad = np.radians(escape_deg)
    # The rotation that costs least once the translation follows it: the
    # Schur complement of the translation block.
    S = H[:3, :3] - H[:3, 3:] @ np.linalg.pinv(H[3:, 3:]) @ H[3:, :3]
    eig, vec = np.linalg.eigh(0.5 * (S + S.T))
    # fit.observability: the eigenvalues of H, ascending.
    largest = max(float(fit.observability[-1]), 1e-300)
    if not misfitting and eig[0] >= _ESCAPE_REL_EIG * largest:
        return fit
    axis = vec[:, 0]
    trunc = max(_ESCAPE_TRUNCATION_MM, 20.0 * fit.scale_mm)
    step = min(trunc / L, np.radians(2.0))
    k = int(np.ceil(span_rad / step))
    angles = np.linspace(-span_rad, span_rad, 2 * k + 1)
    # Three lines are scanned: the turn about the centroid; the turn with the
    # shift that follows it to first order (the least-cost shift per radian by
    # the Schur complement); and that shift fitted to the points at each
    # angle. A disc turns about its centre: the first. A plate that settled
    # turned in its own plane about one of its corners comes back along the
    # second, or, where first order misses it, the third.
    follow = -np.linalg.pinv(H[3:, 3:]) @ H[3:, :3] @ (axis * L)
    found: list[tuple[float, int, Transform, float]] = []
    for line, shift in enumerate((np.zeros(3), follow, follow)):
        starts = [compose(fit.transform, axis * a, shift * a, center) for a in angles]
        score = np.empty(len(angles))
        for i, T_ in enumerate(starts):
            # Both read the points within trunc of the CAD only: the others are
            # answered as beyond it, without the search for their faces.
            for _ in range(_SHIFT_STEPS if line == 2 else 0):
                X = transform_points(T_[:3, :3].copy(), T_[:3, 3].copy(), P)
                _, N, d, _ = closest(tree, X, within_mm=trunc)
                T_[:3, 3] += _shift_to_fit(N, d, trunc)
            X = transform_points(T_[:3, :3].copy(), T_[:3, 3].copy(), P)
            d = closest(tree, X, within_mm=trunc)[2]
            score[i] = np.mean(np.minimum(d * d, trunc * trunc))
        # Local minima of the scan that place clearly more of the points on the
        # CAD than the fit does (the fit's neighbours are its own minimum).
        here = k
        minima = (score[1:-1] <= score[:-2]) & (score[1:-1] <= score[2:])
        found += [
            (float(score[i + 1]), line, starts[i + 1], float(angles[i + 1]))
            for i in range(len(minima))
            if minima[i] and abs(i + 1 - here) > 1 and score[i + 1] < _ESCAPE_GAIN * score[here]
        ]
    better = sorted(found, key=lambda f: (f[0], f[1], f[3]))[:_ESCAPE_STARTS]
    if not better:
        return fit

    tau2 = (INLIER_SIGMAS * fit.scale_mm) ** 2

    def truncated_cost(reg: Registration) -> float:
        r = reg.residuals
        return float(np.mean(np.minimum(r * r, tau2)))

    first = truncated_cost(fit)
    best, best_cost = fit, _ESCAPE_GAIN * first
    turned = 0.0
    for _, _, T_start, angle in better:
        try:
            other = refit(T_start)
            if other.stop_reason is StopReason.MAX_ITERATIONS:
                # Still crawling along the rotation it came back by (a plate
                # turning about a corner): let it arrive.
                other = refit(other.transform)
        except InsufficientOverlap:
            continue
        cost = truncated_cost(other)
        log.debug(
            "escape: %.1f deg about %s, misfit %.4g against the first fit's %.4g",
            np.degrees(angle),
            np.round(axis, 3),
            cost,
            first,
        )
        if cost < best_cost:
            best, best_cost = other, cost
            turned = float(np.degrees(angle))
            if not other.degenerate:
                break
    if best is not fit:
        log.info(
            "register: the fit turned %.1f deg about %s fits better (misfit %.4g, was %.4g)",
            turned,
            np.round(axis, 3),
            best_cost,
            first,
        )
    return best


def _shift_to_fit(N: np.ndarray, d: np.ndarray, trunc: float) -> np.ndarray:
    """The shift that best moves the points within ``trunc`` of the CAD onto
    it (point to plane, least squares): (3,) mm, 0 along directions their
    normals leave free."""
    near = np.abs(d) < trunc
    n, r = N[near], d[near]
    A = n.T @ n
    if len(r) < 3 or not np.isfinite(A).all():
        return np.zeros(3)
    eig, vec = np.linalg.eigh(A)
    keep = eig > 1e-6 * max(float(eig[-1]), 1e-300)
    # Unconstrained directions stay put (a plate may slide in its plane).
    return -(vec[:, keep] @ ((vec[:, keep].T @ (n.T @ r)) / eig[keep]))
