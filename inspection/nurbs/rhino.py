"""NURBS surfaces of Rhino's 3dm files, through ``rhino3dm`` (the optional extra ``step``).

Rhino stores a degree-``p`` knot vector without its two outer knots (``n +
p - 1`` values; the omitted ones repeat their neighbours for a clamped
surface, and only matter for an unclamped one, where they are set to
extend the first and last spans) and its control points in homogeneous
coordinates ``(w x, w y, w z, w)``. Surfaces come from surface objects and
from the faces of polyface objects (breps) as their underlying surface;
rhino3dm does not expose the faces' two-dimensional trim curves, so trims
are not read.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import CadLoadError, InspectionError
from .surface import Surface


def _rhino3dm() -> Any:
    try:
        import rhino3dm
    except ImportError as exc:
        raise CadLoadError(
            "reading .3dm files needs rhino3dm: pip install 'inspection[step]'"
        ) from exc
    return rhino3dm


def _full_knots(rhino_knots: Any, degree: int) -> np.ndarray:
    k = np.array(rhino_knots.ToList(), dtype=np.float64)
    # The superfluous end knots: a repeat for clamped ends, else one more span.
    first = k[0] if k[0] == k[degree - 1] else 2 * k[0] - k[1]
    last = k[-1] if k[-1] == k[-degree] else 2 * k[-1] - k[-2]
    return np.r_[first, k, last]


def _from_rhino(nurbs: Any, scale: float) -> Surface:
    p, q = nurbs.Degree(0), nurbs.Degree(1)
    nu, nv = nurbs.Points.CountU, nurbs.Points.CountV
    hw = np.empty((nu, nv, 4))
    for i in range(nu):
        for j in range(nv):
            c = nurbs.Points.GetControlPoint(i, j)
            hw[i, j] = (c.X, c.Y, c.Z, c.W)
    w = hw[..., 3]
    if not nurbs.IsRational:
        w = np.ones((nu, nv))
        cp = hw[..., :3]
    else:
        cp = hw[..., :3] / w[..., None]
    return Surface(p, q, _full_knots(nurbs.KnotsU, p), _full_knots(nurbs.KnotsV, q), cp * scale, w)


def read_3dm_surfaces(path: str | Path, *, scale: float = 1.0) -> list[Surface]:
    """The NURBS surfaces of a 3dm file: surface objects and brep faces, in file order.

    Parameters
    ----------
    path : a .3dm file
    scale : float > 0, multiplies the coordinates to give millimetres

    Raises
    ------
    CadLoadError
        rhino3dm missing, an unreadable file, or a surface that does not make
        a valid NURBS surface.
    """
    r = _rhino3dm()
    p = Path(path)
    if not np.isfinite(scale) or scale <= 0:
        raise CadLoadError(f"scale must be a finite positive number, got {scale!r}")
    if not p.is_file():
        raise CadLoadError(f"{p}: no such file")
    model = r.File3dm.Read(str(p))
    if model is None:
        raise CadLoadError(f"{p}: not a readable 3dm file")
    out = []
    for obj in model.Objects:
        geo = obj.Geometry
        if isinstance(geo, r.Brep):
            surfaces = [face.UnderlyingSurface() for face in geo.Faces]
        elif isinstance(geo, r.Surface):
            surfaces = [geo]
        else:
            continue
        for s in surfaces:
            try:
                out.append(_from_rhino(s.ToNurbsSurface(), float(scale)))
            except (InspectionError, ValueError) as exc:
                raise CadLoadError(f"{p}: surface of object {obj.Attributes.Id}: {exc}") from exc
    return out


def write_3dm_surfaces(path: str | Path, surfaces: Iterable[Surface]) -> Path:
    """Write surfaces as surface objects of a 3dm file (the inverse of
    :func:`read_3dm_surfaces` at scale 1)."""
    r = _rhino3dm()
    model = r.File3dm()
    for s in surfaces:
        (nu, nv), p, q = s.shape, s.degree_u, s.degree_v
        rs = r.NurbsSurface.Create(3, True, p + 1, q + 1, nu, nv)
        for i in range(nu):
            for j in range(nv):
                w = float(s.weights[i, j])
                x, y, z = (float(c) * w for c in s.control_points[i, j])
                rs.Points[i, j] = r.Point4d(x, y, z, w)
        for k, val in enumerate(s.knots_u[1:-1]):
            rs.KnotsU[k] = float(val)
        for k, val in enumerate(s.knots_v[1:-1]):
            rs.KnotsV[k] = float(val)
        model.Objects.AddSurface(rs)
    out = Path(path)
    if not model.Write(str(out), 7):
        raise CadLoadError(f"{out}: could not be written")
    return out
