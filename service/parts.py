"""The part registry: specs, CAD models and their closest-point trees, ready to inspect with.

A part comes from a spec file in ``configs/parts/`` (the station's parts) or
from an upload through the API. An upload is kept in the result store (its
spec and CAD bytes, :class:`~service.store.StoredPart`), where every API and
station's worker finds it whatever host it runs on, and written under
``<data_dir>/parts/<name>/``, each process's own copy that the loaders read.
Its tree is built once and cached under the trees directory, keyed by the
CAD geometry hash, the build parameters and the tree's format version; a
cached tree that no longer matches is rebuilt.

A STEP CAD whose every face is a B-spline face, in millimetres (or of no
declared unit), is read as NURBS (:func:`inspection.nurbs.read_step_nurbs`):
its tree is built on the faces sampled on regular parameter grids
(``tree.nurbs_cell_mm``), its key then also holds the faces' hash and that
sampling, and deviations are measured to the exact faces (``cad_kind``
"nurbs"). Any other CAD is a mesh.

Trees are built in one background thread, each build reported as a
:class:`~service.models.Job` with its progress. :meth:`PartRegistry.preload`
builds or loads every configured part before the line reports itself ready.

Errors::

    PartError
     ├── UnknownPart          no part of that name
     ├── PartNotReady         its tree is still building, or the build failed
     │    └── PartBroken      the build failed on the part itself: it fails again
     ├── PartConflict         creating a part that exists / deleting a configured one
     └── PathConflict         a part the station's measuring path cannot judge as its spec asks
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, MutableMapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from inspection.alignment import (
    MODEL_FORMAT_VERSION,
    AlignmentModel,
    alignment_model,
    sample_facing,
)
from inspection.alignment.rps import RpsScheme
from inspection.cad import CadModel, load_cad
from inspection.deviations import ComparisonPoint
from inspection.errors import CadLoadError, InspectionError, InvalidInput, TreeMismatch
from inspection.measure import Frame, MeasureParams, PartModel, RegisterParams, measure_cloud
from inspection.nurbs import NurbsModel, read_step_nurbs, step_length_units, tessellate_faces

from .config import (
    GENERATED_STEPPED_PLATE,
    PartSpec,
    PartSpecBase,
    canonical_hash,
    load_part_spec,
    path_refusal,
)
from .models import Job, JobState, PartPublic, PartState
from .names import NAME_RULE, is_valid_name
from .store import PartExists, ResultStore, StoredPart, StoreError, part_key

log = logging.getLogger(__name__)

UPLOAD_SUFFIXES = (".stl", ".obj", ".ply", ".step", ".stp")

SPEC_FILE = "spec.json"
"""An uploaded part's spec, in its folder; it names the CAD file beside it."""

STAGING_PREFIX = ".creating-"
"""Folders an upload is written into before they are renamed to the part's name."""


class PartError(Exception):
    """Base of the registry's errors."""


class UnknownPart(PartError, KeyError):
    """No part of that name."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else "unknown part"


class PartNotReady(PartError):
    """The part exists but its tree is not usable (building, or the build failed)."""


class PartBroken(PartNotReady):
    """The part's build failed on the part itself (its CAD or spec: a bad file, invalid
    input), not on something that passes (a full disk, an unwritable cache): building the
    same files again fails again."""


class PointOffSurface(PartError):
    """A comparison point of a new part lies too far from its CAD surface."""


class PartConflict(PartError):
    """The operation contradicts the registry's state."""


class PathConflict(PartError):
    """The part's spec asks for a check the station's measuring path does not make (a
    ``[surface]`` that fails parts, on the comparison-point path)."""


@dataclass(frozen=True, eq=False)
class LoadedPart:
    """A part ready to inspect: its spec, the model it is measured against, and how.

    Attributes
    ----------
    spec : PartSpec
    model : inspection.PartModel
        The CAD, its tree, its alignment model and comparison points.
    tree_hash : str
        The tree's content hash (``GridTree.hash``): identifies exactly the tree used.
    params : inspection.MeasureParams
        The spec's settings as the measuring sequence takes them.
    revision : int or None
        The store's revision of a part created over the API
        (:attr:`~service.store.StoredPart.revision`); None for a part of the
        station's configuration, or one not kept in a store.
    """

    spec: PartSpec
    model: PartModel
    tree_hash: str
    params: MeasureParams
    revision: int | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def cad(self) -> CadModel:
        return self.model.cad

    @property
    def cad_kind(self) -> str:
        """ "nurbs": deviations are measured to the exact B-spline faces; "mesh": to triangles."""
        return "mesh" if self.model.nurbs is None else "nurbs"


@dataclass(frozen=True, eq=False)
class PartBundle:
    """A part as it travels to another process (a Dask worker, an upload's measuring
    process): its spec and its CAD model, no files.

    Attributes
    ----------
    spec : PartSpec
    cad : inspection.CadModel
    key : str
        Hash of the spec and the CAD geometry: a part changed under the same
        name is another bundle.
    nurbs : inspection.nurbs.NurbsModel or None
        The NURBS faces ``cad`` tessellates, so that the receiver measures to
        them as the sender does; None for a mesh.
    revision : int or None
        :attr:`LoadedPart.revision`: which of two bundles of one name is the newer.
    """

    spec: PartSpec
    cad: CadModel
    key: str
    nurbs: NurbsModel | None = None
    revision: int | None = None

    @classmethod
    def of(cls, part: LoadedPart) -> PartBundle:
        key = canonical_hash({"spec": part.spec.model_dump(mode="json"), "cad": part.cad.hash})
        return cls(part.spec, part.cad, key[:24], part.model.nurbs, part.revision)

    def load(self, trees_dir: Path) -> LoadedPart:
        """The part ready to measure: its tree from ``trees_dir`` (built there if missing)."""
        loaded = part_from_cad(self.spec, self.cad, trees_dir, nurbs=self.nurbs)
        return dataclasses.replace(loaded, revision=self.revision)


def comparison_points(spec: PartSpec) -> tuple[ComparisonPoint, ...]:
    """The spec's comparison points as the measuring sequence takes them."""
    return tuple(
        ComparisonPoint(
            name=p.name,
            position=tuple(p.position_mm),  # type: ignore[arg-type]
            normal=tuple(p.normal),  # type: ignore[arg-type]
            lower_mm=p.lower_mm,
            upper_mm=p.upper_mm,
            radius_mm=p.radius_mm,
            kind=p.kind.value,
            min_support=p.min_support,
            diameter_mm=p.diameter_mm,
            length_mm=p.length_mm,
            axis=None if p.axis is None else tuple(p.axis),  # type: ignore[arg-type]
            mate=None if p.mate_mm is None else tuple(p.mate_mm),  # type: ignore[arg-type]
            tolerances=tuple((k, lo, hi) for k, (lo, hi) in p.tolerances.items()),
        )
        for p in spec.points
    )


def rps_scheme(spec: PartSpecBase) -> RpsScheme | None:
    """The spec's datum scheme (None for a best fit)."""
    scheme: RpsScheme | None = spec.alignment.scheme({p.name: p.position_mm for p in spec.points})
    return scheme


def check_point_offsets(cad: CadModel, spec: PartSpecBase, max_mm: float) -> None:
    """Refuse comparison points that lie farther than ``max_mm`` from the CAD surface.

    A point off the surface measures the distance to where it was put, not a
    deviation: a typo in a coordinate would pass as a process offset.
    """
    # A hole's centre lies in the hole, off the material: it is checked by its rim's
    # measurement (no rim seen: not measurable), not here.
    points = [p for p in spec.points if p.kind.value != "hole"]
    if not points:
        return
    mesh = trimesh.Trimesh(cad.vertices, cad.faces, process=False)
    where = np.array([p.position_mm for p in points], dtype=np.float64)
    _, dist, _ = trimesh.proximity.closest_point(mesh, where)
    far = [(p.name, float(d)) for p, d in zip(points, dist, strict=True) if d > max_mm]
    if far:
        listed = ", ".join(f"{n!r} at {d:.3f} mm" for n, d in far[:10])
        raise PointOffSurface(
            f"comparison points farther than {max_mm:g} mm from the CAD surface: {listed}"
        )


def measure_params(spec: PartSpec, *, guided: bool = True) -> MeasureParams:
    """The measuring sequence's parameters from a part spec (and the station's ``guided``)."""
    r = spec.registration
    return MeasureParams(
        guided=guided,
        max_points=r.max_points,
        min_inlier_fraction=r.min_inlier_fraction,
        max_rms_mm=r.max_rms_mm,
        ambiguous_is_error=r.ambiguous_is_error,
        surface=spec.surface.params(),
        register=RegisterParams(
            loss=r.loss.value,
            max_iterations=r.max_iterations,
            max_distance_mm=r.max_correspondence_mm,
            view_direction=r.view_direction(),
        ),
    )


@dataclass(eq=False)
class _Entry:
    spec: PartSpec
    base_dir: Path
    configured: bool
    state: PartState = PartState.building
    job: str | None = None
    loaded: LoadedPart | None = None
    error: str | None = None
    broken: bool = False
    """The build failed on the part itself (:class:`PartBroken`)."""
    key: str | None = None
    """An upload's revision in the store (:attr:`StoredPart.key`); None: not stored."""
    revision: int | None = None
    """That revision's number (:attr:`StoredPart.revision`)."""
    conflict: str | None = None
    """Why this upload stands in for the store's part of its name (one the store has no
    copy of: :meth:`PartRegistry.sync_store`); None: no conflict."""


# --------------------------------------------------------------------------- building blocks


def panel_spec(params: dict[str, Any]) -> Any:
    """``inspection.panel.PanelSpec`` from TOML/JSON parameters (lists become tuples)."""
    from inspection.panel import Hole, PanelSpec

    kwargs: dict[str, Any] = {}
    for key, value in params.items():
        if key == "holes":
            value = tuple(Hole(**h) if isinstance(h, dict) else Hole(*h) for h in value)
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[key] = value
    try:
        return PanelSpec(**kwargs)
    except TypeError as exc:
        raise ValueError(f"invalid panel parameters: {exc}") from exc


def load_part_cad(spec: PartSpec, base_dir: Path) -> CadModel:
    """The CAD model of a spec: its mesh file, the tessellation of its NURBS
    faces (:func:`load_part_nurbs`), or a generated part."""
    nurbs = load_part_nurbs(spec, base_dir)
    if nurbs is not None:
        return nurbs.cad
    if spec.cad == GENERATED_STEPPED_PLATE:
        from inspection.holography import stepped_plate

        return CadModel.from_mesh(stepped_plate(), name=spec.name)
    if spec.is_generated:
        from inspection.panel import sheet_metal_panel

        return sheet_metal_panel(panel_spec(spec.panel), name=spec.name)
    return load_cad(spec.cad_path(base_dir), scale=spec.scale, name=spec.name)


def load_part_nurbs(spec: PartSpec, base_dir: Path) -> NurbsModel | None:
    """The NURBS faces of a spec's STEP CAD, sampled for its tree, or None
    (a mesh, a generated panel, or a STEP with faces of other kinds)."""
    if spec.is_generated:
        return None
    return read_nurbs(spec.cad_path(base_dir), spec)


def read_nurbs(path: Path, spec: PartSpecBase) -> NurbsModel | None:
    """The NURBS faces of the CAD file ``path`` (STEP, B-spline faces only, in
    millimetres or of no declared unit) tessellated on cells of
    ``spec.tree.nurbs_cell_mm``, or None."""
    if path.suffix.lower() not in (".step", ".stp"):
        return None
    units = step_length_units(path)
    if any(u != "mm" for u in units):
        # Our reader does not convert units; the mesh reader does.
        log.info("%s: length units %s, not mm only: read as a mesh", path.name, ", ".join(units))
        return None
    faces = read_step_nurbs(path, scale=spec.scale)
    if not faces:
        return None
    return tessellate_faces(faces, cell_mm=spec.tree.nurbs_cell_mm, name=spec.name)


def tree_format_version() -> int:
    """The tree file format version of the installed :mod:`inspection.grid`."""
    from inspection.grid import FORMAT_VERSION

    return int(FORMAT_VERSION)


def tree_cache_path(
    trees_dir: Path, cad: CadModel, spec: PartSpec, nurbs: NurbsModel | None = None
) -> Path:
    """Where the tree of ``cad`` with ``spec``'s build parameters is cached.

    The name holds the CAD hash, a hash of the build parameters and the
    format version: any change of the three gives another file. For NURBS
    faces (``cad`` is ``nurbs.cad``) the parameters also hold the faces' hash
    and their sampling.
    """
    made_of: dict[str, Any] = dict(spec.tree.build_kwargs())
    if nurbs is not None:
        made_of |= {"nurbs": nurbs.faces_hash(), "nurbs_cell_mm": spec.tree.nurbs_cell_mm}
    params = canonical_hash(made_of)[:12]
    return trees_dir / f"{cad.hash[:24]}-{params}-v{tree_format_version()}.npz"


def build_or_load_tree(
    cad: CadModel,
    spec: PartSpec,
    trees_dir: Path,
    progress: Callable[[float, str], None] | None = None,
    nurbs: NurbsModel | None = None,
) -> Any:
    """The tree of ``cad``: loaded from the cache when it matches, built (and cached) otherwise.

    ``nurbs``: the NURBS faces ``cad`` tessellates (a key of the cache).

    Returns
    -------
    GridTree
        Its ``hash`` identifies it (recorded in every result as ``tree_hash``).
    """
    from inspection.grid import GridTree

    report = progress or (lambda f, m: None)
    path = tree_cache_path(trees_dir, cad, spec, nurbs)
    if path.is_file():
        try:
            tree = GridTree.load(path, cad=cad)
            expected = _expected_params(spec)
            if {k: tree.params.to_dict()[k] for k in expected} == expected:
                log.info("part %s: tree %s loaded from %s", spec.name, tree.hash[:12], path)
                report(0.9, "tree loaded from the cache")
                return tree
            log.warning("part %s: cached tree %s has other parameters; rebuilding", spec.name, path)
        except (TreeMismatch, InvalidInput, OSError, ValueError, KeyError) as exc:
            log.warning("part %s: cached tree %s unusable (%s); rebuilding", spec.name, path, exc)
    # The message is what start-up tells: building a tree is the slow part of a first start.
    report(0.1, "building tree")
    t0 = time.perf_counter()
    tree = GridTree.build(
        cad,
        **spec.tree.build_kwargs(),
        progress=lambda f: report(0.1 + 0.8 * float(f), "building tree"),
    )
    log.info("part %s: tree built in %.1f s", spec.name, time.perf_counter() - t0)
    report(0.9, "saving tree")
    tree.save(path)  # atomic: written to a temporary file and renamed
    return tree


def _expected_params(spec: PartSpec) -> dict[str, float]:
    """The build parameters a tree for ``spec`` has (the grid's defaults for unset ones).

    Checked on load, so a change of the defaults rebuilds cached trees.
    """
    from inspection.grid import DEFAULT_BAND_MM, DEFAULT_SPACING_MM

    return {"spacing_mm": DEFAULT_SPACING_MM, "band_mm": DEFAULT_BAND_MM} | spec.tree.build_kwargs()


def load_part(
    spec: PartSpec,
    base_dir: Path,
    trees_dir: Path,
    progress: Callable[[float, str], None] | None = None,
    *,
    alignment: bool = True,
    models: MutableMapping[str, AlignmentModel] | None = None,
) -> LoadedPart:
    """Load the CAD of a spec, build or load its tree and (``alignment``) its alignment model.

    ``models``: alignment models the caller keeps in memory, by CAD hash (a
    registry's own); consulted first and given the model loaded or computed.
    """
    report = progress or (lambda f, m: None)
    report(0.05, "loading CAD")
    nurbs = load_part_nurbs(spec, base_dir)
    cad = nurbs.cad if nurbs is not None else load_part_cad(spec, base_dir)
    return part_from_cad(
        spec, cad, trees_dir, report, alignment=alignment, models=models, nurbs=nurbs
    )


def part_from_cad(
    spec: PartSpec,
    cad: CadModel,
    trees_dir: Path,
    progress: Callable[[float, str], None] | None = None,
    *,
    alignment: bool = True,
    models: MutableMapping[str, AlignmentModel] | None = None,
    nurbs: NurbsModel | None = None,
) -> LoadedPart:
    """:func:`load_part` from a CAD model already loaded (or received from another host).

    ``nurbs``: the NURBS faces ``cad`` tessellates; deviations are then
    measured to them. None: ``cad`` is a mesh.
    """
    report = progress or (lambda f, m: None)
    tree = build_or_load_tree(cad, spec, trees_dir, report, nurbs)
    model = None
    if alignment:
        cached = alignment_model_path(trees_dir, cad).is_file()
        report(0.95, "loading resting poses" if cached else "computing resting poses")
        model = models.get(cad.hash) if models is not None else None
        if model is None:
            model = load_alignment_model(cad, trees_dir)
        if models is not None:
            models[cad.hash] = model
    report(1.0, "ready")
    return LoadedPart(
        spec=spec,
        model=PartModel(
            cad,
            tree,
            model,
            comparison_points(spec),
            surface_node_mm=spec.surface.node_mm,
            rps=rps_scheme(spec),
            nurbs=nurbs,
        ),  # fmt: skip
        tree_hash=tree.hash,
        params=measure_params(spec),
    )


def alignment_model_path(trees_dir: Path, cad: CadModel) -> Path:
    """Where the alignment model of ``cad`` is cached, beside its trees.

    The name holds the CAD hash and the model's format version.
    """
    return trees_dir / f"{cad.hash[:24]}-align-v{int(MODEL_FORMAT_VERSION)}.npz"


def load_alignment_model(cad: CadModel, trees_dir: Path) -> AlignmentModel:
    """The global alignment's per-part model (resting poses, templates) of ``cad``.

    Computed once per CAD geometry (seconds of work) and cached on disk beside
    the trees, so a worker, a replay or the API started later reads it
    instead; a cached file that does not load is recomputed.
    """
    path = alignment_model_path(trees_dir, cad)
    if path.is_file():
        try:
            model = AlignmentModel.load(path, key=cad.hash)
            log.info("%s: %d resting poses loaded from %s", cad.name, len(model.poses), path)
            return model
        except InvalidInput as exc:
            log.warning("%s: cached alignment model unusable (%s); recomputing", cad.name, exc)
    t0 = time.perf_counter()
    model = alignment_model(cad)
    log.info("%s: %d resting poses in %.1f s", cad.name, len(model.poses), time.perf_counter() - t0)
    try:
        model.save(path, key=cad.hash)
    except OSError as exc:  # a read-only cache still lets the part load
        log.warning("%s: alignment model not cached: %s", cad.name, exc)
    return model


def warm_up(part: LoadedPart, *, points: int = 3000) -> float:
    """Measure the part once on points of its own surface; returns seconds.

    The numerical kernels compile on their first call (seconds); doing it
    while the part loads keeps that off the first inspected part.
    """
    t0 = time.perf_counter()
    cad = part.cad
    # Points spread evenly over the faces looking up: a cloud like the rig's.
    try:
        cloud, _ = sample_facing(
            cad.vertices, cad.faces, cad.face_normals, np.eye(4), points, seed=0, min_cos=0.3
        )
    except InspectionError as exc:
        log.info("warm-up of %s skipped: %s", part.name, exc)
        return time.perf_counter() - t0
    frames: tuple[Frame, ...] = ("rig", "cad") if part.model.alignment is not None else ("cad",)
    for frame in frames:
        try:
            m = measure_cloud(part.model, cloud, part.params, frame=frame)
        except InspectionError as exc:
            log.info("warm-up of %s incomplete: %s", part.name, exc)
            break
        if m.verdict is None:
            log.info("warm-up of %s (%s frame): %s", part.name, frame, m.reason)
    return time.perf_counter() - t0


# --------------------------------------------------------------------------- registry


def hide_paths(message: str, names: dict[Path, str]) -> str:
    """``message`` with each path of ``names`` (as given and resolved) replaced by its name.

    Longer paths first, so that a file inside a folder becomes the file's name.
    """
    pairs = {str(p): n for p, n in names.items()} | {str(p.resolve()): n for p, n in names.items()}
    for path in sorted(pairs, key=len, reverse=True):
        message = message.replace(path, pairs[path])
    return message


def stored_spec(stored: StoredPart) -> PartSpec:
    """The spec of a part revision the store holds, checked to name a plain CAD file.

    Raises
    ------
    ValueError
        Not a part spec, another name than the revision's, or a CAD that is
        not a file name with a CAD suffix.
    """
    spec = PartSpec.model_validate_json(stored.spec)
    if spec.name != stored.name:
        raise ValueError(f"the store's part {stored.name!r} has a spec named {spec.name!r}")
    if Path(spec.cad).name != spec.cad or Path(spec.cad).suffix.lower() not in UPLOAD_SUFFIXES:
        raise ValueError(f"the store's part {stored.name!r} names a CAD file {spec.cad!r}")
    return spec


def stored_cad(stored: StoredPart) -> tuple[PartSpec, CadModel]:
    """The spec and CAD model of a part revision the store holds (what a simulator renders),
    read from a temporary copy of its CAD file.

    Raises
    ------
    ValueError, inspection.CadLoadError
    """
    spec = stored_spec(stored)
    with tempfile.TemporaryDirectory(prefix="inspection-part-") as folder:
        (Path(folder) / spec.cad).write_bytes(stored.cad)
        return spec, load_part_cad(spec, Path(folder))


def _spec_in(folder: Path) -> PartSpec | None:
    """The spec an uploads folder holds, or None."""
    try:
        return PartSpec.model_validate_json((folder / SPEC_FILE).read_text())
    except (OSError, ValueError):
        return None


class PartRegistry:
    """The parts a service knows, their trees and the jobs that build them.

    Parameters
    ----------
    trees_dir : Path
        The tree cache.
    uploads_dir : Path
        Where parts created through the API keep their spec and CAD file.
    alignment : bool
        Compute each part's global-alignment model (needed to inspect clouds
        in the rig frame; a registry that only lists parts can skip it).
    path : {"cloud", "comparison_points"}
        The station's measuring path: a part it cannot judge as its spec asks
        is refused (:class:`PathConflict`).
    store : ResultStore, optional
        Where uploads are kept for every process: :meth:`create` writes a part
        there, :meth:`delete` retires it, :meth:`sync_store` takes the parts
        other processes created. None: the uploads folder alone.
    """

    def __init__(
        self,
        trees_dir: str | Path,
        uploads_dir: str | Path,
        *,
        alignment: bool = True,
        path: str = "cloud",
        store: ResultStore | None = None,
    ) -> None:
        self.alignment = alignment
        self.path = path
        self.store = store
        self.trees_dir = Path(trees_dir)
        self.uploads_dir = Path(uploads_dir)
        self._lock = threading.RLock()
        self._entries: dict[str, _Entry] = {}
        self._jobs: dict[str, Job] = {}
        self._futures: dict[str, Future[None]] = {}
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tree-build")
        # Alignment models by CAD hash: a part deleted and created again, or two parts of one
        # geometry, reuse the model. Only the build thread (the pool's one worker) touches it.
        self._alignment_models: dict[str, AlignmentModel] = {}
        self._job_counter = 0
        self._watchers: list[Callable[[Job], None]] = []

    @classmethod
    def from_config(
        cls,
        cfg: Any,
        *,
        store: ResultStore | None = None,
        uploads: bool = True,
        uploads_dir: Path | None = None,
    ) -> PartRegistry:
        """A registry with the station's parts of a :class:`~service.config.LineConfig` and,
        with ``uploads``, the parts created over the API: those of ``store`` (see
        :meth:`sync_store`), else those of the uploads folder (``uploads_dir``, default
        ``<data_dir>/parts``).

        Nothing is built yet: call :meth:`preload` (blocking) or :meth:`start`.

        Raises
        ------
        StoreError
            ``store`` cannot be read.
        """
        reg = cls(
            cfg.storage.trees_path(),
            Path(cfg.storage.data_dir) / "parts" if uploads_dir is None else uploads_dir,
            path=cfg.station.path,
            store=store,
        )
        for path in cfg.part_spec_paths():
            reg.add(load_part_spec(path), path.parent, configured=True)
        if uploads:
            reg.add_uploaded()
            if store is not None:
                reg.sync_store()
        return reg

    def close(self) -> None:
        """Stop accepting builds and wait for the running one."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> PartRegistry:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ adding

    def add(self, spec: PartSpec, base_dir: Path, *, configured: bool) -> None:
        """Register a spec (not yet loaded).

        Raises
        ------
        PartConflict
            A part of that name is registered.
        PathConflict
            The station's path cannot judge the part as its spec asks.
        """
        self._check_path(spec)
        with self._lock:
            if spec.name in self._entries:
                raise PartConflict(f"part {spec.name!r} is defined twice")
            self._entries[spec.name] = _Entry(
                spec=spec, base_dir=Path(base_dir), configured=configured
            )

    def _check_path(self, spec: PartSpecBase) -> None:
        refusal = path_refusal(spec, self.path)
        if refusal is not None:
            raise PathConflict(refusal)

    def add_uploaded(self) -> None:
        """Register the parts created through the API in an earlier run.

        Only folders that :meth:`create` made count: a direct child of the
        uploads folder (no link), named as its ``spec.json`` names the part.
        Anything else there (a creation cut short, a folder someone put
        there) is left alone.
        """
        if not self.uploads_dir.is_dir():
            return
        for spec_file in sorted(self.uploads_dir.glob(f"*/{SPEC_FILE}")):
            folder = spec_file.parent
            try:
                spec = PartSpec.model_validate_json(spec_file.read_text())
            except ValueError as exc:
                log.error("ignoring uploaded part %s: %s", folder, exc)
                continue
            if folder.name != spec.name or folder.is_symlink():
                log.warning("ignoring %s: not a part folder the service made", folder)
                continue
            with self._lock:
                if spec.name in self._entries:
                    log.warning("uploaded part %s shadowed by a configured one", spec.name)
                    continue
            try:
                self.add(spec, folder, configured=False)
            except PathConflict as exc:  # kept on disk for a station measuring the cloud
                log.error("ignoring uploaded part %s: %s", folder, exc)

    def _upload_dir(self, name: str) -> Path:
        """The folder of uploaded part ``name``, checked to be a direct child of the uploads root.

        Raises
        ------
        PartConflict
            ``name`` is not a valid name, or the folder resolves (through a
            link, say) to somewhere other than the uploads root's own child.
        """
        if not is_valid_name(name):
            raise PartConflict(f"part name {name!r} is not a name: {NAME_RULE}")
        root = self.uploads_dir.resolve()
        folder = (root / name).resolve()
        if folder.parent != root or folder.name != name:
            raise PartConflict(f"part {name!r}: its folder would lie outside the uploads folder")
        return folder

    def create(
        self,
        spec: PartSpecBase,
        cad_bytes: bytes,
        filename: str,
        *,
        max_point_offset_mm: float | None = None,
    ) -> Job:
        """Create a part from an uploaded CAD file and start building its tree.

        The files are written into a new staging folder of the service's own,
        the CAD is checked (loaded), and only then is the folder renamed to
        the part's name: a bad upload leaves no trace, and a failure removes
        the staging folder alone. Returns the build job.

        Raises
        ------
        PartConflict
            A part of that name exists, or a folder of that name that the
            service did not make is in the way.
        inspection.CadLoadError
            The upload is not a usable mesh, or its file name has no CAD suffix.
        PointOffSurface
            A comparison point farther than ``max_point_offset_mm`` from the surface.
        PathConflict
            The station's path cannot judge the part as its spec asks.
        """
        self._check_path(spec)
        suffix = Path(filename).suffix.lower()
        if suffix not in UPLOAD_SUFFIXES:
            raise CadLoadError(
                f"the CAD file must end in one of {', '.join(UPLOAD_SUFFIXES)}, got {filename!r}"
            )
        target = self._upload_dir(spec.name)
        full = PartSpec(**spec.model_dump(), cad=f"cad{suffix}")
        with self._lock:
            if spec.name in self._entries:
                raise PartConflict(f"part {spec.name!r} exists; delete it first")
            if target.exists() or target.is_symlink():
                raise PartConflict(
                    f"part {spec.name!r}: a folder of that name, not made by the service, "
                    "is in the uploads folder"
                )
            # Reserve the name while the upload is checked.
            self._entries[spec.name] = _Entry(spec=full, base_dir=target, configured=False)
        staging: Path | None = None
        try:
            self.uploads_dir.mkdir(parents=True, exist_ok=True)
            # mkdtemp makes a new folder or fails: whatever it names is ours to remove.
            staging = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=self.uploads_dir.resolve()))
            (staging / full.cad).write_bytes(cad_bytes)
            try:
                # Fail fast: the NURBS faces are read (and sampled) as the build will.
                nurbs = read_nurbs(staging / full.cad, full)
                cad = (
                    nurbs.cad
                    if nurbs is not None
                    else load_cad(staging / full.cad, scale=full.scale, name=full.name)
                )
            except (CadLoadError, InvalidInput) as exc:
                # Its message starts with the staging file's path: name the client's file.
                raise CadLoadError(
                    hide_paths(str(exc), {staging / full.cad: filename, staging: "upload"})
                ) from exc
            if max_point_offset_mm is not None:
                check_point_offsets(cad, full, max_point_offset_mm)
            (staging / SPEC_FILE).write_text(full.model_dump_json(indent=2))
            if target.exists() or target.is_symlink():
                raise PartConflict(f"part {spec.name!r}: a folder of that name appeared meanwhile")
            if self.store is not None:
                # Last before the rename: a part the store refuses leaves no folder here.
                try:
                    stored = self.store.add_part(full.name, full.model_dump_json(), cad_bytes)
                except PartExists as exc:  # created meanwhile through another API
                    raise PartConflict(str(exc)) from exc
                self._entries[spec.name].key = stored.key
                self._entries[spec.name].revision = stored.revision
            staging.rename(target)
        except BaseException:
            with self._lock:
                entry = self._entries.pop(spec.name, None)
            if entry is not None and entry.key is not None and self.store is not None:
                with contextlib.suppress(StoreError):
                    self.store.retire_part(spec.name, entry.key)
            if staging is not None and staging.exists():
                shutil.rmtree(staging, ignore_errors=True)
            raise
        return self.start(spec.name)

    def delete(self, name: str) -> None:
        """Forget an uploaded part, retire it in the store and remove the files the
        service wrote for it.

        Removes the part's ``spec.json`` and the CAD file it names, then the
        folder if nothing else is left in it; never a folder's whole tree.
        Its cached tree stays, keyed by hash; its revision stays in the store,
        retired (the results measured with it name it).

        Raises
        ------
        PartConflict
            A configured part, one still being built, or one not in its folder.
        StoreError
            The store cannot be written: nothing was deleted.
        """
        with self._lock:
            entry = self._get_entry(name)
            if entry.configured:
                raise PartConflict(
                    f"part {name!r} is defined in the line configuration; remove it there"
                )
            if entry.state == PartState.building:
                raise PartConflict(f"part {name!r} is still being built; delete it when done")
            folder = self._upload_dir(name)
            if folder != entry.base_dir.resolve():
                raise PartConflict(f"part {name!r} is not kept in its uploads folder")
        if self.store is not None and entry.key is not None:
            # Its own revision only: another API may have created the part again meanwhile.
            self.store.retire_part(name, entry.key)
        self.forget(name, entry)

    def forget(self, name: str, entry: _Entry | None = None) -> None:
        """Drop uploaded part ``name`` (``entry``: only if it is still that one) and the
        files the service wrote for it, leaving the store alone (it was retired there)."""
        with self._lock:
            current = self._entries.get(name)
            if (
                current is None
                or current.configured
                or (entry is not None and current is not entry)
            ):
                return
            del self._entries[name]
        self._remove_files(name, current.spec)

    def _remove_files(self, name: str, spec: PartSpec) -> None:
        folder = self._upload_dir(name)
        for written in (spec.cad, SPEC_FILE):
            path = folder / written
            # A spec edited by hand could name another file: remove only a plain file in place.
            if Path(written).name == written and path.parent == folder and not path.is_symlink():
                path.unlink(missing_ok=True)
        try:
            folder.rmdir()
        except FileNotFoundError:
            pass
        except OSError:
            log.warning(
                "part %s deleted; %s kept, it holds files the service did not write", name, folder
            )

    # ------------------------------------------------------------------ the store's parts

    def sync_store(self) -> None:
        """Make the registry's uploads those of the store (at a start).

        An upload of the uploads folder that the store never had (made before
        parts were kept there) is written to it; one the store holds a copy of
        (the same spec and CAD, in any revision) but no longer as its current
        revision (deleted, or created again, through another API) gives way to
        the store's. An upload the store has no copy of, under a name the store
        knows otherwise (two stations' uploads of one name and other CADs, on
        one plant database), is kept, files and all, and measured here, and the
        store's part of that name is not taken: an error names the conflict at
        every start until one of the two is created again under another name.
        Every other current part of the store is then registered, written into
        the uploads folder where it is missing.

        Raises
        ------
        StoreError
        """
        store = self.store
        if store is None:
            return
        index = store.part_index()
        current = {r.name: r for r in index if r.retired_ns is None}
        keys = {name: r.key for name, r in current.items()}
        copies = {(r.name, r.key) for r in index}
        with self._lock:
            uploads = [(n, e) for n, e in self._entries.items() if not e.configured]
        for name, entry in uploads:
            spec_json = entry.spec.model_dump_json()
            try:
                cad = entry.spec.cad_path(entry.base_dir).read_bytes()
            except OSError as exc:
                log.error("ignoring uploaded part %s: %s", name, exc)
                self.forget(name, entry)
                continue
            key = part_key(spec_json, cad)
            if keys.get(name) == key:
                entry.key, entry.revision = key, current[name].revision
                continue
            if (name, key) in copies:
                log.info("uploaded part %s: the store holds another revision; taking that", name)
                self.forget(name, entry)
                continue
            if not any(n == name for n, _ in copies):
                try:
                    added = store.add_part(name, spec_json, cad)
                    entry.key, entry.revision = added.key, added.revision
                    keys[name] = added.key
                    log.info("uploaded part %s: written to the store %s", name, store.where)
                    continue
                except PartExists:  # another API wrote its own part of that name meanwhile
                    pass
            entry.conflict = (
                f"part {name!r}: the upload in {entry.base_dir} (key {key}) is not the part "
                f"of that name in the store {store.where}, which has no copy of it; kept and "
                "measured here, the store's part is not taken here. Create one of the two "
                "again under another name"
            )
            log.error("%s", entry.conflict)
        for name in sorted(keys):
            with self._lock:
                entry_now = self._entries.get(name)
            if entry_now is not None:
                if entry_now.configured:
                    log.warning("the store's part %s is shadowed by a configured one", name)
                continue
            stored = store.part(name)
            if stored is not None:
                try:
                    self._register(stored)
                except (PartError, ValueError, OSError) as exc:
                    log.error("ignoring the store's part %s: %s", name, exc)

    def adopt(self, stored: StoredPart) -> Job | None:
        """Make revision ``stored`` this registry's part of its name and build it.

        Returns the job that builds it (the one under way when the registry holds that
        revision; a build of it that failed is run again), or None when it is loaded. A revision
        replacing another is written over the old one's files; the old part's
        loaded objects stay valid for whoever holds them.

        Raises
        ------
        PartConflict
            A configured part has that name (the station's own wins), or an upload the
            store has no copy of (:meth:`sync_store`).
        PathConflict
            The station's path cannot judge the part as its spec asks.
        ValueError
            The stored spec is not a valid part spec.
        """
        with self._lock:
            entry = self._entries.get(stored.name)
            if entry is not None and entry.configured:
                raise PartConflict(
                    f"part {stored.name!r} is defined in the line configuration; "
                    "the store's part of that name is not used here"
                )
            if entry is not None and entry.conflict is not None:
                raise PartConflict(entry.conflict)
            if entry is not None and entry.key == stored.key:
                if entry.loaded is not None:
                    return None
                if entry.job is not None and entry.state is not PartState.failed:
                    return self._jobs[entry.job]
        self._register(stored)
        return self._submit(stored.name)

    def _register(self, stored: StoredPart) -> None:
        """Write ``stored`` into the uploads folder (over an older revision) and register it."""
        spec = stored_spec(stored)
        self._check_path(spec)
        target = self._upload_dir(spec.name)
        self.uploads_dir.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=self.uploads_dir.resolve()))
        try:
            (staging / spec.cad).write_bytes(stored.cad)
            (staging / SPEC_FILE).write_text(spec.model_dump_json(indent=2))
            with self._lock:
                old = self._entries.pop(spec.name, None)
            if old is not None:
                self._remove_files(spec.name, old.spec)
            elif target.exists():  # a copy from an earlier run
                self._remove_files(spec.name, _spec_in(target) or spec)
            staging.rename(target)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        with self._lock:
            self._entries[spec.name] = _Entry(
                spec=spec,
                base_dir=target,
                configured=False,
                key=stored.key,
                revision=stored.revision,
            )

    # ------------------------------------------------------------------ building

    def start(self, name: str | None = None) -> Job:
        """Queue the tree build of ``name`` (default: every part not loaded); return the job."""
        names = (
            [name]
            if name is not None
            else [n for n, e in self._entries.items() if e.loaded is None]
        )
        job: Job | None = None
        for n in names:
            job = self._submit(n)
        if job is None:
            raise PartConflict("nothing to build")
        return job

    def _submit(self, name: str) -> Job:
        with self._lock:
            entry = self._get_entry(name)
            self._job_counter += 1
            job = Job(
                id=f"job-{self._job_counter}-{time.time_ns()}",
                part=name,
                state=JobState.queued,
                progress=0.0,
                message="queued",
                created_ns=time.time_ns(),
            )
            self._jobs[job.id] = job
            entry.state = PartState.building
            entry.job = job.id
            entry.error = None
            entry.broken = False
            self._futures[job.id] = self._pool.submit(self._build, name, job.id)
            return job

    def _update_job(self, job_id: str, **changes: Any) -> None:
        with self._lock:
            job = self._jobs[job_id] = self._jobs[job_id].model_copy(update=changes)
            watchers = list(self._watchers)
        for watch in watchers:  # outside the lock: a watcher may query the registry
            watch(job)

    def watch(self, watcher: Callable[[Job], None]) -> Callable[[], None]:
        """Call ``watcher`` with every change of a job (from the build thread); returns
        the function that stops it."""
        with self._lock:
            self._watchers.append(watcher)

        def unwatch() -> None:
            with self._lock:
                self._watchers.remove(watcher)

        return unwatch

    def _build(self, name: str, job_id: str) -> None:
        with self._lock:
            entry = self._entries.get(name)
        if entry is None:
            self._update_job(job_id, state=JobState.failed, message="the part was deleted")
            return
        self._update_job(job_id, state=JobState.running, message="starting")

        def progress(fraction: float, message: str) -> None:
            self._update_job(job_id, progress=min(max(fraction, 0.0), 1.0), message=message)

        try:
            loaded = load_part(
                entry.spec,
                entry.base_dir,
                self.trees_dir,
                progress,
                alignment=self.alignment,
                models=self._alignment_models,
            )
        except Exception as exc:
            if isinstance(exc, (InspectionError, OSError)):
                # A bad CAD file or an unusable cache folder: the message says it all.
                log.error("part %s: tree build failed: %s", name, exc)
            else:
                log.exception("part %s: tree build failed", name)
            # The message reaches clients (the job, 409s): the server's folders stay in the log.
            folders = {entry.base_dir: "<part folder>", self.trees_dir: "<tree cache>"}
            with self._lock:
                entry.state = PartState.failed
                entry.error = f"{type(exc).__name__}: {hide_paths(str(exc), folders)}"
                # An OSError (a full disk, a cache folder not writable) may pass; a bad CAD
                # file or spec does not.
                entry.broken = isinstance(exc, (InspectionError, ValueError))
            self._update_job(
                job_id, state=JobState.failed, message=entry.error, finished_ns=time.time_ns()
            )
            return
        if self.alignment:
            from inspection.deviations import warmup as deviations_warmup
            from inspection.grid import warmup

            # Readiness means the first real part is not the one paying for compilation.
            # Each step is a job message: on a first start they compile for minutes.
            steps: list[tuple[str, Callable[[], object]]] = [
                ("warm-up 1/3: the grid's kernels load or compile", warmup),
                ("warm-up 2/3: the deviations' kernels load or compile", deviations_warmup),
                ("warm-up 3/3: measuring the part once (fit and search kernels)",
                 lambda: warm_up(loaded)),
            ]  # fmt: skip
            for k, (message, step) in enumerate(steps):
                self._update_job(job_id, progress=0.97 + 0.01 * k, message=message)
                t0 = time.perf_counter()
                step()
                log.info("part %s: %s in %.1f s", name, message, time.perf_counter() - t0)
        with self._lock:
            entry.loaded = dataclasses.replace(loaded, revision=entry.revision)
            entry.state = PartState.ready
        self._update_job(
            job_id, state=JobState.done, progress=1.0, message="ready", finished_ns=time.time_ns()
        )

    def preload(self) -> None:
        """Build or load every registered part's tree now, in this thread's time (blocking).

        Failures are recorded per part (state ``failed``) and do not stop the
        others; :meth:`ready` then stays False.
        """
        jobs = [self._submit(n) for n in self.names()]
        for job in jobs:
            self.wait(job.id)

    def wait(self, job_id: str, timeout_s: float | None = None) -> Job:
        """Block until job ``job_id`` has finished; returns its final state.

        Raises
        ------
        UnknownPart
            No such job.
        TimeoutError
            Not finished within ``timeout_s`` (the build goes on).
        """
        with self._lock:
            fut = self._futures.get(job_id)
        if fut is None:
            raise UnknownPart(f"no job {job_id!r}")
        fut.result(timeout=timeout_s)
        return self.job(job_id)

    # ------------------------------------------------------------------ queries

    def _get_entry(self, name: str) -> _Entry:
        entry = self._entries.get(name)
        if entry is None:
            raise UnknownPart(f"no part named {name!r}")
        return entry

    def names(self) -> list[str]:
        with self._lock:
            return sorted(self._entries)

    def get(self, name: str) -> LoadedPart:
        """The loaded part ``name``.

        Raises
        ------
        UnknownPart, PartNotReady
            :class:`PartBroken` when its build failed on the part itself.
        """
        with self._lock:
            entry = self._get_entry(name)
            if entry.loaded is None:
                failed = entry.state == PartState.failed
                why = entry.error if failed else "its tree is being built"
                raise (PartBroken if failed and entry.broken else PartNotReady)(
                    f"part {name!r} is not ready: {why}"
                )
            return entry.loaded

    def job(self, job_id: str) -> Job:
        with self._lock:
            job = self._jobs.get(job_id)
        if job is None:
            raise UnknownPart(f"no job {job_id!r}")
        return job

    def public(self, name: str) -> PartPublic:
        with self._lock:
            e = self._get_entry(name)
            loaded = e.loaded
            return PartPublic(
                name=e.spec.name,
                version=e.spec.version,
                description=e.spec.description,
                cad=e.spec.cad,
                scale=e.spec.scale,
                cad_hash=loaded.cad.hash if loaded else None,
                tree_hash=loaded.tree_hash if loaded else None,
                state=e.state,
                job=e.job,
                points=list(e.spec.points),
                subgroup_size=e.spec.subgroup_size,
                faces=len(loaded.cad.faces) if loaded else None,
                extents_mm=[float(x) for x in loaded.cad.extents] if loaded else None,
                cad_kind=loaded.cad_kind if loaded else None,  # type: ignore[arg-type]
                nurbs_faces=(
                    len(loaded.model.nurbs.surfaces)
                    if loaded and loaded.model.nurbs is not None
                    else None
                ),
            )

    def loaded(self, names: list[str]) -> dict[str, LoadedPart]:
        """The loaded parts ``names`` (what a worker measures with: the same objects the API uses).

        Raises
        ------
        UnknownPart, PartNotReady
        """
        return {n: self.get(n) for n in names}

    def ready(self) -> bool:
        """True when every configured part is loaded (uploads being built do not block the line)."""
        with self._lock:
            configured = [e for e in self._entries.values() if e.configured]
            return all(e.state == PartState.ready for e in configured)

    def states(self) -> dict[str, str]:
        with self._lock:
            return {n: e.state.value for n, e in sorted(self._entries.items())}
