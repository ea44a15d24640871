"""Reading uploaded point clouds: NPY or PLY, recognised by their first bytes.

The file name and the declared content type of a part are hints a client
easily gets wrong; the magic bytes are not (``\\x93NUMPY``, ``ply``).
"""

from __future__ import annotations

import io

import numpy as np

from inspection.errors import InvalidInput

NPY_MAGIC = b"\x93NUMPY"
PLY_MAGIC = b"ply"


class UnsupportedCloudFormat(ValueError):
    """The upload is neither NPY nor PLY."""


def cloud_format(data: bytes) -> str:
    """``"npy"`` or ``"ply"`` from the first bytes; raises :class:`UnsupportedCloudFormat`."""
    if data.startswith(NPY_MAGIC):
        return "npy"
    if data[:3] == PLY_MAGIC and data[3:4] in (b"\n", b"\r"):
        return "ply"
    raise UnsupportedCloudFormat(
        "the cloud must be a NumPy .npy array (N, 3) or a PLY file; these bytes are neither"
    )


def parse_cloud(data: bytes) -> np.ndarray:
    """The points of an uploaded cloud, (N, 3) float64 in the file's units (mm).

    Raises
    ------
    UnsupportedCloudFormat
        Neither NPY nor PLY.
    InvalidInput
        Truncated or malformed files, object arrays, wrong shapes. (Finite
        values and point counts are checked by the pipeline.)
    """
    fmt = cloud_format(data)
    if fmt == "npy":
        try:
            arr = np.load(io.BytesIO(data), allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise InvalidInput(f"unreadable .npy cloud (truncated?): {exc}") from exc
        if arr.dtype.names:  # a structured array with x, y, z fields
            try:
                arr = np.stack([arr["x"], arr["y"], arr["z"]], axis=-1)
            except (KeyError, ValueError) as exc:
                raise InvalidInput("a structured .npy cloud needs fields x, y and z") from exc
    else:
        arr = _read_ply(data)
    if arr.dtype.kind not in "fiu":
        raise InvalidInput(f"point coordinates must be numbers, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidInput(f"a point cloud is an (N, 3) array, got shape {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def _read_ply(data: bytes) -> np.ndarray:
    import trimesh

    header_end = data.find(b"end_header")
    if header_end < 0:
        raise InvalidInput("unreadable PLY cloud: no end_header (truncated header?)")
    try:
        loaded = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    except Exception as exc:  # trimesh raises many kinds on bad bytes
        raise InvalidInput(f"unreadable PLY cloud (truncated?): {exc}") from exc
    vertices = np.asarray(getattr(loaded, "vertices", np.empty((0, 3))))
    expected = _ply_vertex_count(data[:header_end])
    if expected is not None and len(vertices) != expected:
        raise InvalidInput(
            f"unreadable PLY cloud: the header announces {expected} vertices, "
            f"{len(vertices)} were read"
        )
    return vertices


def _ply_vertex_count(header: bytes) -> int | None:
    for line in header.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == b"element" and parts[1] == b"vertex":
            try:
                return int(parts[2])
            except ValueError:
                return None
    return None
