"""The encodings the grid kernels share: cell codes, region codes and the layout of a face record.

Conventions
-----------
tri : (F, 3, 3) float64, mm
    The triangles' corners a, b, c.
Region codes returned by :func:`.face.closest_on_triangle`: 0 interior,
1, 2, 3 the corners a, b, c, and 4, 5, 6 the edges ab, bc, ca (edge e of a
face joins its corners e and (e + 1) % 3).
Faces are numbered in the tree's own (spatial) order; ``face_id`` maps that
number to the CAD model's face index, which is what the queries return.
Cell codes of the fine grid: ``>= 0`` a face that is closest to all eight
corners of the cell, ``-1`` unknown (a corner lies outside the computed band:
use the exact slow path), ``<= -2`` mixed: the cell is split in eight
subcells of half its edge, whose codes are ``subcells[8 * (-code - 2) + s]``
(``s = 4 sx + 2 sy + sz``, the half the point lies in along each axis).
Subcell codes read like cell codes, except that a mixed one, ``<= -2``,
indexes a list of candidate faces: ``mixed_faces[mixed_ptr[m]:mixed_ptr[m + 1]]``
with ``m = -code - 2`` (the distinct faces closest to the subcell's corners).
"""

from __future__ import annotations

REGION_INTERIOR = 0
CELL_UNKNOWN = -1
# ``out_face`` of a query the fast path leaves to the slow one.
FACE_SLOW = -1

# A single-face cell code carries this bit when the foot point of every point
# of the cell lies inside the face (checked at the eight corners: the foot is
# an affine function of the point, the cell convex).
INTERIOR_FLAG = 1 << 30
FACE_MASK = INTERIOR_FLAG - 1

# Layout of a face record, one row of the (F, HOT_WIDTH) 4-byte array the
# queries read (as float32, and as int32 for the integer columns): 128
# bytes, two cache lines per face. Line 0 holds what the plane test needs
# (most queries read nothing else), line 1 the corners and the
# neighbourhood for the exact test and the walk. Geometry is stored
# relative to the face's home point (origin + home * home_step, the home
# packed in HOT_HOME as three HOME_BITS-bit integers, corner a within a
# few block edges of it): p - home is taken in float64, so the float32
# values (relative error 6e-8) place planes and corners to nanometres.
HOT_WIDTH = 32
# Line 0: unit normal n (3), n.(a - home); U (3), U.(a - home); V (3),
# V.(a - home) (U, V: the dual basis of the edges ab, ac in the plane).
HOT_N, HOT_U, HOT_V = 0, 4, 8
HOT_HOME = 12  # int32: home x | y << HOME_BITS | z << 2 * HOME_BITS
HOT_SMOOTH = 13  # int32 (3): the face across edge e where it is smooth, else -1
# Line 1: a - home (3), b - a (3), c - a (3).
HOT_A, HOT_AB, HOT_AC = 16, 19, 22
HOT_ADJ = 25  # int32 (3): the face across edge e, or -1
HOT_VERT = 28  # int32 (3): the vertex index of corner e
# int32: for each edge e, bits 2e..2e+1: the corner of the face g across
# edge e opposite their shared edge (3: unknown); bits 6+2e..7+2e: the side
# of this face's plane g lies on (ACROSS_ABOVE, ACROSS_BELOW, or 0).
HOT_ACROSS = 31
ACROSS_ABOVE = 1
ACROSS_BELOW = 2
HOME_BITS = 10
HOME_MASK = (1 << HOME_BITS) - 1
