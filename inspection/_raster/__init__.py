"""The numba kernels of the rig simulator: z-buffer, shading of every pixel, and sensor noise.

The renderer works in two steps per camera, so that lens distortion is exact
and triangle edges stay straight where they are straight:

1. :func:`rasterize` (:mod:`.zbuffer`) draws the mesh into an *ideal*
   (undistorted pinhole) buffer that stores, per ideal pixel, the depth and
   the index of the nearest face (a classic z-buffer; 1/z is interpolated,
   since it is the quantity that is linear in screen space).
2. :func:`shade_scene` (:mod:`.shading`) visits every *real* (distorted)
   pixel, takes its exact viewing ray (precomputed by undistortion), looks up
   the face seen along that ray in the ideal buffer, and intersects the ray
   with that face's plane. Geometry is therefore exact to floating point
   inside faces; which face a pixel sees is decided at the resolution of the
   buffer, and where the buffer holds no face near the ray (faces thinner than
   a pixel along an outline) by walking across the mesh's edges. A pixel on
   the part's outline is shaded along several rays through its area. The
   light it gets comes from :mod:`.flash`, the belt's from :mod:`.belt`.

The projector's shadow map is the same rasteriser run from the projector.
:func:`shade_board` renders the calibration board, :func:`sensor_noise`
(:mod:`.sensor`) turns irradiance into 8-bit pixels.

The kernels are serial and release the GIL: :mod:`inspection.simulate` runs
the cameras in parallel Python threads, which is safe under every numba
threading layer (numba's own ``parallel=True`` under the "workqueue" layer
aborts the process when two threads launch kernels at once).

Internal package: callers are trusted (shapes and dtypes are checked in
:mod:`inspection.simulate`).
"""

from __future__ import annotations

from .belt import belt_static
from .sensor import sensor_noise
from .shading import shade_board, shade_scene
from .zbuffer import NEAR_MM, rasterize

__all__ = ["NEAR_MM", "belt_static", "rasterize", "sensor_noise", "shade_board", "shade_scene"]
