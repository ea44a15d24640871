"""A light reader of the B-spline surfaces of a STEP file (ISO 10303-21).

Reads the entities of the DATA section and turns every
``B_SPLINE_SURFACE_WITH_KNOTS`` (and the complex entity that adds
``RATIONAL_B_SPLINE_SURFACE`` weights) into a :class:`Surface`; faces of
other kinds (planes, cylinders) and the faces' trimming loops are not read.
STEP stores knots as distinct values with their multiplicities and the
control points as rows along u of ``CARTESIAN_POINT`` references.

The file's length unit is not interpreted: ``scale`` multiplies the
coordinates to give millimetres, as for :func:`inspection.load_cad`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import CadLoadError, InspectionError
from .surface import Surface

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
    p = Path(path)
    try:
        text = p.read_text(encoding="latin-1")
    except OSError as exc:
        raise CadLoadError(f"{p}: {exc.strerror or exc}") from exc
    if not np.isfinite(scale) or scale <= 0:
        raise CadLoadError(f"scale must be a finite positive number, got {scale!r}")
    try:
        entities = _entities(text)
    except ValueError as exc:
        raise CadLoadError(f"{p}: not a STEP file: {exc}") from exc
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
