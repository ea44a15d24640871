"""The tree file: one uncompressed ``.npz`` of the tree's arrays and a JSON header.

A file whose arrays or header fields are not exactly those of this
:data:`FORMAT_VERSION` is refused rather than half read.
:meth:`GridTree.save <inspection.grid.GridTree.save>` and
:meth:`GridTree.load <inspection.grid.GridTree.load>` read and write through
:func:`write_tree` and :func:`read_tree`.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidInput, TreeMismatch

FORMAT_VERSION = 6
"""Version of the saved file layout; bump when arrays or their meaning change.

1: the first layout. 2: adds the face hierarchy of the exact slow path
(``bvh_order``, ``bvh_lo``, ``bvh_hi``, ``bvh_child``, ``bvh_span``).
3: faces in the tree's own spatial order, ``face_id`` maps them to the CAD's.
4: mixed cells are split in eight ``subcells``; the candidate lists
(``mixed_ptr``, ``mixed_faces``) belong to the mixed subcells.
5: a one-face subcell is marked safe only where every foot lies inside its
face (trees of 4 could give a point by a plate's edge the face farther off).
"""

# Exactly these arrays and metadata keys make up a saved tree of this
# version: a file with any missing or extra one was written by other code
# and is refused rather than half read.
_ARRAY_KEYS = frozenset(
    {
        "vertices",
        "faces",
        "face_normals",
        "face_adj",
        "smooth_adj",
        "plane",
        "vf_ptr",
        "vf_idx",
        "edge_pn",
        "vert_pn",
        "origin",
        "dims",
        "coarse",
        "cells",
        "subcells",
        "mixed_ptr",
        "mixed_faces",
        "bvh_order",
        "bvh_lo",
        "bvh_hi",
        "bvh_child",
        "bvh_span",
        "face_id",
    }
)
_META_KEYS = frozenset({"format_version", "name", "cad_hash", "tree_hash", "params"})
_PARAM_KEYS = frozenset({"spacing_mm", "band_mm", "block"})


def write_tree(path: Path, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> Path:
    """Write ``arrays`` and the JSON header ``meta`` to ``path``, atomically.

    The file is written to a temporary file first and renamed, so readers
    never see half a tree. Returns the path written.
    """
    arrays = dict(arrays)
    arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)  # type: ignore[arg-type]
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_tree(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header and the (read-only) arrays of a file written by :func:`write_tree`.

    Raises
    ------
    TreeMismatch
        The file is of another format version, or lacks or adds an array or
        a metadata field of this version.
    InvalidInput
        The file is missing or not a saved tree.
    """
    if path.is_dir():
        raise InvalidInput(f"{path}: a directory, not a tree file")
    if not path.is_file():
        raise InvalidInput(f"{path}: no such tree file")
    # numpy would read a lone .npy too, or pickles; a tree is an .npz archive.
    if not zipfile.is_zipfile(path):
        raise InvalidInput(f"{path}: not a saved GridTree (not an .npz archive)")
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(z["meta"].tobytes().decode())
            if not isinstance(meta, dict):
                raise ValueError("meta is not a JSON object")
            _check_layout(path, meta, set(z.files) - {"meta"})
            a = {k: z[k] for k in z.files if k != "meta"}
    except (
        OSError,
        ValueError,
        KeyError,
        EOFError,
        zipfile.BadZipFile,
        json.JSONDecodeError,
    ) as exc:
        if "allow_pickle" in str(exc):
            # numpy's advice is to unpickle, which runs code from the file: never.
            raise InvalidInput(
                f"{path}: not a saved GridTree (it holds Python objects, which are never loaded)"
            ) from exc
        raise InvalidInput(f"{path}: not a saved GridTree ({exc})") from exc
    for arr in a.values():
        arr.setflags(write=False)
    return meta, a


def _check_layout(path: Path, meta: dict[str, Any], arrays: set[str]) -> None:
    """Raise TreeMismatch unless a saved tree has this version's exact layout."""
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise TreeMismatch(
            f"{path}: tree format version {version}, this software reads "
            f"{FORMAT_VERSION}; rebuild it with `inspection build-tree`"
        )
    params = meta.get("params")
    problems = []
    for what, have, want in (
        ("array", arrays, _ARRAY_KEYS),
        ("metadata field", set(meta), _META_KEYS),
        ("parameter", set(params) if isinstance(params, dict) else set(), _PARAM_KEYS),
    ):
        if missing := sorted(want - have):
            problems.append(f"missing {what}(s) {', '.join(missing)}")
        if extra := sorted(have - want):
            problems.append(f"unknown {what}(s) {', '.join(extra)}")
    if problems:
        raise TreeMismatch(
            f"{path}: not a version {FORMAT_VERSION} tree ({'; '.join(problems)}); "
            "rebuild it with `inspection build-tree`"
        )
