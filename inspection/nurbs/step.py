"""A light reader of the B-spline surfaces of a STEP file (ISO 10303-21).

Reads the entities of the DATA section and turns every
``B_SPLINE_SURFACE_WITH_KNOTS`` (and the complex entity that adds
``RATIONAL_B_SPLINE_SURFACE`` weights) into a :class:`Surface`; faces of
other kinds (planes, cylinders) are not read. STEP stores knots as distinct
values with their multiplicities and the control points as rows along u of
``CARTESIAN_POINT`` references.

:func:`read_step_faces` also reads each B-spline face's bounds as a
:class:`Trim` (the outer boundary and its holes): the loops' edges (lines,
circles and B-spline curves, bare or inside a ``SURFACE_CURVE``) are sampled
in space between their vertices and projected onto the face's surface, which
gives the boundary polygons in parameter space whatever parameter curves the
file carries.

The file's length unit is not interpreted: ``scale`` multiplies the
coordinates to give millimetres, as for :func:`inspection.load_cad`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import CadLoadError, InspectionError
from .closest import Trim, closest_points
from .curve import Curve
from .surface import Surface

# The largest chord error (mm) of a trim polygon along a circular edge, and
# the samples of other edges (lines on a curved face map to curves in (u, v)).
TRIM_CHORD_MM = 1e-3
EDGE_SAMPLES = 64
BSPLINE_EDGE_SAMPLES = 256

_TOKEN = re.compile(
    r"""\s*(?:
        (?P<str>'(?:[^']|'')*')
      | (?P<ref>\#\d+)
      | (?P<enum>\.[A-Za-z_0-9]+\.)
      | (?P<num>[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)
      | (?P<id>[A-Za-z_][A-Za-z_0-9]*)
      | (?P<sym>[(),$*=;])
    )""",
    re.VERBOSE,
)
_ENTITY = re.compile(r"#(\d+)\s*=\s*(.*?);\s*(?=#\d+\s*=|ENDSEC)", re.DOTALL)


class _Ref(int):
    """A reference ``#n`` to another entity."""


def _parse(text: str) -> list[Any]:
    """The tokens of one entity's right-hand side as nested lists: a simple
    entity is ``[name, args]``, a complex one ``[[name, args], ...]``."""
    tokens: list[tuple[str, str]] = []
    pos = 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            if text[pos:].strip() == "":
                break
            raise ValueError(f"unexpected text {text[pos : pos + 20]!r}")
        kind = m.lastgroup
        assert kind is not None
        tokens.append((kind, m.group(kind)))
        pos = m.end()
    items, _ = _items(tokens, 0)
    return items


def _items(tokens: list[tuple[str, str]], i: int) -> tuple[list[Any], int]:
    out: list[Any] = []
    while i < len(tokens):
        kind, val = tokens[i]
        if kind == "sym" and val == ")":
            return out, i + 1
        if kind == "sym" and val == ",":
            i += 1
            continue
        if kind == "sym" and val == "(":
            inner, i = _items(tokens, i + 1)
            if out and _is_name(out[-1]):
                out[-1] = [out[-1], inner]
            else:
                out.append(inner)
            continue
        if kind == "ref":
            out.append(_Ref(int(val[1:])))
        elif kind == "num":
            out.append(float(val))
        elif kind == "id":
            out.append(_Name(val))
        else:
            out.append(val)
        i += 1
    return out, i


class _Name(str):
    """An entity's type name."""


def _is_name(x: Any) -> bool:
    return isinstance(x, _Name)


def _entities(text: str) -> dict[int, str]:
    """The unparsed right-hand side of every entity of the DATA section; only
    the surfaces and their points are parsed, as they are needed."""
    start = text.find("DATA;")
    if start < 0:
        raise ValueError("no DATA section")
    return {int(m.group(1)): m.group(2) for m in _ENTITY.finditer(text, start)}


def _parts(entity: list[Any]) -> dict[str, list[Any]]:
    """The entity's parts by type name (one for a simple entity, several for a complex one)."""
    if len(entity) == 1 and isinstance(entity[0], list) and entity[0] and _is_name(entity[0][0]):
        return {entity[0][0]: entity[0][1]}
    if len(entity) == 1 and isinstance(entity[0], list):
        return {p[0]: p[1] for p in entity[0] if isinstance(p, list) and p and _is_name(p[0])}
    return {}


def _expand(knots: list[float], mults: list[float]) -> np.ndarray:
    return np.repeat(np.array(knots, dtype=np.float64), np.array(mults, dtype=np.int64))


def _read_entities(path: str | Path, scale: float) -> tuple[Path, dict[int, str]]:
    p = Path(path)
    try:
        text = p.read_text(encoding="latin-1")
    except OSError as exc:
        raise CadLoadError(f"{p}: {exc.strerror or exc}") from exc
    if not np.isfinite(scale) or scale <= 0:
        raise CadLoadError(f"scale must be a finite positive number, got {scale!r}")
    try:
        return p, _entities(text)
    except ValueError as exc:
        raise CadLoadError(f"{p}: not a STEP file: {exc}") from exc


def read_step_surfaces(path: str | Path, *, scale: float = 1.0) -> list[Surface]:
    """The B-spline surfaces of a STEP file, in file order.

    Parameters
    ----------
    path : a .step or .stp file
    scale : float > 0, multiplies the coordinates to give millimetres

    Returns
    -------
    list of Surface (empty when the file has no B-spline surface)

    Raises
    ------
    CadLoadError
        Not a readable STEP file, or a B-spline surface that does not make a
        valid NURBS surface (the reason is given).
    """
    p, entities = _read_entities(path, scale)
    out = []
    for eid in sorted(entities):
        if "B_SPLINE_SURFACE_WITH_KNOTS" not in entities[eid]:
            continue
        try:
            parts = _parts(_parse(entities[eid]))
            out.append(_surface(entities, parts, scale))
        except (InspectionError, ValueError, KeyError, IndexError, TypeError) as exc:
            raise CadLoadError(f"{p}: B-spline surface #{eid}: {exc}") from exc
    return out


def read_step_faces(path: str | Path, *, scale: float = 1.0) -> list[tuple[Surface, Trim]]:
    """The B-spline faces of a STEP file with their bounds, in file order.

    Parameters
    ----------
    path : a .step or .stp file
    scale : float > 0, multiplies the coordinates to give millimetres

    Returns
    -------
    list of (Surface, Trim)

    Raises
    ------
    CadLoadError
        Not a readable STEP file, or a B-spline face whose surface or
        boundary cannot be read (the reason is given).
    """
    p, entities = _read_entities(path, scale)
    return _faces(p, entities, scale)[0]


_SI_LENGTH = re.compile(r"SI_UNIT\s*\(\s*(\$|\.[A-Z]+\.)\s*,\s*\.METRE\.\s*\)")
_CONVERTED = re.compile(r"CONVERSION_BASED_UNIT\s*\(\s*'((?:[^']|'')*)'")
_SI_PREFIX = {"$": "m", ".MILLI.": "mm", ".CENTI.": "cm", ".DECI.": "dm", ".MICRO.": "um"}


def step_length_units(path: str | Path) -> tuple[str, ...]:
    """The length units a STEP file declares, in file order: "mm", "m", "cm",
    ... for SI units, the name of a conversion-based one ("INCH"); empty
    when it declares none (as our writer's files).

    The reader does not convert units (``scale`` does): a caller that reads
    a part's faces checks that they are in millimetres.

    Raises
    ------
    CadLoadError
        Not a readable STEP file.
    """
    _, entities = _read_entities(path, 1.0)
    units = []
    for eid in sorted(entities):
        text = entities[eid]
        if "LENGTH_UNIT" not in text:
            continue
        converted = _CONVERTED.search(text)
        si = _SI_LENGTH.search(text)
        if converted:
            units.append(converted.group(1).replace("''", "'"))
        elif si:
            units.append(_SI_PREFIX.get(si.group(1), si.group(1).strip(".").lower() + "m"))
    return tuple(units)


def read_step_nurbs(path: str | Path, *, scale: float = 1.0) -> list[tuple[Surface, Trim | None]]:
    """The whole part as NURBS faces, or nothing: the B-spline faces of a STEP
    file with their trims, or, in a file of bare surfaces without topology,
    every B-spline surface untrimmed.

    Returns
    -------
    list of (Surface, Trim or None)
        Empty when the file holds no B-spline surface, or faces of other
        kinds too (planes, cylinders): these the reader does not evaluate,
        so such a part is measured against its mesh.

    Raises
    ------
    CadLoadError
        As :func:`read_step_faces`.
    """
    p, entities = _read_entities(path, scale)
    faces, others = _faces(p, entities, scale)
    if others:
        return []
    if faces:
        return list(faces)
    return [(s, None) for s in read_step_surfaces(p, scale=scale)]


def _faces(
    p: Path, entities: dict[int, str], scale: float
) -> tuple[list[tuple[Surface, Trim]], int]:
    """The B-spline faces with their trims, and the number of faces of other kinds."""
    out = []
    others = 0
    for eid in sorted(entities):
        text = entities[eid]
        if not text.lstrip().startswith("ADVANCED_FACE"):
            continue
        try:
            _, bounds, surface_ref = _parts(_parse(text))["ADVANCED_FACE"][:3]
            sparts = _parts(_parse(entities[surface_ref]))
            if "B_SPLINE_SURFACE_WITH_KNOTS" not in sparts:
                others += 1
                continue
            surface = _surface(entities, sparts, scale)
            out.append((surface, _face_trim(entities, bounds, surface, scale)))
        except (InspectionError, ValueError, KeyError, IndexError, TypeError) as exc:
            raise CadLoadError(f"{p}: face #{eid}: {exc}") from exc
    return out, others


def _face_trim(entities: dict[int, str], bounds: list[Any], surface: Surface, scale: float) -> Trim:
    """The face's bounds as parameter-space polygons: the outer one (or the
    first, when none is marked outer) and the others as holes."""
    outer = None
    loops = []
    for ref in bounds:
        parts = _parts(_parse(entities[ref]))
        kind = "FACE_OUTER_BOUND" if "FACE_OUTER_BOUND" in parts else "FACE_BOUND"
        _, loop_ref, orientation = parts[kind][:3]
        loop = _parts(_parse(entities[loop_ref]))
        if "EDGE_LOOP" not in loop:
            continue  # a vertex loop: a point, no area
        uv = _loop_params(entities, loop["EDGE_LOOP"][1], orientation, surface, scale)
        if kind == "FACE_OUTER_BOUND" and outer is None:
            outer = uv
        else:
            loops.append(uv)
    if outer is None:
        if not loops:
            raise ValueError("the face has no edge loop")
        outer = loops.pop(0)
    return Trim(outer, tuple(loops))


def _loop_params(
    entities: dict[int, str], edges: list[Any], orientation: str, surface: Surface, scale: float
) -> np.ndarray:
    """(k, 2) parameters of points along an edge loop, projected onto the surface."""
    samples = []
    for oe_ref in edges:
        _, _, _, edge_ref, oe_sense = _parts(_parse(entities[oe_ref]))["ORIENTED_EDGE"][:5]
        pts = _edge_samples(entities, edge_ref, scale)
        if oe_sense == ".F.":
            pts = pts[::-1]
        samples.append(pts[:-1])  # the next edge starts where this one ends
    xyz = np.concatenate(samples)
    if orientation == ".F.":
        xyz = xyz[::-1]
    return closest_points(surface, xyz).params


def _edge_samples(entities: dict[int, str], edge_ref: int, scale: float) -> np.ndarray:
    """(k, 3) points along an EDGE_CURVE from its start vertex to its end."""
    _, v0, v1, geom_ref, same_sense = _parts(_parse(entities[edge_ref]))["EDGE_CURVE"][:5]
    a = np.array(_vertex(entities, v0)) * scale
    b = np.array(_vertex(entities, v1)) * scale
    geom = _parts(_parse(entities[geom_ref]))
    for wrapper in ("SURFACE_CURVE", "SEAM_CURVE"):
        if wrapper in geom:
            geom = _parts(_parse(entities[geom[wrapper][1]]))
    s = np.linspace(0.0, 1.0, EDGE_SAMPLES + 1)
    if "LINE" in geom:
        return a + s[:, None] * (b - a)
    if "CIRCLE" in geom:
        _, placement, radius = geom["CIRCLE"][:3]
        centre, axis, ref = _placement(entities, placement, scale)
        other = np.cross(axis, ref)
        r = float(radius) * scale

        def angle(x: np.ndarray) -> float:
            d = x - centre
            return float(np.arctan2(d @ other, d @ ref))

        t0, t1 = angle(a), angle(b)
        sense = 1.0 if same_sense == ".T." else -1.0
        sweep = (sense * (t1 - t0)) % (2 * np.pi) or 2 * np.pi
        # Chords of angle 2 acos(1 - e / r) err by e from the arc.
        step = 2 * np.arccos(max(1.0 - TRIM_CHORD_MM / r, -1.0))
        n = max(int(np.ceil(sweep / step)), 2)
        t = t0 + sense * sweep * np.linspace(0.0, 1.0, n + 1)
        return centre + r * (np.cos(t)[:, None] * ref + np.sin(t)[:, None] * other)
    if "B_SPLINE_CURVE_WITH_KNOTS" in geom:
        curve = _curve(entities, geom, scale)
        dense = np.linspace(*curve.domain, 2001)
        pts = curve.evaluate(dense)
        ends = [dense[int(np.argmin(np.linalg.norm(pts - x, axis=1)))] for x in (a, b)]
        t0, t1 = curve.project(np.stack([a, b]), np.array(ends))
        if same_sense != ".T.":
            t0, t1 = t1, t0
        pts = curve.evaluate(t0 + np.linspace(0.0, 1.0, BSPLINE_EDGE_SAMPLES + 1) * (t1 - t0))
        return pts if same_sense == ".T." else pts[::-1]
    raise ValueError(
        f"edge #{edge_ref}: its curve {sorted(geom)} is not a line, circle or B-spline"
    )


def _vertex(entities: dict[int, str], ref: int) -> list[float]:
    return _point(entities, _parts(_parse(entities[ref]))["VERTEX_POINT"][1])


def _placement(
    entities: dict[int, str], placement: int, scale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre (mm), unit axis and unit reference direction of an AXIS2_PLACEMENT_3D."""
    _, loc, axis_ref, dir_ref = _parts(_parse(entities[placement]))["AXIS2_PLACEMENT_3D"][:4]
    centre = np.array(_point(entities, loc)) * scale
    # Omitted ($) directions default to z and x.
    axis = np.array(_direction(entities, axis_ref) if isinstance(axis_ref, _Ref) else [0, 0, 1.0])
    ref = np.array(_direction(entities, dir_ref) if isinstance(dir_ref, _Ref) else [1.0, 0, 0])
    axis = axis / np.linalg.norm(axis)
    ref = ref - (ref @ axis) * axis
    return centre, axis, ref / np.linalg.norm(ref)


def _direction(entities: dict[int, str], ref: int) -> list[float]:
    return [float(c) for c in _parts(_parse(entities[ref]))["DIRECTION"][1]]


def _curve(entities: dict[int, str], parts: dict[str, list[Any]], scale: float) -> Curve:
    knots_part = parts["B_SPLINE_CURVE_WITH_KNOTS"]
    if "B_SPLINE_CURVE" in parts:
        degree, refs = parts["B_SPLINE_CURVE"][:2]
        mults, knots = knots_part[:2]
    else:
        degree, refs = knots_part[1:3]
        mults, knots = knots_part[6:8]
    cp = np.array([_point(entities, r) for r in refs], dtype=np.float64) * scale
    weights = None
    if "RATIONAL_B_SPLINE_CURVE" in parts:
        weights = np.array(parts["RATIONAL_B_SPLINE_CURVE"][0], dtype=np.float64)
    return Curve(int(degree), _expand(knots, mults), cp, weights)


def _surface(entities: dict[int, str], parts: dict[str, list[Any]], scale: float) -> Surface:
    knots_part = parts["B_SPLINE_SURFACE_WITH_KNOTS"]
    if "B_SPLINE_SURFACE" in parts:
        # Complex entity: the common part holds degrees and control points.
        du, dv, grid = parts["B_SPLINE_SURFACE"][:3]
        mu, mv, ku, kv = knots_part[:4]
    else:
        # Simple entity: name, degrees, points, form, closed u/v, self-intersect, knots.
        du, dv, grid = knots_part[1:4]
        mu, mv, ku, kv = knots_part[8:12]
    cp = np.array(
        [[_point(entities, ref) for ref in row] for row in grid], dtype=np.float64
    ) * float(scale)
    weights = None
    if "RATIONAL_B_SPLINE_SURFACE" in parts:
        weights = np.array(parts["RATIONAL_B_SPLINE_SURFACE"][0], dtype=np.float64)
    return Surface(int(du), int(dv), _expand(ku, mu), _expand(kv, mv), cp, weights)


def _point(entities: dict[int, str], ref: int) -> list[float]:
    parts = _parts(_parse(entities[ref]))
    if "CARTESIAN_POINT" not in parts:
        raise ValueError(f"control point #{ref} is not a CARTESIAN_POINT")
    return [float(c) for c in parts["CARTESIAN_POINT"][1]]


def write_step_surfaces(path: str | Path, surfaces: list[Surface]) -> Path:
    """Write surfaces as rational B-spline surface entities of a STEP file (the
    inverse of :func:`read_step_surfaces` at scale 1; geometry only, no
    topology or product structure)."""
    lines: list[str] = []
    next_id = 1

    def add(text: str) -> int:
        nonlocal next_id
        lines.append(f"#{next_id} = {text};")
        next_id += 1
        return next_id - 1

    def reals(values: Any) -> str:
        return "(" + ",".join(repr(float(v)) for v in values) + ")"

    for s in surfaces:
        rows = []
        for row in s.control_points:
            ids = [add(f"CARTESIAN_POINT('',{reals(c)})") for c in row]
            rows.append("(" + ",".join(f"#{i}" for i in ids) + ")")
        ku, mu = np.unique(s.knots_u, return_counts=True)
        kv, mv = np.unique(s.knots_v, return_counts=True)
        ints = lambda a: "(" + ",".join(str(int(x)) for x in a) + ")"  # noqa: E731
        weights = "(" + ",".join(reals(r) for r in s.weights) + ")"
        add(
            f"( BOUNDED_SURFACE() B_SPLINE_SURFACE({s.degree_u},{s.degree_v},"
            f"({','.join(rows)}),.UNSPECIFIED.,.F.,.F.,.F.) "
            f"B_SPLINE_SURFACE_WITH_KNOTS({ints(mu)},{ints(mv)},{reals(ku)},{reals(kv)},"
            f".UNSPECIFIED.) GEOMETRIC_REPRESENTATION_ITEM() "
            f"RATIONAL_B_SPLINE_SURFACE({weights}) REPRESENTATION_ITEM('') SURFACE() )"
        )
    text = (
        "ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION(('NURBS surfaces'),'2;1');\n"
        "FILE_NAME('','',(''),(''),'','','');\nFILE_SCHEMA(('AUTOMOTIVE_DESIGN'));\nENDSEC;\n"
        "DATA;\n" + "\n".join(lines) + "\nENDSEC;\nEND-ISO-10303-21;\n"
    )
    out = Path(path)
    out.write_text(text, encoding="latin-1")
    return out
