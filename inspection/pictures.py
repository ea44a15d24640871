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
    """Top view (x-y) and front view (y-z) of the rig: cameras, projector,
    measurement volume, belt, each camera's field of view on the belt, and
    the stereo pairs.

    Parameters
    ----------
    rig : Rig
    scale : float
        Pixels per mm of the top view (the front view is drawn at 0.6 x scale).

    Returns
    -------
    (H, W, 3) uint8 RGB
    """
    vx, vy, vz = VOLUME_MM
    pad = 40
    span_x, span_y = 1100.0, 900.0
    top_w = int(span_x * scale) + 2 * pad
    top_h = int(span_y * scale) + 2 * pad
    fs = 0.6 * scale
    front_w = int(1000.0 * fs) + 2 * pad
    img = np.full((top_h, top_w + front_w, 3), 255, np.uint8)  # RGB
    grey = (150, 150, 150)
    colours = [(30, 90, 220), (40, 150, 40), (220, 90, 20), (170, 40, 170)]
    font = cv2.FONT_HERSHEY_SIMPLEX

    def top(p: npt.ArrayLike) -> tuple[int, int]:
        q = np.asarray(p, dtype=float)
        return int(round(top_w / 2 + q[0] * scale)), int(round(top_h / 2 - q[1] * scale))

    def front(p: npt.ArrayLike) -> tuple[int, int]:
        q = np.asarray(p, dtype=float)
        return int(round(top_w + front_w / 2 + q[1] * fs)), int(round(top_h - pad - q[2] * fs))

    # top view: belt, volume, axes
    half_belt = rig.conveyor.width_mm / 2
    cv2.rectangle(
        img, top((-span_x / 2, half_belt)), top((span_x / 2, -half_belt)), (228, 228, 228), -1
    )
    cv2.rectangle(img, top((-vx / 2, vy / 2)), top((vx / 2, -vy / 2)), grey, 2)
    for k, cam in enumerate(rig.cameras):
        corners = np.array(
            [[0, 0], [cam.width - 1, 0], [cam.width - 1, cam.height - 1], [0, cam.height - 1]],
            float,
        )
        o, d = cam.rays(corners)
        foot = o + (-o[:, 2] / d[:, 2])[:, None] * d
        cv2.polylines(
            img, [np.array([top(p) for p in foot], np.int32)], True, colours[k % 4], 1, cv2.LINE_AA
        )
    for a, b in rig.ring_pairs:
        cv2.line(
            img,
            top(rig.cameras[a].centre),
            top(rig.cameras[b].centre),
            (200, 170, 220),
            1,
            cv2.LINE_AA,
        )
    for a, b in rig.stereo_pairs:
        cv2.line(
            img,
            top(rig.cameras[a].centre),
            top(rig.cameras[b].centre),
            (120, 0, 160),
            3,
            cv2.LINE_AA,
        )
    cv2.arrowedLine(img, top((0, 0)), top((150, 0)), (220, 0, 0), 2, cv2.LINE_AA, tipLength=0.15)
    cv2.arrowedLine(img, top((0, 0)), top((0, 150)), (0, 150, 0), 2, cv2.LINE_AA, tipLength=0.15)
    cv2.putText(img, "x: belt motion", top((160, -8)), font, 0.45, (220, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "y", top((10, 150)), font, 0.45, (0, 150, 0), 1, cv2.LINE_AA)
    for k, cam in enumerate(rig.cameras):
        c = top(cam.centre)
        cv2.circle(img, c, 7, colours[k % 4], -1, cv2.LINE_AA)
        cv2.putText(img, cam.name, (c[0] + 10, c[1] - 8), font, 0.5, colours[k % 4], 1, cv2.LINE_AA)
    pc = top(rig.projector.centre)
    cv2.drawMarker(img, pc, (0, 0, 0), cv2.MARKER_DIAMOND, 14, 2)
    cv2.putText(img, "projector", (pc[0] - 30, pc[1] + 22), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(
        img,
        f"top view: volume {vx:g} x {vy:g} mm (grey), belt {rig.conveyor.width_mm:g} mm wide, "
        "fields of view on the belt",
        (8, 16),
        font,
        0.42,
        (0, 0, 0),
        1,
        cv2.LINE_AA,
    )
    cv2.putText(
        img,
        "bold: stereo pairs, thin: ring pairs",
        (8, top_h - 10),
        font,
        0.42,
        (120, 0, 160),
        1,
        cv2.LINE_AA,
    )
    # front view (y-z), looking along the belt
    cv2.line(img, (top_w, 0), (top_w, top_h), (200, 200, 200), 1)
    cv2.line(img, front((0, -half_belt, 0)), front((0, half_belt, 0)), (90, 90, 90), 3)
    cv2.rectangle(img, front((0, -vy / 2, vz)), front((0, vy / 2, 0)), grey, 2)
    aim = np.array([0.0, 0.0, 100.0])
    for k, cam in enumerate(rig.cameras):
        centre = cam.centre
        cv2.line(img, front(centre), front(aim), colours[k % 4], 1, cv2.LINE_AA)
        cv2.circle(img, front(centre), 6, colours[k % 4], -1, cv2.LINE_AA)
    cv2.drawMarker(img, front(rig.projector.centre), (0, 0, 0), cv2.MARKER_DIAMOND, 14, 2)
    cv2.putText(img, "front view (y-z)", (top_w + 8, 16), font, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    h_cam = float(np.mean([c.centre[2] for c in rig.cameras]))
    cv2.putText(
        img,
        f"{h_cam:.0f} mm",
        (front((0, 0, h_cam))[0] - 25, front((0, 0, h_cam))[1] + 30),
        font,
        0.42,
        (0, 0, 0),
        1,
        cv2.LINE_AA,
    )
    return img


def draw_frames(
    rig: Rig,
    images: Sequence[Image],
    *,
    axis_mm: float = 150.0,
    width: int = 1280,
    grey_levels: int = 256,
) -> npt.NDArray[np.uint8]:
    """The four camera images tiled 2 x 2, with the rig frame's axes drawn in each.

    Parameters
    ----------
    rig : Rig
    images : four (H, W) uint8
    axis_mm : float
        Length of the drawn x (red), y (green) and z (blue) axes.
    width : int
        Width of the output picture, pixels.
    grey_levels : int
        Quantise the images to this many grey levels (fewer make a smaller
        PNG of the noisy frames, e.g. for documentation).

    Returns
    -------
    (H', width, 3) uint8 RGB
    """
    if len(images) != len(rig.cameras):
        raise InvalidInput(f"draw_frames needs {len(rig.cameras)} images, got {len(images)}")
    tiles = []
    axes = np.array([[0, 0, 0], [axis_mm, 0, 0], [0, axis_mm, 0], [0, 0, axis_mm]], float)
    for cam, im in zip(rig.cameras, images, strict=True):
        grey = np.asarray(im, np.uint8)
        if grey_levels < 256:
            step = 256 // max(grey_levels, 2)
            grey = (grey // step * step).astype(np.uint8)
        rgb = cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB)
        px = cam.project(axes)
        o = tuple(int(round(v)) for v in px[0])
        for k, col in enumerate([(255, 40, 40), (40, 220, 40), (60, 120, 255)]):
            cv2.arrowedLine(
                rgb, o, tuple(int(round(v)) for v in px[k + 1]), col, 4, cv2.LINE_AA, tipLength=0.15
            )
        cv2.putText(
            rgb, cam.name, (20, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.5, (255, 255, 0), 3, cv2.LINE_AA
        )
        tiles.append(rgb)
    grid = np.vstack([np.hstack(tiles[0:2]), np.hstack(tiles[2:4])])
    h = int(round(grid.shape[0] * width / grid.shape[1]))
    small = cv2.resize(grid, (width, h), interpolation=cv2.INTER_AREA)
    if grey_levels < 256:
        step = 256 // max(grey_levels, 2)
        grey_px = (small[..., 0] == small[..., 1]) & (small[..., 1] == small[..., 2])
        small[grey_px] = small[grey_px] // step * step
    return np.asarray(small, dtype=np.uint8)


def write_rig_pictures(directory: str | os.PathLike[str], *, seed: int = 0) -> list[Path]:
    """Write the README's rig pictures: ``rig_layout.png`` and ``rig_frames.png``.

    The frames show the demo panel (400 x 260 mm) turned by 30° on the belt,
    rendered with the rig as built, with the rig frame's axes drawn in.

    Returns
    -------
    list of Path
        The files written.
    """
    from .panel import PanelSpec, sheet_metal_panel
    from .simulate import simulate

    out = Path(directory)
    rig = Rig.nominal()
    mesh = sheet_metal_panel(PanelSpec().scaled(400.0, 260.0))
    a = np.deg2rad(30.0)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = (60.0, -40.0, 0.0)
    images = simulate(rig, mesh, T, seed=seed)
    return [
        write_png(out / "rig_layout.png", draw_rig_layout(rig), compression=9),
        write_png(
            out / "rig_frames.png",
            draw_frames(rig, images, width=800, grey_levels=16),
            compression=9,
        ),
    ]
