"""The GridTree: the closest-point grid of one CAD model, and its queries.

The tree is built by :mod:`.build`, saved and loaded through :mod:`.io`;
its queries run the fast path of :mod:`.kernels.query` and, for the points
it leaves, the exact slow path of :mod:`.kernels.bvh`. :func:`warmup` loads
the kernels before the first part needs them.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import numbers
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..arrays import Faces, Indices, Points, Scalars, Vectors
from ..cad import CadModel
from ..errors import InvalidInput, TreeMismatch
from .build import BLOCK, DEFAULT_BAND_MM, DEFAULT_SPACING_MM, ProgressFn, build_grid
from .io import FORMAT_VERSION, read_tree, write_tree
from .kernels.bvh import query_bvh
from .kernels.layout import CELL_UNKNOWN, FACE_SLOW, INTERIOR_FLAG
from .kernels.query import QUERY_CHUNK, query_grid
from .mesh import Mesh, hot_records, mesh_from_saved

log = logging.getLogger(__name__)


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
        mesh: Mesh,
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
        self._home_step, self._hot, self._hot_i = hot_records(
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
        if len(cad.faces) >= INTERIOR_FLAG:
            raise InvalidInput(f"{len(cad.faces)} faces: at most {INTERIOR_FLAG - 1} are supported")
        spacing_mm = _positive("spacing_mm", spacing_mm)
        band_mm = float(band_mm)
        if not math.isfinite(band_mm) or band_mm < 0:
            raise InvalidInput(f"band_mm must be a finite number >= 0, got {band_mm!r}")
        t0 = time.perf_counter()
        mesh, grid = build_grid(cad, spacing_mm, band_mm, progress)
        params = GridParams(spacing_mm=spacing_mm, band_mm=band_mm, block=BLOCK)
        tree = cls(
            mesh=mesh,
            params=params,
            cad_hash=cad.hash,
            origin=grid.origin,
            dims=grid.dims,
            coarse=grid.coarse,
            cells=grid.cells,
            subcells=grid.subcells,
            mixed_ptr=grid.mixed_ptr,
            mixed_faces=grid.mixed_faces,
            name=cad.name,
            cad=cad,
        )
        log.debug(
            "GridTree %s: %d faces, %d blocks, %d mixed cells, %.1f MB, %.2f s",
            cad.name,
            len(cad.faces),
            tree.n_blocks,
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
            the notes on accuracy of :mod:`inspection.grid`).

        Raises
        ------
        InvalidInput
            Not an (N, 3) array of finite numbers.
        """
        return self._query(points, math.inf)

    def query_within(self, points: np.ndarray, within_mm: float) -> Closest:
        """Closest points on the CAD surface of the points within ``within_mm`` of it.

        Answers as :meth:`query` does, to the bit, every point nearer the
        surface than ``within_mm``. A point farther off may be answered so
        too (the fast path answers the whole band), or as beyond reach: face
        -1, distance ``+inf``, NaN point and normal. Far points cost the
        exact search only the few boxes within reach, where :meth:`query`
        searches on until it finds their face: for callers that truncate
        distances anyway (a score capped at a few millimetres).

        Parameters
        ----------
        points : (N, 3) float, mm, CAD frame
        within_mm : float
            Positive reach, mm.

        Raises
        ------
        InvalidInput
            Not an (N, 3) array of finite numbers, or a reach that is not
            a positive number.
        """
        if not (
            isinstance(within_mm, numbers.Real)
            and not isinstance(within_mm, bool)
            and 0.0 < within_mm < math.inf
        ):
            raise InvalidInput(f"within_mm must be a positive finite number, got {within_mm!r}")
        return self._query(points, float(within_mm) ** 2)

    def _query(self, points: np.ndarray, reach2: float) -> Closest:
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
            n_slow = np.empty((n + QUERY_CHUNK - 1) // QUERY_CHUNK, dtype=np.int64)
            query_grid(
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
                slow = np.flatnonzero(out_face == FACE_SLOW)
                _check_finite(p[slow])
                if reach2 <= self.params.band_mm**2:
                    # The fast path answers every point within the band: these
                    # lie beyond it, so beyond reach.
                    out_pts[slow] = np.nan
                    out_nrm[slow] = np.nan
                    out_dist[slow] = np.inf
                else:
                    self._query_slow(p, slow, out_pts, out_nrm, out_dist, out_face, reach2)
        return Closest(points=out_pts, normals=out_nrm, distances=out_dist, face=out_face)

    def _query_slow(self, p, rows, out_pts, out_nrm, out_dist, out_face, reach2) -> None:
        """Exact closest faces of p[rows] through the bounding volume hierarchy, of those
        within ``sqrt(reach2)`` of the surface."""
        m = self._mesh
        query_bvh(
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
            reach2,
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
            "unknown_cells": int((self._cells == CELL_UNKNOWN).sum()),
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
        meta = {
            "format_version": FORMAT_VERSION,
            "name": self.name,
            "cad_hash": self.cad_hash,
            "tree_hash": self.hash,
            "params": self.params.to_dict(),
        }
        return write_tree(Path(path), self._arrays(), meta)

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
        meta, a = read_tree(path)
        if cad is not None:
            if not isinstance(cad, CadModel):
                raise InvalidInput(f"cad must be a CadModel, got {type(cad).__name__}")
            if cad.hash != meta["cad_hash"]:
                raise TreeMismatch(
                    f"{path}: tree built for CAD {meta['cad_hash'][:12]}, "
                    f"given CAD {cad.name!r} is {cad.hash[:12]}"
                )
        mesh = mesh_from_saved(a)
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
