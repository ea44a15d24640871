"""The rig's stereo pairs, rectified to look straight down at the belt.

Rectification is chosen for this rig, not left to ``cv2.stereoRectify``:
both rectified cameras of a pair look straight down at the belt (the
rectified z axis is the rig's -z made orthogonal to the baseline, x runs
along the baseline). A horizontal surface then has one disparity everywhere
in the image, so the disparity range a search must cover is set by the
heights in the measurement volume alone and does not grow with the
convergence of the cameras. The principal points of the two rectified images
are shifted so that the volume fills both and its disparities are small
numbers; a point at depth ``Z`` along the rectified axis has the disparity

    d = f B / Z + (cx_left - cx_right),

and a rectified left pixel ``(x, y)`` with disparity ``d`` triangulates back
to ``Z = f B / (d - offset)``, ``X = (x - cx) Z / f``, ``Y = (y - cy) Z / f``.
:meth:`Reconstructor.build <inspection.reconstruct.Reconstructor.build>`
rectifies every pair once per rig (:func:`rectified_pair`), and draws the
disparity of the plane just above the belt, which separates the part from
the conveyor (:func:`belt_disparity`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ..rig import Camera, Rig

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class RectifiedPair:
    """One stereo pair rectified to a common, belt-facing orientation.

    Attributes
    ----------
    left, right : int
        Camera indices in the rig.
    R_rect_rig : (3, 3) float64
        Rotation rig -> rectified frame (rows: x along the baseline, y, z down).
    centre_left : (3,) float64, mm
        Optical centre of the left camera in the rig frame (the rectified frame's origin).
    baseline_mm : float
        Distance between the two optical centres.
    f_px : float
        Focal length of both rectified images.
    cx_left, cx_right, cy : float
        Principal points of the rectified images (pixels).
    size : (int, int)
        (width, height) of both rectified images.
    maps_left, maps_right : tuple of two (H, W) float32
        ``cv2.remap`` maps from rectified pixels to the original (distorted) image.
    """

    left: int
    right: int
    R_rect_rig: F64
    centre_left: F64
    baseline_mm: float
    f_px: float
    cx_left: float
    cx_right: float
    cy: float
    size: tuple[int, int]
    maps_left: tuple[F32, F32]
    maps_right: tuple[F32, F32]

    @property
    def name(self) -> str:
        return f"{self.left}-{self.right}"

    @property
    def fb(self) -> float:
        """f * B (px mm): disparity times depth."""
        return self.f_px * self.baseline_mm

    @property
    def offset_px(self) -> float:
        """Disparity of a point at infinite depth (the principal point shift)."""
        return self.cx_left - self.cx_right

    # -- geometry -----------------------------------------------------------
    def to_rect(self, points_rig: F64) -> F64:
        """Rig-frame points (N, 3) -> rectified left-camera frame (N, 3), mm."""
        return (points_rig - self.centre_left) @ self.R_rect_rig.T

    def project(self, points_rig: F64) -> tuple[F64, F64, F64]:
        """Rig-frame points -> rectified left pixel (x, y) and depth Z (mm)."""
        p = self.to_rect(points_rig)
        z = p[:, 2]
        return self.f_px * p[:, 0] / z + self.cx_left, self.f_px * p[:, 1] / z + self.cy, z

    def disparity_of_depth(self, z: F64 | float) -> F64 | float:
        """Rectified disparity (px) of a point at depth ``z`` (mm) along the rectified axis."""
        return self.fb / z + self.offset_px

    def triangulate(self, x: F64, y: F64, d: F64) -> F64:
        """Rectified left pixels and disparities (N,) -> rig-frame points (N, 3), mm."""
        z = self.fb / (d - self.offset_px)
        p = np.empty((len(x), 3))
        p[:, 0] = (x - self.cx_left) * z / self.f_px
        p[:, 1] = (y - self.cy) * z / self.f_px
        p[:, 2] = z
        return p @ self.R_rect_rig + self.centre_left

    def disparity_range(self, lo: F64, hi: F64) -> tuple[float, float]:
        """Disparities spanned by the box ``lo``..``hi`` (rig frame, mm)."""
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        z = self.to_rect(corners)[:, 2]
        d = self.fb / z + self.offset_px
        return float(d.min()), float(d.max())


def rectify_pair(
    cam_l: Camera, cam_r: Camera, left: int, right: int, lo: F64, hi: F64, margin_px: int = 8
) -> RectifiedPair:
    """Build the belt-facing rectification of one pair (see the module docstring).

    Parameters
    ----------
    cam_l, cam_r : Camera
        Left (lower x) and right camera.
    left, right : int
        Their indices in the rig.
    lo, hi : (3,) float64, mm
        The measurement volume (rig frame) that the rectified images must cover.
    margin_px : int
        Extra pixels around the projected volume.
    """
    c_l = cam_l.centre
    c_r = cam_r.centre
    base = c_r - c_l
    baseline = float(np.linalg.norm(base))
    ex = base / baseline
    down = np.array([0.0, 0.0, -1.0])
    ez = down - ex * (ex @ down)
    ez /= np.linalg.norm(ez)
    ey = np.cross(ez, ex)
    R = np.stack([ex, ey, ez])
    f = float(np.mean([cam_l.K[0, 0], cam_l.K[1, 1], cam_r.K[0, 0], cam_r.K[1, 1]]))
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    # Ideal (principal-point-free) rectified coordinates of the volume in both views.
    xs, ys = [], []
    for c in (c_l, c_r):
        p = (corners - c) @ R.T
        xs.append(f * p[:, 0] / p[:, 2])
        ys.append(f * p[:, 1] / p[:, 2])
    cx_l = margin_px - float(xs[0].min())
    cx_r = margin_px - float(xs[1].min())
    width = (
        int(math.ceil(max(xs[0].max() - xs[0].min(), xs[1].max() - xs[1].min()))) + 2 * margin_px
    )
    y_all = np.concatenate(ys)
    cy = margin_px - float(y_all.min())
    height = int(math.ceil(y_all.max() - y_all.min())) + 2 * margin_px
    maps = []
    for cam, cx in ((cam_l, cx_l), (cam_r, cx_r)):
        K_new = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        R_cam_rect = R @ cam.R.T  # camera -> rectified (OpenCV's R argument)
        m1, m2 = cv2.initUndistortRectifyMap(
            cam.K, cam.dist, R_cam_rect, K_new, (width, height), cv2.CV_32FC1
        )
        maps.append((np.asarray(m1, np.float32), np.asarray(m2, np.float32)))
    R.setflags(write=False)
    return RectifiedPair(
        left, right, R, c_l.copy(), baseline, f, cx_l, cx_r, cy, (width, height), maps[0], maps[1]
    )


def rectified_pair(
    rig: Rig, a: int, b: int, lo: npt.NDArray[np.float64], hi: npt.NDArray[np.float64]
) -> RectifiedPair:
    """The rectified pair of cameras a and b; its "left" camera is the one at the
    lower end of the baseline's main direction (rectified x grows along it)."""
    ca, cb = rig.cameras[a], rig.cameras[b]
    base = cb.centre - ca.centre
    k = int(np.argmax(np.abs(base[:2])))
    if base[k] < 0:
        a, b, ca, cb = b, a, cb, ca
    return rectify_pair(ca, cb, a, b, lo, hi)


def rectify(
    img: npt.NDArray[np.uint8], maps: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]
) -> npt.NDArray[np.float32]:
    """``img`` resampled into a rectified view (``maps``: :attr:`RectifiedPair.maps_left`
    or ``maps_right``), bilinearly and in float32 so that the refinement sees no second
    quantisation; 0 outside the camera's image."""
    out = cv2.remap(
        img.astype(np.float32), maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )
    return np.asarray(out, dtype=np.float32)


def belt_disparity(pair: RectifiedPair, z_mm: float) -> npt.NDArray[np.float32]:
    """Disparity of the plane z = ``z_mm`` (rig frame) at every rectified left pixel."""
    w, h = pair.size
    # Rectified ray through pixel (x, y): r = R^T [(x - cx)/f, (y - cy)/f, 1]; it meets
    # z = z_mm at depth Z = (z_mm - C_z) / r_z along the rectified axis.
    R = pair.R_rect_rig
    xn = (np.arange(w, dtype=np.float64) - pair.cx_left) / pair.f_px
    yn = (np.arange(h, dtype=np.float64) - pair.cy) / pair.f_px
    rz = R[0, 2] * xn[None, :] + R[1, 2] * yn[:, None] + R[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (z_mm - pair.centre_left[2]) / rz
        d = pair.fb / depth + pair.offset_px
    return np.where(depth > 0, d, np.inf).astype(np.float32)


__all__ = ["RectifiedPair", "belt_disparity", "rectified_pair", "rectify", "rectify_pair"]
