"""Building the grid: the blocks near the surface, the closest face at every node, the cell codes.

The stages of :func:`build_grid`, in order: number the faces in a spatial
order, list the faces near each block, give every node within reach of the
surface its closest face and every cell its code, then split the mixed cells
in eight subcells (:func:`_split_mixed`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..cad import CadModel
from ..errors import InvalidInput
from .kernels.build import (
    block_face_lists,
    block_nodes,
    cells_from_nodes,
    face_block_ranges,
    mark_safe_subcells,
    subcell_nodes,
)
from .kernels.layout import CELL_UNKNOWN
from .mesh import COS_SMOOTH, Mesh, across_codes, mesh_arrays

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

ProgressFn = Callable[[float], None]


@dataclass(frozen=True)
class Grid:
    """The sparse grid of a tree (see :mod:`inspection.grid` for the codes).

    Attributes
    ----------
    origin : (3,) float64, mm
        Corner of block (0, 0, 0).
    dims : (3,) int64
        Blocks along each axis of the coarse grid.
    coarse : (nbx * nby * nbz,) int32
        Block id of each coarse cell, or -1 far from the surface.
    cells : (B * BLOCK^3,) int32
        Cell codes of the blocks.
    subcells : (8 M,) int32
        Codes of the eight subcells of each mixed cell.
    mixed_ptr, mixed_faces : (L + 1,) int64, (P,) int32
        Candidate lists of the mixed subcells.
    """

    origin: np.ndarray
    dims: np.ndarray
    coarse: np.ndarray
    cells: np.ndarray
    subcells: np.ndarray
    mixed_ptr: np.ndarray
    mixed_faces: np.ndarray


def build_grid(
    cad: CadModel, h: float, band_mm: float, progress: ProgressFn | None = None
) -> tuple[Mesh, Grid]:
    """The mesh arrays and the grid of spacing ``h`` mm over a CAD model.

    The caller has checked ``h > 0`` and ``band_mm >= 0``.

    Raises
    ------
    InvalidInput
        A grid too large for memory (usually a model in the wrong unit).
    """
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
            f"a {h} mm grid over a {cad.extents.round(1).tolist()} mm "
            f"model needs {n_coarse} blocks; is the model in mm? (use a larger spacing_mm)"
        )
    origin = lo_box.astype(np.float64)

    # Number the faces in the raster order of the blocks holding their
    # centroids, the order in which a query batch visits the blocks: the
    # face records a batch reads then lie close together in memory.
    centroid = cad.vertices[cad.faces].mean(axis=1)
    cb = np.clip(((centroid - origin) // block_mm).astype(np.int64), 0, dims - 1)
    face_id = np.argsort((cb[:, 0] * dims[1] + cb[:, 1]) * dims[2] + cb[:, 2], kind="stable")
    mesh = mesh_arrays(cad.vertices, cad.faces[face_id], cad.face_normals[face_id], face_id)
    tri = mesh.tri
    lo = tri.min(axis=1) - reach
    hi = tri.max(axis=1) + reach
    centre = tri.mean(axis=1)
    radius = np.sqrt(((tri - centre[:, None, :]) ** 2).sum(axis=2)).max(axis=1)
    ranges = face_block_ranges(lo, hi, origin, block_mm, dims)
    coarse, coords, ptr, face_idx = block_face_lists(ranges, dims)
    nblocks = len(coords)
    if nblocks * BLOCK**3 > _MAX_FINE_CELLS:
        raise InvalidInput(
            f"the band needs {nblocks * BLOCK**3} fine cells; "
            "use a larger spacing_mm or a smaller band_mm"
        )
    cells = np.empty(nblocks * BLOCK**3, dtype=np.int32)
    reach2 = reach * reach

    def nodes_of(b0: int, b1: int) -> np.ndarray:
        return block_nodes(
            b0, b1, coords, ptr, face_idx, lo, hi, centre, radius, tri, origin, h, BLOCK, reach2
        )

    lists = _cells(cells, coords, nodes_of, mesh, origin, h, BLOCK, progress)
    subcells, mixed_ptr, mixed_faces = _split_mixed(cells, coords, lists, mesh, origin, h, reach2)
    grid = Grid(origin, dims, coarse, cells, subcells, mixed_ptr, mixed_faces)
    return mesh, grid


def _cells(
    out: np.ndarray,
    coords: np.ndarray,
    nodes_of: Callable[[int, int], np.ndarray],
    mesh: Mesh,
    origin: np.ndarray,
    h: float,
    block: int,
    progress: ProgressFn | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Cell codes of blocks of block^3 cells of edge h, a chunk of blocks per
    kernel call, written to ``out``; returns their candidate lists.

    Block b has its corner at ``origin + coords[b] * block * h``;
    ``nodes_of(b0, b1)`` gives the closest faces of the (block+1)^3 nodes of
    blocks b0..b1-1. Used for the blocks of the grid and for the subcells of
    its mixed cells (blocks of 2^3).
    """
    n = len(coords)
    chunk = max(1, (_CHUNK_BLOCKS * BLOCK**3) // block**3)
    counts_parts: list[np.ndarray] = []
    faces_parts: list[np.ndarray] = []
    n_mixed = 0
    b3 = block**3
    for b0 in range(0, n, chunk):
        b1 = min(n, b0 + chunk)
        counts, mixed = cells_from_nodes(
            nodes_of(b0, b1),
            b0,
            coords,
            origin,
            h,
            block,
            mesh.tri,
            mesh.plane,
            mesh.faces,
            mesh.face_normals,
            COS_SMOOTH,
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
    mesh: Mesh,
    origin: np.ndarray,
    h: float,
    reach2: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split every mixed cell in eight subcells of edge h / 2.

    A mixed cell (corners with different closest faces) lies where regions
    of faces meet across a sharp edge or a hole; a query there tests every
    candidate, several times the cost of a single-face cell. Its 19 new
    subcell corners get their closest face among the cell's candidates,
    which are the faces closest to its corners, the faces of their smooth
    patches that hold the corners' plane feet, and the faces across sharp
    edges from there (:func:`subcell_nodes`): the subcells that then see
    one face (or one smooth patch) take the single-face path, and the
    others keep the shorter list of their own corners' faces.
    A one-face subcell is answered by its face's plane alone only where no
    face across a sharp edge of it can be closer (:func:`mark_safe_subcells`);
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
    where = np.flatnonzero(cells < CELL_UNKNOWN)
    b3 = BLOCK**3
    local = where % b3
    # A mixed cell's integer grid coordinates: as a "block" of 2^3 subcells of
    # edge h / 2 its corner is origin + ijk * 2 * (h / 2).
    ijk = coords[where // b3] * BLOCK + np.stack(
        [local // (BLOCK * BLOCK), (local // BLOCK) % BLOCK, local % BLOCK], axis=1
    )
    ijk = np.ascontiguousarray(ijk, dtype=np.int64)
    subcells = np.empty(8 * n_mixed, dtype=np.int32)

    def nodes_of(b0: int, b1: int) -> np.ndarray:
        return subcell_nodes(
            b0, b1, ijk, origin, h / 2, ptr0, faces0, mesh.tri, mesh.plane, mesh.face_adj,
            mesh.smooth_adj, reach2,
        )  # fmt: skip

    mixed_ptr, mixed_faces = _cells(subcells, ijk, nodes_of, mesh, origin, h / 2, 2)
    mark_safe_subcells(
        subcells, ijk, origin, h / 2, mesh.plane, mesh.face_adj, mesh.smooth_adj, across_codes(mesh)
    )
    return subcells, mixed_ptr, mixed_faces
