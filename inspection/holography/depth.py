"""The CAD as the head sees it: height, normal and face of every pixel.

Orthographic along the head's -z: the faces are rasterised (z-buffer) onto
the pixel grid, and each pixel's height comes exactly from its face's plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .._raster.zbuffer import rasterize
from ..arrays import Transform, mesh_arrays
from ..errors import InvalidInput
from ..transforms import apply
from .head import HoloHead

# The z-buffer interpolates depth perspective-correctly; seen from this far away
# its interpolation is orthographic to well under a micrometre (visibility only:
# heights come from the face planes).
_VIEW_DISTANCE_MM = 1000.0


@dataclass(frozen=True)
class DepthMap:
    """The CAD surface under each pixel, head frame.

    Attributes
    ----------
    height_mm : (n, n) float64, mm
        z of the first surface along each pixel's ray; NaN where it misses.
    normals : (n, n, 3) float64
        Unit outward normal of that surface (z >= 0 for a visible face).
    face : (n, n) int64
        Index of the face hit, -1 where the ray misses.
    """

    height_mm: npt.NDArray[np.float64]
    normals: npt.NDArray[np.float64]
    face: npt.NDArray[np.int64]

    @property
    def hit(self) -> npt.NDArray[np.bool_]:
        return self.face >= 0

    def edges(self, jump_mm: float, band_px: int) -> npt.NDArray[np.bool_]:
        """Pixels within ``band_px`` of a height jump larger than ``jump_mm`` between
        neighbours, or of the surface's outline."""
        from scipy.ndimage import binary_dilation

        h = np.where(self.hit, self.height_mm, np.nan)
        edge = np.zeros(h.shape, dtype=bool)
        for axis in (0, 1):
            d = np.abs(np.diff(h, axis=axis))
            jump = ~(d <= jump_mm)  # NaN (an outline) counts as a jump
            if axis == 0:
                edge[:-1] |= jump
                edge[1:] |= jump
            else:
                edge[:, :-1] |= jump
                edge[:, 1:] |= jump
        if band_px > 0:
            edge = binary_dilation(edge, iterations=band_px)
        return edge | ~self.hit


def depth_map(head: HoloHead, mesh: object, T_head_part: Transform) -> DepthMap:
    """Rasterise ``mesh`` at the pose ``T_head_part`` under the head.

    Parameters
    ----------
    head : HoloHead
    mesh : anything with ``vertices`` (V, 3) and ``faces`` (F, 3), part frame, mm
    T_head_part : (4, 4) float64
        Maps part-frame points into the head frame.
    """
    vertices, faces = mesh_arrays(mesh)
    T = np.asarray(T_head_part, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InvalidInput(f"T_head_part must be a finite (4, 4) array, got shape {T.shape}")
    v = apply(T, vertices)
    n = head.pixels
    sx = v[:, 0] / head.pitch_mm + (n - 1) / 2.0
    sy = v[:, 1] / head.pitch_mm + (n - 1) / 2.0
    top = float(v[:, 2].max())
    sz = _VIEW_DISTANCE_MM + (top - v[:, 2])
    zbuf = np.full((n, n), np.inf, dtype=np.float32)
    fbuf = np.full((n, n), -1, dtype=np.int32)
    rasterize(sx, sy, sz, faces, zbuf, fbuf)

    # Face planes in the head frame: n . p = n . v0.
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    nrm = np.cross(b - a, c - a)
    length = np.linalg.norm(nrm, axis=1)
    nrm /= np.where(length > 0, length, 1.0)[:, None]
    nrm[nrm[:, 2] < 0] *= -1.0  # the visible side faces the head
    offset = np.einsum("ij,ij->i", nrm, a)

    face = fbuf.astype(np.int64)
    hit = face >= 0
    x, y = head.grid()
    height = np.full((n, n), np.nan)
    normals = np.zeros((n, n, 3))
    fh = face[hit]
    nz = nrm[fh, 2]
    height[hit] = (offset[fh] - nrm[fh, 0] * x[hit] - nrm[fh, 1] * y[hit]) / np.where(
        nz > 1e-9, nz, np.nan
    )
    normals[hit] = nrm[fh]
    face[hit & ~np.isfinite(height)] = -1
    return DepthMap(height_mm=height, normals=normals, face=face)
