"""A character line (a crease, a rounded step or bend of the panel) measured from the cloud.

A character line is where two regions of the surface meet at an angle or a
step; it has no outline the images show, but the cloud shows where the
surface turns. Its nominal near a comparison point is the CAD's line through
``position`` along ``normal x n`` (``n`` the CAD's normal there, ``normal``
the direction across the line in the surface, of a positive offset),
projected onto the CAD. Per cross-section along it, every ``station_mm``:

1. the cloud's points within ``band_mm`` across the line and half a station
   along it are taken with their signed distances ``d_i`` from the CAD and the
   CAD's normals ``n_i`` at their closest points;
2. a surface moved by ``s`` across the line (along ``e``) lies off the CAD by
   ``d_i = c + s (e . n_i)`` to first order (``c`` the surface's own offset
   along its normal): ``(c, s)`` by least squares, points beyond three robust
   sigmas dropped; the points are moved back by ``s`` and the step repeated
   (Gauss-Newton), so that a shift of several tenths is found exactly;
3. a section whose CAD normals barely turn (``e . n_i`` spread below
   ``min_turn``) does not see the line and is left out.

The crease's measured points (each section's nominal point moved by its
``s``) are fitted as a curve (:func:`inspection.edge_curve.curve_offset`):
its mean offset across the line and its largest, and where. The sections
reach ``margin_mm`` beyond the span measured and the curve is read over the
span alone: a fitted curve follows its last points least firmly, and its
largest offset would otherwise most often lie at an end of the span.

The cloud must not have been matched with windows shaped by the CAD (a
guided pass): those follow the drawn crease and hide its bend.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .arrays import Points
from .edge_curve import CurveParams, EdgeCurve, curve_offset, nominal_curve
from .errors import InvalidInput
from .protocols import ClosestPointQuery

__all__ = ["LineParams", "crease_points", "measure_character_line"]

# The robust sigma of a section's residuals, from their MAD.
_MAD_SIGMA = 1.482602218505602


@dataclass(frozen=True)
class LineParams:
    """How a character line is found in the cloud.

    Attributes
    ----------
    band_mm : float
        Cloud points within this far across the line are used: wider than the
        crease's rounding, so that each section sees the surface turn.
    station_mm : float
        Spacing of the cross-sections along the line.
    max_distance_mm : float
        Points farther than this from the CAD are not the surface.
    min_points : int
        Points a section needs.
    min_turn : float
        Least spread (standard deviation) of ``e . n_i`` over a section's
        points: below it the normals do not turn and the shift is not seen.
    iterations : int
        Gauss-Newton steps per section.
    reject_sigma : float
    margin_mm : float
        Sections are also taken this far beyond either end of the span measured:
        the curve through them is read over the span alone, whose ends then are
        not the curve's, where it follows the last sections least firmly.
    """

    band_mm: float = 12.0
    station_mm: float = 2.0
    max_distance_mm: float = 1.0
    min_points: int = 20
    min_turn: float = 0.05
    iterations: int = 3
    reject_sigma: float = 3.0
    margin_mm: float = 10.0


def _frame(
    tree: ClosestPointQuery, position: Points, across: Points
) -> tuple[np.ndarray, np.ndarray]:
    """The line's direction and the unit direction across it (``across`` made normal to it)."""
    n = tree.query(position[None, :]).normals[0]
    t = np.cross(n, across)
    if np.linalg.norm(t) < 1e-6:
        raise InvalidInput("a character line's normal must not lie along the surface normal")
    t /= np.linalg.norm(t)
    e = across - (across @ t) * t
    return t, e / np.linalg.norm(e)


def crease_points(
    tree: ClosestPointQuery,
    points_cad: Points,
    position: Points,
    across: Points,
    half_length_mm: float,
    params: LineParams | None = None,
) -> tuple[Points, Points, np.ndarray, np.ndarray]:
    """The nominal line's sections and the crease found in each (steps 1-3 above).

    Parameters
    ----------
    tree : the CAD's closest points
    points_cad : (N, 3) float64, mm, CAD frame
    position : (3,) float64, mm, a point of the nominal line
    across : (3,) float64, unit, in the surface across the line
    half_length_mm : float
        The line is measured this far either side of ``position``.

    Returns
    -------
    nominal : (K, 3) float64, mm
        Every section's nominal point on the CAD (all sections).
    across : (3,) float64
        The direction the shifts are along.
    shift : (K,) float64, mm
        Each section's shift along ``across``; NaN where the section does not see the line.
    support : (K,) int64
        Points each section used.
    """
    p = params if params is not None else LineParams()
    p0 = np.asarray(position, dtype=np.float64)
    t, e = _frame(tree, p0, np.asarray(across, dtype=np.float64))
    k = max(int(math.floor(half_length_mm / p.station_mm)), 0)
    tau = np.arange(-k, k + 1) * p.station_mm
    nominal = tree.query(p0 + tau[:, None] * t).points
    P = np.asarray(points_cad, dtype=np.float64)
    rel = P - p0
    along = rel @ t
    near = (np.abs(along) <= tau[-1] + p.station_mm / 2) & (np.abs(rel @ e) <= 2 * p.band_mm)
    P, along = P[near], along[near]
    station = np.rint(along / p.station_mm).astype(np.int64) + k
    shift = np.full(len(tau), np.nan)
    support = np.zeros(len(tau), np.int64)
    for j in range(len(tau)):
        pts = P[station == j]
        pts = pts[np.abs((pts - nominal[j]) @ e) <= p.band_mm]
        if len(pts) < p.min_points:
            continue
        shift[j], support[j] = _section_shift(tree, pts, e, p)
    return nominal, e, shift, support


def _section_shift(
    tree: ClosestPointQuery, pts: Points, e: np.ndarray, p: LineParams
) -> tuple[float, int]:
    """One section's shift along ``e`` by Gauss-Newton on ``d_i = c + s (e . n_i)``."""
    s = 0.0
    keep = np.ones(len(pts), bool)
    for _ in range(p.iterations):
        q = tree.query(pts - s * e)
        d, g = q.distances, q.normals @ e
        keep &= np.abs(d) <= p.max_distance_mm
        if keep.sum() < p.min_points or float(np.std(g[keep])) < p.min_turn:
            return math.nan, 0
        A = np.column_stack([np.ones(int(keep.sum())), g[keep]])
        sol, *_ = np.linalg.lstsq(A, d[keep], rcond=None)
        r = d - (sol[0] + sol[1] * g)
        scale = _MAD_SIGMA * float(np.median(np.abs(r[keep] - np.median(r[keep]))))
        inlier = keep & (np.abs(r) <= p.reject_sigma * max(scale, 1e-3))
        if inlier.sum() >= p.min_points:
            A = np.column_stack([np.ones(int(inlier.sum())), g[inlier]])
            sol, *_ = np.linalg.lstsq(A, d[inlier], rcond=None)
            keep = inlier
        s += float(sol[1])
    return s, int(keep.sum())


def measure_character_line(
    tree: ClosestPointQuery,
    points_cad: Points,
    position: Points,
    across: Points,
    half_length_mm: float,
    *,
    params: LineParams | None = None,
    curve: CurveParams | None = None,
    min_support: int = 10,
) -> tuple[EdgeCurve | None, str | None]:
    """A character line's offset across itself and its largest deviation, from the cloud.

    ``min_support`` is the number of sections that must see the line.

    Returns
    -------
    measurement : EdgeCurve or None
        Offsets along ``across`` (made normal to the line).
    reason : str or None
        Why there is none.
    """
    p = params if params is not None else LineParams()
    nominal, e, shift, _ = crease_points(
        tree, points_cad, position, across, half_length_mm + p.margin_mm, p
    )
    # The sections lie every station either side of the middle one, at ``position``.
    k = (len(nominal) - 1) // 2
    read = np.abs(np.arange(len(nominal)) - k) * p.station_mm <= half_length_mm + 1e-9
    seen = np.isfinite(shift)
    if (seen & read).sum() < min_support:
        return (
            None,
            f"{int((seen & read).sum())} sections along the line see it in the cloud, "
            f"{min_support} needed",
        )
    # Sections beyond the span count only where they see the line: past its end, the
    # nominal's points would lie off the line (on whatever surface is nearest there).
    keep = read | seen
    nominal, shift, read, seen = nominal[keep], shift[keep], read[keep], seen[keep]
    measured = nominal[seen] + shift[seen, None] * e
    line = nominal_curve(nominal)
    # One point per section: shorter spans, or less smoothing, follow the cloud's own
    # wiggles at the crease (tenths of a mm over a few mm) into the largest offset.
    c = CurveParams(points_per_span=5, min_span_mm=20.0, smoothing=0.1)
    c = curve if curve is not None else c
    return curve_offset(measured, line, nominal, np.tile(e, (len(nominal), 1)), c,
                        min_support=min_support, read=read)  # fmt: skip
