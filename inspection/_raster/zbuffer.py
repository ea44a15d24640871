"""The z-buffer: the nearest face of every pixel of an ideal (undistorted) image.

With it, :func:`in_face` tells whether a point of that image lies inside a
projected face (the shading's exact test near a face's edges).
"""

from __future__ import annotations

import math

from numba import njit

from .._jit import NO_RUNTIME

NEAR_MM = 1.0
"""Faces with a vertex closer than this to the image plane are skipped."""


@njit(cache=True, nogil=True, **NO_RUNTIME)
def rasterize(sx, sy, sz, faces, zbuf, fbuf):  # pragma: no cover - compiled
    """Z-buffer rasterisation of triangles.

    Parameters
    ----------
    sx, sy : (V,) float64
        Vertex positions in buffer pixels (pixel centres at integers).
    sz : (V,) float64, mm
        Vertex depth along the optical axis.
    faces : (F, 3) int64
    zbuf : (H, W) float32, mm
        Depth buffer, initialised to +inf; updated in place.
    fbuf : (H, W) int32
        Face index buffer, initialised to -1; updated in place.
    """
    H, W = zbuf.shape
    for f in range(faces.shape[0]):
        a = faces[f, 0]
        b = faces[f, 1]
        c = faces[f, 2]
        za = sz[a]
        zb = sz[b]
        zc = sz[c]
        if za < NEAR_MM or zb < NEAR_MM or zc < NEAR_MM:
            continue
        x0 = sx[a]
        y0 = sy[a]
        x1 = sx[b]
        y1 = sy[b]
        x2 = sx[c]
        y2 = sy[c]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        xmin = max(int(math.ceil(min(x0, min(x1, x2)))), 0)
        xmax = min(int(math.floor(max(x0, max(x1, x2)))), W - 1)
        ymin = max(int(math.ceil(min(y0, min(y1, y2)))), 0)
        ymax = min(int(math.floor(max(y0, max(y1, y2)))), H - 1)
        if xmin > xmax or ymin > ymax:
            continue
        inv = 1.0 / area
        iz0 = 1.0 / za
        iz1 = 1.0 / zb
        iz2 = 1.0 / zc
        # Barycentric weights are affine in (x, y): step them incrementally.
        # w0 = ((x1 - x)(y2 - y) - (x2 - x)(y1 - y)) / area, likewise w1.
        dw0dx = (y1 - y2) * inv
        dw1dx = (y2 - y0) * inv
        for y in range(ymin, ymax + 1):
            w0 = ((x1 - xmin) * (y2 - y) - (x2 - xmin) * (y1 - y)) * inv
            w1 = ((x2 - xmin) * (y0 - y) - (x0 - xmin) * (y2 - y)) * inv
            for x in range(xmin, xmax + 1):
                w2 = 1.0 - w0 - w1
                if w0 >= -1e-9 and w1 >= -1e-9 and w2 >= -1e-9:
                    z = 1.0 / (w0 * iz0 + w1 * iz1 + w2 * iz2)
                    if z < zbuf[y, x]:
                        zbuf[y, x] = z
                        fbuf[y, x] = f
                w0 += dw0dx
                w1 += dw1dx


@njit(cache=True, nogil=True, inline="always")
def in_face(sx, sy, faces, f, pu, pv):  # pragma: no cover - compiled
    """Is the point (pu, pv) inside projected face f (either winding, 1e-9 tolerance)?"""
    a = faces[f, 0]
    b = faces[f, 1]
    c = faces[f, 2]
    x0 = sx[a]
    y0 = sy[a]
    x1 = sx[b]
    y1 = sy[b]
    x2 = sx[c]
    y2 = sy[c]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    if area == 0.0:
        return False
    w0 = ((x1 - pu) * (y2 - pv) - (x2 - pu) * (y1 - pv)) / area
    w1 = ((x2 - pu) * (y0 - pv) - (x0 - pu) * (y2 - pv)) / area
    return w0 >= -1e-9 and w1 >= -1e-9 and 1.0 - w0 - w1 >= -1e-9
