"""The whole surface: which measured points the field's statistics count, and surface defects.

A :class:`SurfaceModel` samples the CAD surface into nodes on a
:data:`NODE_MM` grid (one node per grid cell and side of the surface) and
links the nodes within the defect search's support radius. Per part:

- **Classes of points.** A point off the CAD's edge (its offset from its
  closest CAD point runs across the surface, not along the normal: the
  reconstruction carried the surface past a boundary or an occlusion), or
  within :data:`EDGE_MM` of a CAD boundary (the outline, the holes), of a
  bend sharper than :data:`BEND_DEG` over 2 mm, or of an occlusion edge
  (an edge of the CAD the cameras see as a silhouette at the fitted pose,
  where depth jumps in their view) is an *edge* point; a
  point beyond the fit's rejection distance (where Tukey's weight reaches
  zero) is an *outlier*; a point beyond the correspondence distance is
  *far* (background). The field's statistics count the rest only.
- **Surface defects.** The signed field is taken per node (the median of its
  points) and smoothed over the support (the point-weighted mean of the
  nodes within :data:`SUPPORT_MM`); nodes whose smoothed value leaves the
  band ``[lower_mm, upper_mm]`` are joined into connected regions, dents
  and bumps apart. Edge points carry their own rim's artefacts, so a node
  away from the edges is smoothed over points away from the edges only,
  and a region must cover ``min_area_mm2`` away from the edges; flagged
  nodes at an edge join the region they touch, and join into one region
  the pieces of a dent that a bend or an edge runs across. So a dent by a
  hole or on a bend is found whole, with its part at the rim, and a hole's
  rim alone is not a defect. The large artefacts are at the outline, the
  holes and the silhouettes, where windows straddle a depth jump; a bend
  away from all of them (a character line, an embossing's shoulder seen
  from every camera) is rounded by little, so a node there whose field
  leaves the band by more than that rounding's allowance, and which kept
  its points, counts towards the area as one away from the edges, and a
  dent on it is found.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .arrays import Points, Scalars, Vectors
from .errors import InvalidInput

__all__ = [
    "BEND_DEG",
    "EDGE_MM",
    "NODE_MM",
    "SUPPORT_MM",
    "PointClasses",
    "SurfaceDefect",
    "SurfaceModel",
    "SurfaceParams",
]

NODE_MM = 2.0
"""Edge of the grid cells the CAD surface is sampled into, mm."""
SUPPORT_MM = 6.0
"""Radius the defect search smooths the field over, mm: a defect's depth is
the field's mean over a disc of this radius."""
EDGE_MM = 4.0
"""Points within this distance of a CAD boundary, a bend or an occlusion edge are edge
points, mm."""
BEND_DEG = 10.0
"""Where the CAD's surface turns by more than this within :data:`_BEND_SPAN_MM` (a bend
radius below about 11 mm: a flange, a character line, an emboss's shoulder), the
reconstruction rounds it: a bend is an edge."""
_BEND_SPAN_MM = 2.0
_JOIN_MM = 1.75 * NODE_MM
"""Nodes closer than this are neighbours in a region (cells sharing a face, edge or corner)."""
_MIN_NORMAL_COS = 0.5
"""Nodes whose normals differ by more than 60 degrees do not smooth each other (a flange, the
far side of a sheet)."""
_LATERAL_MM = 0.05
_LATERAL_SLOPE = 0.1
"""A point is off the edge when its offset runs across the surface by more than
``_LATERAL_MM + _LATERAL_SLOPE * |distance|``."""
_EDGE_STEP_MM = 0.5
"""Edges are sampled at this step to measure distances to them."""
_BEND_ALLOWANCE_MM = 0.15
"""How far the reconstruction's rounding of a bend away from the outline and the
silhouettes may take the field beyond the band: a node there counts towards a defect's
area only where its field leaves the band by more than this, mm."""


@dataclass(frozen=True)
class SurfaceParams:
    """How the surface between the comparison points is judged.

    Attributes
    ----------
    lower_mm, upper_mm : float
        Signed band the smoothed field must stay in (negative: into the
        material, a dent).
    min_area_mm2 : float
        Smallest region out of the band reported as a defect, mm^2.
    fails_part : bool
        Whether a defect fails the part.
    """

    lower_mm: float = -0.15
    upper_mm: float = 0.15
    min_area_mm2: float = 80.0
    fails_part: bool = True

    def __post_init__(self) -> None:
        for label in ("lower_mm", "upper_mm", "min_area_mm2"):
            v = getattr(self, label)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise InvalidInput(f"surface {label} must be a finite number, got {v!r}")
        if not self.lower_mm < 0.0 < self.upper_mm:
            raise InvalidInput(
                f"the surface band must hold 0: lower_mm {self.lower_mm} < 0 < upper_mm "
                f"{self.upper_mm}"
            )
        if self.min_area_mm2 < 0:
            raise InvalidInput(f"surface min_area_mm2 must be >= 0, got {self.min_area_mm2}")
        if not isinstance(self.fails_part, bool):
            raise InvalidInput(f"surface fails_part must be true or false, got {self.fails_part!r}")
        object.__setattr__(self, "lower_mm", float(self.lower_mm))
        object.__setattr__(self, "upper_mm", float(self.upper_mm))
        object.__setattr__(self, "min_area_mm2", float(self.min_area_mm2))


@dataclass(frozen=True)
class SurfaceDefect:
    """A connected region of the surface whose deviation leaves the band.

    Attributes
    ----------
    center_mm : (3,) float64, mm, CAD frame
        Centre of the region (its nodes weighted by area and depth).
    area_mm2 : float
        Area of the CAD surface the region covers.
    peak_mm : float
        The smoothed field's extreme over the region, signed (positive outward).
    mean_mm : float
        The smoothed field's mean over the region (by area), signed.
    nearest_point : str or None
        The comparison point nearest to the centre (None: the part has none).
    points : int
        Measured points in the region.
    """

    center_mm: np.ndarray = field(repr=False)
    area_mm2: float
    peak_mm: float
    mean_mm: float
    nearest_point: str | None
    points: int = 0

    @property
    def kind(self) -> str:
        """``dent`` (into the material) or ``bump``."""
        return "dent" if self.peak_mm < 0 else "bump"

    def to_dict(self) -> dict[str, object]:
        return {
            "kind": self.kind,
            "center_mm": [float(v) for v in self.center_mm],
            "area_mm2": self.area_mm2,
            "peak_mm": self.peak_mm,
            "mean_mm": self.mean_mm,
            "nearest_point": self.nearest_point,
            "points": self.points,
        }

    def describe(self) -> str:
        """One line for a reason: kind, depth, area, where."""
        x, y, z = (float(v) for v in self.center_mm)
        near = f", near {self.nearest_point}" if self.nearest_point else ""
        return (
            f"{self.kind} {abs(self.peak_mm):.2f} mm over {self.area_mm2:.0f} mm^2 "
            f"at ({x:.1f}, {y:.1f}, {z:.1f}){near}"
        )


@dataclass(frozen=True, eq=False)
class PointClasses:
    """What each measured point is, for the field's statistics and the defect search.

    Attributes
    ----------
    edge : (N,) bool
        Off the CAD's edge, or within :data:`EDGE_MM` of a boundary, a bend or an
        occlusion edge.
    outlier : (N,) bool
        Beyond the fit's rejection distance (and not an edge point).
    far : (N,) bool
        Beyond the correspondence distance (background; neither of the above).
    """

    edge: np.ndarray
    outlier: np.ndarray
    far: np.ndarray

    @property
    def surface(self) -> np.ndarray:
        """(N,) bool: the points the field's statistics count."""
        return ~(self.edge | self.outlier | self.far)


@dataclass(frozen=True, eq=False)
class SurfaceModel:
    """The CAD surface as nodes for the defect search, built once per part (:meth:`build`).

    Attributes
    ----------
    origin : (3,) float64, mm
        Corner of the node grid.
    dims : (3,) int64
        Cells of the grid along x, y, z.
    keys : (M,) int64, sorted
        Each node's cell and side (the octant of its normal).
    centres : (M, 3) float64, mm
    normals : (M, 3) float64
    areas : (M,) float64, mm^2
    support : scipy.sparse.csr_matrix (M, M)
        1 where two nodes lie within :data:`SUPPORT_MM` with compatible normals (and on
        the diagonal).
    join : scipy.sparse.csr_matrix (M, M)
        The same within :data:`_JOIN_MM`: neighbours in a region.
    boundary : (B, 3) float64, mm
        Samples along the CAD's boundary edges (outline, holes) and the centres
        of the nodes on bends.
    boundary_mm : (M,) float64
        Each node's distance to those.
    edge_faces : (E, 2) int64
        The two faces of each interior edge of the CAD.
    edge_ends : (E, 2, 3) float64, mm
        Its end points.
    face_normals : (F, 3) float64
    centre_tree : scipy.spatial.cKDTree
        Of ``centres``: the nearest node of a point its cell's samples missed.
    node_mm : float
        Edge of the node grid's cells; every length of the search (the
        support, the edge distance, the bend span) scales with it from the
        module's defaults (:data:`NODE_MM`, :data:`SUPPORT_MM`,
        :data:`EDGE_MM`), which suit a stereo cloud of a part of 100-1000 mm.
        A sensor that samples a small field finely (a holographic head's
        tens of micrometres) takes a finer grid.
    """

    origin: np.ndarray
    dims: np.ndarray
    keys: np.ndarray
    centres: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    support: sp.csr_matrix = field(repr=False)
    join: sp.csr_matrix = field(repr=False)
    boundary: np.ndarray = field(repr=False)
    boundary_mm: np.ndarray = field(repr=False)
    outline_mm: np.ndarray = field(repr=False)
    edge_faces: np.ndarray = field(repr=False)
    edge_ends: np.ndarray = field(repr=False)
    face_normals: np.ndarray = field(repr=False)
    centre_tree: cKDTree = field(repr=False)
    node_mm: float = NODE_MM

    @property
    def support_mm(self) -> float:
        """Radius the field is smoothed over, mm."""
        return SUPPORT_MM * self.node_mm / NODE_MM

    @property
    def edge_mm(self) -> float:
        """Points this near a boundary, a bend or an occlusion edge are edge points, mm."""
        return EDGE_MM * self.node_mm / NODE_MM

    @classmethod
    def build(
        cls,
        vertices: Points,
        faces: np.ndarray,
        face_normals: Vectors,
        *,
        node_mm: float = NODE_MM,
    ) -> SurfaceModel:
        """Sample the surface of a CAD (``CadModel.vertices``, ``faces``, ``face_normals``)
        into cells of ``node_mm``."""
        if isinstance(node_mm, bool) or not (
            isinstance(node_mm, int | float) and math.isfinite(node_mm) and node_mm > 0
        ):
            raise InvalidInput(f"the surface's node_mm must be a positive number, got {node_mm!r}")
        node = float(node_mm)
        k = node / NODE_MM
        V = np.asarray(vertices, dtype=np.float64)
        F = np.asarray(faces, dtype=np.int64)
        N = np.asarray(face_normals, dtype=np.float64)
        tri = V[F]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        # Samples at about four per cell: the cells' areas and centroids to a few percent.
        per_face = np.maximum(1, np.ceil(area / (0.5 * node) ** 2)).astype(np.int64)
        fi = np.repeat(np.arange(len(F)), per_face)
        rng = np.random.default_rng(0)
        u, v = rng.random((2, len(fi)))
        flip = u + v > 1.0
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        t = tri[fi]
        S = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
        w = (area / per_face)[fi]
        origin = V.min(axis=0) - node
        dims = np.ceil((V.max(axis=0) + node - origin) / node).astype(np.int64) + 1
        keys, inv = np.unique(_keys(origin, dims, node, S, N[fi]), return_inverse=True)
        M = len(keys)
        areas = np.bincount(inv, w, M).astype(np.float64)
        sums = np.stack([np.bincount(inv, w * S[:, j], M) for j in range(3)], axis=1)
        centres = sums.astype(np.float64) / areas[:, None]
        turned = np.stack([np.bincount(inv, w * N[fi, j], M) for j in range(3)], axis=1)
        normals = turned / np.maximum(np.linalg.norm(turned, axis=1, keepdims=True), 1e-300)

        pairs = cKDTree(centres).query_pairs(SUPPORT_MM * k, output_type="ndarray")
        compatible = np.einsum("ij,ij->i", normals[pairs[:, 0]], normals[pairs[:, 1]])
        pairs = pairs[compatible > _MIN_NORMAL_COS]
        gap = np.linalg.norm(centres[pairs[:, 0]] - centres[pairs[:, 1]], axis=1)
        support = _adjacency(pairs, M)
        join = _adjacency(pairs[gap <= _JOIN_MM * k], M)

        edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        owner = np.tile(np.arange(len(F)), 3)
        order = np.lexsort((edges[:, 1], edges[:, 0]))
        edges, owner = edges[order], owner[order]
        same = np.r_[False, (edges[1:] == edges[:-1]).all(axis=1)]
        starts = np.flatnonzero(~same)
        counts = np.diff(np.r_[starts, len(edges)])
        lone = starts[counts == 1]
        bends = _bends(centres, normals, _BEND_SPAN_MM * k)
        sampled = _sample_segments(V[edges[lone]], _EDGE_STEP_MM * k)
        boundary = np.concatenate([sampled, centres[bends]])
        pair = starts[counts == 2]
        edge_faces = np.stack([owner[pair], owner[pair + 1]], axis=1)
        edge_ends = V[edges[pair]]
        boundary_mm, outline_mm = (
            cKDTree(b).query(centres)[0] if len(b) else np.full(M, np.inf)
            for b in (boundary, sampled)
        )
        return cls(
            origin=origin, dims=dims, keys=keys, centres=centres, normals=normals, areas=areas,
            support=support, join=join, boundary=boundary, boundary_mm=boundary_mm,
            outline_mm=outline_mm, edge_faces=edge_faces, edge_ends=edge_ends, face_normals=N,
            centre_tree=cKDTree(centres), node_mm=node,
        )  # fmt: skip

    def nodes_of(self, points: Points, normals: Vectors) -> np.ndarray:
        """(N,) int64: the node of each closest CAD point (with its face's normal).

        The node of its cell and side; a point on a sliver of surface that
        the cell's samples missed takes the nearest node whose normal agrees
        (-1 if none within two cells).
        """
        out = _cell_nodes(self.origin, self.dims, self.node_mm, self.keys,
                          _f64(points), _f64(normals))  # fmt: skip
        return self._nearest_nodes(out, points, normals)

    def _nearest_nodes(self, out: np.ndarray, points: Points, normals: Vectors) -> np.ndarray:
        """``out`` with the nodes its cells missed (-1) found among the nearest ones."""
        missed = np.flatnonzero(out < 0)
        if len(missed):
            k = min(4, len(self.keys))
            _, near = self.centre_tree.query(
                np.asarray(points)[missed], k=k, distance_upper_bound=2 * self.node_mm
            )
            near = near.reshape(len(missed), k)
            n = np.asarray(normals)[missed]
            for j in range(k - 1, -1, -1):  # the nearest agreeing node wins
                ok = near[:, j] < len(self.keys)
                agree = np.zeros(len(missed), dtype=bool)
                agree[ok] = (
                    np.einsum("ij,ij->i", self.normals[near[ok, j]], n[ok]) > _MIN_NORMAL_COS
                )
                out[missed[agree]] = near[agree, j]
        return out

    def occlusion_edges(
        self, viewpoints: Points | None = None, directions: Vectors | None = None
    ) -> np.ndarray:
        """(S, 3) mm: samples along the CAD's edges seen as silhouettes, CAD frame.

        An interior edge is a silhouette for a camera when one of its faces
        turns towards the camera and the other away: where the depth the
        camera sees jumps. ``viewpoints`` are camera centres, ``directions``
        are views from infinitely far (towards the sensor), both in the CAD frame.
        """
        if len(self.edge_faces) == 0:
            return np.empty((0, 3))
        silhouette = _silhouettes(
            self.edge_faces,
            self.edge_ends,
            _f64(self.face_normals),
            _f64(np.empty((0, 3)) if viewpoints is None else viewpoints).reshape(-1, 3),
            _f64(np.empty((0, 3)) if directions is None else directions).reshape(-1, 3),
        )
        return _sample_segments(self.edge_ends[silhouette], _EDGE_STEP_MM * self.node_mm / NODE_MM)

    def assess(
        self,
        points: Points,
        closest: Points,
        normals: Vectors,
        distances: Scalars,
        params: SurfaceParams,
        *,
        outlier_mm: float,
        max_distance_mm: float,
        min_support: int,
        viewpoints: Points | None = None,
        directions: Vectors | None = None,
        comparison: tuple[tuple[str, tuple[float, float, float]], ...] = (),
    ) -> tuple[PointClasses, tuple[SurfaceDefect, ...]]:
        """The class of each point, and the surface's defects (largest first).

        Parameters
        ----------
        points : (N, 3) float64, mm, CAD frame
        closest, normals, distances : (N, 3), (N, 3), (N,)
            Each point's closest CAD point, that face's unit normal and the signed distance.
        params : SurfaceParams
        outlier_mm : float
            The fit's rejection distance.
        max_distance_mm : float
            The correspondence distance (farther points are background).
        min_support : int
            Points a smoothed node needs to be judged.
        viewpoints, directions : see :meth:`occlusion_edges`.
        comparison : (name, position) of each comparison point, for ``nearest_point``.
        """
        d = np.asarray(distances, dtype=np.float64)
        # One pass over the points for their cells' nodes and the offsets across the surface.
        nodes, off = _point_nodes(
            self.origin, self.dims, self.node_mm, self.keys, _f64(points), _f64(closest),
            _f64(normals), d, _LATERAL_MM * self.node_mm / NODE_MM, _LATERAL_SLOPE,
        )  # fmt: skip
        nodes = self._nearest_nodes(nodes, closest, normals)
        occlusion = self.occlusion_edges(viewpoints, directions)
        occlusion_mm = self._occlusion_distance(occlusion)
        edge_mm = np.minimum(self.boundary_mm, occlusion_mm)
        edge = off | self._near_edges(closest, nodes, occlusion, edge_mm)
        far = (np.abs(d) > max_distance_mm) & ~edge
        outlier = (np.abs(d) > outlier_mm) & ~edge & ~far
        classes = PointClasses(edge=edge, outlier=outlier, far=far)
        usable = ~off & (np.abs(d) <= max_distance_mm) & (nodes >= 0)
        found = self._defects(
            d, nodes, usable, edge, edge_mm, occlusion_mm, params, min_support, comparison
        )
        return classes, found

    def off_edge(
        self, points: Points, closest: Points, normals: Vectors, distances: Scalars
    ) -> np.ndarray:
        """(N,) bool: points whose offset from the CAD runs across its surface."""
        offset = np.asarray(points) - np.asarray(closest)
        along = np.einsum("ij,ij->i", offset, normals)
        lateral = np.linalg.norm(offset - along[:, None] * normals, axis=1)
        lateral_mm = _LATERAL_MM * self.node_mm / NODE_MM
        return lateral > lateral_mm + _LATERAL_SLOPE * np.abs(np.asarray(distances))

    def _occlusion_distance(self, occlusion: Points) -> np.ndarray:
        """(M,) mm: each node's distance to the occlusion edges (inf beyond twice
        :attr:`edge_mm`)."""
        if len(occlusion) == 0:
            return np.full(len(self.keys), np.inf)
        return _nearest_within(_f64(self.centres), _f64(occlusion), 2.0 * self.edge_mm)

    def _near_edges(
        self, closest: Points, nodes: np.ndarray, occlusion: Points, edge_mm: np.ndarray
    ) -> np.ndarray:
        """(N,) bool: closest points within :attr:`edge_mm` of the boundary or an occlusion
        edge.

        Decided per node where the whole cell lies inside or outside that
        distance, per point in the cells that straddle it.
        """
        reach = self.edge_mm
        half_cell = 0.5 * math.sqrt(3.0) * self.node_mm
        at = np.where(nodes >= 0, edge_mm[np.maximum(nodes, 0)], reach)
        near = (at <= reach - half_cell) & (nodes >= 0)
        unsure = np.flatnonzero(~near & (at <= reach + half_cell))
        samples = np.concatenate([self.boundary, np.asarray(occlusion).reshape(-1, 3)])
        if len(unsure) and len(samples):
            dist = _nearest_within(_f64(np.asarray(closest)[unsure]), _f64(samples), reach + 1e-9)
            near[unsure] = dist <= reach
        return near

    def _defects(
        self,
        d: np.ndarray,
        nodes: np.ndarray,
        usable: np.ndarray,
        edge: np.ndarray,
        edge_mm: np.ndarray,
        occlusion_mm: np.ndarray,
        params: SurfaceParams,
        min_support: int,
        comparison: tuple[tuple[str, tuple[float, float, float]], ...],
    ) -> tuple[SurfaceDefect, ...]:
        """Regions out of the band: a node away from the edges is smoothed over points away
        from the edges, a node at an edge over all; a region is the flagged nodes away from
        the edges, or at a quiet edge (a bend alone, ``occlusion_mm`` and the outline far
        off) beyond the band by more than the bend's allowance, joined through the flagged
        edge nodes they touch, and needs ``min_area_mm2`` of those."""
        M = len(self.keys)
        rim = edge_mm <= self.edge_mm
        median_inner, count_inner, median_all, count_all = _node_medians(
            d, nodes, usable, usable & ~edge, M
        )
        inner = self._smoothed(median_inner, count_inner)
        at_rim = self._smoothed(median_all, count_all)
        s = np.where(rim, at_rim[0], inner[0])
        n = np.where(rim, at_rim[1], inner[1])
        judged = n >= min_support
        allowance = _BEND_ALLOWANCE_MM * self.node_mm / NODE_MM
        # A node at a bend alone, away from the outline, the holes and the silhouettes, is
        # judged like one away from the edges, with an allowance: such a bend is rounded by
        # little. Where the cloud lost most of its points there, the few left are the
        # reconstruction's trouble, not the surface: such a node counts only where its
        # support holds at least half the points a node away from the edges holds.
        away_n = n[judged & ~rim]
        dense = n >= 0.5 * float(np.median(away_n)) if len(away_n) else np.zeros(M, bool)
        far_off = 2 * self.edge_mm
        quiet = (self.outline_mm > far_off) & (occlusion_mm > far_off) & dense
        out: list[SurfaceDefect] = []
        for flagged, beyond in (
            (judged & (s < params.lower_mm), s < params.lower_mm - allowance),
            (judged & (s > params.upper_mm), s > params.upper_mm + allowance),
        ):
            away = flagged & ~rim
            core = away | (flagged & quiet & beyond)
            if not core.any():
                continue
            # A dent across a bend is cut in two by the band of edge nodes, as wide as
            # the bend and the edge distance on both sides: the flagged edge nodes
            # within two supports of the core join its pieces into one region. Its
            # peak is read within one support of the nodes away from the edges (on a
            # quiet bend's nodes where it has none), as edge nodes further out rest
            # on the rim's artefacts.
            beside = flagged & rim
            peaked = away | (beside & (self.support @ away.astype(np.float64) > 0))
            reach = self.support @ (peaked | core).astype(np.float64) > 0
            kept = np.flatnonzero(core | (beside & reach))
            k, label = connected_components(self.join[kept][:, kept], directed=False)
            core_area = np.bincount(label, self.areas[kept] * core[kept], k)
            has_core = np.bincount(label, core[kept], k) > 0  # edge nodes alone are no defect
            for j in np.flatnonzero(has_core & (core_area >= params.min_area_mm2)):
                region = kept[label == j]
                read = peaked[region] if peaked[region].any() else core[region]
                out.append(self._defect(region, read, s, count_all, comparison))
        out.sort(key=lambda f: -f.area_mm2)
        return tuple(out)

    def smoothed(
        self, distances: Scalars, nodes: np.ndarray, keep: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(M,) each node's field as the defect search smooths it, from the points ``keep``
        selects (their signed ``distances`` and :meth:`nodes_of`): the point-weighted mean,
        over the support, of the nodes' medians (NaN where no point), and the points it
        rests on."""
        d = np.asarray(distances, dtype=np.float64)
        sel = np.asarray(keep, dtype=bool) & (np.asarray(nodes) >= 0)
        median, count, _, _ = _node_medians(d, np.asarray(nodes), sel, sel, len(self.keys))
        return self._smoothed(median, count)

    def _smoothed(self, median: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per node: the point-weighted mean of the node medians within the support, and the
        points it rests on."""
        c = count.astype(np.float64)
        total = self.support @ c
        field = (self.support @ (median * c)) / np.maximum(total, 1.0)
        return np.where(total > 0, field, np.nan), total

    def _defect(
        self,
        region: np.ndarray,
        peaked: np.ndarray,
        s: np.ndarray,
        counts: np.ndarray,
        comparison: tuple[tuple[str, tuple[float, float, float]], ...],
    ) -> SurfaceDefect:
        """The defect of the nodes ``region``, its peak among those ``peaked`` marks."""
        a = self.areas[region]
        v = s[region]
        w = a * np.abs(v)
        centre = (self.centres[region] * w[:, None]).sum(axis=0) / w.sum()
        nearest = None
        if comparison:
            gaps = [float(np.linalg.norm(np.asarray(p) - centre)) for _, p in comparison]
            nearest = comparison[int(np.argmin(gaps))][0]
        return SurfaceDefect(
            center_mm=centre,
            area_mm2=float(a.sum()),
            peak_mm=float(v[peaked][np.argmax(np.abs(v[peaked]))]),
            mean_mm=float((a * v).sum() / a.sum()),
            nearest_point=nearest,
            points=int(counts[region].sum()),
        )


@njit(cache=True, nogil=True)
def _silhouettes(edge_faces, edge_ends, normals, viewpoints, directions):  # pragma: no cover
    """(E,) bool: the edges one of whose faces turns towards a viewpoint (or a
    direction) and the other away (:meth:`SurfaceModel.occlusion_edges`)."""
    out = np.zeros(edge_faces.shape[0], dtype=np.bool_)
    for e in range(edge_faces.shape[0]):
        f, g = edge_faces[e, 0], edge_faces[e, 1]
        mx = 0.5 * (edge_ends[e, 0, 0] + edge_ends[e, 1, 0])
        my = 0.5 * (edge_ends[e, 0, 1] + edge_ends[e, 1, 1])
        mz = 0.5 * (edge_ends[e, 0, 2] + edge_ends[e, 1, 2])
        for c in range(viewpoints.shape[0] + directions.shape[0]):
            if c < viewpoints.shape[0]:
                tx = viewpoints[c, 0] - mx
                ty = viewpoints[c, 1] - my
                tz = viewpoints[c, 2] - mz
            else:
                u = c - viewpoints.shape[0]
                tx, ty, tz = directions[u, 0], directions[u, 1], directions[u, 2]
            a = normals[f, 0] * tx + normals[f, 1] * ty + normals[f, 2] * tz
            b = normals[g, 0] * tx + normals[g, 1] * ty + normals[g, 2] * tz
            if (a > 0.0) != (b > 0.0):
                out[e] = True
                break
    return out


# Points of a node up to which :func:`_node_medians` sorts them by insertion.
_INSERTION_MAX = 64


@njit(cache=True, nogil=True)
def _node_medians(
    d: np.ndarray, nodes: np.ndarray, first: np.ndarray, second: np.ndarray, m: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Per node, the median of ``d`` over the points selected by ``second`` and its count,
    then the same over ``first`` (a superset): bucketed by node, each bucket sorted."""
    counts = np.zeros(m + 1, dtype=np.int64)
    for i in range(d.shape[0]):
        if first[i]:
            counts[nodes[i] + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    values = np.empty(start[-1])
    inner = np.empty(start[-1], dtype=np.bool_)
    for i in range(d.shape[0]):
        if first[i]:
            values[fill[nodes[i]]] = d[i]
            inner[fill[nodes[i]]] = second[i]
            fill[nodes[i]] += 1
    med_second = np.zeros(m)
    n_second = np.zeros(m, dtype=np.int64)
    med_first = np.zeros(m)
    n_first = np.zeros(m, dtype=np.int64)
    # A node holds about ten points: sorted in place by insertion in scratch
    # arrays, which spares it the allocations of a sort (a crowded node is
    # sorted by argsort, as insertion takes the square of its count).
    longest = 0
    for j in range(m):
        longest = max(longest, start[j + 1] - start[j])
    bucket = np.empty(longest)
    keep = np.empty(longest, dtype=np.bool_)
    sub = np.empty(longest)
    for j in range(m):
        a, b = start[j], start[j + 1]
        k = b - a
        if k == 0:
            continue
        if k > _INSERTION_MAX:
            order = np.argsort(values[a:b])
            bucket[:k] = values[a:b][order]
            keep[:k] = inner[a:b][order]
        else:
            for i in range(k):
                v = values[a + i]
                f = inner[a + i]
                t = i
                while t > 0 and bucket[t - 1] > v:
                    bucket[t] = bucket[t - 1]
                    keep[t] = keep[t - 1]
                    t -= 1
                bucket[t] = v
                keep[t] = f
        med_first[j] = 0.5 * (bucket[(k - 1) // 2] + bucket[k // 2])
        n_first[j] = k
        q = 0
        for i in range(k):
            if keep[i]:
                sub[q] = bucket[i]
                q += 1
        if q:
            med_second[j] = 0.5 * (sub[(q - 1) // 2] + sub[q // 2])
            n_second[j] = q
    return med_second, n_second, med_first, n_first


def _f64(a: object) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


# Cells of the binned samples of :func:`_nearest_within`, at most, and per
# sample: past that the cells grow wider than the reach (still exact, with
# more samples per cell) rather than the grid outgrowing the search.
_MAX_SAMPLE_CELLS = 1 << 22
_CELLS_PER_SAMPLE = 8


@njit(cache=True, nogil=True)
def _nearest_within(queries, samples, reach):  # pragma: no cover - compiled
    """(Q,) float64, mm: each query point's distance to its nearest sample where that
    is below ``reach``, inf elsewhere (what ``cKDTree(samples).query(queries,
    distance_upper_bound=reach)`` gives).

    The samples are binned into cells at least ``reach`` wide over their box
    grown by ``reach``, so that a query searches its own cell and the 26
    around it, and a query outside the box none.
    """
    nq = queries.shape[0]
    out = np.full(nq, np.inf)
    ns = samples.shape[0]
    if ns == 0 or not reach > 0.0:
        return out
    lo = np.empty(3)
    dims = np.empty(3, dtype=np.int64)
    ext = np.empty(3)
    for a in range(3):
        lo[a] = samples[:, a].min() - reach
        ext[a] = samples[:, a].max() + reach - lo[a]
    max_cells = min(_MAX_SAMPLE_CELLS, _CELLS_PER_SAMPLE * ns + 64)
    cell = reach
    while True:
        total = 1
        for a in range(3):
            dims[a] = int(ext[a] / cell) + 1
            total *= dims[a]
        if total <= max_cells:
            break
        cell *= 1.5
    inv = 1.0 / cell
    slot = np.empty(ns, dtype=np.int64)
    start = np.zeros(total + 1, dtype=np.int64)
    for i in range(ns):
        ix = min(int((samples[i, 0] - lo[0]) * inv), dims[0] - 1)
        iy = min(int((samples[i, 1] - lo[1]) * inv), dims[1] - 1)
        iz = min(int((samples[i, 2] - lo[2]) * inv), dims[2] - 1)
        slot[i] = (ix * dims[1] + iy) * dims[2] + iz
        start[slot[i] + 1] += 1
    for c in range(total):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(ns, dtype=np.int64)
    for i in range(ns):
        order[fill[slot[i]]] = i
        fill[slot[i]] += 1
    r2 = reach * reach
    for q in range(nq):
        gx = (queries[q, 0] - lo[0]) * inv
        gy = (queries[q, 1] - lo[1]) * inv
        gz = (queries[q, 2] - lo[2]) * inv
        if not (0.0 <= gx < dims[0] and 0.0 <= gy < dims[1] and 0.0 <= gz < dims[2]):
            continue  # farther than reach from every sample (and NaN)
        ix, iy, iz = int(gx), int(gy), int(gz)
        best = np.inf
        for x in range(max(ix - 1, 0), min(ix + 2, dims[0])):
            for y in range(max(iy - 1, 0), min(iy + 2, dims[1])):
                base = (x * dims[1] + y) * dims[2]
                for c in range(base + max(iz - 1, 0), base + min(iz + 2, dims[2])):
                    for j in range(start[c], start[c + 1]):
                        k = order[j]
                        dx = queries[q, 0] - samples[k, 0]
                        dy = queries[q, 1] - samples[k, 1]
                        dz = queries[q, 2] - samples[k, 2]
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 < best:
                            best = d2
        if best < r2:
            out[q] = math.sqrt(best)
    return out


@njit(cache=True, nogil=True, inline="always")
def _key(origin, dims, node_mm, p, n):  # pragma: no cover - compiled
    """The cell of point ``p`` and the octant of normal ``n``, as :func:`_keys` makes them."""
    key = 0
    for a in range(3):
        c = int(math.floor((p[a] - origin[a]) / node_mm))
        c = min(max(c, 0), dims[a] - 1)
        key = key * dims[a] + c if a else c
    octant = (1 if n[0] >= 0 else 0) | (2 if n[1] >= 0 else 0) | (4 if n[2] >= 0 else 0)
    return key * 8 + octant


@njit(cache=True, nogil=True)
def _cell_nodes(origin, dims, node_mm, keys, points, normals):  # pragma: no cover - compiled
    """(N,) int64: the node of each point's cell and normal side, -1 where there is none."""
    # The sorted keys of one (i, j) column of cells are contiguous: where each
    # column's run starts, so that a point searches only its own column's few
    # nodes, not all of them.
    per_column = dims[2] * 8
    n_columns = dims[0] * dims[1]
    starts = np.empty(n_columns + 1, dtype=np.int64)
    j = 0
    for c in range(n_columns + 1):
        while j < keys.shape[0] and keys[j] < c * per_column:
            j += 1
        starts[c] = j
    out = np.empty(points.shape[0], dtype=np.int64)
    for i in range(points.shape[0]):
        key = _key(origin, dims, node_mm, points[i], normals[i])
        c = key // per_column
        lo = starts[c]
        hi = starts[c + 1]
        while lo < hi:
            mid = (lo + hi) // 2
            if keys[mid] < key:
                lo = mid + 1
            else:
                hi = mid
        out[i] = lo if lo < starts[c + 1] and keys[lo] == key else -1
    return out


@njit(cache=True, nogil=True)
def _point_nodes(  # pragma: no cover - compiled
    origin, dims, node_mm, keys, points, closest, normals, d, lateral_mm, slope
):
    """The node of each closest point (as :func:`_cell_nodes`), and whether the point's
    offset from it runs across the surface (:meth:`SurfaceModel.off_edge`)."""
    nodes = _cell_nodes(origin, dims, node_mm, keys, closest, normals)
    off = np.empty(points.shape[0], dtype=np.bool_)
    for i in range(points.shape[0]):
        o0 = points[i, 0] - closest[i, 0]
        o1 = points[i, 1] - closest[i, 1]
        o2 = points[i, 2] - closest[i, 2]
        along = o0 * normals[i, 0] + o1 * normals[i, 1] + o2 * normals[i, 2]
        l0 = o0 - along * normals[i, 0]
        l1 = o1 - along * normals[i, 1]
        l2 = o2 - along * normals[i, 2]
        off[i] = math.sqrt(l0 * l0 + l1 * l1 + l2 * l2) > lateral_mm + slope * abs(d[i])
    return nodes, off


def _keys(
    origin: np.ndarray, dims: np.ndarray, node_mm: float, points: Points, normals: Vectors
) -> np.ndarray:
    """Cell of each point and the octant of its normal, as one int64."""
    ijk = np.floor((np.asarray(points) - origin) / node_mm).astype(np.int64)
    ijk = np.clip(ijk, 0, dims - 1)
    n = np.asarray(normals)
    octant = (n[:, 0] >= 0) | ((n[:, 1] >= 0).astype(np.int64) << 1) | ((n[:, 2] >= 0) << 2)
    return ((ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]) * 8 + octant


def _bends(centres: np.ndarray, normals: np.ndarray, span_mm: float) -> np.ndarray:
    """(M,) bool: nodes with a neighbour within ``span_mm`` whose normal turns by more
    than BEND_DEG."""
    pairs = cKDTree(centres).query_pairs(span_mm, output_type="ndarray")
    turned = np.einsum("ij,ij->i", normals[pairs[:, 0]], normals[pairs[:, 1]]) < math.cos(
        math.radians(BEND_DEG)
    )
    out = np.zeros(len(centres), dtype=bool)
    out[pairs[turned].ravel()] = True
    return out


def _adjacency(pairs: np.ndarray, m: int) -> sp.csr_matrix:
    """Symmetric 0/1 matrix of ``pairs`` with ones on the diagonal."""
    i = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(m)])
    j = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(m)])
    return sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(m, m))


def _sample_segments(ends: np.ndarray, step_mm: float) -> np.ndarray:
    """(S, 3): points every ``step_mm`` or less along each segment of ``ends`` (E, 2, 3)."""
    if len(ends) == 0:
        return np.empty((0, 3))
    a, b = ends[:, 0], ends[:, 1]
    steps = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / step_mm)).astype(np.int64)
    seg = np.repeat(np.arange(len(a)), steps + 1)
    t = np.arange(len(seg)) - np.repeat(np.cumsum(steps + 1) - (steps + 1), steps + 1)
    t = t / steps[seg]
    return a[seg] + t[:, None] * (b[seg] - a[seg])
