"""Perspective maps: which point of a slightly moved CAD surface a pixel sees, without a ray cast.

A :class:`PerspectiveMap` is the CAD drawn once into a view (a camera, or
the rectified left view of a stereo pair) at a reference pose: per pixel the
face it sees, the 3D point, the face's normal and its plane's offset
``c = n . p``. When the part then lies at a pose a small rigid motion
``T = (R, t)`` away from the reference (rig frame: moved points are
``R x + t``), the face's plane moves to ``(R n) . x = c + (R n) . t``, and
the pixel's ray ``o + s d`` meets it at

    s = (c + n' . t - n' . o) / (n' . d),   n' = R n,

exact for a planar facet (:meth:`PerspectiveMap.query`). The answer holds
while the ray still meets that facet inside its edges, which is checked by
mapping the point back into the reference pose (barycentric coordinates of
the facet), and while no other part of the surface moves in front of it.

**Validity range.** The map is built for motions that move no point of the
part by more than ``max_motion_mm``. Occlusion changes only where the view
shows a depth step (an outline, a flange over the belt): the pixels within
as many pixels of a step as such a motion can shift it are marked at build
time and always ray cast. A pixel whose point leaves its facet (a crease
crossed, a facet's edge) is ray cast as well. A motion beyond the range is
answered by ray casting every pixel. Ray casts are exact: the facet comes
from the mesh's ray intersector, the point from the same plane
intersection in float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit
from scipy.spatial import cKDTree

from ._jit import NO_RUNTIME
from .arrays import Faces, Points, Transform, Vectors, mesh_arrays
from .errors import InvalidInput
from .validate import validate_transform

DEFAULT_MAX_MOTION_MM = 2.0
"""The validity range's default: no point of the part moved by more than this."""

# A depth step between neighbouring pixels: their points further apart than this
# many footprints (a surface seen at 84 deg from its normal stretches ~10).
_STEP_FOOTPRINTS = 12.0
# A point back in its facet: barycentric coordinates down to -this (float64
# rounding on a facet's edge, where both facets give the same point).
_INSIDE_EPS = 1e-9
# Facets a point may walk across from the one it was seen on (a motion within the
# range crosses a few facets of a fine mesh).
_WALK = 16


class RayCaster:
    """Exact ray casting on a mesh in its own frame: the first facet hit and the point.

    The facet comes from trimesh's intersector (Embree where installed), the
    point from the ray's intersection with that facet's plane in float64.

    Parameters
    ----------
    mesh : CadModel or trimesh.Trimesh
        Anything with ``vertices`` (V, 3) mm and ``faces`` (F, 3).
    """

    def __init__(self, mesh: Any) -> None:
        import trimesh  # reading CAD already needs it; imported where used

        v, f = mesh_arrays(mesh)
        self.vertices: Points = v
        self.faces: Faces = f
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1)
        self.normals = n / np.where(norm > 0, norm, 1.0)[:, None]
        self.offsets = np.einsum("ij,ij->i", self.normals, tri[:, 0])
        self.triangles: npt.NDArray[np.float64] = np.ascontiguousarray(tri)
        self.neighbours = face_neighbours(f)
        centres = tri.mean(axis=1)
        self._reach = float(np.linalg.norm(tri - centres[:, None], axis=2).max()) if len(f) else 0.0
        self._centres = cKDTree(centres)
        self._mesh = trimesh.Trimesh(v, f, process=False)
        self._intersector = self._mesh.ray

    def near(self, point: npt.ArrayLike, radius_mm: float) -> npt.NDArray[np.int64]:
        """(K,) int64, sorted: the facets with a point within ``radius_mm`` of ``point``
        (and a few more: those whose centre lies within the radius and the largest
        facet's reach)."""
        idx = self._centres.query_ball_point(np.asarray(point, dtype=np.float64),
                                             radius_mm + self._reach)  # fmt: skip
        return np.sort(np.asarray(idx, dtype=np.int64))

    def cast(self, origins: Points, directions: Points) -> tuple[npt.NDArray[np.int64], Points]:
        """First hits of rays (mesh frame): facet (M,) int64, -1 for a miss, and point (M, 3),
        NaN for a miss."""
        m = len(origins)
        face = np.full(m, -1, np.int64)
        pts = np.full((m, 3), np.nan)
        if m == 0:
            return face, pts
        hit = np.asarray(self._intersector.intersects_first(origins, directions), np.int64)
        ok = hit >= 0
        face[ok] = hit[ok]
        n = self.normals[hit[ok]]
        o, d = origins[ok], directions[ok]
        s = (self.offsets[hit[ok]] - np.einsum("ij,ij->i", n, o)) / np.einsum("ij,ij->i", n, d)
        pts[ok] = o + s[:, None] * d
        return face, pts


@dataclass(frozen=True, eq=False)
class PerspectiveMap:
    """The CAD seen through a rectangle of a view's pixels at a reference pose.

    Build with :meth:`build`; query with :meth:`query`.

    Attributes
    ----------
    corner : (int, int)
        The rectangle's first pixel (x0, y0) in the view.
    shape : (int, int)
        Its (height, width); the maps below are flat, row by row (N = H W).
    origins, directions : (N, 3) float64, rig frame
        Each pixel's ray (unit directions).
    face : (N,) int64
        The facet seen at the reference pose (-1: none).
    points : (N, 3) float64, mm, rig frame
        The point seen (NaN: none).
    normals : (N, 3) float64
        The facet's unit normal at the reference pose.
    offsets : (N,) float64, mm
        ``normals . points``: the facet's plane.
    step : (N,) bool
        Pixels near a depth step, always ray cast (see the module notes).
    T_rig_cad : (4, 4) float64
        The reference pose.
    max_motion_mm : float
        The validity range: motions that move no point of the part further.
    margin_px : int
        How far from a depth step such a motion can shift the view.
    caster : RayCaster
        The CAD's exact ray casting (CAD frame), for what the map cannot answer.
    """

    corner: tuple[int, int]
    shape: tuple[int, int]
    origins: Points = field(repr=False)
    directions: Points = field(repr=False)
    face: npt.NDArray[np.int64] = field(repr=False)
    points: Points = field(repr=False)
    normals: Points = field(repr=False)
    offsets: npt.NDArray[np.float64] = field(repr=False)
    step: npt.NDArray[np.bool_] = field(repr=False)
    T_rig_cad: Transform = field(repr=False)
    max_motion_mm: float
    margin_px: int
    caster: RayCaster = field(repr=False)

    @classmethod
    def build(
        cls,
        caster: RayCaster,
        T_rig_cad: npt.ArrayLike,
        origins: npt.ArrayLike,
        directions: npt.ArrayLike,
        shape: tuple[int, int],
        *,
        corner: tuple[int, int] = (0, 0),
        max_motion_mm: float = DEFAULT_MAX_MOTION_MM,
        faces: npt.ArrayLike | None = None,
    ) -> PerspectiveMap:
        """Draw the CAD at ``T_rig_cad`` through the given pixel rays.

        Parameters
        ----------
        caster : RayCaster
            The CAD's (built once per part).
        T_rig_cad : (4, 4)
            The reference pose (CAD frame -> rig frame).
        origins, directions : (H W, 3) float64, rig frame
            The rays of the rectangle's pixels, row by row (:func:`camera_rays`,
            :func:`rectified_rays`).
        shape : (int, int)
            (H, W).
        corner : (int, int)
            The rectangle's first pixel in the view (bookkeeping for callers).
        max_motion_mm : float
            The validity range (see the module notes).
        faces : (H W,) int, optional
            The facet each pixel sees, drawn by a rasteriser (:func:`pinhole_faces`):
            each pixel's point is then found from it by the query's plane
            intersection and walk, and ray cast only where that fails. None:
            every pixel is ray cast.
        """
        T = validate_transform(T_rig_cad, name="T_rig_cad")
        h, w = int(shape[0]), int(shape[1])
        o = np.ascontiguousarray(origins, dtype=np.float64)
        d = np.ascontiguousarray(directions, dtype=np.float64)
        if o.shape != (h * w, 3) or d.shape != (h * w, 3) or h < 1 or w < 1:
            raise InvalidInput(f"origins and directions must be ({h * w}, 3) for shape {shape}")
        if not (np.isfinite(o).all() and np.isfinite(d).all()):
            raise InvalidInput("pixel rays must be finite")
        if not (math.isfinite(max_motion_mm) and max_motion_mm > 0):
            raise InvalidInput(f"max_motion_mm must be finite and > 0, got {max_motion_mm!r}")
        d = d / _norms(d)[:, None]
        return draw_map(caster, T, o, d, (h, w), corner, float(max_motion_mm), faces)

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]

    def motion_mm(self, T_delta: Transform) -> float:
        """The largest displacement of the CAD's bounding-box corners under ``T_delta``
        (rig frame, applied to the part at the reference pose)."""
        v = self.caster.vertices
        lo, hi = v.min(axis=0), v.max(axis=0)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])  # fmt: skip
        c = corners @ self.T_rig_cad[:3, :3].T + self.T_rig_cad[:3, 3]
        moved = c @ T_delta[:3, :3].T + T_delta[:3, 3]
        return float(np.linalg.norm(moved - c, axis=1).max())

    def query(
        self, pixels: npt.ArrayLike, T_delta: npt.ArrayLike
    ) -> tuple[Points, npt.NDArray[np.int64], int]:
        """The points that ``pixels`` see on the surface moved by ``T_delta``.

        Parameters
        ----------
        pixels : (M,) int
            Indices into the map (row-major over its rectangle).
        T_delta : (4, 4)
            The motion from the reference pose, rig frame: the part lies at
            ``T_delta @ T_rig_cad``.

        Returns
        -------
        points : (M, 3) float64, mm, rig frame
            NaN where the ray misses the part.
        face : (M,) int64
            The facet seen, -1 for a miss.
        cast : int
            How many of the pixels were ray cast (beyond the range, near a
            depth step, or off their facet).
        """
        T = validate_transform(T_delta, name="T_delta")
        idx = np.asarray(pixels, dtype=np.int64)
        if idx.ndim != 1 or (len(idx) and (idx.min() < 0 or idx.max() >= self.size)):
            raise InvalidInput(f"pixels must be indices into the map's {self.size} pixels")
        m = len(idx)
        out = np.full((m, 3), np.nan)
        face = np.full(m, -1, np.int64)
        todo = np.ones(m, np.bool_)
        if self.motion_mm(T) <= self.max_motion_mm:
            T_rig = T @ self.T_rig_cad
            c = self.caster
            _query_planes(
                idx, self.origins, self.directions, self.face, self.step,
                np.ascontiguousarray(np.linalg.inv(T_rig)), np.ascontiguousarray(T_rig),
                c.triangles, c.normals, c.offsets, c.neighbours, out, face, todo,
            )  # fmt: skip
        if todo.any():
            T_cad = np.linalg.inv(T @ self.T_rig_cad)
            R, t = T_cad[:3, :3], T_cad[:3, 3]
            o, d = self.origins[idx[todo]], self.directions[idx[todo]]
            f, p = self.caster.cast(o @ R.T + t, d @ R.T)
            Ti = T @ self.T_rig_cad
            face[todo] = f
            out[todo] = p @ Ti[:3, :3].T + Ti[:3, 3]
        return out, face, int(todo.sum())


def draw_map(
    caster: RayCaster,
    T: Transform,
    o: Points,
    d: Points,
    shape: tuple[int, int],
    corner: tuple[int, int],
    max_motion_mm: float,
    faces: npt.ArrayLike | None,
) -> PerspectiveMap:
    """:meth:`PerspectiveMap.build` for callers inside the package, trusted: ``T`` a rigid
    transform, ``o`` and ``d`` (H W, 3) C-contiguous float64 with unit directions."""
    h, w = shape
    face, points, normals = surface_seen(caster, T, o, d, faces)
    seen = face >= 0
    offsets = np.full(h * w, np.nan)
    offsets[seen] = np.einsum("ij,ij->i", normals[seen], points[seen])
    # The view's angular pixel pitch and the nearest depth set the margin a
    # motion of max_motion_mm can shift a depth step by, in pixels.
    pitch = _pixel_pitch(d, h, w)
    depth = np.where(seen, np.einsum("ij,ij->i", points - o, d), np.nan)
    near = float(depth[seen].min()) if seen.any() else 1.0
    margin = int(math.ceil(max_motion_mm / (pitch * near))) + 1
    step = _depth_steps(points.reshape(h, w, 3), seen.reshape(h, w), depth.reshape(h, w) * pitch)
    step = _dilate(step, margin).ravel()
    return PerspectiveMap(
        (int(corner[0]), int(corner[1])), (h, w), o, d, face, points, normals, offsets,
        step, T, max_motion_mm, margin, caster,
    )  # fmt: skip


def surface_seen(
    caster: RayCaster, T: Transform, o: Points, d: Points, faces: npt.ArrayLike | None
) -> tuple[npt.NDArray[np.int64], Points, Vectors]:
    """What each ray sees of the CAD at the pose ``T`` (CAD -> ray frame): its facet (-1:
    none), point and normal, in the rays' frame (NaN where none); what a
    :class:`PerspectiveMap` holds, without what it needs to answer moved poses. Trusted
    arguments, as :func:`draw_map`'s; ``faces``: a rasteriser's facet per ray, or None
    to cast every ray."""
    T_cad_rig = _rigid_inverse(T)
    R, t = T_cad_rig[:3, :3], T_cad_rig[:3, 3]
    if faces is None:
        face, p_cad = caster.cast(o @ R.T + t, d @ R.T)
    else:
        face, p_cad = _from_faces(caster, T, o, d, np.asarray(faces, dtype=np.int64))
    R_rc = T[:3, :3]
    points = p_cad @ R_rc.T + T[:3, 3]
    seen = face >= 0
    normals = np.full((len(face), 3), np.nan)
    normals[seen] = caster.normals[face[seen]] @ R_rc.T
    return face, points, normals


def _rigid_inverse(T: Transform) -> Transform:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _norms(v: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Euclidean norms along the last axis (einsum: cheaper than linalg.norm on small arrays)."""
    out: npt.NDArray[np.float64] = np.sqrt(np.einsum("...i,...i->...", v, v))
    return out


@njit(cache=True, nogil=True, **NO_RUNTIME)
def _query_planes(
    idx,
    origins,
    directions,
    faces,
    step,
    T_cad,
    T_rig,
    tri,
    normals,
    offsets,
    neighbours,
    out,
    face,
    todo,
):  # pragma: no cover - compiled
    """The plane intersections of :meth:`PerspectiveMap.query` for each listed pixel not
    near a depth step; ``todo`` stays True where the pixel must be ray cast.

    The moved facet's plane met by the pixel's ray in the rig frame is the CAD
    facet's plane met by the ray mapped into the CAD frame (``T_cad``): the
    same equation, one transform per ray instead of one per facet. A point
    outside its facet walks to the neighbour across the edge it left by, at
    most ``_WALK`` facets (a continuous surface)."""
    for k in range(idx.shape[0]):
        i = idx[k]
        f = faces[i]
        if step[i]:
            continue
        if f < 0:  # off the part and, within the range, off the moved part too
            todo[k] = False
            continue
        o0 = (
            T_cad[0, 0] * origins[i, 0]
            + T_cad[0, 1] * origins[i, 1]
            + T_cad[0, 2] * origins[i, 2]
            + T_cad[0, 3]
        )
        o1 = (
            T_cad[1, 0] * origins[i, 0]
            + T_cad[1, 1] * origins[i, 1]
            + T_cad[1, 2] * origins[i, 2]
            + T_cad[1, 3]
        )
        o2 = (
            T_cad[2, 0] * origins[i, 0]
            + T_cad[2, 1] * origins[i, 1]
            + T_cad[2, 2] * origins[i, 2]
            + T_cad[2, 3]
        )
        d0 = (
            T_cad[0, 0] * directions[i, 0]
            + T_cad[0, 1] * directions[i, 1]
            + T_cad[0, 2] * directions[i, 2]
        )
        d1 = (
            T_cad[1, 0] * directions[i, 0]
            + T_cad[1, 1] * directions[i, 1]
            + T_cad[1, 2] * directions[i, 2]
        )
        d2 = (
            T_cad[2, 0] * directions[i, 0]
            + T_cad[2, 1] * directions[i, 1]
            + T_cad[2, 2] * directions[i, 2]
        )
        for _ in range(_WALK):
            den = normals[f, 0] * d0 + normals[f, 1] * d1 + normals[f, 2] * d2
            if den >= 0.0:  # the facet faces away from the view: not this one
                break
            s = (offsets[f] - normals[f, 0] * o0 - normals[f, 1] * o1 - normals[f, 2] * o2) / den
            q0 = o0 + s * d0
            q1 = o1 + s * d1
            q2 = o2 + s * d2
            edge = _leaves_by(tri, f, q0, q1, q2)
            if edge < 0:
                out[k, 0] = T_rig[0, 0] * q0 + T_rig[0, 1] * q1 + T_rig[0, 2] * q2 + T_rig[0, 3]
                out[k, 1] = T_rig[1, 0] * q0 + T_rig[1, 1] * q1 + T_rig[1, 2] * q2 + T_rig[1, 3]
                out[k, 2] = T_rig[2, 0] * q0 + T_rig[2, 1] * q1 + T_rig[2, 2] * q2 + T_rig[2, 3]
                face[k] = f
                todo[k] = False
                break
            f = neighbours[f, edge]
            if f < 0:
                break


@njit(cache=True, nogil=True, inline="always")
def _leaves_by(tri, f, q0, q1, q2):  # pragma: no cover - compiled
    """-1 when the point q (on facet f's plane) lies inside the facet (barycentric
    coordinates >= -_INSIDE_EPS), else the vertex whose coordinate is the most negative:
    the point left across the edge opposite it."""
    a0, a1, a2 = tri[f, 0, 0], tri[f, 0, 1], tri[f, 0, 2]
    e00, e01, e02 = tri[f, 1, 0] - a0, tri[f, 1, 1] - a1, tri[f, 1, 2] - a2
    e10, e11, e12 = tri[f, 2, 0] - a0, tri[f, 2, 1] - a1, tri[f, 2, 2] - a2
    w0, w1, w2 = q0 - a0, q1 - a1, q2 - a2
    d00 = e00 * e00 + e01 * e01 + e02 * e02
    d01 = e00 * e10 + e01 * e11 + e02 * e12
    d11 = e10 * e10 + e11 * e11 + e12 * e12
    d20 = w0 * e00 + w1 * e01 + w2 * e02
    d21 = w0 * e10 + w1 * e11 + w2 * e12
    den = d00 * d11 - d01 * d01
    if den <= 0.0:
        return 0
    b1 = (d11 * d20 - d01 * d21) / den
    b2 = (d00 * d21 - d01 * d20) / den
    b0 = 1.0 - b1 - b2
    if b0 >= -_INSIDE_EPS and b1 >= -_INSIDE_EPS and b2 >= -_INSIDE_EPS:
        return -1
    if b0 <= b1 and b0 <= b2:
        return 0
    if b1 <= b2:
        return 1
    return 2


def _from_faces(
    caster: RayCaster, T_rig_cad: Transform, o: Points, d: Points, hint: npt.NDArray[np.int64]
) -> tuple[npt.NDArray[np.int64], Points]:
    """Each ray's facet and point (CAD frame) from a rasteriser's facets: the plane met and
    walked on as in a query without motion, ray cast where that fails."""
    n = len(o)
    if hint.shape != (n,) or (hint >= len(caster.faces)).any():
        raise InvalidInput(f"faces must be ({n},) facet indices of the mesh (-1: none)")
    out = np.full((n, 3), np.nan)
    face = np.full(n, -1, np.int64)
    todo = np.ones(n, np.bool_)
    T_cad = np.ascontiguousarray(_rigid_inverse(T_rig_cad))
    _query_planes(
        np.arange(n, dtype=np.int64), o, d, hint, np.zeros(n, np.bool_), T_cad,
        np.eye(4), caster.triangles, caster.normals, caster.offsets, caster.neighbours,
        out, face, todo,
    )  # fmt: skip
    todo &= hint >= 0  # a facet drawn there, yet the ray leaves it: cast it exactly
    if todo.any():
        R, t = T_cad[:3, :3], T_cad[:3, 3]
        face[todo], out[todo] = caster.cast(o[todo] @ R.T + t, d[todo] @ R.T)
    return face, out


@dataclass(frozen=True, eq=False)
class FacetSet:
    """Some facets of a :class:`RayCaster`'s mesh, as a mesh of their own (for drawing).

    Attributes
    ----------
    ids : (K,) int64
        The facets.
    vertices : (U,) int64
        The mesh's vertices they use.
    faces : (K, 3) int64
        The facets, indexing ``vertices``.
    """

    ids: npt.NDArray[np.int64]
    vertices: npt.NDArray[np.int64]
    faces: npt.NDArray[np.int64]

    @classmethod
    def of(cls, caster: RayCaster, ids: npt.ArrayLike) -> FacetSet:
        f = np.asarray(ids, dtype=np.int64)
        used, local = np.unique(caster.faces[f], return_inverse=True)
        return cls(f, used.astype(np.int64), local.reshape(-1, 3).astype(np.int64))


def pinhole_faces(
    caster: RayCaster,
    T_rig_cad: Transform,
    facets: FacetSet,
    R_view_rig: npt.NDArray[np.float64],
    centre: npt.NDArray[np.float64],
    f_px: float,
    principal: tuple[float, float],
    corner: tuple[int, int],
    shape: tuple[int, int],
) -> npt.NDArray[np.int64]:
    """The facet (of ``facets``) nearest to a pinhole view at each pixel of a rectangle, by
    the simulator's z-buffer: the ``faces`` hint of :meth:`PerspectiveMap.build`. Callers
    are trusted (``T_rig_cad`` rigid).

    Parameters
    ----------
    caster : RayCaster
    T_rig_cad : (4, 4) float64
        The pose the CAD is drawn at.
    facets : FacetSet
        The facets drawn (e.g. those near a point); others are never seen.
    R_view_rig, centre, f_px, principal
        The pinhole: rotation rig -> view (rows x, y, optical axis), its
        centre (rig frame, mm), focal length and principal point (px).
    corner, shape
        The rectangle's first pixel (x0, y0) and (H, W).

    Returns
    -------
    (H W,) int64
        Facet indices of the mesh, row by row; -1 where none is drawn.
    """
    from ._raster import rasterize

    R = np.asarray(R_view_rig) @ T_rig_cad[:3, :3]
    q = caster.vertices[facets.vertices] @ R.T + (R_view_rig @ (T_rig_cad[:3, 3] - centre))
    z = q[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = f_px * q[:, 0] / z + principal[0] - corner[0]
        sy = f_px * q[:, 1] / z + principal[1] - corner[1]
    h, w = shape
    zbuf = np.full((h, w), np.inf, np.float32)
    fbuf = np.full((h, w), -1, np.int32)
    rasterize(sx, sy, z, facets.faces, zbuf, fbuf)
    out = np.full(h * w, -1, np.int64)
    drawn = fbuf.ravel() >= 0
    out[drawn] = facets.ids[fbuf.ravel()[drawn]]
    return out


def face_neighbours(faces: Faces) -> npt.NDArray[np.int64]:
    """(F, 3) int64: the facet across the edge opposite each vertex of each facet (-1: an
    open or non-manifold edge)."""
    nf = len(faces)
    a = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    b = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    key = np.minimum(a, b).astype(np.int64) * (int(faces.max()) + 1) + np.maximum(a, b)
    slot = np.arange(3 * nf)  # slot k * nf + f: facet f's edge opposite its vertex k
    order = np.argsort(key, kind="stable")
    ks = key[order]
    first = np.r_[True, ks[1:] != ks[:-1]]
    start = np.flatnonzero(first)
    count = np.diff(np.r_[start, len(ks)])
    out = np.full(3 * nf, -1, np.int64)
    two = start[count == 2]
    s0, s1 = slot[order[two]], slot[order[two + 1]]
    out[s0] = s1 % nf
    out[s1] = s0 % nf
    return np.ascontiguousarray(out.reshape(3, nf).T)


def _pixel_pitch(d: Points, h: int, w: int) -> float:
    """The smallest angle between neighbouring pixels' rays (radians), along the rectangle's
    border rows and columns (the pitch varies smoothly across a view)."""
    g = d.reshape(h, w, 3)
    pitches = []
    if w > 1:
        pitches += [float(_norms(g[k, 1:] - g[k, :-1]).min()) for k in (0, h - 1)]
    if h > 1:
        pitches += [float(_norms(g[1:, k] - g[:-1, k]).min()) for k in (0, w - 1)]
    return min(pitches) if pitches else 1e-3


def _depth_steps(
    points: npt.NDArray[np.float64], seen: npt.NDArray[np.bool_], footprint: npt.NDArray[np.float64]
) -> npt.NDArray[np.bool_]:
    """Pixels beside a depth step: a neighbour that sees nothing (an outline), or whose
    point lies more than ``_STEP_FOOTPRINTS`` footprints away."""
    step = np.zeros(seen.shape, np.bool_)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis] = slice(None, -1)
        b[axis] = slice(1, None)
        sa, sb = tuple(a), tuple(b)
        with np.errstate(invalid="ignore"):
            gap = _norms(points[sa] - points[sb])
            far = gap > _STEP_FOOTPRINTS * np.fmin(footprint[sa], footprint[sb])
        edge = (seen[sa] != seen[sb]) | (seen[sa] & seen[sb] & far)
        step[sa] |= edge
        step[sb] |= edge
    return step


def _dilate(mask: npt.NDArray[np.bool_], r: int) -> npt.NDArray[np.bool_]:
    import cv2

    if not mask.any() or r <= 0:
        return mask
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return np.asarray(cv2.dilate(mask.astype(np.uint8), k), dtype=bool)


def camera_rays(
    camera: Any, corner: tuple[int, int], shape: tuple[int, int]
) -> tuple[Points, Points]:
    """The rays (rig frame) of a rectangle of a :class:`~inspection.rig.Camera`'s pixels,
    row by row, lens distortion undone exactly."""
    (x0, y0), (h, w) = corner, shape
    v, u = np.mgrid[y0 : y0 + h, x0 : x0 + w]
    px = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    o, d = camera.rays(px)
    return np.ascontiguousarray(o), np.ascontiguousarray(d)


def rectified_rays(
    pair: Any, corner: tuple[int, int], shape: tuple[int, int]
) -> tuple[Points, Points]:
    """The rays (rig frame) of a rectangle of a rectified pair's left view, row by row
    (:class:`~inspection.reconstruct.pairs.RectifiedPair`: a pinhole without distortion)."""
    (x0, y0), (h, w) = corner, shape
    v, u = np.mgrid[y0 : y0 + h, x0 : x0 + w]
    r = np.empty((h * w, 3))
    r[:, 0] = (u.ravel() - pair.cx_left) / pair.f_px
    r[:, 1] = (v.ravel() - pair.cy) / pair.f_px
    r[:, 2] = 1.0
    d = r @ pair.R_rect_rig
    d /= _norms(d)[:, None]
    o = np.broadcast_to(pair.centre_left, d.shape).copy()
    return o, d


__all__ = [
    "DEFAULT_MAX_MOTION_MM",
    "FacetSet",
    "PerspectiveMap",
    "RayCaster",
    "camera_rays",
    "draw_map",
    "face_neighbours",
    "pinhole_faces",
    "rectified_rays",
    "surface_seen",
]
