"""Reading CAD models into a validated triangle mesh in millimetres."""

from __future__ import annotations

import hashlib
import logging
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from .arrays import Faces, Points, Vectors
from .errors import CadLoadError, InvalidInput

log = logging.getLogger(__name__)

MESH_SUFFIXES = {".stl": "stl", ".obj": "obj", ".ply": "ply"}
STEP_SUFFIXES = {".step", ".stp"}

# A face whose area is below this fraction of the squared mean edge length is
# treated as degenerate (a sliver or a collapsed triangle).
_DEGENERATE_REL_AREA = 1e-12


@dataclass(frozen=True)
class CadReport:
    """What happened while loading a CAD file.

    Attributes
    ----------
    source : str
        Path or description of the origin.
    scale : float
        Factor applied to the stored coordinates to get millimetres.
    faces_read : int
        Faces in the file.
    degenerate_faces_dropped : int
        Faces removed because they had (almost) no area or repeated vertices.
    vertices_merged : int
        Duplicate vertices merged (STL stores every triangle separately).
    """

    source: str
    scale: float
    faces_read: int
    degenerate_faces_dropped: int
    vertices_merged: int


@dataclass(frozen=True, eq=False)
class CadModel:
    """A validated triangle mesh of a part, in millimetres.

    Attributes
    ----------
    vertices : (V, 3) float64, mm
    faces : (F, 3) int64
        Indices into ``vertices``, counter-clockwise seen from the outside.
    face_normals : (F, 3) float64
        Unit normals of the faces.
    name : str
    hash : str
        SHA-256 of the vertices and faces (after scaling), hex. Identifies the
        geometry: trees and results record it.
    report : CadReport
    """

    vertices: Points
    faces: Faces
    face_normals: Vectors
    name: str
    hash: str
    report: CadReport = field(repr=False)

    @classmethod
    def from_arrays(
        cls,
        vertices: np.ndarray,
        faces: np.ndarray,
        *,
        name: str = "part",
        source: str = "<arrays>",
        scale: float = 1.0,
    ) -> CadModel:
        """Validate a vertex and face array and build a model.

        Parameters
        ----------
        vertices : (V, 3) float, stored units
        faces : (F, 3) int
        scale : float
            Multiplies the vertices to give millimetres.

        Raises
        ------
        CadLoadError
            No faces, non-finite coordinates, indices out of range.
        """
        if not np.isfinite(scale) or scale <= 0:
            raise InvalidInput(f"scale must be a finite positive number, got {scale!r}")
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise CadLoadError(f"{source}: no vertices (shape {v.shape})")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise CadLoadError(f"{source}: the model has no triangle faces")
        if not np.issubdtype(f.dtype, np.integer):
            raise CadLoadError(f"{source}: face indices are not integers")
        f = f.astype(np.int64)
        if not np.isfinite(v).all():
            bad = int((~np.isfinite(v)).any(axis=1).sum())
            raise CadLoadError(f"{source}: {bad} vertices have non-finite coordinates (NaN or inf)")
        if f.min() < 0 or f.max() >= len(v):
            raise CadLoadError(f"{source}: face indices out of range 0..{len(v) - 1}")
        v = v * float(scale)
        faces_read = len(f)

        mesh = trimesh.Trimesh(v, f, process=False, validate=False)
        before = len(mesh.vertices)
        mesh.merge_vertices()
        merged = before - len(mesh.vertices)
        v, f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)

        tri = v[f]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area2 = np.linalg.norm(cross, axis=1)
        edges = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2)
        ref = float(np.mean(edges)) ** 2 if len(edges) else 0.0
        repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
        good = (~repeated) & (area2 > _DEGENERATE_REL_AREA * max(ref, 1e-300))
        dropped = int((~good).sum())
        if not good.any():
            raise CadLoadError(f"{source}: every face is degenerate (zero area)")
        if dropped:
            log.debug("%s: dropped %d degenerate faces", source, dropped)
        f = f[good]
        normals = cross[good] / area2[good, None]
        # Drop vertices no longer used, keeping their order.
        used = np.zeros(len(v), dtype=bool)
        used[f.ravel()] = True
        if not used.all():
            remap = np.cumsum(used) - 1
            v = v[used]
            f = remap[f]

        v = np.ascontiguousarray(v)
        f = np.ascontiguousarray(f)
        normals = np.ascontiguousarray(normals)
        for a in (v, f, normals):
            a.setflags(write=False)
        return cls(
            vertices=v,
            faces=f,
            face_normals=normals,
            name=name,
            hash=geometry_hash(v, f),
            report=CadReport(
                source=source,
                scale=float(scale),
                faces_read=faces_read,
                degenerate_faces_dropped=dropped,
                vertices_merged=merged,
            ),
        )

    @classmethod
    def from_mesh(
        cls, mesh: trimesh.Trimesh, *, name: str = "part", scale: float = 1.0
    ) -> CadModel:
        """Build a model from a trimesh mesh (already in stored units)."""
        return cls.from_arrays(
            mesh.vertices, mesh.faces, name=name, source=f"<mesh {name}>", scale=scale
        )

    def to_trimesh(self) -> trimesh.Trimesh:
        """A new trimesh mesh of this model (a copy; the model stays immutable)."""
        return trimesh.Trimesh(self.vertices.copy(), self.faces.copy(), process=False)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64, mm: the axis-aligned bounding box, min row then max row."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def extents(self) -> np.ndarray:
        """(3,) float64, mm: size of the bounding box."""
        b = self.bounds
        return b[1] - b[0]

    @property
    def area(self) -> float:
        """Surface area, mm^2."""
        tri = self.vertices[self.faces]
        return float(
            0.5
            * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
        )


def geometry_hash(vertices: np.ndarray, faces: np.ndarray) -> str:
    """SHA-256 (hex) of float64 vertices and int64 faces, little-endian, C order."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(faces, dtype="<i8").tobytes())
    return h.hexdigest()


def load_cad(path: str | Path, *, scale: float = 1.0, name: str | None = None) -> CadModel:
    """Read a CAD model from STL, OBJ, PLY or (with the ``step`` extra) STEP.

    Parameters
    ----------
    path : str or Path
    scale : float
        Multiplies the stored coordinates to give millimetres. STEP files are
        converted from the reader's metres first, so ``scale`` stays 1 for them.
    name : str, optional
        Defaults to the file name without suffix.

    Returns
    -------
    CadModel

    Raises
    ------
    CadLoadError
        Missing, empty or unreadable files, unknown formats, meshes without
        faces or with non-finite coordinates, STEP without the optional reader.
    """
    p = Path(path)
    name = name or p.stem
    suffix = p.suffix.lower()
    if suffix not in MESH_SUFFIXES and suffix not in STEP_SUFFIXES:
        known = ", ".join(sorted([*MESH_SUFFIXES, *STEP_SUFFIXES]))
        raise CadLoadError(
            f"{p}: unknown CAD format {suffix or '(no suffix)'!r}; expected one of {known}"
        )
    if not p.is_file():
        raise CadLoadError(f"{p}: no such file")
    if p.stat().st_size == 0:
        raise CadLoadError(f"{p}: the file is empty")
    if suffix in STEP_SUFFIXES:
        vertices, faces = _read_step(p)
        return CadModel.from_arrays(vertices, faces, name=name, source=str(p), scale=scale)
    try:
        loaded = trimesh.load(str(p), file_type=MESH_SUFFIXES[suffix], force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds on bad bytes
        raise CadLoadError(f"{p}: cannot read as {suffix[1:].upper()}: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(getattr(loaded, "faces", ())) == 0:
        raise CadLoadError(
            f"{p}: no triangle faces could be read; is it really {suffix[1:].upper()}?"
        )
    return CadModel.from_arrays(
        loaded.vertices, loaded.faces, name=name, source=str(p), scale=scale
    )


def _read_step(p: Path) -> tuple[np.ndarray, np.ndarray]:
    """Tessellate a STEP file with cascadio; returns vertices in mm and faces."""
    try:
        import cascadio
    except ImportError as exc:
        raise CadLoadError(
            f"{p}: reading STEP needs the optional reader; "
            "install it with pip install 'inspection[step]'"
        ) from exc
    with tempfile.TemporaryDirectory() as tmp:
        glb = Path(tmp) / "part.glb"
        try:
            cascadio.step_to_glb(str(p), str(glb), tol_linear=0.01, tol_angular=0.5)
            scene = trimesh.load(str(glb), file_type="glb", force="scene")
        except Exception as exc:
            raise CadLoadError(f"{p}: cannot read as STEP: {exc}") from exc
    if not isinstance(scene, trimesh.Scene):
        raise CadLoadError(f"{p}: the STEP reader gave no scene")
    meshes = [g for g in scene.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not meshes:
        raise CadLoadError(f"{p}: the STEP file holds no surface geometry")
    mesh = trimesh.util.concatenate(meshes)
    assert isinstance(mesh, trimesh.Trimesh)
    # cascadio writes glTF, whose unit is the metre.
    return np.asarray(mesh.vertices, dtype=np.float64) * 1000.0, np.asarray(mesh.faces)
