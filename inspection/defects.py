"""Injected defects: records of what the simulator did to a part, and pressing them into a mesh.

The simulated line, the benchmarks, the tests and the pictures all damage
parts through this module, so they all press the same defect: a known truth
to check the measurement against. A :class:`Dent` is round, with a flat
bottom out to ``flat_mm`` from its axis (its depth is the deviation over any
support radius within that) and a smoothstep rim that blends back into the
surface at ``radius_mm``; a negative depth makes a bump.

Later kinds (hole shifts, trim offsets, drifts) are further records beside
:class:`Dent`, each with its ``kind``; a FrameSet's truth lists them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import numpy.typing as npt

from .arrays import mesh_arrays
from .errors import InvalidInput

if TYPE_CHECKING:
    import trimesh

FACING_COS = 0.5
"""A vertex is pressed only if its normal lies within 60 degrees of the dent's normal."""


@dataclass(frozen=True)
class Dent:
    """A round dent pressed into a part's surface (part frame, mm).

    Attributes
    ----------
    center_mm : (3,) float, mm
        A point on the dent's axis, normally the surface point at its middle.
    normal : (3,) float
        Outward surface normal there (normalised on construction); the axis
        runs along it, and the surface is pressed along ``-(vertex normal)``.
    depth_mm : float
        Depth of the flat bottom, mm: > 0 into the material, < 0 a bump.
    radius_mm : float
        Where the dent has blended back into the surface, mm (distance from the axis).
    flat_mm : float
        Radius of the flat bottom, mm, ``0 <= flat_mm < radius_mm`` (0: a smooth bowl).
    """

    kind: ClassVar[str] = "dent"

    center_mm: tuple[float, float, float]
    normal: tuple[float, float, float]
    depth_mm: float
    radius_mm: float
    flat_mm: float = 0.0

    def __post_init__(self) -> None:
        c = np.asarray(self.center_mm, dtype=np.float64)
        n = np.asarray(self.normal, dtype=np.float64)
        if (
            c.shape != (3,)
            or n.shape != (3,)
            or not (np.isfinite(c).all() and np.isfinite(n).all())
        ):
            raise InvalidInput("a dent needs a finite center_mm and normal of three numbers")
        length = float(np.linalg.norm(n))
        if not length > 1e-9:
            raise InvalidInput("a dent's normal must not be zero")
        if not np.isfinite(self.depth_mm):
            raise InvalidInput(f"dent depth_mm must be finite, got {self.depth_mm!r}")
        if not (np.isfinite(self.radius_mm) and 0.0 <= self.flat_mm < self.radius_mm):
            raise InvalidInput(
                f"a dent needs 0 <= flat_mm < radius_mm, got {self.flat_mm!r}, {self.radius_mm!r}"
            )
        object.__setattr__(self, "center_mm", tuple(float(v) for v in c))
        object.__setattr__(self, "normal", tuple(float(v) for v in n / length))
        object.__setattr__(self, "depth_mm", float(self.depth_mm))
        object.__setattr__(self, "radius_mm", float(self.radius_mm))
        object.__setattr__(self, "flat_mm", float(self.flat_mm))

    def profile(self, r_mm: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """How far the surface is pressed at distance ``r_mm`` from the axis, as a fraction
        of the depth: 1 across the flat bottom, a smoothstep down to 0 at ``radius_mm``."""
        r = np.asarray(r_mm, dtype=np.float64)
        t = np.clip((r - self.flat_mm) / (self.radius_mm - self.flat_mm), 0.0, 1.0)
        return 1.0 - t * t * (3.0 - 2.0 * t)

    def _frame(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Two unit vectors across the axis (exact for an axis along a coordinate axis)."""
        n = np.asarray(self.normal)
        helper = np.eye(3)[int(np.argmin(np.abs(n)))]
        e1 = np.cross(n, helper)
        e1 /= np.linalg.norm(e1)
        return e1, np.cross(n, e1)

    def axis_distance(self, points: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """(N,) mm: the distance of each point from the dent's axis."""
        e1, e2 = self._frame()
        d = points - np.asarray(self.center_mm)
        return np.hypot(d @ e1, d @ e2)


Defect = Dent
"""Any injected defect (a union as further kinds arrive)."""


def press(
    mesh: Any,
    defects: Sequence[Defect],
    *,
    edge_mm: float = 1.5,
) -> trimesh.Trimesh:
    """A copy of a part with defects pressed into it: a known truth for the measurement.

    Around each dent the mesh is refined first so that its shape is
    resolved: faces whose centres lie within ``radius_mm`` of the axis, plus
    the longest edge there rounded up to whole mm, are split in four as often
    as it takes to bring that edge to ``edge_mm`` or less. Then every vertex
    within ``radius_mm`` of the axis that faces the dent (its normal within
    60 degrees of the dent's) and lies on the outermost such surface (at most
    ``radius_mm`` below the highest one along the normal: a surface further
    in is left alone) moves along its own vertex normal by
    ``depth_mm * profile(r)``. Each dent is measured on the undamaged
    surface; where dents overlap, their depths add.

    Parameters
    ----------
    mesh : trimesh.Trimesh, CadModel, or anything with ``vertices`` (V, 3) and ``faces`` (F, 3)
        The part in its own frame, mm.
    defects : sequence of Dent
        Dents of zero depth are skipped.
    edge_mm : float
        Edge length the mesh is refined to around a dent, mm.

    Returns
    -------
    trimesh.Trimesh
        A new mesh (``process=False``); ``mesh`` is not changed.

    Raises
    ------
    InvalidInput
        A record that is not a Dent, a bad ``edge_mm``, or a dent that touches
        no surface facing its normal.
    """
    import trimesh

    vertices, faces = mesh_arrays(mesh)
    if not (np.isfinite(edge_mm) and edge_mm > 0):
        raise InvalidInput(f"edge_mm must be finite and > 0, got {edge_mm!r}")
    for d in defects:
        if not isinstance(d, Dent):
            raise InvalidInput(f"defects must be Dent records, got {type(d).__name__}")
    out = trimesh.Trimesh(vertices.copy(), faces.copy(), process=False)
    dents = [d for d in defects if d.depth_mm != 0.0]
    if not dents:
        return out
    rounds, margins = [], []
    for d in dents:
        near = d.axis_distance(out.triangles_center) < d.radius_mm
        tri = out.triangles[near] if near.any() else out.triangles
        longest = float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max())
        rounds.append(max(0, int(np.ceil(np.log2(longest / edge_mm)))))
        # A face with a vertex that moves has its centre within one edge of the rim: with
        # that margin no moving midpoint lies on an unrefined neighbour's edge (no cracks).
        margins.append(float(np.ceil(longest)))
    for k in range(max(rounds)):
        centres = out.triangles_center
        near = np.zeros(len(out.faces), dtype=bool)
        for d, n_rounds, margin in zip(dents, rounds, margins, strict=True):
            if k < n_rounds:
                near |= d.axis_distance(centres) < d.radius_mm + margin
        v, f = trimesh.remesh.subdivide(out.vertices, out.faces, face_index=np.nonzero(near)[0])
        out = trimesh.Trimesh(v, f, process=False)
    v = out.vertices.copy()
    normals = out.vertex_normals
    for d in dents:
        n = np.asarray(d.normal)
        r = d.axis_distance(out.vertices)
        facing = (normals @ n > FACING_COS) & (r < d.radius_mm)
        if not facing.any():
            raise InvalidInput(f"the dent at {d.center_mm} touches no surface facing {d.normal}")
        height = out.vertices @ n
        pressed = facing & (height >= height[facing].max() - d.radius_mm)
        v -= (d.depth_mm * d.profile(r) * pressed)[:, None] * normals
    return trimesh.Trimesh(v, out.faces, process=False)


def random_dent(
    mesh: Any,
    rng: np.random.Generator,
    *,
    up: npt.ArrayLike = (0.0, 0.0, 1.0),
    depth_mm: tuple[float, float] = (0.2, 2.0),
    radius_mm: tuple[float, float] = (12.0, 20.0),
    flat_mm: float = 7.0,
    bump_fraction: float = 0.5,
) -> Dent:
    """A dent at a random point of the surface that faces ``up`` (the cameras' side).

    The point is drawn uniformly over the area of the faces whose normal lies
    within about 45 degrees of ``up`` (part frame), so dents land anywhere
    the cameras see: by holes, at the outline, on the character line.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part in its own frame, mm.
    rng : numpy.random.Generator
    up : (3,) float
        Towards the cameras, part frame.
    depth_mm : (lo, hi)
        Range of the depth's size, mm, drawn uniformly.
    radius_mm : (lo, hi)
        Range of the radius, mm, drawn uniformly (above ``flat_mm``).
    flat_mm : float
        Radius of the flat bottom, mm.
    bump_fraction : float
        Share of bumps (negative depths), 0..1.
    """
    lo, hi = (float(v) for v in depth_mm)
    r_lo, r_hi = (float(v) for v in radius_mm)
    if not (0 < lo <= hi and flat_mm < r_lo <= r_hi and 0 <= bump_fraction <= 1):
        raise InvalidInput(
            "random_dent needs 0 < depth lo <= hi, flat_mm < radius lo <= hi, "
            f"0 <= bump_fraction <= 1; got {depth_mm}, {radius_mm}, {flat_mm}, {bump_fraction}"
        )
    u = np.asarray(up, dtype=np.float64)
    visible = np.flatnonzero(mesh.face_normals @ (u / np.linalg.norm(u)) > 0.7)
    if len(visible) == 0:
        raise InvalidInput("no face of the part turns towards the cameras")
    weights = mesh.area_faces[visible] / mesh.area_faces[visible].sum()
    face = int(visible[rng.choice(len(visible), p=weights)])
    a, b = rng.random(2)
    if a + b > 1:
        a, b = 1 - a, 1 - b
    tri = mesh.triangles[face]
    centre = tri[0] + a * (tri[1] - tri[0]) + b * (tri[2] - tri[0])
    depth = float(rng.uniform(lo, hi))
    if rng.random() < bump_fraction:
        depth = -depth
    return Dent(
        tuple(float(v) for v in centre),  # type: ignore[arg-type]
        tuple(float(v) for v in mesh.face_normals[face]),  # type: ignore[arg-type]
        depth,
        float(rng.uniform(r_lo, r_hi)),
        float(flat_mm),
    )
