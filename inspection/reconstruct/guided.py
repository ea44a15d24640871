"""What the part's CAD tells the matching: its heights, and at a fitted pose its shape.

A :class:`Prior` (the band of heights a part lying on the belt can occupy)
narrows the disparities the coarse matching searches, which makes it faster
and less ambiguous.

**CAD-guided matching.** The windows of the first pass take their shape from
the measured field, which is itself smoothed where the surface bends. Once
the part is aligned, a :class:`Guide` (its CAD at the fitted pose) gives the
shape exactly: each pair's disparity field is rendered from the CAD into the
rectified left view (:func:`guide_disparity`, the simulator's z-buffer, exact
for planar faces since ``1/z`` is interpolated) and the windows are warped by
it where it agrees with the measured field (:mod:`.warping`). A guided pass
starts from the first pass's square windows (a
:class:`~inspection.reconstruct.Matching`), so it runs only the warped passes,
the triangulation and the fusion again.

**The ring pairs.** The rig's two other pairs (cam0-cam2, cam1-cam3,
baselines along y) see the part with independent speckle windows and the
walls facing +-x head on. With a guide they need no coarse search: each is
started from the guide's disparities where the CAD is seen, refined with
square windows and then warped like the other pairs (:func:`ring_pair`).

**Matching the bends again.** A guided window is fitted for its centre's
disparity only; its shape is the guide's. Where the guide sits a little off,
a bend's shape lands beside the real one, and the window's disparity is
pulled towards the guide where the slope changes inside the window; on a
character line that pull is the same all along it, and turns the fitted
part. After the guided cloud has been fitted, :func:`rematch_pair` fits
again, from their guided fit, only the windows that span a bend or reach the
outline of a guide at the new pose; every other window keeps its match.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from .._raster import rasterize
from ..arrays import Points, mesh_arrays
from ..errors import InvalidInput
from ..transforms import apply
from ..validate import validate_transform
from . import kernels
from .matching import PairFrame, PairResult, PairState, crops, grid_pixels, triangulate_state
from .pairs import RectifiedPair, rectify
from .params import SATURATION_DN, ReconstructParams
from .result import PairReport
from .warping import bends, finish_pair, guide_maps, warp


@dataclass(frozen=True)
class Prior:
    """What is known about the part before matching: the band of heights it can occupy.

    Attributes
    ----------
    z_max_mm : float
        Highest point of the part above the belt (mm), with margin.
    """

    z_max_mm: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.z_max_mm) and self.z_max_mm > 0):
            raise InvalidInput(f"Prior.z_max_mm must be finite and > 0, got {self.z_max_mm!r}")

    @classmethod
    def from_cad(cls, cad: Any, *, margin_mm: float = 10.0) -> Prior:
        """The height band of a part lying on the belt on one of its large faces.

        The part's height is bounded by the smallest extent of its principal
        (inertia) box: a sheet-metal part rests on its flange or its face,
        never on an edge. Parts that may stand upright need an explicit
        :class:`Prior` (or none).

        Parameters
        ----------
        cad : CadModel or trimesh.Trimesh or (V, 3) array of vertices (mm)
        margin_mm : float
            Added to the height (tilt, warp, tolerance).
        """
        v = np.asarray(
            cad if isinstance(cad, np.ndarray) else mesh_arrays(cad)[0], dtype=np.float64
        )
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or not np.all(np.isfinite(v)):
            raise InvalidInput("Prior.from_cad needs a mesh or an (N, 3) array of finite vertices")
        c = v - v.mean(axis=0)
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        extent = np.ptp(c @ vt.T, axis=0)
        return cls(float(extent.min()) + margin_mm)


@dataclass(frozen=True, eq=False)
class Guide:
    """The part's CAD at its fitted pose: the shape that the matching windows follow.

    See "CAD-guided matching" in the module notes. Build it with
    :meth:`from_cad` from the first alignment of an unguided cloud, and match
    the same frames again with it (:meth:`Reconstructor.guided`).

    Attributes
    ----------
    vertices : (V, 3) float64, mm, rig frame
        The CAD's vertices at the fitted pose.
    faces : (F, 3) int64
    """

    vertices: Points
    faces: npt.NDArray[np.int64]

    @classmethod
    def from_cad(cls, cad: Any, T_rig_part: npt.ArrayLike) -> Guide:
        """The guide of ``cad`` (CadModel or trimesh.Trimesh, part frame) posed by ``T_rig_part``.

        Parameters
        ----------
        cad : CadModel or trimesh.Trimesh
            Anything with ``vertices`` (V, 3) and ``faces`` (F, 3).
        T_rig_part : (4, 4) array
            Maps part-frame points into the rig frame: the inverse of a
            registration's ``transform`` (T_cad_rig).
        """
        v, f = mesh_arrays(cad)
        T = validate_transform(T_rig_part, name="T_rig_part")
        return cls(apply(T, v), f)


def guide_disparity(pair: RectifiedPair, guide: Guide) -> npt.NDArray[np.float32]:
    """The guide's disparity at every rectified left pixel of ``pair`` (NaN: not on the part).

    The CAD is drawn into the rectified left view with the simulator's
    z-buffer rasteriser (exact for planar faces: 1/z is interpolated).
    """
    q = pair.to_rect(guide.vertices)
    z = q[:, 2]
    w, h = pair.size
    zbuf = np.full((h, w), np.inf, np.float32)
    fbuf = np.full((h, w), -1, np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = pair.f_px * q[:, 0] / z + pair.cx_left
        sy = pair.f_px * q[:, 1] / z + pair.cy
    rasterize(sx, sy, z, guide.faces, zbuf, fbuf)
    seen = np.isfinite(zbuf)
    out = np.full((h, w), np.nan, np.float32)
    out[seen] = pair.fb / zbuf[seen].astype(np.float64) + pair.offset_px
    return out


def finish_guided(
    pair: RectifiedPair,
    st: PairState,
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
    guide: Guide,
    guide_field: npt.NDArray[np.float32] | None = None,
) -> PairResult:
    """The guided passes and the triangulation of one pair, from its square windows
    ``st`` (``guide_field``: the guide's disparities, :func:`guide_disparity`, when
    already drawn)."""
    t = time.perf_counter()
    if guide_field is None:
        guide_field = guide_disparity(pair, guide)
    shape = guide_field[st.roi] + np.float32(st.shift)
    timings[f"guide{k}"] = (time.perf_counter() - t) * 1e3
    return finish_pair(pair, st, p, timings, k, shape)


def ring_pair(
    pair: RectifiedPair,
    frames: Sequence[npt.NDArray[np.uint8]],
    guide: Guide,
    lo: npt.NDArray[np.float64],
    hi: npt.NDArray[np.float64],
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
) -> PairResult:
    """A pair matched only with a guide (pair ``k`` of the reconstructor's
    ``pairs + guide_pairs``): started from the guide's disparities where the CAD is seen
    (no coarse search), a square-window refinement, then the guided passes of the
    other pairs. ``lo``, ``hi``: the volume searched (rig frame, mm)."""
    t = time.perf_counter()
    left = rectify(frames[pair.left], pair.maps_left)
    right = rectify(frames[pair.right], pair.maps_right)
    sat_l = left >= SATURATION_DN - 0.5
    sat_r = right >= SATURATION_DN - 0.5
    g = guide_disparity(pair, guide)
    seen = np.isfinite(g)
    if not seen.any():
        return PairResult(PairReport(pair.name), np.zeros((0, 3)), np.zeros(0, np.float32))
    d_min, d_max = float(g[seen].min()), float(g[seen].max())
    report = PairReport(pair.name, foreground=int(seen.sum()), disparity_range=(d_min, d_max))
    frame = PairFrame(g.shape, lo, hi, report, None)
    roi, x0, y0, rx0, left_n, right_n, wl, wr = crops(
        left, right, sat_l, sat_r, seen, d_min, d_max, p
    )
    py, px = grid_pixels(seen[roi] & ~sat_l[roi], x0, y0, p.stride, p.row_stride)
    d_init = g[roi][py, px].astype(np.float32)
    shift = float(rx0 - x0)
    d_sq = np.empty(len(px), np.float32)
    score = np.empty(len(px), np.float32)
    step = np.empty(len(px), np.float32)
    fit = (p.window // 2, p.iterations, d_sq, score, step)
    start = (d_init + shift).astype(np.float32)
    kernels.refine_pixels(
        left_n, right_n, wl, wr, px.astype(np.int64), py.astype(np.int64), start, *fit
    )
    timings[f"refine{k}"] = (time.perf_counter() - t) * 1e3
    state = PairState(
        left_n, right_n, wl, wr, px, py, d_init, d_sq, score, step, shift, x0, y0, roi, frame
    )
    return finish_guided(pair, state, p, timings, k, guide, g)


def rematch_pair(
    pair: RectifiedPair,
    st: PairState,
    guided: tuple[npt.NDArray[np.float32], ...],
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
    guide: Guide,
) -> PairResult:
    """One pair of :meth:`Reconstructor.rematch_bends
    <inspection.reconstruct.Reconstructor.rematch_bends>`: the guided windows that span a
    bend or reach the outline of ``guide``, warped by it again from their guided fit."""
    t = time.perf_counter()
    shape = guide_disparity(pair, guide)[st.roi] + np.float32(st.shift)
    d_ref, score, step = (a.copy() for a in guided)
    g_field, g_mask, shade, bent = guide_maps(shape, p)
    px, py = st.px, st.py
    ok = (
        np.isfinite(d_ref)
        & (score >= p.min_score)
        & (np.abs(d_ref - (st.d_init + st.shift)) <= p.max_shift_px)
        & (g_mask[py, px] > 0.0)
        & (np.abs(g_field[py, px] - d_ref) <= p.guide_tolerance_px)
    )
    kw = (p.warp_window, p.warp_window)
    inside = cv2.boxFilter(g_mask, cv2.CV_32F, kw, normalize=False, borderType=cv2.BORDER_CONSTANT)
    outline = inside < p.warp_window * p.warp_window - 0.5
    images = (st.left_n, st.right_n, st.wl, st.wr, g_field, g_mask, px, py)
    if bent is not None:
        warp(*images, ok & bent[py, px], d_ref, score, step, p, shade)
        plain = ok & ~bent[py, px] & outline[py, px]
    else:
        plain = ok & (bends(g_field, g_mask, px, py, p) | outline[py, px])
    warp(*images, plain, d_ref, score, step, p)
    timings[f"rematch{k}"] = (time.perf_counter() - t) * 1e3
    return triangulate_state(pair, st, (d_ref, score, step), p, timings, k, True)


__all__ = ["Guide", "Prior", "finish_guided", "guide_disparity", "rematch_pair", "ring_pair"]
