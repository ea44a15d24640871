"""The four-camera flash rig: cameras, pattern projector and conveyor, as TOML.

The rig frame (DESIGN.md §3): origin at the centre of the measurement volume
on the conveyor surface, x along the conveyor's motion (the 800 mm side), y
across it (500 mm), z up (200 mm). Units are millimetres.

Layout of the rig as built (:meth:`Rig.nominal`), seen from above::

        y ^
          |   cam2 (-250, +300)        cam3 (+250, +300)
          |
          |               projector (0, 0)
          |        +---------------------------+
          |        |   measurement volume      |  500 mm across
          |        +---------------------------+
          |   cam0 (-250, -300)        cam1 (+250, -300)
          +-------------------------------------------> x (conveyor motion)

All four cameras hang 1300 mm above the belt and look at the centre of the
volume (0, 0, 100). Why this layout:

- **Two stereo pairs with baselines along x** (cam0-cam1 and cam2-cam3, 500 mm
  each, ~21° between the views at 1.35 m). Each pair is rectified with small
  rotations (the image x axes already point along rig x), so epipolar lines
  stay close to the image rows and SGBM's disparity search is short. The two
  pairs look from opposite sides in y, so a flange or a hole wall hidden from
  one pair is usually seen by the other: the pairs complement each other's
  occlusions. 500 mm of baseline at ~1.35 m gives ~2.2 mm of depth per
  pixel of disparity at the belt (z^2 / (f b)): 0.1 px of matching gives
  ~0.2 mm per point, and pooling the points within a comparison point's
  support radius brings it below 0.05 mm.
- **The ring pairs** cam0-cam2 and cam1-cam3 (600 mm baselines along y) are
  also usable (:attr:`Rig.ring_pairs`) where time allows: they see walls that
  face ±x, which the x pairs see at grazing angles.
- **8 mm lenses on 1280 x 1024 sensors with 4.8 µm pixels** (f ≈ 1667 px):
  the smallest standard focal length that still makes every camera see the
  whole 800 x 500 x 200 mm volume, including the top corners, with ~40 px to
  spare. A pixel covers ~0.8 mm on the belt.
- **The projector** hangs in the middle, 1300 mm up, looking straight down, so
  it lights everything the cameras see except the far side of steep walls.

The pattern is a **random binary speckle** (:class:`Pattern`), not fringes:
the part moves at ~1 m/s and is captured in a single flash, and phase-shifted
fringes need several exposures of a still scene (or accept motion blur and
phase errors). A random speckle gives every pixel neighbourhood a unique
texture, which is exactly what single-shot stereo block matching (SGBM) needs,
on bare sheet metal that has no texture of its own. The speckle grain is set to
~3 camera pixels on the part, coarse enough to survive the lens blur, fine
enough for dense matching.

Cameras follow OpenCV's model: ``X_cam = R @ X_rig + t`` then pinhole ``K``
with distortion ``(k1, k2, p1, p2, k3)``; image x to the right, y down, z
forward; pixel centres at integer coordinates.
"""

from __future__ import annotations

import hashlib
import importlib.resources
import logging
import math
import os
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .arrays import Points, Transform
from .errors import InvalidInput

log = logging.getLogger(__name__)

RIG_FORMAT = "inspection-rig/1"
ENV_RIG = "INSPECTION_RIG"
"""Environment variable naming a rig TOML file that :meth:`Rig.default` reads instead."""

DEFAULT_RIG_DATA = "data/rig.toml"
"""The calibrated rig shipped with the package: package data of ``inspection``
(``inspection/data/rig.toml``, declared in pyproject.toml), so that an installed
wheel has it. :meth:`Rig.default` reads it."""

# The measurement volume (x, y, z extents, mm) the nominal rig is built for.
VOLUME_MM = (800.0, 500.0, 200.0)

# Undistortion: fixed-point iterations converge by a factor ~3*k1*r^2 (< 0.1
# for our lenses) per step; 30 steps reach machine precision with room to spare.
_UNDISTORT_ITERATIONS = 30


def _as_matrix(value: Any, shape: tuple[int, ...], what: str) -> npt.NDArray[np.float64]:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{what} must be numeric with shape {shape}") from exc
    if arr.shape != shape:
        raise InvalidInput(f"{what} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInput(f"{what} must be finite")
    arr.setflags(write=False)
    return arr


def _check_points(points: Any) -> Points:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInput(f"points must have shape (N, 3), got {arr.shape}")
    return arr


def _check_pixels(pixels: Any) -> npt.NDArray[np.float64]:
    arr = np.asarray(pixels, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InvalidInput(f"pixels must have shape (N, 2), got {arr.shape}")
    return arr


def distort_normalized(
    xy: npt.NDArray[np.float64], dist: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """Apply OpenCV's radial-tangential distortion to normalised coordinates.

    Parameters
    ----------
    xy : (N, 2) float64
        Ideal normalised image coordinates (x/z, y/z).
    dist : (5,) float64
        k1, k2, p1, p2, k3.

    Returns
    -------
    (N, 2) float64
        Distorted normalised coordinates.
    """
    k1, k2, p1, p2, k3 = dist
    x = xy[:, 0]
    y = xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def undistort_normalized(
    xy_d: npt.NDArray[np.float64], dist: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """Invert :func:`distort_normalized` by fixed-point iteration.

    OpenCV's ``undistortPoints`` stops after 5 iterations by default, which
    leaves errors of ~0.01 px at the corners of our lenses; calibration and
    rendering need the exact inverse, so iterate to convergence.

    Parameters
    ----------
    xy_d : (N, 2) float64
        Distorted normalised coordinates.
    dist : (5,) float64

    Returns
    -------
    (N, 2) float64
        Ideal normalised coordinates.
    """
    k1, k2, p1, p2, k3 = dist
    xd = xy_d[:, 0]
    yd = xy_d[:, 1]
    x = xd.copy()
    y = yd.copy()
    for _ in range(_UNDISTORT_ITERATIONS):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x_new = (xd - dx) / radial
        y_new = (yd - dy) / radial
        # Converged to ~1e-10 px at f ~ 2000 px: further steps change nothing.
        step = max(
            float(np.max(np.abs(x_new - x), initial=0.0)),
            float(np.max(np.abs(y_new - y), initial=0.0)),
        )
        x, y = x_new, y_new
        if step < 1e-14:
            break
    return np.stack([x, y], axis=1)


def look_at(
    centre: npt.ArrayLike, target: npt.ArrayLike, right: npt.ArrayLike = (1.0, 0.0, 0.0)
) -> npt.NDArray[np.float64]:
    """Rotation rig -> camera for a camera at ``centre`` looking at ``target``.

    Parameters
    ----------
    centre, target : (3,) float64, mm, rig frame
    right : (3,) float64
        Direction in the rig frame that the image x axis should follow as
        closely as possible.

    Returns
    -------
    R : (3, 3) float64
        Rows are the camera axes (x right, y down, z forward) in the rig frame.
    """
    c = np.asarray(centre, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - c
    z /= np.linalg.norm(z)
    x = np.asarray(right, dtype=np.float64)
    x = x - z * (x @ z)
    norm = np.linalg.norm(x)
    if norm < 1e-9:
        raise InvalidInput("look_at: 'right' is parallel to the viewing direction")
    x /= norm
    y = np.cross(z, x)
    return np.stack([x, y, z])


def belt_pose(x_mm: float, y_mm: float, yaw_deg: float, z_mm: float = 0.0) -> Transform:
    """Pose of a part on the belt: turned by ``yaw_deg`` about the rig's vertical
    (z), then moved to (``x_mm``, ``y_mm``, ``z_mm``).

    Returns
    -------
    T_rig_part : (4, 4) float64
        Maps part-frame points into the rig frame; a part resting on its own
        z = 0 plane lies on the belt for ``z_mm`` = 0.
    """
    if not np.isfinite([x_mm, y_mm, yaw_deg, z_mm]).all():
        raise InvalidInput("belt_pose needs finite x_mm, y_mm, yaw_deg and z_mm")
    a = np.deg2rad(yaw_deg)
    c, s = np.cos(a), np.sin(a)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x_mm, y_mm, z_mm)
    return T


def _rotation_ok(R: npt.NDArray[np.float64], what: str) -> None:
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0.0:
        raise InvalidInput(f"{what} must be a rotation matrix (orthonormal, det +1)")


@dataclass(frozen=True, eq=False)
class Camera:
    """One camera in OpenCV's model.

    Attributes
    ----------
    name : str
    width, height : int
        Image size in pixels.
    K : (3, 3) float64
        Intrinsic matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, pixels.
    dist : (5,) float64
        Distortion k1, k2, p1, p2, k3 (OpenCV order).
    R : (3, 3) float64
        Rotation rig -> camera.
    t : (3,) float64, mm
        Translation rig -> camera: ``X_cam = R @ X_rig + t``.
    """

    name: str
    width: int
    height: int
    K: npt.NDArray[np.float64]
    dist: npt.NDArray[np.float64]
    R: npt.NDArray[np.float64]
    t: npt.NDArray[np.float64]

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise InvalidInput("camera name must be a non-empty string")
        for attr in ("width", "height"):
            value = getattr(self, attr)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, np.integer))
                or not 16 <= value <= 20000
            ):
                raise InvalidInput(
                    f"camera {self.name}: {attr} must be an int in [16, 20000], got {value!r}"
                )
            object.__setattr__(self, attr, int(value))
        K = _as_matrix(self.K, (3, 3), f"camera {self.name}: K")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
            raise InvalidInput(
                f"camera {self.name}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
                "with fx, fy > 0"
            )
        R = _as_matrix(self.R, (3, 3), f"camera {self.name}: R")
        _rotation_ok(R, f"camera {self.name}: R")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", _as_matrix(self.dist, (5,), f"camera {self.name}: dist"))
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", _as_matrix(self.t, (3,), f"camera {self.name}: t"))

    # -- poses ---------------------------------------------------------------
    @property
    def centre(self) -> npt.NDArray[np.float64]:
        """(3,) float64, mm: the optical centre in the rig frame (``-R.T @ t``)."""
        return -self.R.T @ self.t

    @property
    def T_cam_rig(self) -> Transform:
        """(4, 4) float64: maps rig-frame points into the camera frame."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    @property
    def T_rig_cam(self) -> Transform:
        """(4, 4) float64: maps camera-frame points into the rig frame."""
        T = np.eye(4)
        T[:3, :3] = self.R.T
        T[:3, 3] = self.centre
        return T

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels, OpenCV's order."""
        return (self.width, self.height)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width): the numpy shape of this camera's images."""
        return (self.height, self.width)

    # -- projection ----------------------------------------------------------
    def to_camera(self, points_rig: npt.ArrayLike) -> Points:
        """Rig-frame points (N, 3) mm -> camera-frame points (N, 3) mm."""
        pts = _check_points(points_rig)
        return pts @ self.R.T + self.t

    def project(self, points_rig: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Project rig-frame points to distorted pixel coordinates.

        Parameters
        ----------
        points_rig : (N, 3) float64, mm, rig frame

        Returns
        -------
        (N, 2) float64
            Pixel coordinates (x right, y down). Points at or behind the
            camera plane get NaN.
        """
        pc = self.to_camera(points_rig)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = pc[:, :2] / z[:, None]
        xy[z <= 1e-9] = np.nan
        return self.normalized_to_pixels(distort_normalized(xy, self.dist))

    def normalized_to_pixels(self, xy_d: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Distorted normalised coordinates (N, 2) -> pixels (N, 2) through K."""
        K = self.K
        u = K[0, 0] * xy_d[:, 0] + K[0, 1] * xy_d[:, 1] + K[0, 2]
        v = K[1, 1] * xy_d[:, 1] + K[1, 2]
        return np.stack([u, v], axis=1)

    def undistort(self, pixels: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Distorted pixels (N, 2) -> ideal normalised coordinates (N, 2) (x/z, y/z)."""
        px = _check_pixels(pixels)
        K = self.K
        yd = (px[:, 1] - K[1, 2]) / K[1, 1]
        xd = (px[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        return undistort_normalized(np.stack([xd, yd], axis=1), self.dist)

    def rays(
        self, pixels: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Viewing rays of pixels, in the rig frame.

        Parameters
        ----------
        pixels : (N, 2) float64
            Distorted pixel coordinates.

        Returns
        -------
        origins : (N, 3) float64, mm
            The camera centre, repeated.
        directions : (N, 3) float64
            Unit directions in the rig frame.
        """
        xy = self.undistort(pixels)
        d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        d = d_cam @ self.R  # R.T @ d for each row
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.centre, d.shape).copy(), d

    def pixel_grid(self) -> npt.NDArray[np.float64]:
        """(H*W, 2) float64: the centres of all pixels, row by row."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)

    def with_size(self, width: int, height: int) -> Camera:
        """The same camera with the image scaled to ``width`` x ``height`` (K scaled)."""
        sx = width / self.width
        sy = height / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        # Pixel centres sit at integer coordinates: keep the image edges fixed.
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return Camera(self.name, width, height, K, self.dist, self.R, self.t)


@dataclass(frozen=True)
class Pattern:
    """The projected pattern: a random binary speckle, blurred by the optics.

    Attributes
    ----------
    kind : str
        ``"speckle"`` (the only kind: see the module docstring for why).
    seed : int
        Seed of the random pattern (the pattern is a property of the projector
        slide, fixed for a rig).
    grain_px : float
        Correlation length of the speckle in projector pixels (the standard
        deviation of the Gaussian that smooths the white noise before it is
        thresholded into black and white).
    blur_px : float
        Optical blur of the projector (Gaussian sigma, projector pixels).
    low, high : float
        Relative intensity of dark and bright speckle (a projector never
        reaches black).
    """

    kind: str = "speckle"
    seed: int = 7
    grain_px: float = 1.6
    blur_px: float = 0.7
    low: float = 0.2
    high: float = 1.0

    def __post_init__(self) -> None:
        if self.kind != "speckle":
            raise InvalidInput(f"pattern kind must be 'speckle', got {self.kind!r}")
        if not (self.grain_px > 0 and self.blur_px >= 0 and 0.0 <= self.low < self.high <= 1.0):
            raise InvalidInput("pattern needs grain_px > 0, blur_px >= 0 and 0 <= low < high <= 1")

    def image(self, width: int, height: int) -> npt.NDArray[np.float32]:
        """Render the slide.

        Returns
        -------
        (height, width) float32
            Relative intensity in [low, high].
        """
        import cv2

        rng = np.random.default_rng(self.seed)
        noise = rng.standard_normal((height, width), dtype=np.float32)
        smooth = cv2.GaussianBlur(noise, (0, 0), self.grain_px, borderType=cv2.BORDER_REFLECT)
        binary = (np.asarray(smooth) > 0).astype(np.float32)
        if self.blur_px > 0:
            binary = np.asarray(
                cv2.GaussianBlur(binary, (0, 0), self.blur_px, borderType=cv2.BORDER_REFLECT),
                dtype=np.float32,
            )
        return (self.low + (self.high - self.low) * binary).astype(np.float32)


@dataclass(frozen=True, eq=False)
class Projector:
    """The flash: a pinhole projector (no distortion) with a speckle slide.

    Attributes
    ----------
    width, height : int
        Slide resolution in projector pixels.
    K : (3, 3) float64
        Intrinsics of the projector lens, pixels.
    R : (3, 3) float64
        Rotation rig -> projector.
    t : (3,) float64, mm
        Translation rig -> projector.
    pattern : Pattern
    power : float
        Irradiance scale of the flash at 1300 mm (1.0 nominal).
    """

    width: int
    height: int
    K: npt.NDArray[np.float64]
    R: npt.NDArray[np.float64]
    t: npt.NDArray[np.float64]
    pattern: Pattern = field(default_factory=Pattern)
    power: float = 1.0

    def __post_init__(self) -> None:
        for attr in ("width", "height"):
            value = getattr(self, attr)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, np.integer))
                or not 16 <= value <= 20000
            ):
                raise InvalidInput(f"projector {attr} must be an int in [16, 20000], got {value!r}")
            object.__setattr__(self, attr, int(value))
        K = _as_matrix(self.K, (3, 3), "projector K")
        R = _as_matrix(self.R, (3, 3), "projector R")
        _rotation_ok(R, "projector R")
        if not (self.power > 0 and math.isfinite(self.power)):
            raise InvalidInput("projector power must be positive")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", _as_matrix(self.t, (3,), "projector t"))

    @property
    def centre(self) -> npt.NDArray[np.float64]:
        """(3,) float64, mm: the projector's optical centre in the rig frame."""
        return -self.R.T @ self.t

    def project(self, points_rig: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Rig-frame points (N, 3) mm -> slide pixel coordinates (N, 2)."""
        pc = _check_points(points_rig) @ self.R.T + self.t
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = pc[:, :2] / pc[:, 2:3]
        return np.stack(
            [
                self.K[0, 0] * xy[:, 0] + self.K[0, 1] * xy[:, 1] + self.K[0, 2],
                self.K[1, 1] * xy[:, 1] + self.K[1, 2],
            ],
            axis=1,
        )


@dataclass(frozen=True)
class Conveyor:
    """The belt under the rig.

    Attributes
    ----------
    speed_mm_s : float
        Belt speed along +x, mm/s.
    surface_z_mm : float
        Height of the belt surface in the rig frame (0 by definition of the frame).
    width_mm : float
        Belt width across y (the belt ends at ``|y| = width_mm / 2``; beyond it
        the cameras see the dark machine floor).
    albedo : float
        Mean diffuse reflectance of the belt (dark rubber ~0.2).
    texture_contrast : float
        Relative amplitude of the belt's texture (fabric and wear).
    texture_seed : int
        Seed of the belt texture.
    """

    speed_mm_s: float = 1000.0
    surface_z_mm: float = 0.0
    width_mm: float = 900.0
    albedo: float = 0.22
    texture_contrast: float = 0.35
    texture_seed: int = 11

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speed_mm_s) and self.speed_mm_s >= 0):
            raise InvalidInput("conveyor speed_mm_s must be finite and >= 0")
        if self.surface_z_mm != 0.0:
            raise InvalidInput(
                "conveyor surface_z_mm must be 0: the belt surface defines z = 0 of the rig frame"
            )
        if not (self.width_mm > 0 and 0 < self.albedo <= 1 and 0 <= self.texture_contrast < 1):
            raise InvalidInput(
                "conveyor needs width_mm > 0, 0 < albedo <= 1, 0 <= texture_contrast < 1"
            )


@dataclass(frozen=True, eq=False)
class Rig:
    """Four cameras, the pattern projector and the conveyor, in the rig frame.

    Attributes
    ----------
    cameras : tuple of Camera
        Four cameras (``cam0`` .. ``cam3``, see the module docstring).
    projector : Projector
    conveyor : Conveyor
    stereo_pairs : tuple of (int, int)
        The pairs a reconstruction should rectify first (left, right): the two
        pairs with baselines along x, left camera at lower x.
    ring_pairs : tuple of (int, int)
        Further pairs with baselines along y (first camera at lower y).
    source : str
        How the numbers were obtained ("nominal", or a calibration summary).
    reprojection_rms_px : tuple of float
        Per camera, the RMS reprojection error of the calibration (empty for
        the nominal rig).
    """

    cameras: tuple[Camera, ...]
    projector: Projector
    conveyor: Conveyor = field(default_factory=Conveyor)
    stereo_pairs: tuple[tuple[int, int], ...] = ((0, 1), (2, 3))
    ring_pairs: tuple[tuple[int, int], ...] = ((0, 2), (1, 3))
    source: str = "nominal"
    reprojection_rms_px: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        if len(cams) != 4 or not all(isinstance(c, Camera) for c in cams):
            raise InvalidInput(f"a rig has four Camera objects, got {len(cams)}")
        names = [c.name for c in cams]
        if len(set(names)) != 4:
            raise InvalidInput(f"camera names must be unique, got {names}")
        object.__setattr__(self, "cameras", cams)
        for attr in ("stereo_pairs", "ring_pairs"):
            pairs = tuple((int(a), int(b)) for a, b in getattr(self, attr))
            for a, b in pairs:
                if not (0 <= a < 4 and 0 <= b < 4 and a != b):
                    raise InvalidInput(f"{attr}: bad camera pair {(a, b)}")
            object.__setattr__(self, attr, pairs)
        rms = tuple(float(r) for r in self.reprojection_rms_px)
        if rms and len(rms) != 4:
            raise InvalidInput("reprojection_rms_px has one value per camera, or none")
        object.__setattr__(self, "reprojection_rms_px", rms)

    # -- access --------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        if isinstance(key, str):
            for cam in self.cameras:
                if cam.name == key:
                    return cam
            raise KeyError(key)
        return self.cameras[key]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)

    @property
    def image_shape(self) -> tuple[int, int]:
        """(height, width) of the first camera's images (all four are equal in the default rigs)."""
        return self.cameras[0].shape

    # -- identity ------------------------------------------------------------
    @property
    def id(self) -> str:
        """Calibration id: the first 16 hex digits of SHA-256 over the content.

        Computed from every number and name that :meth:`save` writes (except
        ``source``), so a saved and reloaded rig keeps its id, and any edit
        changes it. Results record it as ``calibration_id``.
        """
        h = hashlib.sha256()
        h.update(RIG_FORMAT.encode())
        for cam in self.cameras:
            h.update(cam.name.encode() + b"\0")
            h.update(np.array([cam.width, cam.height], dtype=np.int64).tobytes())
            for arr in (cam.K, cam.dist, cam.R, cam.t):
                h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
        p = self.projector
        h.update(np.array([p.width, p.height], dtype=np.int64).tobytes())
        for arr in (p.K, p.R, p.t):
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
        h.update(
            repr((p.pattern, p.power, self.conveyor, self.stereo_pairs, self.ring_pairs)).encode()
        )
        return h.hexdigest()[:16]

    # -- construction --------------------------------------------------------
    @classmethod
    def nominal(cls, width: int = 1280, height: int = 1024) -> Rig:
        """The rig as built: the simulator's truth.

        Four cameras with 8 mm lenses on 1280 x 1024, 4.8 µm sensors, 1300 mm
        above the belt at (±250, ±300) mm, looking at (0, 0, 100); each with
        its own small mounting errors, principal point offset and lens
        distortion, as a real rig has. Other image sizes scale the sensor
        (same field of view).

        Parameters
        ----------
        width, height : int
            Image size in pixels.
        """
        f_px = 8.0 / 0.0048  # 8 mm lens, 4.8 µm pixels
        target = np.array([0.0, 0.0, 100.0])
        # As-built deviations from the drawing: mounting angle errors (rad),
        # position errors (mm), principal point offsets (px) and distortion.
        # Fixed numbers, so the truth never changes with library versions.
        built = [
            # name, (x, y), d_angle (rx, ry, rz), d_pos, d_pp, dist
            (
                "cam0",
                (-250.0, -300.0),
                (0.004, -0.003, 0.006),
                (1.2, -0.8, 2.1),
                (6.2, -4.1),
                (-0.082, 0.071, 0.0006, -0.0004, -0.012),
            ),
            (
                "cam1",
                (250.0, -300.0),
                (-0.002, 0.005, -0.004),
                (-0.7, 1.5, -1.3),
                (-3.5, 5.4),
                (-0.091, 0.088, -0.0003, 0.0005, -0.021),
            ),
            (
                "cam2",
                (-250.0, 300.0),
                (0.003, 0.002, 0.003),
                (0.4, 0.9, -0.6),
                (2.8, 7.3),
                (-0.076, 0.062, 0.0004, 0.0002, -0.008),
            ),
            (
                "cam3",
                (250.0, 300.0),
                (-0.005, -0.004, -0.005),
                (-1.6, -0.3, 1.7),
                (-5.9, -2.2),
                (-0.087, 0.079, -0.0005, -0.0003, -0.016),
            ),
        ]
        cams = []
        for name, (x, y), d_ang, d_pos, d_pp, dist in built:
            C = np.array([x, y, 1300.0]) + np.array(d_pos)
            R = _rotvec_matrix(np.array(d_ang)) @ look_at(C, target)
            K = np.array(
                [
                    [f_px * 1.0004, 0.0, 639.5 + d_pp[0]],
                    [0.0, f_px * 0.9997, 511.5 + d_pp[1]],
                    [0.0, 0.0, 1.0],
                ]
            )
            cam = Camera(name, 1280, 1024, K, np.array(dist), R, -R @ C)
            if (width, height) != (1280, 1024):
                cam = cam.with_size(width, height)
            cams.append(cam)
        C_p = np.array([0.0, 0.0, 1300.0])
        R_p = look_at(C_p, np.array([0.0, 0.0, 0.0]))
        K_p = np.array([[2300.0, 0.0, 959.5], [0.0, 2300.0, 599.5], [0.0, 0.0, 1.0]])
        projector = Projector(1920, 1200, K_p, R_p, -R_p @ C_p)
        return cls(tuple(cams), projector, Conveyor(), source="nominal")

    @classmethod
    def default(cls) -> Rig:
        """The calibrated rig the line measures with.

        Reads ``$INSPECTION_RIG`` if set, else the rig shipped with the package
        (:data:`DEFAULT_RIG_DATA`, produced by ``inspection calibrate`` from
        rendered ChArUco images), which an installed wheel carries as package
        data.

        Raises
        ------
        FileNotFoundError
            When ``$INSPECTION_RIG`` names no file, or the package lacks its
            rig (an incomplete installation).
        InvalidInput
            When it is not a valid rig file.
        """
        env = os.environ.get(ENV_RIG)
        if env:
            path = Path(env)
            if not path.is_file():
                raise FileNotFoundError(
                    f"no rig calibration at {path} (from ${ENV_RIG}): "
                    f"run `inspection calibrate --out {path}`"
                )
            return cls.load(path)
        resource = importlib.resources.files("inspection").joinpath(DEFAULT_RIG_DATA)
        try:
            text = resource.read_text(encoding="utf-8")
        except FileNotFoundError as exc:
            raise FileNotFoundError(
                f"the package's calibrated rig {resource} is missing: the installation is "
                "incomplete (the wheel must carry it as package data)"
            ) from exc
        return cls.from_toml(text, where=str(resource))

    def with_image_size(self, width: int, height: int) -> Rig:
        """This rig with every camera's image scaled to ``width`` x ``height``."""
        cams = tuple(c.with_size(width, height) for c in self.cameras)
        return Rig(
            cams,
            self.projector,
            self.conveyor,
            self.stereo_pairs,
            self.ring_pairs,
            self.source,
            self.reprojection_rms_px,
        )

    # -- TOML ----------------------------------------------------------------
    def to_toml(self) -> str:
        """The rig as documented TOML text (see :meth:`save`)."""
        f = _fmt
        lines = [
            "# The four-camera flash rig of the inspection line.",
            "#",
            "# Frame: origin at the centre of the measurement volume on the conveyor",
            "# surface; x along the conveyor's motion, y across it, z up. Units: mm.",
            "# Cameras use OpenCV's model: X_cam = R @ X_rig + t, then the pinhole K",
            "# (pixels; pixel centres at integer coordinates) with the distortion",
            "# dist = [k1, k2, p1, p2, k3]. R, t map rig -> camera.",
            "# id: SHA-256 of the content (first 16 hex digits), checked on load; delete",
            "# the line after editing numbers by hand.",
            "",
            f'format = "{RIG_FORMAT}"',
            f'id = "{self.id}"',
            f"source = {_quote(self.source)}",
            f"stereo_pairs = {f([list(p) for p in self.stereo_pairs])}",
            f"ring_pairs = {f([list(p) for p in self.ring_pairs])}",
        ]
        if self.reprojection_rms_px:
            lines.append(f"reprojection_rms_px = {f(list(self.reprojection_rms_px))}")
        for cam in self.cameras:
            lines += [
                "",
                "[[camera]]",
                f"name = {_quote(cam.name)}",
                f"width = {cam.width}",
                f"height = {cam.height}",
                f"K = {f(cam.K.tolist())}",
                f"dist = {f(cam.dist.tolist())}",
                f"R = {f(cam.R.tolist())}",
                f"t = {f(cam.t.tolist())}",
                f"# centre in the rig frame (mm, read only): {np.round(cam.centre, 3).tolist()}",
            ]
        p = self.projector
        pat = p.pattern
        c = self.conveyor
        lines += [
            "",
            "[projector]",
            "# pinhole without distortion; R, t map rig -> projector",
            f"width = {p.width}",
            f"height = {p.height}",
            f"K = {f(p.K.tolist())}",
            f"R = {f(p.R.tolist())}",
            f"t = {f(p.t.tolist())}",
            f"power = {f(p.power)}",
            "",
            "[projector.pattern]",
            f"kind = {_quote(pat.kind)}",
            f"seed = {pat.seed}",
            f"grain_px = {f(pat.grain_px)}",
            f"blur_px = {f(pat.blur_px)}",
            f"low = {f(pat.low)}",
            f"high = {f(pat.high)}",
            "",
            "[conveyor]",
            f"speed_mm_s = {f(c.speed_mm_s)}",
            f"surface_z_mm = {f(c.surface_z_mm)}",
            f"width_mm = {f(c.width_mm)}",
            f"albedo = {f(c.albedo)}",
            f"texture_contrast = {f(c.texture_contrast)}",
            f"texture_seed = {c.texture_seed}",
            "",
        ]
        return "\n".join(lines)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the rig as TOML (floats written exactly, so a reload is bit-identical).

        Returns
        -------
        Path
            The path written.
        """
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(out.suffix + ".tmp")
        tmp.write_text(self.to_toml(), encoding="utf-8")
        tmp.replace(out)
        log.debug("saved rig %s to %s", self.id, out)
        return out

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Rig:
        """Read a rig TOML file written by :meth:`save` (or by hand, same layout).

        Raises
        ------
        FileNotFoundError
            When the file does not exist.
        InvalidInput
            When the file is not valid TOML, misses keys, has unknown keys, or
            its ``id`` does not match its content.
        """
        p = Path(path)
        return cls.from_toml(p.read_text(encoding="utf-8"), where=str(p))

    @classmethod
    def from_toml(cls, text: str, *, where: str = "rig") -> Rig:
        """Read a rig from TOML text written by :meth:`to_toml`.

        ``where`` names the text's origin in error messages.

        Raises
        ------
        InvalidInput
            As :meth:`load`.
        """
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise InvalidInput(f"{where}: not valid TOML: {exc}") from exc
        return cls.from_dict(data, where=where)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, where: str = "rig") -> Rig:
        """Build a rig from the parsed TOML structure (see :meth:`to_toml`)."""
        try:
            _keys(
                data,
                {
                    "format",
                    "id",
                    "source",
                    "stereo_pairs",
                    "ring_pairs",
                    "reprojection_rms_px",
                    "camera",
                    "projector",
                    "conveyor",
                },
                where,
            )
            if data.get("format") != RIG_FORMAT:
                raise InvalidInput(
                    f"{where}: format must be {RIG_FORMAT!r}, got {data.get('format')!r}"
                )
            cams = []
            for i, c in enumerate(data["camera"]):
                _keys(c, {"name", "width", "height", "K", "dist", "R", "t"}, f"{where}: camera {i}")
                cams.append(
                    Camera(c["name"], c["width"], c["height"], c["K"], c["dist"], c["R"], c["t"])
                )
            pj = dict(data["projector"])
            _keys(pj, {"width", "height", "K", "R", "t", "power", "pattern"}, f"{where}: projector")
            pattern = Pattern(**pj.pop("pattern", {}))
            projector = Projector(pattern=pattern, **pj)
            conveyor = Conveyor(**data.get("conveyor", {}))
            rig = cls(
                tuple(cams),
                projector,
                conveyor,
                stereo_pairs=tuple(tuple(x) for x in data.get("stereo_pairs", ((0, 1), (2, 3)))),
                ring_pairs=tuple(tuple(x) for x in data.get("ring_pairs", ((0, 2), (1, 3)))),
                source=str(data.get("source", "")),
                reprojection_rms_px=tuple(data.get("reprojection_rms_px", ())),
            )
        except KeyError as exc:
            raise InvalidInput(f"{where}: missing key {exc}") from exc
        except TypeError as exc:
            raise InvalidInput(f"{where}: {exc}") from exc
        stored = data.get("id")
        if stored is not None and stored != rig.id:
            raise InvalidInput(
                f"{where}: id {stored!r} does not match the content ({rig.id!r}); the numbers were "
                "edited after calibration: delete the id line to accept them"
            )
        return rig

    def summary(self) -> str:
        """A few lines for people: cameras, centres, pairs."""
        out = [f"rig {self.id} ({self.source})"]
        for cam in self.cameras:
            out.append(
                f"  {cam.name}: {cam.width}x{cam.height} "
                f"f=({cam.K[0, 0]:.1f}, {cam.K[1, 1]:.1f}) px "
                f"centre={np.round(cam.centre, 1).tolist()} mm"
            )
        out.append(f"  stereo pairs {self.stereo_pairs}, ring pairs {self.ring_pairs}")
        return "\n".join(out)


def _rotvec_matrix(rotvec: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Rodrigues: rotation vector (3,) rad -> (3, 3) rotation."""
    theta = float(np.linalg.norm(rotvec))
    if theta < 1e-15:
        return np.eye(3)
    k = rotvec / theta
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * Kx + (1.0 - math.cos(theta)) * (Kx @ Kx)


def _keys(table: dict[str, Any], allowed: set[str], where: str) -> None:
    unknown = set(table) - allowed
    if unknown:
        raise InvalidInput(f"{where}: unknown keys {sorted(unknown)}")


def _fmt(value: Any) -> str:
    """TOML literal for numbers and nested lists; floats via repr (exact round trip)."""
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    v = float(value)
    if not math.isfinite(v):
        raise InvalidInput("cannot write a non-finite number to a rig file")
    text = repr(v)
    return text if ("." in text or "e" in text or "inf" in text) else text + ".0"


def _quote(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ") + '"'


def rigid_align(src: npt.ArrayLike, dst: npt.ArrayLike) -> Transform:
    """Least-squares rigid transform (Kabsch) mapping ``src`` points onto ``dst``.

    Parameters
    ----------
    src, dst : (N, 3) float64, mm, N >= 3, not collinear

    Returns
    -------
    (4, 4) float64
        ``T`` with ``dst ≈ T[:3, :3] @ src + T[:3, 3]``.
    """
    a = _check_points(src)
    b = _check_points(dst)
    if a.shape != b.shape or len(a) < 3:
        raise InvalidInput("rigid_align needs two (N, 3) arrays of equal N >= 3")
    ca = a.mean(axis=0)
    cb = b.mean(axis=0)
    H = (a - ca).T @ (b - cb)
    U, S, Vt = np.linalg.svd(H)
    if S[1] < 1e-9 * max(S[0], 1e-300):
        raise InvalidInput("rigid_align: points are collinear")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cb - R @ ca
    return T
