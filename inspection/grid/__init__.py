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
data are larger than the caches, queries arrive in any order): what counts
is how many cache lines a query reads and whether their misses overlap.
Everything a query reads of a face sits in one 128-byte record of float32
values (:mod:`.kernels.layout`): the first cache line holds the plane and
the dual basis of the barycentric test plus the smooth neighbours, which is
all most queries read; the second the corners and the neighbourhood for the
exact test and the walk. Queries are taken in their input order, in chunks
whose passes each issue loads that do not depend on one another (cell codes,
then prefetches of the face records they name, then a prefetch of the face a
walk steps to), so that the misses overlap instead of following one another.
In a cell with a candidate list the candidates' planes bound their distances
from below, so few need the full point-to-triangle test; where no
candidate's plane foot lies inside it (the closest face is often closest at
none of the corners), the query steps from the nearest by its plane across
smooth edges as a one-face cell does, and so it does from any candidate
whose plane is nearer than the best answer so far (inside a thin plate by an
edge, the face across the edge). Such lists cost a query several times
a single face, which is why mixed cells are split in subcells, whose lists
are shorter. A subcell left with one face also looks across that face's
sharp edges, unless the build proved no face there can be closer, so
splitting changes no answer. Faces are numbered in a spatial order
(``face_id`` maps them back to the CAD's numbering). Each query's answer
depends on that query alone: results are the same for any order, chunking
or number of threads.

Points outside the band, outside the bounding box, or in cells whose corners
lie outside the band take the exact slow path: a bounding volume hierarchy
over the faces, searched depth first with the nearer box first and every box
farther than the best face so far pruned. A caller that needs only the
points within a reach (``query_within``: a score that truncates distances)
spares that search: within the band it is not run, past it every box beyond
the reach is pruned from the start.

Accuracy: cells with one face are exact where the surface is smooth (two
adjacent faces meeting at less than 0.02 rad can swap on the concave side,
erring by at most distance * angle^2; the walk looks across such edges only
in the far path); cells with a candidate list are exact unless a surface
feature smaller than a cell (a wall thinner than the spacing, a rib's edge)
lies between the corners, in which case a point beside it may get the next
surface instead. Likewise on the concave side of a bend meshed finer than a
cell, and deep inside a solid wall by its end face, a face closest at none
of a cell's corners can be missed. A finer ``spacing_mm`` makes all of these
rarer; ``bench/bench_grid.py`` measures how often they happen. The face
records hold planes and corners in float32 relative to a home point of the
face (a block corner near it; the query's offset from it is taken in
float64), which rounds them by about 6e-8 of their distance from that
point: where the fast path has the closest face, its points and distances
are exact to a few nanometres, its normals unit vectors within 1e-7 rad of
the face's. The far path is exact in float64.

Compilation: the kernels are numba functions cached on disk (``cache=True``).
The first query of a fresh process loads (or, on a new machine, compiles) them;
call :func:`warmup` at service start-up so that no part pays for it.

Modules: :mod:`.tree` (the tree and its queries), :mod:`.build` (the build
stages), :mod:`.mesh` (the mesh arrays and face records the kernels read),
:mod:`.io` (the tree file), :mod:`.kernels` (the numba kernels).
"""

from __future__ import annotations

from .build import BLOCK, DEFAULT_BAND_MM, DEFAULT_SPACING_MM, ProgressFn
from .io import FORMAT_VERSION
from .tree import Closest, GridParams, GridTree, warmup

__all__ = [
    "BLOCK",
    "DEFAULT_BAND_MM",
    "DEFAULT_SPACING_MM",
    "FORMAT_VERSION",
    "Closest",
    "GridParams",
    "GridTree",
    "ProgressFn",
    "warmup",
]
