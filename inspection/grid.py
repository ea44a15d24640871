"""The CAD tree: a precomputed closest-point grid over a CAD surface.

Our take on the Distance Varying Grid tree (DVG tree) of the published
in-line inspection system: answering "which point of the CAD surface is
closest to p?" by index arithmetic instead of a search.

Structure (sparse; two levels, three where faces meet at an edge)::

    coarse grid  (nbx, nby, nbz) int32        block id, or -1 far from the surface
       │  only blocks within the band (plus their own size) exist
       ▼
    blocks of block^3 fine cells (spacing h)  per cell: the face closest to all
                                              eight corners, or "mixed", or
                                              "unknown"
       │  mixed cells only (where regions of faces meet at a sharp edge)
       ▼
    2^3 subcells (spacing h / 2)              per subcell: one face, or a short
                                              list of candidate faces

A query finds its cell (two array reads, three in a mixed cell), computes
the exact point-to-triangle distance to the cell's face(s) and walks to a
neighbouring face when the foot point lies on an edge or corner of the
current one. Cells hold a face per *corner* of the cell rather than per
centre, so a query inside the cell has the faces of all the regions around
it to start from; the walk then makes the answer exact wherever the surface
is connected. Signs come from the angle-weighted pseudo-normal of the
closest feature (face, edge or corner).

Memory, not arithmetic, sets the speed of a batch (the cells and the face
data are tens of MB, queries arrive in any order): what counts is how many
cache lines a query reads and whether their misses overlap. Everything a
query reads of a face sits in one 128-byte record of float32 values
(``K.HOT_*``): the first cache line holds the plane and the dual basis of
the barycentric test plus the smooth neighbours, which is all most queries
read; the second the corners and the neighbourhood for the exact test and
the walk. Queries are taken in their input order, in chunks of 64 whose
passes each issue loads that do not depend on one another (cell codes, then
prefetches of the face records they name, then a prefetch of the face a walk
steps to), so that the misses overlap instead of following one another. In
a cell with a candidate list the candidates' planes bound their distances
from below, so few need the full point-to-triangle test; where no
candidate's plane foot lies inside it (a third of such queries: the closest
face is often closest at none of the corners), the query steps from the
nearest by its plane across smooth edges as a one-face cell does. Such
lists cost a query several times a single face, which is why mixed cells
are split: on the 600 x 400 mm panel 12 % of near queries fall in mixed
cells, 8 % in mixed subcells, whose lists are shorter (2.6 faces on average,
from 3.9).
A subcell left with one face also looks across that face's sharp edges,
unless the build proved no face there can be closer (93 % of them), so
splitting changes no answer. Faces are numbered in a spatial order
(``face_id`` maps them back to the CAD's numbering). Each query's answer
depends on that query alone: results are the same for any order, chunking
or number of threads.

Points outside the band, outside the bounding box, or in cells whose corners
lie outside the band take the exact slow path: a bounding volume hierarchy
over the faces, searched depth first with the nearer box first and every box
farther than the best face so far pruned.

Accuracy: cells with one face are exact where the surface is smooth (two
adjacent faces meeting at less than 0.02 rad can swap on the concave side,
erring by at most distance * angle^2, about 2 um at the band's edge; the
walk looks across such edges only in the far path); cells
with a candidate list are exact unless a surface feature smaller than a cell
(a wall thinner than the spacing, a rib's edge) lies between the corners, in
which case a point beside it may get the next surface instead (seen on the
counter model for ~0.1 % of points within 3 mm, up to 0.6 mm off). Likewise
on the concave side of a bend meshed finer than a cell, a face closest at
none of a cell's corners can be missed: on the 600 x 400 mm panel, 0.09 % of
points within 3 mm, 2-3 mm off its 0.7 mm-meshed radii, get a face up to
31 um farther than the closest (0.2 %, up to 50 um, on the 240 x 160 mm
one). A finer ``spacing_mm`` makes both rarer.
The face records hold planes and corners in float32 relative to a home point
of the face (a block corner near it; the query's offset from it is taken in
float64), which rounds them by about 6e-8 of their distance from that point:
where the fast path has the closest face, its points and distances are exact
to a few nanometres (the tests allow 10 nm), its normals unit vectors within
1e-7 rad of the face's. The far path is exact in float64.

Compilation: the kernels are numba functions cached on disk (``cache=True``).
The first query of a fresh process loads (or, on a new machine, compiles) them;
call :func:`warmup` at service start-up so that no part pays for it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import tempfile
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import _grid_kernels as K
from ._faces import face_planes
from .arrays import Faces, Indices, Points, Scalars, Vectors
from .cad import CadModel
from .errors import InvalidInput, TreeMismatch

log = logging.getLogger(__name__)

FORMAT_VERSION = 4
"""Version of the saved file layout; bump when arrays or their meaning change.

1: the first layout. 2: adds the face hierarchy of the exact slow path
(``bvh_order``, ``bvh_lo``, ``bvh_hi``, ``bvh_child``, ``bvh_span``).
3: faces in the tree's own spatial order, ``face_id`` maps them to the CAD's.
4: mixed cells are split in eight ``subcells``; the candidate lists
(``mixed_ptr``, ``mixed_faces``) belong to the mixed subcells.
"""

# Exactly these arrays and metadata keys make up a saved tree of this
# version: a file with any missing or extra one was written by other code
# and is refused rather than half read.
_ARRAY_KEYS = frozenset(
    {
        "vertices",
        "faces",
        "face_normals",
        "face_adj",
        "smooth_adj",
        "plane",
        "vf_ptr",
        "vf_idx",
        "edge_pn",
        "vert_pn",
        "origin",
        "dims",
        "coarse",
        "cells",
        "subcells",
        "mixed_ptr",
        "mixed_faces",
        "bvh_order",
        "bvh_lo",
        "bvh_hi",
        "bvh_child",
        "bvh_span",
        "face_id",
    }
)
_META_KEYS = frozenset({"format_version", "name", "cad_hash", "tree_hash", "params"})
_PARAM_KEYS = frozenset({"spacing_mm", "band_mm", "block"})

DEFAULT_SPACING_MM = 1.0
DEFAULT_BAND_MM = 4.0
BLOCK = 8
"""Fine cells per block edge (a block is BLOCK^3 cells)."""

# Safety limit on the coarse grid and the fine cells, so a wrong unit (a
# model in micrometres) fails with a message instead of exhausting memory.
_MAX_COARSE_CELLS = 50_000_000
_MAX_FINE_CELLS = 400_000_000
# Blocks whose nodes are computed per kernel call: bounds the build's scratch
# memory ((BLOCK+1)^3 int32 per block) and sets the progress granularity.
_CHUNK_BLOCKS = 2048
# Adjacent faces meeting at less than this dihedral angle count as one smooth
# patch, whose cells store a single face. Where their regions overlap (the
# concave side) picking the wrong one errs by at most distance * angle^2:
# 5.7 mm * 0.02^2 = 2.3 um at the edge of the band, far less on average.
_COS_SMOOTH = math.cos(0.02)

ProgressFn = Callable[[float], None]


@dataclass(frozen=True)
class GridParams:
    """Build parameters of a :class:`GridTree`.

    Attributes
    ----------
    spacing_mm : float
        Edge of a fine cell, mm.
    band_mm : float
        Queries within this distance of the surface take the fast path.
    block : int
        Fine cells per block edge.
    """

    spacing_mm: float
    band_mm: float
    block: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "spacing_mm": self.spacing_mm,
            "band_mm": self.band_mm,
            "block": self.block,
        }


@dataclass(frozen=True)
class Closest:
    """Closest points on the CAD surface, one row per query point.

    Attributes
    ----------
    points : (N, 3) float64, mm, CAD frame
        The closest point of the surface.
    normals : (N, 3) float64
        Unit normal of the face the closest point lies on.
    distances : (N,) float64, mm
        Signed distance: positive on the side the surface normals point to
        (the outer side), negative behind it. Off an edge or corner the sign
        follows the angle-weighted pseudo-normal of that edge or corner.
    face : (N,) int64
        Index of that face in the CAD model's ``faces``.
    """

    points: Points
    normals: Vectors
    distances: Scalars
    face: Indices


@dataclass(frozen=True)
class _Mesh:
    """Per-face and per-vertex arrays the kernels read (all C-contiguous)."""

    vertices: Points
    faces: Faces
    face_normals: Vectors
    tri: np.ndarray  # (F, 3, 3) float64
    plane: np.ndarray  # (F, 12) float64: corner a, unit normal, dual basis U, V of the edges
    face_adj: np.ndarray  # (F, 3) int32: face across edge e, or -1
    smooth_adj: np.ndarray  # (F, 3) int32: face_adj where the dihedral angle is small, else -1
    vf_ptr: np.ndarray  # (V+1,) int64
    vf_idx: np.ndarray  # (sum,) int32: faces around each vertex
    edge_pn: np.ndarray  # (F, 3, 3) float64: pseudo-normal of edge e of face f
    vert_pn: np.ndarray  # (V, 3) float64: angle-weighted vertex pseudo-normal
    bvh_order: np.ndarray  # (F,) int32: faces in leaf order
    bvh_lo: np.ndarray  # (N, 3) float64: node boxes
    bvh_hi: np.ndarray  # (N, 3) float64
    bvh_child: np.ndarray  # (N, 2) int32: children, -1 for a leaf
    bvh_span: np.ndarray  # (N, 2) int32: a leaf's [start, end) in bvh_order
    face_id: np.ndarray  # (F,) int64: the CAD face index of each (spatially ordered) face


class GridTree:
    """Precomputed closest-point structure of one CAD model.

    Build with :meth:`build`, or read a saved one with :meth:`load`. The
    object is immutable after construction.

    Attributes
    ----------
    params : GridParams
    cad_hash : str
        :attr:`CadModel.hash` of the geometry the tree was built for.
    hash : str
        SHA-256 (hex) of the tree's content, its parameters and the format
        version: identifies this tree in results (``tree_hash``).
    cad : CadModel or None
        The model, when the tree was built from it or loaded with it.
    """

    def __init__(
        self,
        *,
        mesh: _Mesh,
        params: GridParams,
        cad_hash: str,
        origin: np.ndarray,
        dims: np.ndarray,
        coarse: np.ndarray,
        cells: np.ndarray,
        subcells: np.ndarray,
        mixed_ptr: np.ndarray,
        mixed_faces: np.ndarray,
        name: str,
        tree_hash: str | None = None,
        cad: CadModel | None = None,
    ) -> None:
        self._mesh = mesh
        self.params = params
        self.cad_hash = cad_hash
        self.name = name
        self.cad = cad
        self._origin = origin
        self._dims = dims
        self._coarse = coarse
        self._cells = cells
        self._subcells = subcells
        self._mixed_ptr = mixed_ptr
        self._mixed_faces = mixed_faces
        # Read-only everywhere, built or loaded: numba compiles one
        # specialisation per array mutability, so mixing them would compile
        # the kernels twice.
        for arr in (origin, dims, coarse, cells, subcells, mixed_ptr, mixed_faces):
            arr.setflags(write=False)
        self._n_blocks = int((coarse >= 0).sum())
        # Asked for by every registration before its first query: computed once.
        self._bounds = np.stack([mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)])
        self._bounds.setflags(write=False)
        # The queries' copy of face_id: half the cache lines of the int64 one.
        self._face_id32 = mesh.face_id.astype(np.int32)
        self._face_id32.setflags(write=False)
        self._home_step, self._hot, self._hot_i = _hot_records(
            mesh, origin, dims, params.block * params.spacing_mm
        )
        # The public faces and normals are in the CAD's order, the mesh's in
        # the tree's own.
        self._cad_faces = np.empty_like(mesh.faces)
        self._cad_faces[mesh.face_id] = mesh.faces
        self._cad_normals = np.empty_like(mesh.face_normals)
        self._cad_normals[mesh.face_id] = mesh.face_normals
        self._cad_faces.setflags(write=False)
        self._cad_normals.setflags(write=False)
        self.hash = tree_hash if tree_hash is not None else self._content_hash()

    # ------------------------------------------------------------------ build
    @classmethod
    def build(
        cls,
        cad: CadModel,
        *,
        spacing_mm: float = DEFAULT_SPACING_MM,
        band_mm: float = DEFAULT_BAND_MM,
        progress: ProgressFn | None = None,
    ) -> GridTree:
        """Precompute the closest faces of a CAD model on a sparse two-level grid.

        Parameters
        ----------
        cad : CadModel
            The part, in mm.
        spacing_mm : float
            Fine cell edge, mm. 1 mm suits parts of 100-1000 mm: the exact
            local correction makes the answer independent of the spacing; a
            finer grid only reduces the number of candidate faces per cell.
        band_mm : float
            Distance from the surface within which every query takes the fast
            path, mm. Farther queries are exact too, through the slow path.
        progress : callable, optional
            Called with the completed fraction (0..1) as blocks are computed.

        Returns
        -------
        GridTree

        Raises
        ------
        InvalidInput
            Non-positive spacing, negative band, or a grid too large for memory
            (usually a model in the wrong unit).
        """
        if not isinstance(cad, CadModel):
            raise InvalidInput(f"cad must be a CadModel, got {type(cad).__name__}")
        if len(cad.faces) >= K.INTERIOR_FLAG:
            raise InvalidInput(
                f"{len(cad.faces)} faces: at most {K.INTERIOR_FLAG - 1} are supported"
            )
        spacing_mm = _positive("spacing_mm", spacing_mm)
        band_mm = float(band_mm)
        if not math.isfinite(band_mm) or band_mm < 0:
            raise InvalidInput(f"band_mm must be a finite number >= 0, got {band_mm!r}")
        t0 = time.perf_counter()
        h = spacing_mm
        block_mm = BLOCK * h
        # Nodes within `reach` of the surface get their exact closest face. A
        # query within band_mm has all eight cell corners within band + the
        # cell diagonal, so those corners are known.
        reach = band_mm + math.sqrt(3.0) * h * 1.0001
        lo_box = cad.vertices.min(axis=0) - reach - h
        hi_box = cad.vertices.max(axis=0) + reach + h
        dims = np.ceil((hi_box - lo_box) / block_mm).astype(np.int64)
        n_coarse = int(np.prod(dims))
        if n_coarse > _MAX_COARSE_CELLS:
            raise InvalidInput(
                f"a {spacing_mm} mm grid over a {cad.extents.round(1).tolist()} mm "
                f"model needs {n_coarse} blocks; is the model in mm? (use a larger spacing_mm)"
            )
        origin = lo_box.astype(np.float64)

        # Number the faces in the raster order of the blocks holding their
        # centroids, the order in which a query batch visits the blocks: the
        # face records a batch reads then lie close together in memory.
        centroid = cad.vertices[cad.faces].mean(axis=1)
        cb = np.clip(((centroid - origin) // block_mm).astype(np.int64), 0, dims - 1)
        face_id = np.argsort((cb[:, 0] * dims[1] + cb[:, 1]) * dims[2] + cb[:, 2], kind="stable")
        mesh = _mesh_arrays(cad.vertices, cad.faces[face_id], cad.face_normals[face_id], face_id)
        tri = mesh.tri
        lo = tri.min(axis=1) - reach
        hi = tri.max(axis=1) + reach
        centre = tri.mean(axis=1)
        radius = np.sqrt(((tri - centre[:, None, :]) ** 2).sum(axis=2)).max(axis=1)
        ranges = K.face_block_ranges(lo, hi, origin, block_mm, dims)
        coarse, coords, ptr, face_idx = K.block_face_lists(ranges, dims)
        nblocks = len(coords)
        if nblocks * BLOCK**3 > _MAX_FINE_CELLS:
            raise InvalidInput(
                f"the band needs {nblocks * BLOCK**3} fine cells; "
                "use a larger spacing_mm or a smaller band_mm"
            )
        cells = np.empty(nblocks * BLOCK**3, dtype=np.int32)
        boxes = (lo, hi, centre, radius)
        lists = _cells(
            cells, coords, (ptr, face_idx), mesh, origin, h, BLOCK, boxes, reach * reach, progress
        )
        subcells, mixed_ptr, mixed_faces = _split_mixed(
            cells, coords, lists, mesh, origin, h, boxes, reach * reach
        )

        params = GridParams(spacing_mm=h, band_mm=band_mm, block=BLOCK)
        tree = cls(
            mesh=mesh,
            params=params,
            cad_hash=cad.hash,
            origin=origin,
            dims=dims,
            coarse=coarse,
            cells=cells,
            subcells=subcells,
            mixed_ptr=mixed_ptr,
            mixed_faces=mixed_faces,
            name=cad.name,
            cad=cad,
        )
        log.debug(
            "GridTree %s: %d faces, %d blocks, %d mixed cells, %.1f MB, %.2f s",
            cad.name,
            len(cad.faces),
            nblocks,
            tree.n_mixed_cells,
            tree.nbytes / 1e6,
            time.perf_counter() - t0,
        )
        return tree

    # ------------------------------------------------------------------ query
    def query(self, points: np.ndarray) -> Closest:
        """Closest points on the CAD surface.

        Parameters
        ----------
        points : (N, 3) float, mm, CAD frame
            Query points; not modified.

        Returns
        -------
        Closest
            One row per query point, in the input order. Points the fast path
            answers (within the band) are exact up to the float32 rounding of
            the face records, a few nanometres, but for a rare point beside a
            feature finer than a cell; the others are exact in float64 (see
            the module notes on accuracy).

        Raises
        ------
        InvalidInput
            Not an (N, 3) array of finite numbers.
        """
        # NaN and inf fail the fast path's range test, so they can only be
        # among the rows it leaves to the slow path: checked there, which
        # spares a pass over the whole batch.
        p = _as_points(points, check_finite=False)
        n = len(p)
        m = self._mesh
        out_pts = np.empty((n, 3))
        out_nrm = np.empty((n, 3))
        out_dist = np.empty(n)
        out_face = np.empty(n, dtype=np.int64)
        if n:
            n_slow = np.empty((n + K.QUERY_CHUNK - 1) // K.QUERY_CHUNK, dtype=np.int64)
            K.query_grid(
                p,
                self._origin,
                1.0 / self.params.spacing_mm,
                self.params.block,
                self._dims,
                self._coarse,
                self._cells,
                self._subcells,
                self._mixed_ptr,
                self._mixed_faces,
                self._hot,
                self._hot_i,
                self._home_step,
                m.tri,
                m.face_normals,
                m.vf_ptr,
                m.vf_idx,
                m.edge_pn,
                m.vert_pn,
                self._face_id32,
                out_pts,
                out_nrm,
                out_dist,
                out_face,
                n_slow,
            )
            if n_slow.sum():
                slow = np.flatnonzero(out_face == K.FACE_SLOW)
                _check_finite(p[slow])
                self._query_slow(p, slow, out_pts, out_nrm, out_dist, out_face)
        return Closest(points=out_pts, normals=out_nrm, distances=out_dist, face=out_face)

    def _query_slow(self, p, rows, out_pts, out_nrm, out_dist, out_face) -> None:
        """Exact closest faces of p[rows] through the bounding volume hierarchy."""
        m = self._mesh
        K.query_bvh(
            p,
            np.asarray(rows, dtype=np.int64),
            m.bvh_order,
            m.bvh_lo,
            m.bvh_hi,
            m.bvh_child,
            m.bvh_span,
            self._hot,
            self._hot_i,
            self._origin,
            self._home_step,
            m.tri,
            m.face_normals,
            m.vf_ptr,
            m.vf_idx,
            m.edge_pn,
            m.vert_pn,
            m.face_id,
            out_pts,
            out_nrm,
            out_dist,
            out_face,
        )

    # ------------------------------------------------------------------ facts
    @property
    def vertices(self) -> Points:
        """(V, 3) float64, mm: the CAD vertices (read-only)."""
        return self._mesh.vertices

    @property
    def faces(self) -> Faces:
        """(F, 3) int64: the CAD faces, in the CAD model's order (read-only)."""
        return self._cad_faces

    @property
    def face_normals(self) -> Vectors:
        """(F, 3) float64: unit face normals, in the CAD model's order (read-only)."""
        return self._cad_normals

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64, mm: bounding box of the CAD model, min row then max row (read-only)."""
        return self._bounds

    @property
    def n_blocks(self) -> int:
        """Fine blocks allocated near the surface."""
        return self._n_blocks

    @property
    def n_mixed_cells(self) -> int:
        """Fine cells whose corners have different closest faces (each split in eight)."""
        return len(self._subcells) // 8

    @property
    def n_mixed_subcells(self) -> int:
        """Subcells of mixed cells that keep a list of candidate faces."""
        return len(self._mixed_ptr) - 1

    @property
    def nbytes(self) -> int:
        """Memory held by the tree's arrays, bytes (mesh, grid, hierarchy)."""
        m = self._mesh
        arrays = [
            m.vertices,
            m.faces,
            m.face_normals,
            m.tri,
            m.plane,
            m.smooth_adj,
            self._hot,
            m.face_id,
            m.face_adj,
            m.vf_ptr,
            m.vf_idx,
            m.edge_pn,
            m.vert_pn,
            self._coarse,
            self._cells,
            self._subcells,
            self._mixed_ptr,
            self._mixed_faces,
            m.bvh_order,
            m.bvh_lo,
            m.bvh_hi,
            m.bvh_child,
            m.bvh_span,
        ]
        return int(sum(a.nbytes for a in arrays))

    def info(self) -> dict[str, Any]:
        """A summary for people and logs: versions, hashes, parameters, sizes."""
        return {
            "format_version": FORMAT_VERSION,
            "name": self.name,
            "cad_hash": self.cad_hash,
            "tree_hash": self.hash,
            "params": self.params.to_dict(),
            "faces": int(len(self._mesh.faces)),
            "vertices": int(len(self._mesh.vertices)),
            "bounds_mm": self.bounds.tolist(),
            "coarse_dims": [int(d) for d in self._dims],
            "blocks": self.n_blocks,
            "fine_cells": int(len(self._cells)),
            "mixed_cells": self.n_mixed_cells,
            "mixed_subcells": self.n_mixed_subcells,
            "unknown_cells": int((self._cells == K.CELL_UNKNOWN).sum()),
            "bvh_nodes": int(len(self._mesh.bvh_lo)),
            "nbytes": self.nbytes,
        }

    def __repr__(self) -> str:
        return (
            f"GridTree({self.name!r}, faces={len(self._mesh.faces)}, blocks={self.n_blocks}, "
            f"spacing_mm={self.params.spacing_mm}, band_mm={self.params.band_mm}, "
            f"{self.nbytes / 1e6:.1f} MB)"
        )

    # ------------------------------------------------------------------ files
    def _arrays(self) -> dict[str, np.ndarray]:
        m = self._mesh
        return {
            "vertices": m.vertices,
            "faces": m.faces,
            "face_normals": m.face_normals,
            "face_adj": m.face_adj,
            "smooth_adj": m.smooth_adj,
            "plane": m.plane,
            "vf_ptr": m.vf_ptr,
            "vf_idx": m.vf_idx,
            "edge_pn": m.edge_pn,
            "vert_pn": m.vert_pn,
            "origin": self._origin,
            "dims": self._dims,
            "coarse": self._coarse,
            "cells": self._cells,
            "subcells": self._subcells,
            "mixed_ptr": self._mixed_ptr,
            "mixed_faces": self._mixed_faces,
            "bvh_order": m.bvh_order,
            "bvh_lo": m.bvh_lo,
            "bvh_hi": m.bvh_hi,
            "bvh_child": m.bvh_child,
            "bvh_span": m.bvh_span,
            "face_id": m.face_id,
        }

    def _content_hash(self) -> str:
        h = hashlib.sha256()
        h.update(
            json.dumps(
                {
                    "format_version": FORMAT_VERSION,
                    "cad_hash": self.cad_hash,
                    "params": self.params.to_dict(),
                },
                sort_keys=True,
            ).encode()
        )
        for key, a in sorted(self._arrays().items()):
            h.update(key.encode())
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    def save(self, path: str | Path) -> Path:
        """Write the tree to one uncompressed ``.npz`` file (fast to load).

        The file holds the format version, the build parameters, the CAD
        geometry hash, the tree hash, the mesh and the grid. It is written to
        a temporary file first and renamed, so readers never see half a tree.

        Returns
        -------
        Path
            The path written.
        """
        path = Path(path)
        meta = {
            "format_version": FORMAT_VERSION,
            "name": self.name,
            "cad_hash": self.cad_hash,
            "tree_hash": self.hash,
            "params": self.params.to_dict(),
        }
        arrays = dict(self._arrays())
        arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **arrays)  # type: ignore[arg-type]
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | Path, cad: CadModel | None = None) -> GridTree:
        """Read a tree written by :meth:`save`.

        Parameters
        ----------
        path : str or Path
        cad : CadModel, optional
            When given, the tree must have been built for this geometry.

        Raises
        ------
        TreeMismatch
            The file is of another format version, lacks or adds an array or
            a metadata field of this version, or (with ``cad``) was built for
            another geometry.
        InvalidInput
            The file is missing or not a saved tree.
        """
        path = Path(path)
        if not path.is_file():
            raise InvalidInput(f"{path}: no such tree file")
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(z["meta"].tobytes().decode())
                if not isinstance(meta, dict):
                    raise ValueError("meta is not a JSON object")
                _check_layout(path, meta, set(z.files) - {"meta"})
                a = {k: z[k] for k in z.files if k != "meta"}
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
            raise InvalidInput(f"{path}: not a saved GridTree ({exc})") from exc
        if cad is not None:
            if not isinstance(cad, CadModel):
                raise InvalidInput(f"cad must be a CadModel, got {type(cad).__name__}")
            if cad.hash != meta["cad_hash"]:
                raise TreeMismatch(
                    f"{path}: tree built for CAD {meta['cad_hash'][:12]}, "
                    f"given CAD {cad.name!r} is {cad.hash[:12]}"
                )
        vertices, faces = a["vertices"], a["faces"]
        tri = np.ascontiguousarray(vertices[faces])
        mesh = _Mesh(
            vertices=vertices,
            faces=faces,
            face_normals=a["face_normals"],
            tri=tri,
            plane=a["plane"],
            smooth_adj=a["smooth_adj"],
            face_adj=a["face_adj"],
            vf_ptr=a["vf_ptr"],
            vf_idx=a["vf_idx"],
            edge_pn=a["edge_pn"],
            vert_pn=a["vert_pn"],
            bvh_order=a["bvh_order"],
            bvh_lo=a["bvh_lo"],
            bvh_hi=a["bvh_hi"],
            bvh_child=a["bvh_child"],
            bvh_span=a["bvh_span"],
            face_id=a["face_id"],
        )
        for arr in (*a.values(), tri):
            arr.setflags(write=False)
        return cls(
            mesh=mesh,
            params=GridParams(**meta["params"]),
            cad_hash=meta["cad_hash"],
            origin=a["origin"],
            dims=a["dims"],
            coarse=a["coarse"],
            cells=a["cells"],
            subcells=a["subcells"],
            mixed_ptr=a["mixed_ptr"],
            mixed_faces=a["mixed_faces"],
            name=meta["name"],
            tree_hash=meta["tree_hash"],
            cad=cad,
        )


def warmup() -> float:
    """Load (or compile, on a new machine) every grid kernel; returns seconds spent.

    Builds and queries a tiny tree, which exercises the build, the fast and
    the slow path. Call it once at service start-up.
    """
    t0 = time.perf_counter()
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    tree = GridTree.build(CadModel.from_arrays(v, f, name="warmup"), spacing_mm=1.0, band_mm=1.0)
    tree.query(np.array([[1.0, 1.0, 0.5], [2.0, 2.0, 40.0]]))
    return time.perf_counter() - t0


# ---------------------------------------------------------------------- helpers
def _check_layout(path: Path, meta: dict[str, Any], arrays: set[str]) -> None:
    """Raise TreeMismatch unless a saved tree has this version's exact layout."""
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise TreeMismatch(
            f"{path}: tree format version {version}, this software reads "
            f"{FORMAT_VERSION}; rebuild it with `inspection build-tree`"
        )
    params = meta.get("params")
    problems = []
    for what, have, want in (
        ("array", arrays, _ARRAY_KEYS),
        ("metadata field", set(meta), _META_KEYS),
        ("parameter", set(params) if isinstance(params, dict) else set(), _PARAM_KEYS),
    ):
        if missing := sorted(want - have):
            problems.append(f"missing {what}(s) {', '.join(missing)}")
        if extra := sorted(have - want):
            problems.append(f"unknown {what}(s) {', '.join(extra)}")
    if problems:
        raise TreeMismatch(
            f"{path}: not a version {FORMAT_VERSION} tree ({'; '.join(problems)}); "
            "rebuild it with `inspection build-tree`"
        )


def _check_finite(p: np.ndarray) -> None:
    """InvalidInput unless every row of p (N, 3) is finite."""
    if not np.isfinite(p).all():
        bad = int((~np.isfinite(p)).any(axis=1).sum())
        raise InvalidInput(f"points: {bad} rows hold NaN or inf")


def _positive(name: str, value: float) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(x) or x <= 0:
        raise InvalidInput(f"{name} must be a finite number > 0, got {value!r}")
    return x


def _as_points(points: Any, *, check_finite: bool = True) -> np.ndarray:
    """(N, 3) C-contiguous float64 view or copy of points, else InvalidInput.

    With ``check_finite=False`` the caller checks for NaN and inf itself
    (see :func:`_check_finite`).
    """
    try:
        p = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"points must be an (N, 3) array of numbers: {exc}") from exc
    if p.ndim != 2 or p.shape[1] != 3:
        raise InvalidInput(f"points must have shape (N, 3), got {p.shape}")
    if check_finite:
        _check_finite(p)
    p = np.ascontiguousarray(p)
    # The kernels are compiled for writable arrays; a read-only view (a
    # frozen cloud, say) would trigger a second compilation.
    return p if p.flags.writeable else p.copy()


def _mesh_arrays(
    vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray, face_id: np.ndarray
) -> _Mesh:
    """Adjacency and pseudo-normals of a triangle mesh whose face i is the CAD's face_id[i]."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    fn = np.ascontiguousarray(face_normals, dtype=np.float64)
    nf, nv = len(f), len(v)
    tri = np.ascontiguousarray(v[f])

    # Edge e of face i joins corners e and e+1; faces sharing an undirected
    # edge are neighbours (on a non-manifold edge, the next one in sort order).
    a = f[:, [0, 1, 2]].ravel()
    b = f[:, [1, 2, 0]].ravel()
    key = np.minimum(a, b) * np.int64(nv) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    adj_flat = np.full(3 * nf, -1, dtype=np.int64)
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    group_len = np.diff(np.r_[start, len(ks)])
    group_of = np.repeat(np.arange(len(start)), group_len)
    pos = np.arange(len(ks)) - start[group_of]
    nxt = np.where(pos + 1 < group_len[group_of], np.arange(len(ks)) + 1, start[group_of])
    multi = group_len[group_of] > 1
    adj_flat[order[multi]] = order[nxt[multi]] // 3
    face_adj = adj_flat.reshape(nf, 3).astype(np.int32)

    # Edge pseudo-normal: sum of the two face normals (one on a border edge).
    other = np.where(face_adj >= 0, face_adj, np.arange(nf)[:, None])
    epn = fn[:, None, :] + fn[other]
    epn /= np.maximum(np.linalg.norm(epn, axis=2, keepdims=True), 1e-300)
    # Opposite normals (a folded sheet) sum to zero: fall back to the face's own.
    flat = np.linalg.norm(fn[:, None, :] + fn[other], axis=2) < 1e-9
    epn[flat] = np.broadcast_to(fn[:, None, :], epn.shape)[flat]

    # Vertex pseudo-normal: normals weighted by the corner angles.
    angles = np.empty((nf, 3))
    for c in range(3):
        e1 = tri[:, (c + 1) % 3] - tri[:, c]
        e2 = tri[:, (c + 2) % 3] - tri[:, c]
        cosang = (e1 * e2).sum(axis=1) / np.maximum(
            np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-300
        )
        angles[:, c] = np.arccos(np.clip(cosang, -1.0, 1.0))
    vpn = np.zeros((nv, 3))
    for c in range(3):
        np.add.at(vpn, f[:, c], fn * angles[:, c : c + 1])
    vpn /= np.maximum(np.linalg.norm(vpn, axis=1, keepdims=True), 1e-300)

    # Faces around each vertex (CSR).
    flat_v = f.ravel()
    vorder = np.argsort(flat_v, kind="stable")
    vf_idx = (vorder // 3).astype(np.int32)
    vf_ptr = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat_v, minlength=nv), out=vf_ptr[1:])

    plane = face_planes(tri, fn)
    bvh = K.bvh_build(tri)
    smooth_adj = _smooth_adjacency(face_adj, fn)
    mesh = _Mesh(
        vertices=v,
        faces=f,
        face_normals=fn,
        tri=tri,
        plane=plane,
        face_adj=face_adj,
        smooth_adj=smooth_adj,
        vf_ptr=vf_ptr,
        vf_idx=vf_idx,
        edge_pn=np.ascontiguousarray(epn),
        vert_pn=vpn,
        bvh_order=bvh[0],
        bvh_lo=bvh[1],
        bvh_hi=bvh[2],
        bvh_child=bvh[3],
        bvh_span=bvh[4],
        face_id=np.ascontiguousarray(face_id, dtype=np.int64),
    )
    for arr in (
        mesh.face_id,
        v,
        f,
        fn,
        tri,
        plane,
        face_adj,
        smooth_adj,
        vf_ptr,
        vf_idx,
        mesh.edge_pn,
        vpn,
        *bvh,
    ):
        arr.setflags(write=False)
    return mesh


def _cells(
    out: np.ndarray,
    coords: np.ndarray,
    lists: tuple[np.ndarray, np.ndarray],
    mesh: _Mesh,
    origin: np.ndarray,
    h: float,
    block: int,
    boxes: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    reach2: float,
    progress: ProgressFn | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Cell codes of blocks of block^3 cells of edge h, a chunk of blocks per
    kernel call, written to ``out``; returns their candidate lists.

    Block b has its corner at ``origin + coords[b] * block * h`` and its
    nodes' closest faces are sought among ``faces[ptr[b]:ptr[b + 1]]`` of
    ``lists = (ptr, faces)``; ``boxes`` are the faces' expanded boxes, centres
    and radii. Used for the blocks of the grid and for the subcells of its
    mixed cells (blocks of 2^3).
    """
    ptr, faces = lists
    lo, hi, centre, radius = boxes
    n = len(coords)
    chunk = max(1, (_CHUNK_BLOCKS * BLOCK**3) // block**3)
    counts_parts: list[np.ndarray] = []
    faces_parts: list[np.ndarray] = []
    n_mixed = 0
    b3 = block**3
    for b0 in range(0, n, chunk):
        b1 = min(n, b0 + chunk)
        nodes = K.block_nodes(
            b0, b1, coords, ptr, faces, lo, hi, centre, radius, mesh.tri, origin, h, block, reach2
        )
        counts, mixed = K.cells_from_nodes(
            nodes,
            b0,
            coords,
            origin,
            h,
            block,
            mesh.tri,
            mesh.plane,
            mesh.faces,
            mesh.face_normals,
            _COS_SMOOTH,
            out[b0 * b3 : b1 * b3],
            n_mixed,
        )
        counts_parts.append(counts)
        faces_parts.append(mixed)
        n_mixed += len(counts)
        if progress is not None:
            progress(b1 / n)
    return _lists(counts_parts, faces_parts)


def _lists(
    counts_parts: list[np.ndarray], faces_parts: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate lists gathered chunk by chunk as (ptr (M+1,) int64, faces (P,) int32)."""
    counts = np.concatenate(counts_parts) if counts_parts else np.zeros(0, dtype=np.int64)
    ptr = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    faces = np.concatenate(faces_parts) if faces_parts else np.zeros(0, dtype=np.int32)
    return ptr, faces.astype(np.int32, copy=False)


def _split_mixed(
    cells: np.ndarray,
    coords: np.ndarray,
    lists: tuple[np.ndarray, np.ndarray],
    mesh: _Mesh,
    origin: np.ndarray,
    h: float,
    boxes: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    reach2: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split every mixed cell in eight subcells of edge h / 2.

    A mixed cell (corners with different closest faces) lies where regions
    of faces meet across a sharp edge or a hole; a query there tests every
    candidate, several times the cost of a single-face cell. Its 19 new
    subcell corners get their closest face among the cell's candidates,
    which are the faces closest to its corners: the subcells that then see
    one face (or one smooth patch) take the single-face path, about half of
    them, and the others keep the shorter list of their own corners' faces.
    A one-face subcell is answered by its face's plane alone only where no
    face across a sharp edge of it can be closer (:func:`K.mark_safe_subcells`);
    elsewhere its queries look across those edges, as a list's would.

    Returns
    -------
    subcells : (8 M,) int32
        Codes of the subcells of mixed cell m at ``8 m + (4 sx + 2 sy + sz)``.
    mixed_ptr, mixed_faces
        Candidate lists of the mixed subcells.
    """
    ptr0, faces0 = lists
    n_mixed = len(ptr0) - 1
    # cells_from_nodes numbers the mixed cells in the order of their cells.
    where = np.flatnonzero(cells < K.CELL_UNKNOWN)
    b3 = BLOCK**3
    local = where % b3
    # A mixed cell's integer grid coordinates: as a "block" of 2^3 subcells of
    # edge h / 2 its corner is origin + ijk * 2 * (h / 2).
    ijk = coords[where // b3] * BLOCK + np.stack(
        [local // (BLOCK * BLOCK), (local // BLOCK) % BLOCK, local % BLOCK], axis=1
    )
    ijk = np.ascontiguousarray(ijk, dtype=np.int64)
    subcells = np.empty(8 * n_mixed, dtype=np.int32)
    mixed_ptr, mixed_faces = _cells(subcells, ijk, lists, mesh, origin, h / 2, 2, boxes, reach2)
    K.mark_safe_subcells(
        subcells, ijk, origin, h / 2, mesh.plane, mesh.face_adj, mesh.smooth_adj, _across(mesh)
    )
    return subcells, mixed_ptr, mixed_faces


def _hot_records(
    mesh: _Mesh, origin: np.ndarray, dims: np.ndarray, block_mm: float
) -> tuple[float, np.ndarray, np.ndarray]:
    """The face records every query reads (see ``K.HOT_*``), 128 bytes per face.

    Each face gets a home point on a lattice of step ``home_step`` (a block
    edge, or a few on a model wider than 2^HOME_BITS blocks) at most one
    step per axis below its corner a, and its plane rows, corners and
    neighbours relative to that point in float32. Queries take ``p - home``
    in float64, so the float32 rounding (relative 6e-8) moves planes and
    corners by about 6e-8 times their distance from the home point: a few
    nanometres near the face, 0.02 um 300 mm along a long triangle.

    Returns
    -------
    home_step : float, mm
    hot : (F, K.HOT_WIDTH) float32, rows 64-byte aligned
    hot_i : (F, K.HOT_WIDTH) int32, the same memory (the integer columns)
    """
    k = max(1, math.ceil(int(dims.max()) / (1 << K.HOME_BITS)))
    home_step = float(block_mm * k)
    tri, plane = mesh.tri, mesh.plane
    nf = len(tri)
    home = np.clip(np.floor((tri[:, 0] - origin) / home_step), 0, K.HOME_MASK).astype(np.int64)
    # The same float64 operations as the kernels' (origin + home * step).
    rel = tri[:, 0] - (origin + home.astype(np.float64) * home_step)
    raw = np.empty(nf * K.HOT_WIDTH + 16, dtype=np.float32)
    skip = (-raw.ctypes.data % 64) // 4
    hot = raw[skip : skip + nf * K.HOT_WIDTH].reshape(nf, K.HOT_WIDTH)
    hot_i = hot.view(np.int32)
    for col in (K.HOT_N, K.HOT_U, K.HOT_V):
        axis = plane[:, col : col + 3].astype(np.float32)
        hot[:, col : col + 3] = axis
        # The offset for the stored (rounded) axis, so that the float32
        # plane still passes through corner a.
        hot[:, col + 3] = (axis.astype(np.float64) * rel).sum(axis=1)
    hot_i[:, K.HOT_HOME] = (
        home[:, 0] | (home[:, 1] << K.HOME_BITS) | (home[:, 2] << (2 * K.HOME_BITS))
    ).astype(np.int32)
    hot_i[:, K.HOT_SMOOTH : K.HOT_SMOOTH + 3] = mesh.smooth_adj
    hot[:, K.HOT_A : K.HOT_A + 3] = rel
    hot[:, K.HOT_AB : K.HOT_AB + 3] = tri[:, 1] - tri[:, 0]
    hot[:, K.HOT_AC : K.HOT_AC + 3] = tri[:, 2] - tri[:, 0]
    hot_i[:, K.HOT_ADJ : K.HOT_ADJ + 3] = mesh.face_adj
    hot_i[:, K.HOT_VERT : K.HOT_VERT + 3] = mesh.faces
    hot_i[:, K.HOT_ACROSS] = _across(mesh)
    hot.setflags(write=False)
    hot_i.setflags(write=False)
    return home_step, hot, hot_i


def _across(mesh: _Mesh) -> np.ndarray:
    """Per face f and edge e, what a query needs to know of the face g across
    it (see ``K.HOT_ACROSS``): bits 2e..2e+1 the corner of g opposite their
    shared edge (3: g's adjacency does not name f back, or no g), bits
    6+2e..7+2e the side of f's plane g lies on (1 above, 2 below, 0 on
    it or unknown). (F,) int32."""
    face_adj, faces = mesh.face_adj, mesh.faces
    nf = len(face_adj)
    out = np.zeros(nf, dtype=np.int32)
    rows = np.arange(nf)
    for e in range(3):
        g = face_adj[:, e]
        has = g >= 0
        gg = np.where(has, g, 0)
        back = face_adj[gg] == rows[:, None]
        k = np.full(nf, 3, dtype=np.int32)
        for e2 in range(3):
            k = np.where(has & back[:, e2] & (k == 3), (e2 + 2) % 3, k)
        # g's corner off the shared edge against f's plane: the whole of g
        # lies on that side.
        far = mesh.vertices[faces[gg, np.minimum(k, 2)]]
        h = np.einsum("ij,ij->i", far - mesh.tri[:, 0], mesh.face_normals)
        side = np.where(h > 1e-9, 1, np.where(h < -1e-9, 2, 0)).astype(np.int32)
        side[~has | (k == 3)] = 0
        out |= (k << (2 * e)) | (side << (6 + 2 * e))
    return out


def _smooth_adjacency(face_adj: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(F, 3) int32: the face across each edge where the dihedral angle is below the
    smooth-patch limit, else -1. The query walks plane feet only across these."""
    other = np.where(face_adj >= 0, face_adj, 0)
    cos = np.einsum("fk,fek->fe", normals, normals[other])
    return np.ascontiguousarray(
        np.where((face_adj >= 0) & (cos >= _COS_SMOOTH), face_adj, -1)
    ).astype(np.int32)


__all__ = ["Closest", "GridParams", "GridTree", "warmup", "FORMAT_VERSION"]
