"""What a part is measured against: its CAD, tree, faces, surface, alignment and points."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..alignment import AlignmentModel, alignment_model
from ..alignment.rps import RpsScheme
from ..cad import CadModel
from ..deviations import ComparisonPoint, check_comparison_points, load_comparison_points
from ..errors import InvalidInput
from ..grid import GridTree
from ..nurbs import ExactTree, NurbsModel
from ..perspective import RayCaster
from ..registration import CadFaces
from ..surface import NODE_MM, SurfaceModel

# What deviations are measured against: the grid tree or, for NURBS faces, the
# tree's closest points refined on the exact surfaces.
DeviationTree = GridTree | ExactTree


@dataclass(frozen=True, eq=False)
class PartModel:
    """Everything measured against, built once per part type.

    Attributes
    ----------
    cad : CadModel
    tree : GridTree
        The closest-point grid of ``cad``.
    alignment : AlignmentModel or None
        Resting poses and templates of the global search; None: clouds can
        only be measured near the CAD frame (``frame="cad"``).
    comparison_points : tuple of ComparisonPoint
    faces : CadFaces
        The CAD's face planes and bounding box, as every fit against ``tree``
        uses them (computed from ``tree`` when not given).
    surface : SurfaceModel
        The CAD's surface as the defect search samples it (built from ``cad``
        when not given).
    caster : RayCaster
        The CAD's exact ray casting, which draws it into the views of the
        comparison-point path (built from ``cad`` when not given).
    surface_node_mm : float
        Cell of the defect search's node grid, which every length of the
        search scales with (see :class:`SurfaceModel`).
    rps : RpsScheme or None
        The part's datum scheme; None: the best fit alone aligns it.
    nurbs : NurbsModel or None
        The NURBS faces ``cad`` tessellates (``cad`` is ``nurbs.cad``); None:
        a mesh-only CAD.
    exact : GridTree or ExactTree
        What deviations are measured against: ``tree`` refined on the exact
        faces (:class:`inspection.nurbs.ExactTree`) when the part has
        ``nurbs``, else ``tree`` itself. The fit keeps ``tree``: on a fine
        enough sampling the chords move the pose little, and a fit to the
        exact faces costs many times more (``bench/bench_nurbs_part.py``).
    """

    cad: CadModel
    tree: GridTree
    alignment: AlignmentModel | None
    comparison_points: tuple[ComparisonPoint, ...] = ()
    faces: CadFaces | None = None
    surface: SurfaceModel | None = None
    caster: RayCaster | None = None
    surface_node_mm: float = NODE_MM
    rps: RpsScheme | None = None
    nurbs: NurbsModel | None = None
    exact: DeviationTree = field(init=False, repr=False)

    @classmethod
    def build(
        cls,
        cad: CadModel | NurbsModel,
        comparison_points: Sequence[ComparisonPoint] = (),
        *,
        spacing_mm: float | None = None,
        band_mm: float | None = None,
        alignment: bool = True,
        surface_node_mm: float = NODE_MM,
        rps: RpsScheme | None = None,
    ) -> PartModel:
        """Build the tree (``GridTree.build``) and the alignment model of ``cad``.

        Parameters
        ----------
        cad : CadModel, or NurbsModel
            A NurbsModel (:func:`inspection.nurbs.tessellate_faces`): the
            tree is built on its tessellation and deviations are measured to
            its exact faces.
        comparison_points : sequence of ComparisonPoint
        spacing_mm, band_mm : float, optional
            The grid's build parameters; None: its defaults.
        alignment : bool
            Compute the global search's model (seconds; needed for clouds
            anywhere in the rig).
        surface_node_mm : float
            The defect search's node grid (finer for a sensor of a small field).
        rps : RpsScheme, optional
            Align by the datums (see :class:`~inspection.alignment.rps.RpsScheme`).
        """
        nurbs = cad if isinstance(cad, NurbsModel) else None
        if nurbs is not None:
            cad = nurbs.cad
        if not isinstance(cad, CadModel):
            raise InvalidInput(f"cad must be a CadModel or NurbsModel, got {type(cad).__name__}")
        tree = GridTree.build(
            cad,
            **({} if spacing_mm is None else {"spacing_mm": spacing_mm}),  # type: ignore[arg-type]
            **({} if band_mm is None else {"band_mm": band_mm}),  # type: ignore[arg-type]
        )
        model = alignment_model(cad) if alignment else None
        return cls(cad, tree, model, check_comparison_points(comparison_points),
                   surface_node_mm=surface_node_mm, rps=rps, nurbs=nurbs)  # fmt: skip

    def __post_init__(self) -> None:
        exact: DeviationTree = self.tree
        if self.nurbs is not None:
            if self.nurbs.cad.hash != self.cad.hash:
                raise InvalidInput("the NURBS model's tessellation is not this part's CAD")
            exact = ExactTree(self.tree, self.nurbs)  # refuses a tree of another CAD
        object.__setattr__(self, "exact", exact)
        object.__setattr__(
            self, "comparison_points", check_comparison_points(self.comparison_points)
        )
        if self.rps is not None:
            if not isinstance(self.rps, RpsScheme):
                raise InvalidInput(f"rps must be an RpsScheme, got {type(self.rps).__name__}")
            named = {cp.name: cp for cp in self.comparison_points}
            for d in self.rps.datums:
                cp = named.get(d.name)
                if cp is None or cp.kind not in ("surface", "hole"):
                    raise InvalidInput(
                        f"RPS datum {d.name!r} must name a surface or hole comparison point"
                    )
        if self.faces is None:
            object.__setattr__(self, "faces", CadFaces.of(self.tree))
        if self.surface is None:
            cad = self.cad
            object.__setattr__(
                self,
                "surface",
                SurfaceModel.build(
                    cad.vertices, cad.faces, cad.face_normals, node_mm=self.surface_node_mm
                ),
            )
        if self.caster is None:
            object.__setattr__(self, "caster", RayCaster(self.cad))

    def save(self, directory: str | Path) -> Path:
        """Write the tree, the alignment model and the comparison points into ``directory``."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        self.tree.save(d / "tree.npz")
        if self.alignment is not None:
            self.alignment.save(d / "alignment.npz", key=self.cad.hash)
        doc = {
            "points": [cp.to_dict() for cp in self.comparison_points],
            "surface_node_mm": self.surface_node_mm,
        }
        (d / "points.json").write_text(json.dumps(doc, indent=2))
        return d

    @classmethod
    def load(
        cls, directory: str | Path, *, cad: CadModel, nurbs: NurbsModel | None = None
    ) -> PartModel:
        """Read what :meth:`save` wrote; refuses a tree or model built from another CAD.

        ``nurbs``: the NURBS faces ``cad`` tessellates (``cad`` is ``nurbs.cad``).

        Raises
        ------
        TreeMismatch
            The tree's CAD hash, parameters or format do not match ``cad``.
        InvalidInput
            A missing or unreadable file, or an alignment model of another CAD.
        """
        d = Path(directory)
        tree = GridTree.load(d / "tree.npz", cad=cad)
        path = d / "alignment.npz"
        model = AlignmentModel.load(path, key=cad.hash) if path.is_file() else None
        node_mm = json.loads((d / "points.json").read_text()).get("surface_node_mm", NODE_MM)
        return cls(cad, tree, model, load_comparison_points(d / "points.json"),
                   surface_node_mm=node_mm, nurbs=nurbs)  # fmt: skip
