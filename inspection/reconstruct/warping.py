"""Windows warped by a disparity field: the measured one, or the one a guide draws from the CAD.

A square window assumes one disparity across it. Where the surface bends
(edge radii, character lines) or is seen at a grazing angle (walls), that is
far from true, and the fit comes out off by an amount whose sign depends on
the side of the part: those are the very points that fix a flat part in its
plane. After the square windows (:mod:`.matching`), the windows over which
the field is far from constant are fitted again with the window warped by
the field (:func:`.kernels.refine_warped`: the right-image sample of window
offset ``(u, v)`` is taken at ``x + u - d - (S(x + u, y + v) - S(x, y))``),
solving for the centre's disparity only; samples off the field (across a
depth edge) get no weight, so a window does not drag a surface past its
outline.

**The measured field** (no guide, ``warp_passes`` passes): the refined
disparities of the previous pass, their row gaps filled and smoothed over
``warp_smooth`` pixels, give the shape. A window is refitted when the mean of
the field over it is off its centre's value by more than
``warp_curvature_px`` (a bend), its slope along the baseline exceeds
``warp_slope`` (foreshortened differently in the two views), or it reaches a
hole in the field (:func:`bends`). Smoothing rounds the bends off, so the
measured shape is least right where it matters most.

**The guide's field** (``guide_passes`` passes): the CAD's disparities at the
fitted pose (:mod:`.guided`) give the shape exactly, wherever they agree with
the smoothed measured field within ``guide_tolerance_px`` at the window's
centre (elsewhere the part departs from its CAD, and the measured shape is
kept). Only the shape comes from the CAD: each window's disparity is still
measured, so a dent is not guided away.

**Light that changes with the surface** (``shading``, with a guide). Bare
metal reflects the flash as a broad sheen as well as diffusely; each camera
of a pair sees the sheen with another strength, and across a bend, where the
normal turns, it changes by a different amount in each view. A window's gain
and offset cannot absorb that, and the match moves. Where the guide shows
that a window spans a bend (a slope of the guide's field that varies by more
than ``shading_bend`` across it), the window also fits light that is a
quadratic function of the surface's orientation
(:func:`.kernels.refine_warped_shaded`): the regressors are the monomials of
the guide's two disparity slopes, a function of the normal (:func:`shading`).
They come from the CAD, not from the images, so they cannot mimic the speckle.
"""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from . import kernels
from .matching import PairResult, PairState, fill_gaps, triangulate_state
from .pairs import RectifiedPair
from .params import ReconstructParams

# Light that changes with the surface (ReconstructParams.shading): the
# regressors are the guide's disparity slopes times this (O(1) on a bend),
# and this times a window's weight is added to their coefficients' diagonal.
_SHADING_SCALE = 10.0
_SHADING_RIDGE = 1e-3


def finish_pair(
    pair: RectifiedPair,
    st: PairState,
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
    shape: npt.NDArray[np.float32] | None = None,
    sparse: bool = False,
) -> PairResult:
    """The warped passes and the triangulation of one pair, from its square windows
    ``st``; ``shape``: a guide's disparity field over the crop (crop disparities, NaN off
    the part; :func:`.guided.finish_guided`), None for the measured field alone.
    ``sparse``: only the windows of every ``p.sparse_rows``-th row are refitted and
    give points (the field they follow, and the disparity map, come from all)."""
    t = time.perf_counter()
    keep = (st.py + st.y0) % p.sparse_rows == 0 if sparse else None
    d_ref, score, step = st.d_square, st.score, st.step
    if p.warp_passes or shape is not None:
        d_ref, score, step = warped_passes(
            st.left_n,
            st.right_n,
            st.wl,
            st.wr,
            st.px,
            st.py,
            st.d_init + st.shift,
            d_ref,
            score,
            step,
            p,
            shape,
            keep,
        )
    timings[f"warp{k}"] = (time.perf_counter() - t) * 1e3
    fit = (d_ref, score, step)
    return triangulate_state(pair, st, fit, p, timings, k, shape is not None, keep)


def warped_passes(
    left_n: npt.NDArray[np.float32],
    right_n: npt.NDArray[np.float32],
    wl: npt.NDArray[np.float32],
    wr: npt.NDArray[np.float32],
    px: npt.NDArray[np.intp],
    py: npt.NDArray[np.intp],
    d_init: npt.NDArray[np.float32],
    d_ref: npt.NDArray[np.float32],
    score: npt.NDArray[np.float32],
    step: npt.NDArray[np.float32],
    p: ReconstructParams,
    guide: npt.NDArray[np.float32] | None = None,
    only: npt.NDArray[np.bool_] | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Refine again, with windows warped by the disparity field found so far (see the
    module notes).

    Only windows whose field is far from constant are refitted
    (:func:`bends`); elsewhere the square window is already right. Each pass
    starts from the previous one's field. With ``guide`` (the CAD's
    disparity field over the crop, NaN off the part), every window whose
    centre lies on it, within ``guide_tolerance_px`` of the measured field,
    is warped by the guide instead (and, spanning a bend with
    ``p.shading``, fits the light as well), in ``guide_passes`` passes.

    Inputs are the crops and pixel lists of :class:`.matching.PairState`
    (disparities in crop coordinates); ``only``: the windows that may be refitted
    (None: all). Returns new ``d_ref``, ``score``, ``step``.
    """
    ks = (p.warp_smooth, p.warp_smooth)
    guided = shade = bent = None
    if guide is not None:
        g_field, g_mask, shade, bent = guide_maps(guide, p)
        guided = (g_field, g_mask)
    passes = p.warp_passes if guide is None else p.guide_passes
    for _ in range(passes):
        ok = (
            np.isfinite(d_ref) & (score >= p.min_score) & (np.abs(d_ref - d_init) <= p.max_shift_px)
        )
        fit = ok if only is None else ok & only
        field_ = np.full(left_n.shape, np.nan, np.float32)
        field_[py[ok], px[ok]] = d_ref[ok]
        fill_gaps(field_, p)
        v = np.empty_like(field_)
        mask = np.empty_like(field_)
        kernels.masked_field(field_, v, mask)
        num = cv2.boxFilter(v, cv2.CV_32F, ks, normalize=False, borderType=cv2.BORDER_CONSTANT)
        den = cv2.boxFilter(mask, cv2.CV_32F, ks, normalize=False, borderType=cv2.BORDER_CONSTANT)
        smooth = np.empty_like(field_)
        kernels.masked_mean(num, den, mask, smooth)
        sel = fit & bends(smooth, mask, px, py, p)
        d_ref, score, step = d_ref.copy(), score.copy(), step.copy()
        if guided is not None:
            g_field, g_mask = guided
            follow = (
                fit
                & (g_mask[py, px] > 0.0)
                & (np.abs(g_field[py, px] - smooth[py, px]) <= p.guide_tolerance_px)
            )
            shaded = follow & bent[py, px] if bent is not None else np.zeros_like(follow)
            images = (left_n, right_n, wl, wr, g_field, g_mask, px, py)
            warp(*images, follow & ~shaded, d_ref, score, step, p)
            if shaded.any():
                warp(*images, shaded, d_ref, score, step, p, shade)
            sel &= ~follow
        warp(left_n, right_n, wl, wr, smooth, mask, px, py, sel, d_ref, score, step, p)
    return d_ref, score, step


def bends(
    field_: npt.NDArray[np.float32],
    mask: npt.NDArray[np.float32],
    px: npt.NDArray[np.intp],
    py: npt.NDArray[np.intp],
    p: ReconstructParams,
) -> npt.NDArray[np.bool_]:
    """Windows over which ``field_`` (0 where ``mask`` is 0) is far from constant: its
    mean off the centre's value by more than ``warp_curvature_px``, a slope along the
    baseline above ``warp_slope``, or a hole in the field inside the window."""
    kw = (p.window, p.window)
    num_w = cv2.boxFilter(field_, cv2.CV_32F, kw, normalize=False, borderType=cv2.BORDER_CONSTANT)
    den_w = cv2.boxFilter(mask, cv2.CV_32F, kw, normalize=False, borderType=cv2.BORDER_CONSTANT)
    uneven = np.empty(len(px), np.bool_)
    # The thresholds in float32, as the field is: numpy compares a float32 array with
    # a Python float so.
    kernels.uneven_windows(
        num_w, den_w, field_, px, py, np.float32(p.warp_curvature_px), np.float32(p.warp_slope),
        np.float32(p.window * p.window - 0.5), uneven,
    )  # fmt: skip
    return uneven


def warp(
    left_n: npt.NDArray[np.float32],
    right_n: npt.NDArray[np.float32],
    wl: npt.NDArray[np.float32],
    wr: npt.NDArray[np.float32],
    shape: npt.NDArray[np.float32],
    mask: npt.NDArray[np.float32],
    px: npt.NDArray[np.intp],
    py: npt.NDArray[np.intp],
    sel: npt.NDArray[np.bool_],
    d_ref: npt.NDArray[np.float32],
    score: npt.NDArray[np.float32],
    step: npt.NDArray[np.float32],
    p: ReconstructParams,
    shade: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None = None,
) -> None:
    """Refit the selected windows warped by ``shape``, in place, from ``d_ref``
    (:func:`refit_windows` with the warped passes' window and iterations)."""
    refit_windows(
        left_n, right_n, wl, wr, shape, mask, px, py, sel, d_ref, p.warp_window // 2,
        p.warp_iterations, d_ref, score, step, shade,
    )  # fmt: skip


def refit_windows(
    left_n: npt.NDArray[np.float32],
    right_n: npt.NDArray[np.float32],
    wl: npt.NDArray[np.float32],
    wr: npt.NDArray[np.float32],
    shape: npt.NDArray[np.float32],
    mask: npt.NDArray[np.float32],
    px: npt.NDArray[np.intp],
    py: npt.NDArray[np.intp],
    sel: npt.NDArray[np.bool_],
    start: npt.NDArray[np.float32],
    radius: int,
    iterations: int,
    out_d: npt.NDArray[np.float32],
    out_score: npt.NDArray[np.float32],
    out_step: npt.NDArray[np.float32],
    shade: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None = None,
) -> None:
    """Fit the selected windows warped by ``shape`` from the disparities ``start``, and
    write their fits to the outputs at the same rows: with
    :func:`.kernels.refine_warped`, or with ``shade`` (the surface coordinates of
    :func:`shading`) :func:`.kernels.refine_warped_shaded` and the ridge the guided
    windows use. ``start`` may be ``out_d``."""
    idx = np.nonzero(sel)[0]
    d2 = np.empty(len(idx), np.float32)
    s2 = np.empty(len(idx), np.float32)
    st2 = np.empty(len(idx), np.float32)
    pixels = (px[idx].astype(np.int64), py[idx].astype(np.int64), start[idx].astype(np.float32))
    fit = (radius, iterations, d2, s2, st2)
    if shade is None:
        kernels.refine_warped(left_n, right_n, wl, wr, shape, mask, *pixels, *fit)
    else:
        kernels.refine_warped_shaded(
            left_n, right_n, wl, wr, shape, mask, *shade, _SHADING_RIDGE, *pixels, *fit
        )
    out_d[idx], out_score[idx], out_step[idx] = d2, s2, st2


def guide_maps(guide: npt.NDArray[np.float32], p: ReconstructParams) -> tuple[Any, ...]:
    """What the warped kernels take of a guide's disparity field over a crop
    (NaN off the part): the field with 0 off the part, its mask (1 on the
    part), and with ``p.shading`` the surface coordinates and the windows on
    bends of :func:`shading` (else None, None)."""
    on_part = np.isfinite(guide)
    g_field = np.where(on_part, guide, 0.0).astype(np.float32)
    g_mask = on_part.astype(np.float32)
    if not p.shading:
        return g_field, g_mask, None, None
    shade, bent = shading(guide, p.warp_window, p.shading_bend)
    return g_field, g_mask, shade, bent


def shading(
    field_: npt.NDArray[np.floating[Any]], window: int, bend: float
) -> tuple[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]], npt.NDArray[np.bool_]]:
    """Surface coordinates for light that changes with the surface, and the windows on bends,
    of a CAD's disparity field (px, NaN off the part).

    The slopes ``(a, b)`` of the field (px/px, one-sided at its outline;
    :func:`.kernels.field_slopes`) are a function of the surface normal: scaled by
    ``_SHADING_SCALE`` (to about 1 on a bend), they are the coordinates whose
    quadratic monomials :func:`.kernels.refine_warped_shaded` fits the light
    with. A window of side ``window`` spans a bend where either slope varies,
    over its on-part pixels, by more than ``bend``.
    """
    on_part = np.isfinite(field_)
    a = np.empty(field_.shape, np.float32)
    b = np.empty(field_.shape, np.float32)
    kernels.field_slopes(np.ascontiguousarray(field_, dtype=np.float32), a, b)
    k = np.ones((window, window), np.uint8)
    # One set of buffers for both slopes: large images allocated afresh cost page
    # faults.
    hi, lo = np.empty_like(a), np.empty_like(a)
    hi_w, lo_w = np.empty_like(a), np.empty_like(a)
    bent = np.zeros(on_part.shape, np.bool_)
    for g in (a, b):
        kernels.range_inputs(g, on_part, hi, lo)
        cv2.dilate(hi, k, dst=hi_w)
        cv2.erode(lo, k, dst=lo_w)
        kernels.mark_wide(hi_w, lo_w, np.float32(bend), bent)
    scale = np.float32(_SHADING_SCALE)
    return (scale * a, scale * b), bent


__all__ = [
    "bends",
    "finish_pair",
    "guide_maps",
    "refit_windows",
    "shading",
    "warp",
    "warped_passes",
]
