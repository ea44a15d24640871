"""The motion blur of a flash: which shifts of the part along the belt a frame averages.

The belt moves the part during the flash while the projector and cameras stay
put, so a frame is the mean of instants; how many instants a frame needs is
decided by how far the travel moves the scene in the images, measured here
cheaply (a bound first) so that a short flash costs next to nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .. import _raster
from .scene import _CameraSetup

MIN_SMEAR_PX = 0.2
"""A motion smear shorter than this (pixels) is not rendered: its spread (0.06 px RMS)
widens the 0.6 px optical blur by half a percent."""
SUB_EXPOSURE_PX = 1.0
"""Largest image step between the sub-exposures of a smeared frame, pixels: the optical
blur (0.6 px) leaves 0.1 % of a ripple at that spacing."""


@dataclass(frozen=True, eq=False)
class _SubExposure:
    """The scene at one instant of the flash: the part moved ``shift_mm`` along +x."""

    shift_mm: float
    V: npt.NDArray[np.float64]  # (V, 3) vertices, rig frame
    d_rig: npt.NDArray[np.float64]  # (F,) plane offsets n . v of the faces
    smap_z: npt.NDArray[np.float32]  # projector's shadow map
    smap_f: npt.NDArray[np.int32]
    dirt_c: npt.NDArray[np.float64]  # (k, 3) dirt centres


def _sub_exposure_shifts(
    V: npt.NDArray[np.float64], travel_mm: float, cams: list[_CameraSetup]
) -> list[float]:
    """Shifts along +x (mm) of the part at the instants a frame averages over the flash.

    ``[0.0]`` (one instant) when the travel smears no vertex of the part nor
    the belt by :data:`MIN_SMEAR_PX` in any image; otherwise an odd number
    of instants, evenly over the travel (midpoints, the middle one at 0)
    and at most :data:`SUB_EXPOSURE_PX` apart in every image.
    """
    if travel_mm == 0.0:
        return [0.0]
    step = np.array([travel_mm, 0.0, 0.0])
    X = np.concatenate([V, *(s.belt_probes for s in cams)])
    # A bound first (one depth per point), so that a short flash costs next to nothing.
    if max(_image_travel_bound(X, step, s) for s in cams) < MIN_SMEAR_PX:
        return [0.0]
    smear_px = max(_image_travel(X, step, s.camera.R, s.camera.t, s.kvec) for s in cams)
    if smear_px < MIN_SMEAR_PX:
        return [0.0]
    count = int(np.ceil(smear_px / SUB_EXPOSURE_PX)) + 1
    count += 1 - count % 2
    return [travel_mm * ((k + 0.5) / count - 0.5) for k in range(count)]


def _image_travel(X, step, R, t, kvec) -> float:
    """The longest image displacement (pixels, pinhole) of points ``X`` (N, 3) moved by
    ``step`` (3,), over those in front of a camera (R, t, K as ``kvec``)."""
    a = X @ R.T + t
    b = a + R @ step
    front = (a[:, 2] > _raster.NEAR_MM) & (b[:, 2] > _raster.NEAR_MM)
    a, b = a[front], b[front]
    if len(a) == 0:
        return 0.0
    ax, ay = a[:, 0] / a[:, 2], a[:, 1] / a[:, 2]
    bx, by = b[:, 0] / b[:, 2], b[:, 1] / b[:, 2]
    du = kvec[0] * (bx - ax) + kvec[1] * (by - ay)
    dv = kvec[3] * (by - ay)
    return float(np.sqrt((du * du + dv * dv).max()))


def _image_travel_bound(X, step, setup: _CameraSetup) -> float:
    """An upper bound of :func:`_image_travel` over the points ``X`` that the camera sees.

    A point at depth z moved by d (camera frame) moves by at most
    (|d_xy| + sqrt(2) r |d_z|) / (z - |d_z|) in normalised coordinates, r the
    largest |x/z| or |y/z| in the image, and K stretches that by at most
    max(fx, fy) + |skew|.
    """
    cam = setup.camera
    d = cam.R @ step
    dz = abs(float(d[2]))
    z = X @ cam.R[2] + cam.t[2]
    z_min = float(z[z > _raster.NEAR_MM].min(initial=np.inf)) - dz
    if not z_min > _raster.NEAR_MM:
        return np.inf
    k = setup.kvec
    gain = max(abs(k[0]), abs(k[3])) + abs(k[1])
    return gain * (float(np.hypot(d[0], d[1])) + np.sqrt(2.0) * setup.ray_extent * dz) / z_min
