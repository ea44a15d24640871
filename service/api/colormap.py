"""A top view of a part's deviations as a PNG picture (OpenCV).

Points are drawn in the CAD frame seen from +z, the highest point of each
pixel on top, coloured on a diverging scale: blue below the CAD, white on it,
red above, saturated at ``limit_mm`` (:func:`inspection.colours.deviation_colours`);
unmeasured points are grey. A colour bar with its scale is drawn on the right.
Each surface defect is outlined (a circle of the region's area, widened by
the search's support) and labelled with its number, kind and peak.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from inspection.colours import deviation_colours
from inspection.surface import SUPPORT_MM

_BACKGROUND = 40
_OUTLINE = (0, 215, 255)  # BGR amber: apart from the blue-white-red scale
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_FONT_SCALE = 0.45


@dataclass(frozen=True)
class Marker:
    """A surface defect to outline: where it is (CAD frame, mm), how large, and its label."""

    center_mm: tuple[float, float, float]
    area_mm2: float
    label: str


@dataclass(frozen=True)
class PointMark:
    """A comparison point to mark: where it is (CAD frame, mm), its name, and whether it failed."""

    position_mm: tuple[float, float, float]
    label: str
    failed: bool = False


def _bgr(deviations_mm: np.ndarray, limit_mm: float) -> np.ndarray:
    """(N, 3) uint8 BGR colours of signed deviations (OpenCV's channel order)."""
    return deviation_colours(deviations_mm, limit_mm)[:, ::-1]


def render_top_view(
    points: np.ndarray,
    distances: np.ndarray,
    *,
    limit_mm: float,
    size_px: int = 800,
    dot_px: int | None = None,
    title: str = "",
    markers: Sequence[Marker] = (),
    points_marked: Sequence[PointMark] = (),
    axes: bool = False,
) -> bytes:
    """PNG bytes of the deviation map.

    Parameters
    ----------
    points : (N, 3) float, CAD frame, mm
    distances : (N,) float, signed deviation, mm; NaN: not measured (grey)
    limit_mm : float
        Deviation at which the colours saturate (> 0).
    size_px : int
        Length of the map's longer side, pixels.
    dot_px : int, optional
        Typical spacing of the points in pixels; gaps up to 1.5 times it
        are filled. Default: from the point density.
    title : str
    markers : sequence of Marker
        Surface defects to outline and label.
    points_marked : sequence of PointMark
        Comparison points to mark with a cross and their name (failed ones in red).
    axes : bool
        Draw x and y axes with ticks in mm (CAD frame) left of and below the map.
    """
    if not limit_mm > 0:
        raise ValueError(f"limit_mm must be positive, got {limit_mm}")
    pts = np.asarray(points, dtype=np.float64)
    d = np.asarray(distances, dtype=np.float64)
    margin, bar_w = 20, 90
    left, bottom = (48, 36) if axes else (margin, margin)
    if len(pts):
        lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
    else:
        lo, hi = np.zeros(2), np.ones(2)
    span = np.maximum(hi - lo, 1e-6)
    scale = (size_px - 1) / float(span.max())
    w = int(np.ceil(span[0] * scale)) + 1
    h = int(np.ceil(span[1] * scale)) + 1
    if dot_px is None:
        # Points spread over the bounding box: about one per dot_px^2 pixels.
        dot_px = int(np.clip(np.ceil(np.sqrt(w * h / max(len(pts), 1))), 1, 8))
    img = np.full((h + margin + bottom, w + left + margin + bar_w, 3), _BACKGROUND, dtype=np.uint8)
    if len(pts):
        # The highest point wins a pixel: draw from low to high z.
        order = np.argsort(pts[:, 2], kind="stable")
        u = ((pts[order, 0] - lo[0]) * scale).round().astype(np.int64) + left
        # Image rows grow downwards; y grows upwards in the view from +z.
        v = ((hi[1] - pts[order, 1]) * scale).round().astype(np.int64) + margin
        img[v, u] = _bgr(d[order], limit_mm)
        drawn = np.zeros(img.shape[:2], dtype=bool)
        drawn[v, u] = True
        _fill_gaps(img, drawn, max_px=1.5 * dot_px)
    for k, mk in enumerate(markers, start=1):
        cx = int(round((mk.center_mm[0] - lo[0]) * scale)) + left
        cy = int(round((hi[1] - mk.center_mm[1]) * scale)) + margin
        radius = max(int(np.ceil((np.sqrt(max(mk.area_mm2, 0.0) / np.pi) + SUPPORT_MM) * scale)), 6)
        # A dark rim under the amber: the map behind it may be any colour, pale most often.
        cv2.circle(img, (cx, cy), radius, (0, 0, 0), 4, cv2.LINE_AA)
        cv2.circle(img, (cx, cy), radius, _OUTLINE, 2, cv2.LINE_AA)
        text = f"{k} {mk.label}"
        (tw, _), _ = cv2.getTextSize(text, _FONT, _FONT_SCALE, 1)
        # Right of the circle, or left of it where the text would leave the map.
        x = cx + radius + 3 if cx + radius + 3 + tw <= left + w else cx - radius - 3 - tw
        _label(img, text, (max(x, 0), cy + 4), _OUTLINE)
    for pm in points_marked:
        px = int(round((pm.position_mm[0] - lo[0]) * scale)) + left
        py = int(round((hi[1] - pm.position_mm[1]) * scale)) + margin
        colour = (40, 40, 230) if pm.failed else (255, 255, 255)
        cv2.drawMarker(img, (px, py), (0, 0, 0), cv2.MARKER_CROSS, 13, 3, cv2.LINE_AA)
        cv2.drawMarker(img, (px, py), colour, cv2.MARKER_CROSS, 11, 1, cv2.LINE_AA)
        _label(img, pm.label, (px + 7, py - 5), colour)
    if axes:
        _axes(img, lo=lo, hi=hi, scale=scale, x0=left, y0=margin, w=w, h=h)
    _colour_bar(img, x0=w + left + margin + 10, y0=margin, height=max(h, 120), limit_mm=limit_mm)
    if title:
        cv2.putText(img, title, (left, margin - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    (230, 230, 230), 1, cv2.LINE_AA)  # fmt: skip
    ok, png = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV always encodes a uint8 BGR image
        raise RuntimeError("PNG encoding failed")
    return png.tobytes()


def _label(img: np.ndarray, text: str, org: tuple[int, int], colour: tuple[int, int, int]) -> None:
    """``text`` at ``org`` in ``colour`` over a dark halo, legible on any part of the map."""
    cv2.putText(img, text, org, _FONT, _FONT_SCALE, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, _FONT, _FONT_SCALE, colour, 1, cv2.LINE_AA)


def _axes(
    img: np.ndarray,
    *,
    lo: np.ndarray,
    hi: np.ndarray,
    scale: float,
    x0: int,
    y0: int,
    w: int,
    h: int,
) -> None:
    """x (below) and y (left) axes of the CAD frame with ticks at round mm values."""
    font, colour = cv2.FONT_HERSHEY_SIMPLEX, (230, 230, 230)
    span = float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-6))
    step = next(s for s in (1, 2, 5, 10, 20, 25, 50, 100, 200, 250, 500, 1000, 1e9)
                if span / s <= 8)  # fmt: skip
    yb = y0 + h + 4
    cv2.line(img, (x0, yb), (x0 + w, yb), colour, 1)
    cv2.line(img, (x0 - 4, y0), (x0 - 4, y0 + h), colour, 1)
    for t in np.arange(np.ceil(lo[0] / step) * step, hi[0] + 1e-9, step):
        u = x0 + int(round((t - lo[0]) * scale))
        cv2.line(img, (u, yb), (u, yb + 4), colour, 1)
        cv2.putText(img, f"{t:g}", (u - 10, yb + 16), font, 0.35, colour, 1, cv2.LINE_AA)
    for t in np.arange(np.ceil(lo[1] / step) * step, hi[1] + 1e-9, step):
        v = y0 + int(round((hi[1] - t) * scale))
        cv2.line(img, (x0 - 8, v), (x0 - 4, v), colour, 1)
        cv2.putText(img, f"{t:g}", (2, v + 4), font, 0.35, colour, 1, cv2.LINE_AA)
    cv2.putText(img, "x mm", (x0 + w - 30, yb + 30), font, 0.4, colour, 1, cv2.LINE_AA)
    cv2.putText(img, "y mm", (2, y0 - 6), font, 0.4, colour, 1, cv2.LINE_AA)


def _fill_gaps(img: np.ndarray, drawn: np.ndarray, *, max_px: float) -> None:
    """Give each empty pixel within ``max_px`` of a drawn one that pixel's colour.

    Sampling gaps between points close up; real holes in the part (wider
    than the point spacing) stay empty.
    """
    empty = (~drawn).astype(np.uint8)
    dist, labels = cv2.distanceTransformWithLabels(
        empty, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
    )
    # Labels number the zero (drawn) pixels in row-major order, from 1.
    rows, cols = np.nonzero(~empty.astype(bool))
    fill = (empty == 1) & (dist <= max_px)
    src = labels[fill] - 1
    img[fill] = img[rows[src], cols[src]]


def _colour_bar(img: np.ndarray, *, x0: int, y0: int, height: int, limit_mm: float) -> None:
    height = min(height, img.shape[0] - y0 - 1)
    if height < 20:
        return
    # Top row +limit, bottom row -limit.
    img[y0 : y0 + height, x0 : x0 + 16] = _bgr(np.linspace(limit_mm, -limit_mm, height), limit_mm)[
        :, None, :
    ]
    font, colour = cv2.FONT_HERSHEY_SIMPLEX, (230, 230, 230)
    for frac, value in ((0.0, limit_mm), (0.5, 0.0), (1.0, -limit_mm)):
        y = y0 + int(frac * (height - 1))
        cv2.putText(img, f"{value:+.2f}", (x0 + 20, y + 4), font, 0.4, colour, 1, cv2.LINE_AA)
    cv2.putText(img, "mm", (x0 + 20, min(y0 + height + 14, img.shape[0] - 2)), font, 0.4, colour, 1)
