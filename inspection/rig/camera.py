"""One camera in OpenCV's model: pose, pinhole intrinsics, lens distortion, projection and rays.

``X_cam = R @ X_rig + t`` then pinhole ``K`` with distortion
``(k1, k2, p1, p2, k3)``; image x to the right, y down, z forward; pixel
centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..arrays import Points, Transform
from ..errors import InvalidInput
from .checks import as_matrix, check_pixels, check_points, rotation_ok

# Undistortion: fixed-point iterations converge by a factor ~3*k1*r^2 (< 0.1
# for our lenses) per step; 30 steps reach machine precision with room to spare.
_UNDISTORT_ITERATIONS = 30


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
        K = as_matrix(self.K, (3, 3), f"camera {self.name}: K")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
            raise InvalidInput(
                f"camera {self.name}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
                "with fx, fy > 0"
            )
        R = as_matrix(self.R, (3, 3), f"camera {self.name}: R")
        rotation_ok(R, f"camera {self.name}: R")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", as_matrix(self.dist, (5,), f"camera {self.name}: dist"))
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", as_matrix(self.t, (3,), f"camera {self.name}: t"))

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
        pts = check_points(points_rig)
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
        px = check_pixels(pixels)
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
