"""Matching one rectified stereo pair: coarse disparities, square windows, triangulation.

The first pass over a pair, in order:

1. **Rectify** both frames (:func:`.pairs.rectify`).
2. **Coarse matching**: OpenCV's StereoSGBM (3-way mode, left-right check)
   at half resolution over the disparities the measurement volume (or the
   part's :class:`~inspection.reconstruct.Prior`) spans
   (:func:`coarse_disparity`). Cheap and robust, but far from sub-pixel.
3. **Region of the part**: coarse disparities above the belt's
   (:func:`.pairs.belt_disparity` at ``z_min_mm``); the conveyor is dropped
   here, before the expensive steps, and the refinement works on crops
   around what is left (:func:`crops`).
4. **Square windows**: each pixel of every ``stride``-th column of every
   ``row_stride``-th row is refined
   at full resolution from its coarse disparity (:func:`.kernels.refine_pixels`
   or, with ``symmetric``, :func:`.kernels.refine_cyclopean`), on images
   normalised by their local mean and contrast (:func:`local_normalise`),
   with saturated pixels (the flash's mirror reflections) given no weight.
   Neighbouring windows overlap, so the skipped columns would add little
   information for as much time.

What this gives, :class:`PairState`, is where the warped passes start
(:mod:`.warping`), in this pass and in the guided one. **Triangulation**
(:func:`triangulate_pair`) keeps the matches that correlate
(``min_score``), have converged (``converged_px``) and moved at most
``max_shift_px`` from their start, triangulates them (``Z = f B / d``, see
:mod:`.pairs`), keeps the points inside the volume above ``z_min_mm``, and
draws the pair's disparity map, in which the other pairs look their points
up when the pairs are fused (:mod:`.fusion`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from scipy import ndimage

from ..rig import Rig
from . import kernels
from .pairs import RectifiedPair, rectify
from .params import SATURATION_DN, ReconstructParams
from .result import PairReport

F32 = npt.NDArray[np.float32]


def local_normalise(img: F32, window: int) -> F32:
    """Subtract the local mean and divide by the local standard deviation (box window)."""
    k = (window, window)
    mean = cv2.boxFilter(img, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    sq = cv2.boxFilter(img * img, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    # The floor under the variance keeps flat, dark regions (shadows) from being
    # amplified into noise.
    out = np.empty(img.shape, np.float32)
    kernels.normalised(img, mean, sq, out)
    return out


def spline_rows(img: F32) -> F32:
    """Cubic B-spline coefficients of each row of ``img`` (mirror boundary).

    What the refinement kernels sample: the spline with these coefficients
    passes through the pixels, and its values and slopes in between come from
    four coefficients (:func:`.kernels._bspline`).
    """
    out = ndimage.spline_filter1d(img, order=3, axis=1, mode="mirror", output=np.float32)
    return np.ascontiguousarray(out, dtype=np.float32)


def coarse_disparity(
    left_u8: npt.NDArray[np.uint8],
    right_u8: npt.NDArray[np.uint8],
    d_min: float,
    d_max: float,
    block: int,
) -> F32:
    """SGBM (3-way) disparity at half resolution, returned at full resolution (px, NaN = none).

    Parameters
    ----------
    left_u8, right_u8 : (H, W) uint8
        Rectified images at full resolution.
    d_min, d_max : float
        Disparity range to search, full-resolution pixels.
    block : int
        SGBM block size at half resolution (odd).
    """
    h, w = left_u8.shape
    lh = cv2.pyrDown(left_u8)
    rh = cv2.pyrDown(right_u8)
    lo = int(math.floor(d_min / 2.0)) - 2
    num = int(math.ceil((d_max / 2.0 - lo + 2) / 16.0)) * 16
    sgbm = cv2.StereoSGBM.create(
        minDisparity=lo,
        numDisparities=num,
        blockSize=block,
        P1=8 * block * block,
        P2=32 * block * block,
        disp12MaxDiff=1,
        preFilterCap=31,
        uniquenessRatio=10,
        speckleWindowSize=40,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    raw = sgbm.compute(lh, rh)
    disp = raw.astype(np.float32) * np.float32(2.0 / 16.0)
    disp[raw <= (lo - 1) * 16] = np.nan
    # Half-resolution pixel i sits at full-resolution pixel 2i (pyrDown's sampling).
    return np.asarray(cv2.resize(disp, (w, h), interpolation=cv2.INTER_NEAREST), dtype=np.float32)


@dataclass(frozen=True, eq=False)
class PairResult:
    """What one pass found in one pair: its points, and what the next pass starts from.

    Attributes
    ----------
    report : PairReport
    points : (N, 3) float64, mm, rig frame
    score : (N,) float32
        Each point's match score (normalised cross-correlation).
    disparity : (H, W) float32 or None
        The pair's refined disparity map at the full rectified size (NaN
        where none), for the other pairs' cross-check.
    coarse : (H, W) float32 or None
        The coarse (SGBM) disparities, belt included (NaN where none), for
        the other pairs' free-space check.
    state : PairState or None
        The matching up to the square windows, where a guided pass starts
        (None: the pair was skipped, saw nothing of the part, or was matched
        with symmetric windows).
    guided : tuple of three (M,) float32 or None
        A guided pass's fit (``d_ref``, ``score``, ``step`` of ``state``'s
        pixels, crop disparities), where the bends' rematch starts.
    """

    report: PairReport
    points: npt.NDArray[np.float64]
    score: npt.NDArray[np.float32]
    disparity: npt.NDArray[np.float32] | None = None
    coarse: npt.NDArray[np.float32] | None = None
    state: PairState | None = None
    guided: tuple[npt.NDArray[np.float32], ...] | None = None


@dataclass(frozen=True, eq=False)
class PairFrame:
    """What one pair's triangulation needs besides its matches: the rectified image
    size, the volume searched, the report so far and the coarse (SGBM) disparities."""

    shape: tuple[int, ...]
    lo: npt.NDArray[np.float64]
    hi: npt.NDArray[np.float64]
    report: PairReport
    coarse: npt.NDArray[np.float32] | None  # None: matched only with a guide


@dataclass(frozen=True, eq=False)
class PairState:
    """One pair's matching up to its square-window refinement (crop coordinates):
    what the warped passes, with or without a guide, start from."""

    left_n: npt.NDArray[np.float32]
    right_n: npt.NDArray[np.float32]  # row B-spline coefficients (spline_rows)
    wl: npt.NDArray[np.float32]
    wr: npt.NDArray[np.float32]
    px: npt.NDArray[np.intp]
    py: npt.NDArray[np.intp]
    d_init: npt.NDArray[np.float32]  # coarse, full-image disparities
    d_square: npt.NDArray[np.float32]  # square-window refinement, crop disparities
    score: npt.NDArray[np.float32]
    step: npt.NDArray[np.float32]
    shift: float  # crop disparity = full-image disparity + shift
    x0: int
    y0: int
    roi: tuple[slice, slice]
    frame: PairFrame


def crops(
    left: npt.NDArray[np.float32],
    right: npt.NDArray[np.float32],
    sat_l: npt.NDArray[np.bool_],
    sat_r: npt.NDArray[np.bool_],
    region: npt.NDArray[np.bool_],
    d_min: float,
    d_max: float,
    p: ReconstructParams,
) -> tuple[Any, ...]:
    """The crops a pair's refinement works on: around ``region`` of the left view
    (padded by the windows), and of the right view where disparities in
    [d_min, d_max] send it. Returns the left crop's slices, its origin (x0, y0),
    the right crop's first column, both crops locally normalised (the right one
    as row spline coefficients, which the kernels sample between pixels) and
    their weights (0 where saturated)."""
    # The region's bounding box from its rows and columns that hold a pixel: two
    # reductions, not a list of every pixel.
    ys = np.flatnonzero(region.any(axis=1))
    xs = np.flatnonzero(region.any(axis=0))
    pad = p.window + p.norm_window
    h_img, w_img = region.shape
    y0 = max(int(ys[0]) - pad, 0)
    y1 = min(int(ys[-1]) + pad + 1, h_img)
    x0 = max(int(xs[0]) - pad, 0)
    x1 = min(int(xs[-1]) + pad + 1, w_img)
    roi = (slice(y0, y1), slice(x0, x1))
    rx0 = max(int(math.floor(x0 - d_max)) - pad, 0)
    rx1 = min(int(math.ceil(x1 - d_min)) + pad, w_img)
    left_n = local_normalise(left[roi], p.norm_window)
    right_n = spline_rows(local_normalise(right[y0:y1, rx0:rx1], p.norm_window))
    wl = (~sat_l[roi]).astype(np.float32)
    wr = (~sat_r[y0:y1, rx0:rx1]).astype(np.float32)
    return roi, x0, y0, rx0, left_n, right_n, wl, wr


def grid_pixels(
    mask: npt.NDArray[np.bool_], x0: int, y0: int, stride: int, row_stride: int
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Rows and columns of the pixels of ``mask`` (a crop whose pixel (0, 0) is the
    image's (y0, x0)) on every ``stride``-th column and ``row_stride``-th row of the
    image, in the order ``np.nonzero`` gives them; found on those rows and columns
    alone."""
    cy = (-y0) % row_stride
    cx = (-x0) % stride
    sy, sx = np.nonzero(mask[cy::row_stride, cx::stride])
    return sy * row_stride + cy, sx * stride + cx


def skipped(rig: Rig, pair: RectifiedPair, usable: Sequence[bool]) -> PairResult:
    """The result of a pair not matched because one of its frames cannot be used."""
    bad = [rig.cameras[i].name for i in (pair.left, pair.right) if not usable[i]]
    return PairResult(
        PairReport(pair.name, skipped=f"unusable frame(s): {', '.join(bad)}"),
        np.zeros((0, 3)),
        np.zeros(0, np.float32),
    )


def match_pair(
    pair: RectifiedPair,
    fg_disparity: npt.NDArray[np.float32],
    img_l: npt.NDArray[np.uint8],
    img_r: npt.NDArray[np.uint8],
    lo: npt.NDArray[np.float64],
    hi: npt.NDArray[np.float64],
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
) -> PairResult | PairState:
    """Steps 1-4 of the module notes for one pair: its square-window fit, ready for the
    warped passes (:func:`.warping.finish_pair`), or its result when there is nothing to
    refine (no coarse match, nothing above the belt) or the windows were symmetric."""
    t = time.perf_counter()
    left = rectify(img_l, pair.maps_left)
    right = rectify(img_r, pair.maps_right)
    sat_l = left >= SATURATION_DN - 0.5
    sat_r = right >= SATURATION_DN - 0.5
    left_u8 = np.clip(left + 0.5, 0, 255).astype(np.uint8)
    right_u8 = np.clip(right + 0.5, 0, 255).astype(np.uint8)
    timings[f"rectify{k}"] = (time.perf_counter() - t) * 1e3

    t = time.perf_counter()
    d_min, d_max = pair.disparity_range(lo, hi)
    d_coarse = coarse_disparity(left_u8, right_u8, d_min, d_max, p.coarse_block)
    coarse_ok = np.isfinite(d_coarse)
    n_coarse = int(coarse_ok.sum())
    timings[f"sgbm{k}"] = (time.perf_counter() - t) * 1e3
    rep = PairReport(pair.name, coarse=n_coarse, disparity_range=(d_min, d_max))
    empty = PairResult(rep, np.zeros((0, 3)), np.zeros(0, np.float32))
    if n_coarse == 0:
        return empty

    t = time.perf_counter()
    # The part's region: coarse depth above the belt (conveyor background removed).
    fg = coarse_ok & (d_coarse > fg_disparity)
    n_fg = int(fg.sum())
    if n_fg == 0:
        return PairResult(
            PairReport(pair.name, coarse=n_coarse, disparity_range=(d_min, d_max)),
            np.zeros((0, 3)),
            np.zeros(0, np.float32),
            None,
            d_coarse,
        )
    roi, x0, y0, rx0, left_n, right_n, wl, wr = crops(
        left, right, sat_l, sat_r, fg, d_min, d_max, p
    )
    todo = fg[roi] & ~sat_l[roi]
    report = PairReport(pair.name, coarse=n_coarse, foreground=n_fg, disparity_range=(d_min, d_max))
    frame = PairFrame(fg.shape, lo, hi, report, d_coarse)
    if p.symmetric:
        py, px = np.nonzero(todo)
        d_init = d_coarse[roi][py, px]
        # Points on the cyclopean view's grid: c = x_left - d / 2 (full-image
        # columns), every stride-th column; the coarse disparity of each comes
        # from the left pixel that maps to it.
        c = np.rint((px + x0) - 0.5 * d_init).astype(np.int64)
        sel = (c % p.stride == 0) & ((py + y0) % p.row_stride == 0)
        c, py_, d_init = c[sel], py[sel], d_init[sel]
        cl = (c - x0).astype(np.float64)
        cr = (c - rx0).astype(np.float64)
        n = len(c)
        d_ref = np.empty(n, np.float32)
        score = np.empty(n, np.float32)
        step = np.empty(n, np.float32)
        kernels.refine_cyclopean(
            spline_rows(left_n),  # sampled between pixels too
            right_n,
            wl,
            wr,
            cl,
            cr,
            py_.astype(np.int64),
            d_init.astype(np.float32),
            p.window // 2,
            p.iterations,
            d_ref,
            score,
            step,
        )
        x_left = c + 0.5 * d_ref.astype(np.float64)
        rows = py_ + y0
    else:
        # Refine every stride-th column of every row_stride-th row only (the
        # windows overlap anyway).
        py, px = grid_pixels(todo, x0, y0, p.stride, p.row_stride)
        d_init = d_coarse[roi][py, px]
        # In the crops, a left pixel x matches right x - d', with d' = d - x0 + rx0.
        shift = float(rx0 - x0)
        n = len(px)
        d_ref = np.empty(n, np.float32)
        score = np.empty(n, np.float32)
        step = np.empty(n, np.float32)
        kernels.refine_pixels(
            left_n,
            right_n,
            wl,
            wr,
            px.astype(np.int64),
            py.astype(np.int64),
            (d_init + shift).astype(np.float32),
            p.window // 2,
            p.iterations,
            d_ref,
            score,
            step,
        )
        timings[f"refine{k}"] = (time.perf_counter() - t) * 1e3
        return PairState(
            left_n,
            right_n,
            wl,
            wr,
            px,
            py,
            d_init,
            d_ref,
            score,
            step,
            shift,
            x0,
            y0,
            roi,
            frame,
        )
    timings[f"refine{k}"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    out = triangulate_pair(pair, x_left, rows, d_ref, score, step, d_init, frame, p)
    timings[f"triangulate{k}"] = (time.perf_counter() - t) * 1e3
    return out


def triangulate_state(
    pair: RectifiedPair,
    st: PairState,
    fit: tuple[npt.NDArray[np.float32], ...],
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
    guided: bool,
    keep: npt.NDArray[np.bool_] | None = None,
) -> PairResult:
    """The pair's result from its warped fit ``(d_ref, score, step)`` (crop
    coordinates), kept with the state it started from (and, ``guided``, the fit);
    ``keep``: the windows that give points (None: all)."""
    t = time.perf_counter()
    d_ref, score, step = fit
    x_left = (st.px + st.x0).astype(np.float64)
    rows = st.py + st.y0
    d_full = d_ref - np.float32(st.shift)
    out = triangulate_pair(pair, x_left, rows, d_full, score, step, st.d_init, st.frame, p, keep)
    timings[f"triangulate{k}"] = (time.perf_counter() - t) * 1e3
    return replace(out, state=st, guided=fit if guided else None)


def triangulate_pair(
    pair: RectifiedPair,
    x_left: npt.NDArray[np.float64],
    rows: npt.NDArray[np.intp],
    d_ref: npt.NDArray[np.float32],
    score: npt.NDArray[np.float32],
    step: npt.NDArray[np.float32],
    d_init: npt.NDArray[np.float32],
    frame: PairFrame,
    p: ReconstructParams,
    keep: npt.NDArray[np.bool_] | None = None,
) -> PairResult:
    """Accepted matches of one pair as rig-frame points, and its disparity map
    (``keep``: the matches that give points; the map is drawn from all of them)."""
    n = len(x_left)
    full = np.full(frame.shape, np.nan, np.float32)
    pts = np.empty((n, 3))
    kept_score = np.empty(n, np.float32)
    geometry = np.array([pair.fb, pair.offset_px, pair.f_px, pair.cx_left, pair.cy])
    limits = np.array([p.z_min_mm, p.min_score, p.max_shift_px, p.converged_px])
    n_out, n_good = kernels.triangulate_matches(
        np.ascontiguousarray(x_left, dtype=np.float64),
        np.ascontiguousarray(rows, dtype=np.int64),
        d_ref,
        score,
        step,
        d_init,
        _NO_KEEP if keep is None else keep,
        geometry,
        pair.R_rect_rig,
        pair.centre_left,
        frame.lo,
        frame.hi,
        limits,
        full,
        pts,
        kept_score,
    )
    # The disparity map of the left view, for the other pair's consistency check.
    fill_gaps(full, p)
    pts = pts[:n_out].copy()
    score = kept_score[:n_out].copy()
    rep = replace(frame.report, refined=int(n_good), in_volume=len(pts))
    return PairResult(rep, pts, score, full, frame.coarse)


_NO_KEEP = np.zeros(0, np.bool_)


def fill_gaps(disparity: npt.NDArray[np.float32], p: ReconstructParams) -> None:
    """Fill the gaps the refinement leaves (the columns and rows not refined), in place,
    from measured neighbours: along rows, then along columns."""
    # Row and column scans rather than box filters over the whole image: a pass touches
    # only the pixels next to a gap.
    kernels.fill_row_gaps(disparity, p.stride)
    if p.row_stride > 1:
        # Gaps of row_stride - 1 rows close in row_stride // 2 passes; more would only grow
        # the outlines by rows no pair measured.
        kernels.fill_column_gaps(disparity, p.row_stride // 2)


__all__ = [
    "PairFrame",
    "PairResult",
    "PairState",
    "coarse_disparity",
    "crops",
    "fill_gaps",
    "grid_pixels",
    "local_normalise",
    "match_pair",
    "skipped",
    "spline_rows",
    "triangulate_pair",
    "triangulate_state",
]
