"""NURBS geometry: rational B-spline curves and surfaces, and fitting curves to points.

- :class:`Surface`: points and first derivatives at arbitrary parameters
  (:meth:`Surface.evaluate`) and on regular parameter grids
  (:meth:`Surface.evaluate_grid`, the basis computed once per grid line);
  :func:`evaluation_flops` counts the arithmetic of both ways.
- :class:`Curve`: points and derivatives up to the second, foot points.
- :func:`fit_curve`: a curve's control points and weights (degree and knots
  fixed) fitted to points by orthogonal distance; :func:`deviation_along`
  the deviation of such a fitted (measured) curve from its nominal, and
  :func:`fit_edge` both for the scattered points measured on an edge.
- :func:`closest_points`: foot points on a surface, inside a :class:`Trim`
  polygon in parameter space when given; :func:`tessellate` and
  :func:`tessellate_faces` turn faces into a CAD model for the grid tree,
  and :class:`ExactTree` refines the tree's closest points on the exact
  surfaces.
- :func:`read_step_surfaces` and :func:`read_step_faces` (a light reader of
  STEP's B-spline surfaces, and of their faces' outer boundaries as trims),
  :func:`read_step_nurbs` (a part whose every face is a B-spline face),
  :func:`step_length_units` (the units the file declares)
  and :func:`read_3dm_surfaces` (Rhino's 3dm, through rhino3dm), with writers.

Modules: :mod:`.basis` (the B-spline basis kernels), :mod:`.kernels` (the
compiled evaluation), :mod:`.knots` (input checks), :mod:`.surface`,
:mod:`.curve`, :mod:`.flops`, :mod:`.fit`, :mod:`.edge`, :mod:`.closest`, :mod:`.model`,
:mod:`.step`, :mod:`.rhino`.
"""

from __future__ import annotations

from .closest import SurfaceClosest, Trim, closest_points
from .curve import Curve
from .edge import EdgeFit, fit_edge
from .fit import METHODS, CurveDeviation, CurveFit, deviation_along, fit_curve
from .flops import EvaluationFlops, basis_flops, evaluation_flops
from .model import ExactTree, NurbsModel, tessellate, tessellate_faces
from .rhino import read_3dm_surfaces, write_3dm_surfaces
from .step import (
    read_step_faces,
    read_step_nurbs,
    read_step_surfaces,
    step_length_units,
    write_step_surfaces,
)
from .surface import Surface

__all__ = [
    "METHODS",
    "Curve",
    "CurveDeviation",
    "CurveFit",
    "EdgeFit",
    "EvaluationFlops",
    "ExactTree",
    "NurbsModel",
    "Surface",
    "SurfaceClosest",
    "Trim",
    "basis_flops",
    "closest_points",
    "deviation_along",
    "evaluation_flops",
    "fit_curve",
    "fit_edge",
    "read_3dm_surfaces",
    "read_step_faces",
    "read_step_nurbs",
    "read_step_surfaces",
    "step_length_units",
    "tessellate",
    "tessellate_faces",
    "write_3dm_surfaces",
    "write_step_surfaces",
]
