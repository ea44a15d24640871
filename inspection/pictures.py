"""Pictures for people: images as PNG, and drawings of the rig.

Drawn with OpenCV only (no plotting library): a top view of the rig layout
with the measurement volume, and the four camera images of a scene tiled with
the rig frame's axes projected into each.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from .arrays import Image
from .errors import InvalidInput
from .rig import VOLUME_MM, Rig


def write_png(path: str | os.PathLike[str], image: npt.ArrayLike, *, compression: int = 6) -> Path:
    """Write an image as PNG (lossless), creating the directory.

    Parameters
    ----------
    path : path-like
    image : (H, W) uint8 grey, or (H, W, 3) uint8 RGB
    compression : int
        zlib level 0-9.

    Returns
    -------
    Path
        The path written.
    """
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        raise InvalidInput(f"write_png: image must be uint8, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    elif arr.ndim != 2:
        raise InvalidInput(f"write_png: image must be (H, W) or (H, W, 3), got {arr.shape}")
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), arr, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]):
        raise OSError(f"could not write {out}")
    return out


def draw_rig_layout(rig: Rig, *, scale: float = 0.5) -> npt.NDArray[np.uint8]:
    """Top and side views of the rig: cameras, projector, volume, stereo pairs.

    Parameters
    ----------
    rig : Rig
    scale : float
        Pixels per mm.

    Returns
    -------
    (H, W, 3) uint8 RGB
    """
    vx, vy, vz = VOLUME_MM
    pad = 60
    span_x = 1000.0
    span_y = 800.0
    top_w = int(span_x * scale) + 2 * pad
    top_h = int(span_y * scale) + 2 * pad
    side_h = int(1500 * scale) + 2 * pad
    img = np.full((top_h + side_h, top_w, 3), 255, np.uint8)
    grey = (150, 150, 150)
    colours = [(200, 40, 40), (40, 140, 40), (40, 80, 210), (200, 120, 0)]

    def top(p: npt.ArrayLike) -> tuple[int, int]:
        q = np.asarray(p, dtype=float)
        return int(round(top_w / 2 + q[0] * scale)), int(round(top_h / 2 - q[1] * scale))

    def side(p: npt.ArrayLike) -> tuple[int, int]:
        q = np.asarray(p, dtype=float)
        return int(round(top_w / 2 + q[0] * scale)), int(round(top_h + side_h - pad - q[2] * scale))

    font = cv2.FONT_HERSHEY_SIMPLEX
    # belt and volume, top view
    half_belt = rig.conveyor.width_mm / 2
    cv2.rectangle(img, top((-span_x / 2, half_belt)), top((span_x / 2, -half_belt)), (225, 225, 225), -1)
    cv2.rectangle(img, top((-vx / 2, vy / 2)), top((vx / 2, -vy / 2)), grey, 2)
    cv2.arrowedLine(img, top((0, 0)), top((120, 0)), (220, 0, 0), 2, tipLength=0.2)
    cv2.arrowedLine(img, top((0, 0)), top((0, 120)), (0, 160, 0), 2, tipLength=0.2)
    cv2.putText(img, "x (belt motion)", top((125, -15)), font, 0.45, (220, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "y", top((8, 125)), font, 0.45, (0, 160, 0), 1, cv2.LINE_AA)
    cv2.putText(img, f"top view: volume {vx:g} x {vy:g} x {vz:g} mm, belt {rig.conveyor.width_mm:g} mm wide",
                (10, 22), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    # stereo pairs
    for a, b in rig.stereo_pairs:
        cv2.line(img, top(rig.cameras[a].centre), top(rig.cameras[b].centre), (120, 0, 160), 2, cv2.LINE_AA)
    for a, b in rig.ring_pairs:
        cv2.line(img, top(rig.cameras[a].centre), top(rig.cameras[b].centre), (190, 160, 210), 1, cv2.LINE_AA)
    # side view (x-z)
    cv2.line(img, side((-span_x / 2, 0, 0)), side((span_x / 2, 0, 0)), (90, 90, 90), 3)
    cv2.rectangle(img, side((-vx / 2, 0, vz)), side((vx / 2, 0, 0)), grey, 2)
    cv2.putText(img, "side view (x-z)", (10, top_h + 22), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    target = np.array([0.0, 0.0, 0.0])
    for k, cam in enumerate(rig.cameras):
        c = cam.centre
        col = colours[k % 4]
        # viewing frustum footprint on the belt, top view
        corners = np.array([[0, 0], [cam.width - 1, 0], [cam.width - 1, cam.height - 1], [0, cam.height - 1]], float)
        o, d = cam.rays(corners)
        s = -o[:, 2] / d[:, 2]
        foot = o + s[:, None] * d
        cv2.polylines(img, [np.array([top(p) for p in foot], np.int32)], True, col, 1, cv2.LINE_AA)
        cv2.circle(img, top(c), 7, col, -1, cv2.LINE_AA)
        cv2.putText(img, cam.name, (top(c)[0] + 9, top(c)[1] - 6), font, 0.5, col, 1, cv2.LINE_AA)
        cv2.circle(img, side(c), 6, col, -1, cv2.LINE_AA)
        axis = cam.R[2]
        s_hit = (target[2] + 100 - c[2]) / axis[2]
        cv2.line(img, side(c), side(c + s_hit * axis), col, 1, cv2.LINE_AA)
    p = rig.projector.centre
    cv2.drawMarker(img, top(p), (0, 0, 0), cv2.MARKER_DIAMOND, 14, 2)
    cv2.putText(img, "projector", (top(p)[0] + 9, top(p)[1] + 16), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.drawMarker(img, side(p), (0, 0, 0), cv2.MARKER_DIAMOND, 14, 2)
    cv2.putText(img, "pairs: bold = stereo pairs, thin = ring pairs", (10, top_h - 12), font, 0.45,
                (120, 0, 160), 1, cv2.LINE_AA)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def draw_frames(rig: Rig, images: Sequence[Image], *, axis_mm: float = 150.0, width: int = 1280) -> npt.NDArray[np.uint8]:
    """The four camera images tiled 2 x 2, with the rig frame's axes drawn in each.

    Parameters
    ----------
    rig : Rig
    images : four (H, W) uint8
    axis_mm : float
        Length of the drawn x (red), y (green) and z (blue) axes.
    width : int
        Width of the output picture, pixels.

    Returns
    -------
    (H', width, 3) uint8 RGB
    """
    if len(images) != len(rig.cameras):
        raise InvalidInput(f"draw_frames needs {len(rig.cameras)} images, got {len(images)}")
    tiles = []
    axes = np.array([[0, 0, 0], [axis_mm, 0, 0], [0, axis_mm, 0], [0, 0, axis_mm]], float)
    for cam, im in zip(rig.cameras, images, strict=True):
        rgb = cv2.cvtColor(np.asarray(im, np.uint8), cv2.COLOR_GRAY2RGB)
        px = cam.project(axes)
        o = tuple(int(round(v)) for v in px[0])
        for k, col in enumerate([(255, 40, 40), (40, 220, 40), (60, 120, 255)]):
            cv2.arrowedLine(rgb, o, tuple(int(round(v)) for v in px[k + 1]), col, 4, cv2.LINE_AA, tipLength=0.15)
        cv2.putText(rgb, cam.name, (20, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 0), 3, cv2.LINE_AA)
        tiles.append(rgb)
    grid = np.vstack([np.hstack(tiles[0:2]), np.hstack(tiles[2:4])])
    h = int(round(grid.shape[0] * width / grid.shape[1]))
    return cv2.resize(grid, (width, h), interpolation=cv2.INTER_AREA)
