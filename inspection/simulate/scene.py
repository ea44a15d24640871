"""The pieces the renderer draws: camera set-ups, rasterised views, dirt, dust, textures.

They are plain functions of arrays and seeds, kept out of the simulator so
that its class reads as the order of rendering and each piece can be read
(and its randomness checked) on its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from .. import _raster
from ..board import CharucoSpec
from ..rig import Camera, Rig
from .options import _BELT_PERIOD_MM, _BOARD_PX_PER_MM, _TEXEL_MM


@dataclass(frozen=True, eq=False)
class _CameraSetup:
    camera: Camera
    rays: npt.NDArray[np.float64]  # (H, W, 2) ideal normalised coordinates
    vignette: npt.NDArray[np.float32]  # (H, W) cos^4
    kvec: npt.NDArray[np.float64]  # fx, skew, cx, fy, cy
    ox: int
    oy: int
    buf_shape: tuple[int, int]
    belt_irr: npt.NDArray[np.float32]  # (H, W) patterned irradiance x cosine on the empty belt
    belt_q: npt.NDArray[np.float32]  # (H, W, 4) slide u, v, projector depth, shadow bias
    belt_alb: npt.NDArray[np.float32]  # (H, W) belt albedo at rest
    belt_probes: npt.NDArray[np.float64]  # (K, 3) belt points seen across the image, rig frame
    ray_extent: float  # the largest |x/z| or |y/z| of a pixel's ray


def _kvec(K: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return np.array([K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]])


def _rasterize_view(V, faces, R, t, kvec, ox, oy, shape):
    """Depth and face buffers of a mesh seen by a pinhole (R, t, K) in a buffer at (ox, oy),
    and the projected vertices (buffer pixels)."""
    q = V @ R.T + t
    z = q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = q[:, 0] / z
        yn = q[:, 1] / z
    sx = kvec[0] * xn + kvec[1] * yn + kvec[2] - ox
    sy = kvec[3] * yn + kvec[4] - oy
    sx = np.where(z > _raster.NEAR_MM, sx, 0.0)
    sy = np.where(z > _raster.NEAR_MM, sy, 0.0)
    zbuf = np.full(shape, np.inf, np.float32)
    fbuf = np.full(shape, -1, np.int32)
    _raster.rasterize(sx, sy, z, faces, zbuf, fbuf)
    return zbuf, fbuf, sx, sy


def _face_neighbours(faces: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Per face, the faces across its three edges (-1: a boundary edge), (F, 3) int64.

    Where more than two faces share an edge, each is given one of the others.
    """
    f = np.asarray(faces, dtype=np.int64)
    n_f = len(f)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.minimum(e[:, 0], e[:, 1]) * (int(f.max(initial=0)) + 1) + np.maximum(e[:, 0], e[:, 1])
    owner = np.tile(np.arange(n_f), 3)
    slot = np.repeat(np.arange(3), n_f)
    order = np.argsort(key, kind="stable")
    k, o, sl = key[order], owner[order], slot[order]
    out = np.full((n_f, 3), -1, np.int64)
    same = k[1:] == k[:-1]
    # Consecutive edges with the same key are the same edge seen from two faces.
    a = np.flatnonzero(same)
    out[o[a], sl[a]] = o[a + 1]
    out[o[a + 1], sl[a + 1]] = o[a]
    return out


def _part_dirt(V, faces, double_area, count, stream):
    """Dirt spots on the part surface: centres, radii and remaining reflectance."""
    if count == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    rng = np.random.default_rng(stream)
    prob = double_area / double_area.sum()
    idx = rng.choice(len(faces), size=count, p=prob)
    r1 = np.sqrt(rng.random(count))
    r2 = rng.random(count)
    a = V[faces[idx, 0]]
    b = V[faces[idx, 1]]
    c = V[faces[idx, 2]]
    centres = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    radii = rng.uniform(1.5, 5.0, count)
    keep = rng.uniform(0.15, 0.5, count)
    return np.ascontiguousarray(centres), radii, keep


def _lens_dust(img: npt.NDArray[np.float32], count: int, rng: np.random.Generator) -> None:
    """Darken ``img`` in place with soft out-of-focus dust blobs."""
    H, W = img.shape
    for _ in range(count):
        cx = rng.uniform(0, W)
        cy = rng.uniform(0, H)
        r = rng.uniform(20.0, 60.0)
        depth = rng.uniform(0.25, 0.55)
        x0, x1 = max(int(cx - r), 0), min(int(cx + r) + 1, W)
        y0, y1 = max(int(cy - r), 0), min(int(cy + r) + 1, H)
        if x0 >= x1 or y0 >= y1:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        s = np.clip(1.0 - np.hypot(xx - cx, yy - cy) / r, 0.0, 1.0)
        img[y0:y1, x0:x1] *= (1.0 - depth * s * s * (3.0 - 2.0 * s)).astype(np.float32)


def _belt_texture(rig: Rig) -> npt.NDArray[np.float32]:
    """Belt albedo: fine fabric grain plus coarse wear, periodic along x."""
    conv = rig.conveyor
    tx = int(round(_BELT_PERIOD_MM / _TEXEL_MM))
    ty = int(np.ceil(conv.width_mm / _TEXEL_MM)) + 2
    rng = np.random.default_rng(conv.texture_seed)
    pad = 96
    noise = rng.standard_normal((ty + 2 * pad, tx), dtype=np.float32)
    wrapped = np.concatenate([noise[:, -pad:], noise, noise[:, :pad]], axis=1)

    def smooth(sigma: float) -> npt.NDArray[np.float32]:
        out = cv2.GaussianBlur(wrapped, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        out = out[pad:-pad, pad:-pad]
        return out / out.std()

    fine = smooth(1.2)  # ~0.6 mm fabric grain
    coarse = smooth(20.0)  # ~10 mm mottling and wear
    t = 0.8 * fine + 0.6 * coarse
    t /= t.std()
    albedo = conv.albedo * np.clip(1.0 + conv.texture_contrast * t, 0.2, 2.0)
    return np.ascontiguousarray(albedo.astype(np.float32))


_BOARD_TEXTURES: dict[CharucoSpec, npt.NDArray[np.uint8]] = {}


def _board_texture(spec: CharucoSpec) -> npt.NDArray[np.uint8]:
    tex = _BOARD_TEXTURES.get(spec)
    if tex is None:
        tex = np.ascontiguousarray(spec.texture(_BOARD_PX_PER_MM))
        _BOARD_TEXTURES.clear()  # one board at a time is the normal case
        _BOARD_TEXTURES[spec] = tex
    return tex
