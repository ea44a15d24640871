"""Synthetic measured clouds for the registration, alignment and deviation tests.

A "measurement" here is the side of a part that faces a sensor above it
(faces turned towards +z, or towards one of the rig's four cameras; no
renderer), with Gaussian noise, optionally with
reflection blobs: clusters of points pushed 1-5 mm off the surface.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from inspection.alignment import DEFAULT_MIN_COS, sample_facing
from inspection.cad import CadModel
from inspection.rig import Rig
from inspection.transforms import apply


def perturbation(rng: np.random.Generator, deg: float, mm: float, center: np.ndarray) -> np.ndarray:
    """A rigid transform turning by ``deg`` about a random axis through ``center``
    and shifting by ``mm`` in a random direction."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R = Rotation.from_rotvec(axis * np.radians(deg)).as_matrix()
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = center - R @ center + mm * d
    return T


def measure(
    cad: CadModel,
    T_data_cad: np.ndarray,
    n: int,
    *,
    noise_mm: float = 0.02,
    seed: int = 0,
    min_cos: float = DEFAULT_MIN_COS,
    views: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Points on the sensor-facing side (faces whose normal's cosine to +z of
    the data frame, or to one of ``views``, exceeds ``min_cos``), in the data
    frame, and their data-frame normals."""
    rng = np.random.default_rng(seed + 1000)
    pts, face = sample_facing(
        cad.vertices,
        cad.faces,
        cad.face_normals,
        T_data_cad,
        n,
        seed=seed,
        min_cos=min_cos,
        views=views,
    )
    normals = cad.face_normals[face] @ T_data_cad[:3, :3].T
    return pts + rng.normal(scale=noise_mm, size=pts.shape), normals


def rig_views() -> np.ndarray:
    """Directions from the middle of the measurement volume towards each
    camera of the line's rig as built (4, 3): the sensor of the line."""
    rig = Rig.nominal()
    middle = np.array([0.0, 0.0, 100.0])
    centres = np.array([cam.centre for cam in rig.cameras])
    d = centres - middle
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def add_blobs(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    fraction: float = 0.25,
    n_blobs: int = 12,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Push ``fraction`` of the points, in ``n_blobs`` compact clusters, 1-5 mm
    off the surface along its normal (reflection blobs). Returns the new
    points and the boolean mask of the moved ones."""
    rng = np.random.default_rng(seed + 2000)
    out = points.copy()
    moved = np.zeros(len(points), dtype=bool)
    kd = cKDTree(points)
    per_blob = int(round(fraction * len(points) / n_blobs))
    while moved.sum() < fraction * len(points) - 0.5:
        centre = points[rng.integers(len(points))]
        _, idx = kd.query(centre, k=min(len(points), 4 * per_blob))
        idx = idx[~moved[idx]][
            : min(per_blob, int(round(fraction * len(points))) - int(moved.sum()))
        ]
        height = rng.uniform(1.0, 5.0) * rng.choice([-1.0, 1.0])
        # Heights vary inside a blob (a smeared reflection), always 1-5 mm off.
        h = np.clip(height + rng.normal(scale=0.3, size=len(idx)), -5.0, 5.0)
        h = np.where(np.abs(h) < 1.0, np.sign(height), h)
        out[idx] += h[:, None] * normals[idx]
        moved[idx] = True
    return out, moved


def pose_errors(T_est: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """Rotation error (degrees) and RMS displacement error (mm) over ``points``."""
    dR = T_est[:3, :3] @ T_true[:3, :3].T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0))))
    a = apply(T_est, points)
    b = apply(T_true, points)
    return angle, float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def holed_disc(
    radius: float = 150.0,
    thickness: float = 8.0,
    holes: tuple[tuple[float, float, float], ...] = (),
    *,
    spacing: float = 6.0,
) -> CadModel:
    """A flat disc (z from 0 to ``thickness``) with round through-holes, each
    given as (distance from the axis, angle in degrees, radius), all mm.
    Seen from above, only the holes' rims fix its turn about the axis."""
    from scipy.spatial import Delaunay

    def ring(cx: float, cy: float, r: float) -> np.ndarray:
        k = max(24, int(np.ceil(2.0 * np.pi * r / (0.5 * spacing))))
        a = np.arange(k) * (2.0 * np.pi / k)
        return np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])

    centres = [(d * np.cos(np.radians(a)), d * np.sin(a * np.pi / 180.0), r) for d, a, r in holes]
    g = np.arange(-radius, radius + spacing, spacing)
    gx, gy = np.meshgrid(g, g)
    inner = np.column_stack([gx.ravel(), gy.ravel()])
    keep = np.hypot(inner[:, 0], inner[:, 1]) < radius - 0.5 * spacing
    for cx, cy, r in centres:
        keep &= np.hypot(inner[:, 0] - cx, inner[:, 1] - cy) > r + 0.5 * spacing
    xy = np.concatenate([ring(0.0, 0.0, radius), *[ring(*c) for c in centres], inner[keep]])
    tri = Delaunay(xy).simplices
    mid = xy[tri].mean(axis=1)
    solid = np.hypot(mid[:, 0], mid[:, 1]) < radius
    for cx, cy, r in centres:
        solid &= np.hypot(mid[:, 0] - cx, mid[:, 1] - cy) > r
    tri = tri[solid]
    # Counter-clockwise seen from above: the top faces look up.
    e1, e2 = xy[tri[:, 1]] - xy[tri[:, 0]], xy[tri[:, 2]] - xy[tri[:, 0]]
    cw = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
    tri[cw] = tri[cw][:, ::-1]
    n = len(xy)
    vertices = np.concatenate(
        [np.column_stack([xy, np.full(n, thickness)]), np.column_stack([xy, np.zeros(n)])]
    )
    # Walls along the edges that only one triangle has (the outline, the holes).
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    _, inverse, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    border = edges[count[inverse.ravel()] == 1]
    a, b = border[:, 0], border[:, 1]
    walls = np.concatenate([np.column_stack([b, a, a + n]), np.column_stack([b, a + n, b + n])])
    faces = np.concatenate([tri, tri[:, ::-1] + n, walls])
    return CadModel.from_arrays(vertices, faces, name="holed disc")
