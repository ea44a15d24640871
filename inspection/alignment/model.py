"""What global alignment precomputes per part type: resting poses, their visible sides, a sampling.

The :class:`AlignmentModel` is built by :func:`alignment_model` and saved
and read by :meth:`AlignmentModel.save` and :meth:`AlignmentModel.load`.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from ..arrays import Faces, Points, Transform, Vectors
from ..errors import InvalidInput
from ..protocols import Triangles
from .sampling import DEFAULT_MIN_COS, sample_facing
from .surface import SampledSurface

log = logging.getLogger(__name__)

MODEL_FORMAT_VERSION = 1
"""Version of the :meth:`AlignmentModel.save` file and of what :func:`alignment_model`
computes by default: raise it when either changes, so that saved models are rebuilt."""


@dataclass(frozen=True, eq=False)
class RestingPose:
    """One stable pose of the part on a flat conveyor.

    Attributes
    ----------
    transform : (4, 4) float64
        ``T_rest_cad``: puts the CAD on the plane z = 0, z up.
    probability : float
        Share of random drops that end in this pose (quasi-static estimate).
    template : (M, 3) float64, mm, resting frame
        Points sampled from the faces that face up in this pose.
    axis_rad : float
        Direction of the major principal axis of the template's footprint
        (its x, y coordinates) in the resting frame, radians in [0, pi).
    elongation : float
        Minor over major principal variance of that footprint, in [0, 1]:
        near 1 for a round or square footprint, whose axis means nothing.
    """

    transform: Transform
    probability: float
    template: Points
    axis_rad: float = 0.0
    elongation: float = 1.0

    @property
    def centroid(self) -> np.ndarray:
        """(3,) float64, mm: centroid of the visible template."""
        return self.template.mean(axis=0)


@dataclass(frozen=True, eq=False)
class AlignmentModel:
    """What global alignment needs of a CAD model, computed once per part type.

    Attributes
    ----------
    poses : tuple of RestingPose
        Stable poses with a visible side, most probable first.
    surface : SampledSurface
        Dense samples of the whole surface for coarse refinement.
    size_mm : float
        Diagonal of the CAD's bounding box.
    """

    poses: tuple[RestingPose, ...]
    surface: SampledSurface
    size_mm: float

    def save(self, path: str | Path, *, key: str = "") -> None:
        """Write the model to an ``.npz`` file (atomically: a temporary file renamed).

        Parameters
        ----------
        path : path
        key : str
            Stored with the model and checked by :meth:`load` (e.g. the CAD's hash).
        """
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                format_version=np.int64(MODEL_FORMAT_VERSION),
                key=np.str_(key),
                transforms=np.stack([p.transform for p in self.poses]),
                probabilities=np.array([p.probability for p in self.poses]),
                templates=np.stack([p.template for p in self.poses]),
                axes=np.array([p.axis_rad for p in self.poses]),
                elongations=np.array([p.elongation for p in self.poses]),
                samples=self.surface.samples,
                normals=self.surface.normals,
                face=self.surface.face,
                spacing_mm=np.float64(self.surface.spacing_mm),
                size_mm=np.float64(self.size_mm),
            )
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path, *, key: str | None = None) -> AlignmentModel:
        """Read a model written by :meth:`save`.

        Parameters
        ----------
        path : path
        key : str, optional
            When given, the stored key must be this.

        Raises
        ------
        InvalidInput
            Unreadable file, another format version, another key.
        """
        try:
            with np.load(Path(path), allow_pickle=False) as z:
                version = int(z["format_version"])
                if version != MODEL_FORMAT_VERSION:
                    raise InvalidInput(
                        f"{path}: alignment model format {version}, expected {MODEL_FORMAT_VERSION}"
                    )
                if key is not None and str(z["key"]) != key:
                    raise InvalidInput(f"{path}: alignment model of {str(z['key'])!r}, not {key!r}")
                arrays = {name: np.array(z[name]) for name in z.files}
        except (OSError, KeyError, ValueError) as exc:
            raise InvalidInput(f"{path}: not a readable alignment model: {exc}") from exc
        poses = tuple(
            RestingPose(T, float(p), tpl, float(a), float(e))
            for T, p, tpl, a, e in zip(
                arrays["transforms"],
                arrays["probabilities"],
                arrays["templates"],
                arrays["axes"],
                arrays["elongations"],
                strict=True,
            )
        )
        samples = np.ascontiguousarray(arrays["samples"], dtype=np.float64)
        surface = SampledSurface(
            samples,
            np.ascontiguousarray(arrays["normals"], dtype=np.float64),
            np.asarray(arrays["face"], dtype=np.int64),
            float(arrays["spacing_mm"]),
            cKDTree(samples),
        )
        return cls(poses, surface, float(arrays["size_mm"]))


def as_triangles(source: object) -> Triangles:
    """``source`` (a CadModel, a GridTree) as a triangle mesh, else InvalidInput."""
    if not isinstance(source, Triangles):
        raise InvalidInput("need a CAD model or a tree with vertices, faces and face_normals")
    return source


def _geometry(source: Triangles) -> tuple[Points, Faces, Vectors]:
    v = np.asarray(source.vertices, dtype=np.float64)
    f = np.asarray(source.faces, dtype=np.int64)
    n = np.asarray(source.face_normals, dtype=np.float64)
    return v, f, n


def alignment_model(
    cad: Triangles,
    *,
    max_poses: int = 12,
    min_probability: float = 0.002,
    template_points: int = 800,
    surface_points: int = 40000,
    min_cos: float = DEFAULT_MIN_COS,
    seed: int = 0,
) -> AlignmentModel:
    """Precompute the stable poses, their visible templates and a surface sampling.

    Parameters
    ----------
    cad : CadModel or GridTree
        Any :class:`~inspection.protocols.Triangles`: ``vertices`` (V, 3),
        ``faces`` (F, 3) and ``face_normals`` (F, 3) in mm.
    max_poses : int
        At most this many poses, most probable first.
    min_probability : float
        Poses less likely than this are left out.
    template_points : int
        Points per visible template.
    surface_points : int
        Samples of the whole surface for coarse refinement.
    min_cos : float
        See :func:`sample_facing`.
    seed : int

    Returns
    -------
    AlignmentModel
    """
    v, f, n = _geometry(as_triangles(cad))
    hull = trimesh.Trimesh(v, f, process=False).convex_hull
    transforms, probs = trimesh.poses.compute_stable_poses(hull, n_samples=1, threshold=0.0)
    poses: list[RestingPose] = []
    for k, (T, p) in enumerate(zip(transforms, probs, strict=True)):
        if p < min_probability or len(poses) >= max_poses:
            break
        T = np.asarray(T, dtype=np.float64)
        if (n @ T[2, :3] > min_cos).sum() == 0:
            log.debug("stable pose %d shows no face to the sensor; skipped", k)
            continue
        tpl, _ = sample_facing(v, f, n, T, template_points, seed=seed + k, min_cos=min_cos)
        axis, elongation = footprint(tpl[:, :2])
        poses.append(RestingPose(T, float(p), tpl, axis, elongation))
    if not poses:
        raise InvalidInput("the part has no stable pose in which any face is seen from above")
    surface = SampledSurface.build(v, f, n, n=surface_points, seed=seed)
    size = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    return AlignmentModel(tuple(poses), surface, size)


def footprint(xy: np.ndarray) -> tuple[float, float]:
    """Major principal axis (radians in [0, pi)) and minor / major variance of 2-D points."""
    d = xy - xy.mean(axis=0)
    w, v = np.linalg.eigh(d.T @ d / max(len(d), 1))  # ascending eigenvalues
    axis = float(np.arctan2(v[1, 1], v[0, 1])) % np.pi
    return axis, float(w[0] / w[1]) if w[1] > 0.0 else 1.0
