"""Fusing the pairs' points into one cloud: cross-pair check, averaging and weights.

Each pair's points are looked up in every other pair's maps, along the other
pair's viewing rays (:func:`check_in_view`: the point's depth ``z`` along the
other pair's rectified axis, and the depth ``z'`` of the surface that pair
measured through the same pixel, interpolated bilinearly in its disparity
map):

- **confirmed**, ``|z' - z| <= consistency_mm``: the point is replaced by the
  mean of itself and the other pair's surface point on the same ray,
  ``C + (p - C) z'/z`` (``C`` the other pair's left centre). The two pairs'
  matching errors are independent, so this halves their variance where both
  see the part;
- **in front of** the other pair's surface, ``z' - z > consistency_mm``, or
  more than ``free_space_mm`` in front of what the other pair's coarse
  matching sees there (belt included): a free-space violation, which drops
  the point. This removes wrong matches at reflections or dirt, and surfaces
  a matching window dragged past an outline facing this pair, where the
  other pair sees the belt;
- **unseen** by every other pair: kept with a reduced weight.

A point's weight is its match quality, ``clip((score - min_score) /
(score_full - min_score), 0, 1)``, times 1 when confirmed and 0.6 otherwise,
so that registration can down-weight doubtful points.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import numpy.typing as npt
from numba import njit

from .._jit import NO_RUNTIME
from ..arrays import Points, Scalars
from .matching import PairResult
from .pairs import RectifiedPair
from .params import ReconstructParams
from .result import PairReport


def fuse(
    pairs: Sequence[RectifiedPair],
    results: Sequence[PairResult],
    p: ReconstructParams,
    executor: ThreadPoolExecutor | None = None,
) -> tuple[Points, Scalars, npt.NDArray[np.int8], list[PairReport]]:
    """Cross-pair check, averaging and weights of the pairs' ``results`` (see the module
    notes): the cloud's points, weights, and pair indices, and the pairs' reports.

    ``pairs[k]`` measured ``results[k]``. Each pair's points are checked on a thread
    of ``executor`` (None: one after the other).
    """

    def one(k: int) -> tuple[Points, Scalars, PairReport] | PairReport:
        res = results[k]
        if len(res.points) == 0:
            return res.report
        quality = np.clip(
            (res.score.astype(np.float64) - p.min_score) / (p.score_full - p.min_score), 0.0, 1.0
        )
        factor = np.full(len(res.points), 0.6)
        drop = np.zeros(len(res.points), bool)
        confirmed = np.zeros(len(res.points), bool)
        fused = res.points.copy()
        points = np.ascontiguousarray(res.points, dtype=np.float64)
        for j, other in enumerate(results):
            if j == k or (other.coarse is None and other.disparity is None):
                continue
            pair = pairs[j]
            # Free space seen by the other pair's coarse matching, belt included:
            # a point well in front of what the other pair sees there would have
            # hidden it. This removes the surfaces that windows drag past an
            # outline facing this pair, where the other pair sees the belt.
            check_in_view(
                points,
                pair.centre_left,
                pair.R_rect_rig,
                pair.f_px,
                pair.cx_left,
                pair.cy,
                pair.fb,
                pair.offset_px,
                _EMPTY_MAP if other.coarse is None else other.coarse,
                _EMPTY_MAP if other.disparity is None else other.disparity,
                p.free_space_mm,
                p.consistency_mm,
                fused,
                confirmed,
                drop,
            )
        factor[confirmed] = 1.0
        drop &= ~confirmed
        keep = ~drop
        r = res.report
        report = PairReport(
            r.pair,
            r.coarse,
            r.foreground,
            r.refined,
            r.in_volume,
            int(confirmed.sum()),
            int((~confirmed & keep).sum()),
            int(drop.sum()),
            r.disparity_range,
            r.skipped,
        )
        return fused[keep], (quality * factor)[keep], report

    # Each pair's points are checked against the others' maps independently.
    if executor is not None and len(results) > 1:
        done = list(executor.map(one, range(len(results))))
    else:
        done = [one(k) for k in range(len(results))]
    pts_out, w_out, which_out, reports = [], [], [], []
    for k, out in enumerate(done):
        if isinstance(out, PairReport):
            reports.append(out)
            continue
        pts, w, report = out
        pts_out.append(pts)
        w_out.append(w)
        which_out.append(np.full(len(pts), k, np.int8))
        reports.append(report)
    if not pts_out:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int8), reports
    return np.concatenate(pts_out), np.concatenate(w_out), np.concatenate(which_out), reports


_EMPTY_MAP = np.zeros((0, 0), np.float32)


@njit(cache=True, nogil=True, inline="always")
def _map_depth(disparity, x, y, fb, offset_px):  # pragma: no cover
    """The depth a view's disparity map measures through rectified pixel (x, y):
    bilinear where the four neighbours are measured, else the nearest pixel's;
    NaN where none (or off the map)."""
    h, w = disparity.shape
    xf = math.floor(x)
    yf = math.floor(y)
    if not (xf >= 0 and xf < w - 1 and yf >= 0 and yf < h - 1):
        return np.nan
    xi = int(xf)
    yi = int(yf)
    fx = x - xf
    fy = y - yf
    d = (
        disparity[yi, xi] * (1.0 - fx) * (1.0 - fy)
        + disparity[yi, xi + 1] * fx * (1.0 - fy)
        + disparity[yi + 1, xi] * (1.0 - fx) * fy
        + disparity[yi + 1, xi + 1] * fx * fy
    )
    if not math.isfinite(d):
        d = disparity[yi + int(round(fy)), xi + int(round(fx))]
    if math.isfinite(d):
        return fb / (d - offset_px)
    return np.nan


@njit(cache=True, nogil=True, **NO_RUNTIME)
def check_in_view(
    points,
    centre,
    R,
    f_px,
    cx,
    cy,
    fb,
    offset_px,
    coarse,
    disparity,
    free_space_mm,
    consistency_mm,
    fused,
    confirmed,
    drop,
):  # pragma: no cover
    """One other view's part of the cross-pair check (see the module notes), in place.

    Each point is projected into the view once, and looked up in its coarse
    map (``coarse``; an empty map: none) for free space, and in its refined
    ``disparity`` map (empty: none): a point the latter confirms and that no
    earlier view confirmed is replaced by the mean of itself and the view's
    surface point on the same ray, and ``confirmed``; one in front of
    either surface is marked in ``drop``.
    """
    use_coarse = coarse.shape[0] > 0
    use_fine = disparity.shape[0] > 0
    for i in range(points.shape[0]):
        a = points[i, 0] - centre[0]
        b = points[i, 1] - centre[1]
        c = points[i, 2] - centre[2]
        z = R[2, 0] * a + R[2, 1] * b + R[2, 2] * c
        if not z > 0.0:
            continue
        x = f_px * (R[0, 0] * a + R[0, 1] * b + R[0, 2] * c) / z + cx
        y = f_px * (R[1, 0] * a + R[1, 1] * b + R[1, 2] * c) / z + cy
        if use_coarse:
            z_coarse = _map_depth(coarse, x, y, fb, offset_px)
            if math.isfinite(z_coarse) and z_coarse - z > free_space_mm:
                drop[i] = True
        if not use_fine:
            continue
        z_other = _map_depth(disparity, x, y, fb, offset_px)
        if not math.isfinite(z_other):
            continue
        dz = z_other - z
        if abs(dz) <= consistency_mm and not confirmed[i]:
            # The view's surface point on the ray from its left centre through
            # this point: the ray scaled by the depth ratio.
            ratio = z_other / z
            for m in range(3):
                other = centre[m] + (points[i, m] - centre[m]) * ratio
                fused[i, m] = 0.5 * (points[i, m] + other)
            confirmed[i] = True
        # dz > 0: the point lies in front of (nearer the camera than) the surface
        # the view sees through it, which would have hidden that surface.
        if dz > consistency_mm:
            drop[i] = True


__all__ = ["check_in_view", "fuse"]
