"""Closest points on a (trimmed) NURBS surface.

The foot point of ``x`` minimises ``1/2 |S(u, v) - x|^2`` over the surface's
parameters. From a start ``(u, v)`` near it (the best sample of a regular
parameter grid, or the parameters of a tessellation's closest point),
Newton's method on the two parameters,

    [S_u.S_u + r.S_uu  S_u.S_v + r.S_uv] [du]     [S_u.r]
    [S_u.S_v + r.S_uv  S_v.S_v + r.S_vv] [dv] = - [S_v.r],    r = S - x,

converges quadratically; where that Hessian is not positive definite (far
off the concave side) the step is Gauss-Newton's (without the ``r.S``
terms), which still descends. Steps are clipped to the domain.

**Trimming.** A :class:`Trim` is the simple model of a trimmed face: a
boundary polygon in parameter space and the polygons of its holes, the face
being the part of the parameter domain inside the one and outside the
others. A foot point found off the face is not on it; the closest point of
the face then lies on its boundary, the image of the polygons' edges, found
by the nearest of dense samples of that image and Gauss-Newton along the
edge's own parameter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InvalidInput
from . import kernels
from .knots import FloatArray
from .surface import Surface

# Gauss-Newton stops when a step moves the point by less than this (mm).
_STEP_TOL_MM = 1e-10
_MAX_STEPS = 30
# Samples per polygon edge of a trim boundary's image (the start of the
# search along the edge).
_EDGE_SAMPLES = 16
# Elements of the (points, edges) arrays of one chunk of Trim.contains.
_CONTAINS_CELLS = 1 << 20


@dataclass(frozen=True)
class Trim:
    """The boundary of a trimmed face in parameter space: an outer polygon and
    the holes in it.

    Parameters
    ----------
    polygon : (k, 2) float64, (u, v) vertices of a simple polygon, k >= 3
        (either orientation; not closed: the last vertex joins the first).
    holes : tuple of (k_i, 2) float64 polygons inside ``polygon``, not
        overlapping one another.
    """

    polygon: FloatArray
    holes: tuple[FloatArray, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "polygon", _loop(self.polygon))
        object.__setattr__(self, "holes", tuple(_loop(h) for h in self.holes))

    def edges(self) -> tuple[FloatArray, FloatArray]:
        """Start and end points (e, 2) of every edge of every loop."""
        a = np.concatenate([self.polygon, *self.holes])
        b = np.concatenate([np.roll(loop, -1, axis=0) for loop in (self.polygon, *self.holes)])
        return a, b

    def check_within(self, surface: Surface) -> None:
        """InvalidInput unless the polygon lies in the surface's parameter domain."""
        lo = np.array([surface.domain_u[0], surface.domain_v[0]])
        hi = np.array([surface.domain_u[1], surface.domain_v[1]])
        if np.any(self.polygon < lo) or np.any(self.polygon > hi):
            raise InvalidInput(
                f"the trim polygon leaves the parameter domain {surface.domain_u} x "
                f"{surface.domain_v}"
            )

    def contains(self, uv: Any) -> np.ndarray:
        """(n,) bool: whether each (u, v) lies on the face: inside the polygon
        and in none of its holes (the even-odd rule over all loops)."""
        p = np.asarray(uv, dtype=np.float64)
        a, b = self.edges()
        out = np.empty(p.shape[0], dtype=bool)
        # In chunks of points: the test holds a (points, edges) array.
        rows = max(1, _CONTAINS_CELLS // max(a.shape[0], 1))
        for lo in range(0, p.shape[0], rows):
            u, v = p[lo : lo + rows, 0:1], p[lo : lo + rows, 1:2]
            crosses = (a[None, :, 1] > v) != (b[None, :, 1] > v)
            with np.errstate(divide="ignore", invalid="ignore"):
                at = a[None, :, 0] + (v - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (
                    b[None, :, 1] - a[None, :, 1]
                )
            out[lo : lo + rows] = np.sum(crosses & (u < at), axis=1) % 2 == 1
        return out


def _loop(polygon: Any) -> FloatArray:
    poly = np.array(polygon, dtype=np.float64)
    if poly.ndim != 2 or poly.shape[1] != 2 or poly.shape[0] < 3:
        raise InvalidInput(f"a trim polygon must have shape (k >= 3, 2), got {poly.shape}")
    if not np.all(np.isfinite(poly)):
        raise InvalidInput("a trim polygon must be finite")
    area = 0.5 * np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    if abs(area) <= 0:
        raise InvalidInput("a trim polygon must enclose an area")
    poly.setflags(write=False)
    return poly


@dataclass(frozen=True)
class SurfaceClosest:
    """Closest points on a surface, one row per query point.

    Attributes
    ----------
    points : (n, 3) float64, mm, the closest surface point
    params : (n, 2) float64, its (u, v)
    normals : (n, 3) float64, unit normal S_u x S_v / |S_u x S_v| there
    distances : (n,) float64, mm, signed: positive on the normal's side
    on_boundary : (n,) bool, the closest point lies on the trim boundary
    converged : (n,) bool, the last step would have moved less than 1e-10 mm
    """

    points: FloatArray
    params: FloatArray
    normals: FloatArray
    distances: FloatArray
    on_boundary: np.ndarray
    converged: np.ndarray


def grid_start(surface: Surface, points: FloatArray, samples: int = 64) -> FloatArray:
    """(n, 2) start parameters: the nearest of a samples x samples parameter grid."""
    us = np.linspace(*surface.domain_u, samples)
    vs = np.linspace(*surface.domain_v, samples)
    grid = surface.evaluate_grid(us, vs)
    _, j = cKDTree(grid.reshape(-1, 3)).query(points)
    return np.stack([us[j // samples], vs[j % samples]], axis=1)


def closest_points(
    surface: Surface, points: Any, start: Any = None, *, trim: Trim | None = None
) -> SurfaceClosest:
    """Closest points on a surface (inside its trim polygon, when given).

    Parameters
    ----------
    surface : Surface
    points : (n, 3) float64, mm
    start : (n, 2) float64 start parameters near the foot points; by default
        the nearest sample of a regular parameter grid (:func:`grid_start`)
    trim : Trim, optional

    Returns
    -------
    SurfaceClosest
    """
    x = np.array(points, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or not np.all(np.isfinite(x)):
        raise InvalidInput(f"points must be a finite (n, 3) array, got shape {x.shape}")
    if trim is not None:
        trim.check_within(surface)
    if start is None:
        uv = grid_start(surface, x)
    else:
        uv = np.array(start, dtype=np.float64)
        if uv.shape != (x.shape[0], 2) or not np.all(np.isfinite(uv)):
            raise InvalidInput(f"start must be a finite ({x.shape[0]}, 2) array, got {uv.shape}")
    lo = np.array([surface.domain_u[0], surface.domain_v[0]])
    hi = np.array([surface.domain_u[1], surface.domain_v[1]])
    uv = np.clip(uv, lo, hi)
    uv, converged, (s, su, sv) = _newton(surface, x, uv, lo, hi)
    on_boundary = np.zeros(x.shape[0], dtype=bool)
    if trim is not None:
        outside = ~trim.contains(uv)
        if outside.any():
            uv[outside] = _closest_on_boundary(surface, trim, x[outside])
            on_boundary[outside] = True
            converged[outside] = True
            s[outside], su[outside], sv[outside] = surface.evaluate(
                uv[outside, 0], uv[outside, 1], derivatives=1
            )
    n = np.cross(su, sv)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = x - s
    along = np.einsum("ij,ij->i", d, n)
    # Off the boundary the offset is along the normal; on it, the distance is
    # the full offset, with the side the normal tells.
    dist = np.where(on_boundary, np.sign(along) * np.linalg.norm(d, axis=1), along)
    return SurfaceClosest(s, uv, n, dist, on_boundary, converged)


def _newton(
    surface: Surface, x: FloatArray, uv: FloatArray, lo: FloatArray, hi: FloatArray
) -> tuple[FloatArray, np.ndarray, tuple[FloatArray, FloatArray, FloatArray]]:
    """Foot parameters, whether each converged, and the surface's point and
    first derivatives there."""
    uv = np.ascontiguousarray(uv, dtype=np.float64).copy()
    n = x.shape[0]
    converged = np.zeros(n, dtype=np.bool_)
    pts, d_du, d_dv = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    kernels.closest_newton(
        surface.degree_u, surface.degree_v, surface.knots_u, surface.knots_v,
        surface.homogeneous, np.ascontiguousarray(x), uv, lo[0], hi[0], lo[1], hi[1],
        _STEP_TOL_MM, _MAX_STEPS, converged, pts, d_du, d_dv,
    )  # fmt: skip
    return uv, converged, (pts, d_du, d_dv)


def _closest_on_boundary(surface: Surface, trim: Trim, x: FloatArray) -> FloatArray:
    """(n, 2) parameters of the closest points of the trim boundary's image."""
    a, b = trim.edges()
    s = np.linspace(0.0, 1.0, _EDGE_SAMPLES, endpoint=False)
    edge = np.repeat(np.arange(a.shape[0]), _EDGE_SAMPLES)
    frac = np.tile(s, a.shape[0])
    uv = a[edge] + frac[:, None] * (b[edge] - a[edge])
    pts = surface.evaluate(uv[:, 0], uv[:, 1])
    _, j = cKDTree(pts).query(x)
    e, t = edge[j], frac[j]
    du = b[e] - a[e]
    # Gauss-Newton along the edge: d/dt S(a + t (b - a)) = S_u du_u + S_v du_v.
    for _ in range(_MAX_STEPS):
        q = a[e] + t[:, None] * du
        p, su, sv = surface.evaluate(q[:, 0], q[:, 1], derivatives=1)
        dt_vec = su * du[:, :1] + sv * du[:, 1:]
        g = np.einsum("ij,ij->i", dt_vec, p - x)
        h = np.einsum("ij,ij->i", dt_vec, dt_vec)
        new = np.clip(t - g / np.maximum(h, 1e-300), 0.0, 1.0)
        moved = np.abs(new - t) * np.sqrt(h)
        t = new
        if np.all(moved < _STEP_TOL_MM):
            break
    return a[e] + t[:, None] * du
