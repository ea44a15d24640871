"""Reading and writing point clouds: PLY, XYZ (text) and NPY.

Read: ``read_cloud(path) -> (N, 3) float64`` in the file's units (mm by our
convention), validated (finite, non-empty, three coordinates). Write:
``write_ply(path, points, scalars=...)`` as binary little-endian PLY with
optional per-point float scalars (e.g. the signed deviation), which viewers
such as CloudCompare and Foxglove colour by.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .arrays import Points
from .errors import InvalidInput

log = logging.getLogger(__name__)

__all__ = ["CLOUD_SUFFIXES", "read_cloud", "write_ply"]

CLOUD_SUFFIXES = (".ply", ".xyz", ".txt", ".csv", ".npy")

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def read_cloud(path: str | Path) -> Points:
    """Read the points of a cloud file.

    Parameters
    ----------
    path : str or Path
        ``.ply`` (ASCII or binary; the ``x y z`` properties of the vertex
        element), ``.xyz`` / ``.txt`` / ``.csv`` (one point per line, the
        first three numbers; ``#`` comments), or ``.npy`` (an (N, 3) or
        (N, >3) array; the first three columns).

    Returns
    -------
    (N, 3) float64

    Raises
    ------
    InvalidInput
        Missing file, unknown suffix, unreadable content, no points, wrong
        shape, non-finite coordinates.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise InvalidInput(
            f"{p}: unknown cloud format {suffix or '(no suffix)'!r}; "
            f"expected one of {', '.join(CLOUD_SUFFIXES)}"
        )
    if p.is_dir():
        raise InvalidInput(f"{p}: a directory, not a cloud file")
    if not p.is_file():
        raise InvalidInput(f"{p}: no such file")
    try:
        if suffix == ".npy":
            arr = _read_npy(p)
        elif suffix == ".ply":
            arr = _read_ply(p)
        else:
            arr = _read_text(p)
    except InvalidInput:
        raise
    except (OSError, ValueError, EOFError) as exc:
        raise InvalidInput(f"{p}: cannot read as {suffix[1:].upper()}: {exc}") from exc
    return _validated(arr, p)


def _read_npy(p: Path) -> np.ndarray:
    """The array of an ``.npy`` file, its header checked before any data is read.

    Never unpickled: an object array would run code from the file, so it is
    refused from its header, with a message of ours rather than numpy's
    advice to load it unsafely.
    """
    fmt = np.lib.format
    with p.open("rb") as fh:
        if fh.read(len(fmt.MAGIC_PREFIX)) != fmt.MAGIC_PREFIX:
            raise InvalidInput(f"{p}: not a NumPy .npy file (no NPY magic)")
        fh.seek(0)
        version = fmt.read_magic(fh)
        if version not in ((1, 0), (2, 0), (3, 0)):
            raise InvalidInput(f"{p}: unknown .npy format version {version}")
        # Version 3 differs from 2 only in allowing UTF-8 field names.
        read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, _, dtype = read_header(fh)
        if dtype.hasobject:
            raise InvalidInput(
                f"{p}: holds Python objects, not numbers; a cloud is an (N, 3) array of "
                "numbers (object arrays are never loaded: unpickling runs code from the file)"
            )
        if len(shape) != 2 or shape[1] < 3:
            raise InvalidInput(f"{p}: expected an (N, 3) array of points, got shape {shape}")
        fh.seek(0)
        return np.asarray(np.load(fh, allow_pickle=False))


def _validated(arr: np.ndarray, p: Path) -> Points:
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InvalidInput(f"{p}: expected an (N, 3) array of points, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise InvalidInput(f"{p}: points must be numbers, got dtype {arr.dtype}")
    pts = np.ascontiguousarray(arr[:, :3], dtype=np.float64)
    if len(pts) == 0:
        raise InvalidInput(f"{p}: the cloud has no points")
    if not np.isfinite(pts).all():
        bad = int((~np.isfinite(pts)).any(axis=1).sum())
        raise InvalidInput(f"{p}: {bad} points have non-finite coordinates (NaN or inf)")
    return pts


def _read_text(p: Path) -> np.ndarray:
    rows = []
    with p.open() as fh:
        for lineno, line in enumerate(fh, 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.replace(",", " ").split()
            if len(parts) < 3:
                raise InvalidInput(f"{p}:{lineno}: expected at least three numbers, got {line!r}")
            try:
                rows.append([float(v) for v in parts[:3]])
            except ValueError as exc:
                raise InvalidInput(f"{p}:{lineno}: not a number in {line!r}") from exc
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


def _read_ply(p: Path) -> np.ndarray:
    data = p.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InvalidInput(f"{p}: not a PLY file (no 'ply' magic or no end_header)")
    nl = data.find(b"\n", end)
    body = data[nl + 1 :] if nl >= 0 else b""
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in header[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise InvalidInput(f"{p}: property before any element")
            if tok[1] == "list":
                elements[-1][2].append((tok[-1], "list"))
            else:
                if tok[1] not in _PLY_TYPES:
                    raise InvalidInput(f"{p}: unknown PLY property type {tok[1]!r}")
                elements[-1][2].append((tok[2], tok[1]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InvalidInput(f"{p}: unknown PLY format {fmt!r}")
    if not elements or elements[0][0] != "vertex":
        raise InvalidInput(f"{p}: the first PLY element must be 'vertex'")
    _, count, props = elements[0]
    names = [n for n, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise InvalidInput(f"{p}: the vertex element has no x, y, z properties")
    if any(t == "list" for _, t in props):
        raise InvalidInput(f"{p}: list properties on vertices are not supported")
    if fmt == "ascii":
        text = body.decode("ascii", errors="replace").split("\n")
        rows = [ln.split() for ln in text[:count]]
        if len(rows) < count or any(len(r) < len(props) for r in rows):
            raise InvalidInput(f"{p}: expected {count} vertex lines with {len(props)} values")
        arr = np.asarray(
            [[float(r[names.index(a)]) for a in "xyz"] for r in rows], dtype=np.float64
        )
        return arr.reshape(-1, 3)
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(n, order + _PLY_TYPES[t]) for n, t in props])
    if len(body) < count * dtype.itemsize:
        raise InvalidInput(f"{p}: truncated: {count} vertices need {count * dtype.itemsize} bytes")
    rec = np.frombuffer(body, dtype=dtype, count=count)
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)


def write_ply(
    path: str | Path,
    points: Points,
    *,
    scalars: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write points (and per-point scalars) as binary little-endian PLY.

    Parameters
    ----------
    path : str or Path
    points : (N, 3) float64, mm
        Written as double.
    scalars : dict of name -> (N,) float, optional
        Extra vertex properties written as float (e.g. ``{"deviation": d}``).

    Returns
    -------
    Path

    Raises
    ------
    InvalidInput
        Wrong shapes or non-finite coordinates, bad scalar names.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInput(f"points must have shape (N, 3), got {pts.shape}")
    if not np.isfinite(pts).all():
        raise InvalidInput("points have non-finite coordinates")
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    extra = {}
    for name, vals in (scalars or {}).items():
        if not name.isidentifier() or name in ("x", "y", "z"):
            raise InvalidInput(f"bad scalar name {name!r}")
        v = np.asarray(vals, dtype=np.float32)
        if v.shape != (len(pts),):
            raise InvalidInput(f"scalar {name!r} must have shape ({len(pts)},), got {v.shape}")
        fields.append((name, "<f4"))
        extra[name] = v
    rec = np.empty(len(pts), dtype=np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    for name, v in extra.items():
        rec[name] = v
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}"]
    header += ["property double x", "property double y", "property double z"]
    header += [f"property float {name}" for name in extra]
    header.append("end_header")
    p = Path(path)
    with p.open("wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    return p
