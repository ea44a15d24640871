"""Global alignment: find the pose of a part lying anywhere on the conveyor.

The sensor looks down (+z of the data frame is up) at a part resting in one
of its stable poses, turned by any angle about the vertical and placed
anywhere in the measurement volume. The search runs in three stages:

1. *Hypotheses.* For every stable resting pose of the CAD (from the convex
   hull: trimesh's ``compute_stable_poses``), the side that faces the sensor
   is sampled once (an :class:`AlignmentModel`, built explicitly and reused
   for every part). Each pose is tried at a few rotations about the
   vertical, with the centroid of its visible side put on the centroid of
   the measured cloud: the two that lay the major axis of the template's
   footprint on the cloud's when both footprints are elongated, else
   ``n_angles`` evenly spread. Each hypothesis is scored by truncated
   nearest-neighbour distances both ways, template to a subsample of the
   cloud and that subsample to the template (kd-trees, so scoring never
   touches the CAD); refinement stops once two distinct hypotheses are
   refined and the rest score clearly worse.
2. *Coarse refinement.* The best few distinct hypotheses are refined by
   :func:`inspection.registration.register` on a subsample of the cloud
   and re-scored with one common truncated residual cost: against the CAD
   tree when the rotation came from the footprints' axes (such hypotheses
   start within a few mm), else against a dense sampling of the CAD
   surface, as cheap far from the surface as near it (point-to-plane
   against the samples' face normals). Two distinct poses that fit equally well (a box turned by
   180 degrees, a disc at any angle) make the result *ambiguous*.
3. *Fine registration* of every point from the best pose with
   :func:`~inspection.registration.register` on the CAD tree.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from .arrays import Faces, Points, Scalars, Transform, Vectors
from .errors import InsufficientOverlap, InvalidInput
from .registration import (
    ClosestPointQuery,
    Registration,
    register,
    validate_points,
    validate_view,
)

log = logging.getLogger(__name__)

__all__ = [
    "MODEL_FORMAT_VERSION",
    "Alignment",
    "AlignmentModel",
    "Candidate",
    "RestingPose",
    "SampledSurface",
    "align",
    "alignment_model",
    "sample_facing",
]

MODEL_FORMAT_VERSION = 1
"""Version of the :meth:`AlignmentModel.save` file and of what :func:`alignment_model`
computes by default: raise it when either changes, so that saved models are rebuilt."""

# Faces whose normal makes less than this cosine with "up" are not seen by
# the sensor above (grazing faces give no usable points).
DEFAULT_MIN_COS = 0.1


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
class SampledSurface:
    """A dense sampling of the CAD surface answering closest-point queries.

    Approximate, cheap, and as fast far from the surface as near it: used to
    refine pose hypotheses before the CAD tree takes over. The distance to
    the nearest sample is split into its part along the sample's face normal
    and the part across it; the part across counts only beyond the sampling
    spacing, so a point above the surface gets its height over the face's
    plane, and a point beyond the surface's border the distance to it.

    Attributes
    ----------
    samples : (S, 3) float64, mm, CAD frame
    normals : (S, 3) float64
    face : (S,) int64
    spacing_mm : float
        Typical distance between neighbouring samples.
    """

    samples: Points
    normals: Vectors
    face: np.ndarray
    spacing_mm: float
    kdtree: cKDTree = field(repr=False)

    @classmethod
    def build(
        cls, vertices: Points, faces: Faces, face_normals: Vectors, *, n: int, seed: int = 0
    ) -> SampledSurface:
        pts, f = _sample_faces(
            vertices, faces, np.arange(len(faces)), n, np.random.default_rng(seed)
        )
        tri = vertices[faces]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        kd = cKDTree(pts)
        # Nearest-neighbour spacing of the samples; a point above the surface
        # can be this far sideways from its nearest sample.
        d, _ = kd.query(pts[: min(len(pts), 2000)], k=2)
        spacing = max(float(np.percentile(d[:, 1], 95)), np.sqrt(area.sum() / n))
        return cls(pts, face_normals[f], f, spacing, kd)

    def query(self, points: Points) -> _Closest:
        """Approximate closest points, normals, signed distances and faces."""
        # An approximate nearest sample (at most 1.5 x the nearest one's
        # distance) is enough for refining hypotheses and makes far queries
        # (points still many mm off) several times cheaper.
        _, idx = self.kdtree.query(points, eps=0.5)
        q = self.samples[idx]
        n = self.normals[idx]
        e = points - q
        dn = np.einsum("ij,ij->i", n, e)
        et = e - dn[:, None] * n
        et_len = np.linalg.norm(et, axis=1)
        excess = np.maximum(et_len - self.spacing_mm, 0.0)
        # A foot such that x - foot = dn n + excess t_hat: its length is the
        # distance, its direction the distance's gradient.
        t_hat = et / np.maximum(et_len, 1e-300)[:, None]
        foot = points - dn[:, None] * n - excess[:, None] * t_hat
        sign = np.where(dn < 0.0, -1.0, 1.0)
        d = sign * np.sqrt(dn * dn + excess * excess)
        return _Closest(foot, n, d, self.face[idx])


@dataclass(frozen=True)
class _Closest:
    points: Points
    normals: Vectors
    distances: Scalars
    face: np.ndarray


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


@dataclass(frozen=True)
class Candidate:
    """A refined pose hypothesis and its score (lower is better).

    Attributes
    ----------
    transform : (4, 4) float64
        ``T_cad_data`` after coarse refinement.
    score : float
        Mean truncated squared residual of the cloud's subsample, mm^2
        (the same truncation for every candidate).
    pose_index : int
        Index into ``AlignmentModel.poses``.
    angle_deg : float
        The starting rotation about the vertical.
    refined : bool
        A finalist: refined on the CAD tree and scored against the other
        finalists (scores of finalists and of the rest are not comparable).
    """

    transform: Transform
    score: float
    pose_index: int
    angle_deg: float
    refined: bool = False


@dataclass(frozen=True, eq=False)
class Alignment(Registration):
    """A :class:`Registration` found from an unknown starting pose.

    Attributes
    ----------
    ambiguous : bool
        Another pose, distinct from the chosen one, fits (almost) as well:
        the part looks symmetric to the sensor and the pose is not unique.
    candidates : tuple of Candidate
        The finalists (``refined``), best first, the first being the one
        refined into ``transform``; then the other distinct hypotheses with
        their coarse scores.
    """

    ambiguous: bool = False
    candidates: tuple[Candidate, ...] = ()


def sample_facing(
    vertices: Points,
    faces: Faces,
    face_normals: Vectors,
    T_view_cad: Transform,
    n: int,
    *,
    seed: int = 0,
    min_cos: float = DEFAULT_MIN_COS,
    views: Vectors | None = None,
) -> tuple[Points, np.ndarray]:
    """Sample the side of a part that faces a sensor looking down.

    Points are spread uniformly over the area of the faces whose normal,
    turned into the view frame, points up (or towards one of ``views``) by
    more than ``min_cos`` (occlusion is ignored).

    Parameters
    ----------
    vertices : (V, 3) float64, mm, CAD frame
    faces : (F, 3) int64
    face_normals : (F, 3) float64
    T_view_cad : (4, 4) float64
        Pose of the part in the view frame (z up).
    n : int
        Number of points.
    seed : int
    min_cos : float
    views : (K, 3) float64, optional
        Directions from the part towards each of K sensors (the cameras of a
        rig), view frame; a face is sampled when it faces any of them. Up
        (+z) when omitted.

    Returns
    -------
    points : (n, 3) float64, mm, view frame
    face : (n,) int64
        The face each point was sampled from.

    Raises
    ------
    InvalidInput
        No face faces the sensor, or bad ``views``.
    """
    R = np.asarray(T_view_cad, dtype=np.float64)[:3, :3]
    if views is None:
        towards = np.array([[0.0, 0.0, 1.0]])
    else:
        towards = np.asarray(views, dtype=np.float64).reshape(-1, 3)
        norm = np.linalg.norm(towards, axis=1, keepdims=True)
        if not len(towards) or not np.isfinite(towards).all() or (norm < 1e-12).any():
            raise InvalidInput("views must be finite, non-zero 3-vectors")
        towards = towards / norm
    # Each face's largest cosine to a sensor, its normal turned into the view frame.
    facing = (face_normals @ R.T @ towards.T).max(axis=1)
    sel = np.flatnonzero(facing > min_cos)
    if len(sel) == 0:
        raise InvalidInput("no face of the part faces the sensor in this pose")
    pts, f = _sample_faces(vertices, faces, sel, n, np.random.default_rng(seed))
    T = np.asarray(T_view_cad, dtype=np.float64)
    return pts @ T[:3, :3].T + T[:3, 3], f


def _sample_faces(
    vertices: Points, faces: Faces, sel: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[Points, np.ndarray]:
    tri = vertices[faces[sel]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    k = rng.choice(len(sel), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[k]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return pts, sel[k]


def _geometry(source: object) -> tuple[Points, Faces, Vectors]:
    try:
        v = np.asarray(source.vertices, dtype=np.float64)  # type: ignore[attr-defined]
        f = np.asarray(source.faces, dtype=np.int64)  # type: ignore[attr-defined]
        n = np.asarray(source.face_normals, dtype=np.float64)  # type: ignore[attr-defined]
    except AttributeError as exc:
        raise InvalidInput(
            "need a CAD model or a tree with vertices, faces and face_normals"
        ) from exc
    return v, f, n


def alignment_model(
    cad: object,
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
        Anything with ``vertices`` (V, 3), ``faces`` (F, 3) and
        ``face_normals`` (F, 3) in mm.
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
    v, f, n = _geometry(cad)
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
        axis, elongation = _footprint(tpl[:, :2])
        poses.append(RestingPose(T, float(p), tpl, axis, elongation))
    if not poses:
        raise InvalidInput("the part has no stable pose in which any face is seen from above")
    surface = SampledSurface.build(v, f, n, n=surface_points, seed=seed)
    size = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    return AlignmentModel(tuple(poses), surface, size)


def _footprint(xy: np.ndarray) -> tuple[float, float]:
    """Major principal axis (radians in [0, pi)) and minor / major variance of 2-D points."""
    d = xy - xy.mean(axis=0)
    w, v = np.linalg.eigh(d.T @ d / max(len(d), 1))  # ascending eigenvalues
    axis = float(np.arctan2(v[1, 1], v[0, 1])) % np.pi
    return axis, float(w[0] / w[1]) if w[1] > 0.0 else 1.0


def _mid_extent(x: np.ndarray) -> np.ndarray:
    """Middle of the 1st-99th percentile range of ``x`` along its first axis."""
    lo, hi = np.percentile(x, [1.0, 99.0], axis=0)
    return 0.5 * (lo + hi)


def _rot_z(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose_distance(A: Transform, B: Transform, pts: Points) -> float:
    """RMS distance, mm, between the images of ``pts`` under two transforms."""
    a = pts @ A[:3, :3].T + A[:3, 3]
    b = pts @ B[:3, :3].T + B[:3, 3]
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def align(
    tree: ClosestPointQuery,
    points: Points,
    *,
    model: AlignmentModel | None = None,
    cad: object | None = None,
    loss: str = "tukey",
    weights: Scalars | None = None,
    n_angles: int = 36,
    n_refine: int = 4,
    sample_points: int = 4000,
    refine_points: int = 500,
    score_points: int = 300,
    footprint_ratio: float = 0.7,
    clear_ratio: float = 2.0,
    ambiguity_ratio: float = 1.25,
    finalist_ratio: float = 2.0,
    n_finalists: int = 3,
    seed: int = 0,
    view_direction: Vectors | None = None,
    **register_kwargs: Any,
) -> Alignment:
    """Find ``T_cad_data`` for a part lying anywhere, then refine it.

    Parameters
    ----------
    tree : ClosestPointQuery
        The CAD tree (``GridTree``); used for the final fine registration and,
        when neither ``model`` nor ``cad`` is given, as the source of geometry.
    points : (N, 3) float64, mm, data frame with z up (the rig frame)
        The measured cloud: the side of the part that faces the sensor.
    model : AlignmentModel, optional
        From :func:`alignment_model`; build it once per part type and reuse
        it (it costs ~0.1-1 s). Built from ``cad`` or ``tree`` when omitted.
    cad : CadModel, optional
    loss : str
        Loss of the final registration (see :func:`register`).
    weights : (N,) float64, optional
        Per-point input weights for the final registration.
    n_angles : int
        Rotations about the vertical tried per resting pose whose footprint
        (or the cloud's) has no clear major axis.
    n_refine : int
        Distinct hypotheses refined on the subsample.
    sample_points : int
        Size of the cloud's subsample used to score hypotheses.
    refine_points : int
        Size of the (smaller) subsample used to refine them.
    score_points : int
        Points of each resting pose's template placed per hypothesis to
        score it (a prefix of the template).
    footprint_ratio : float
        A footprint (x, y of the template or of the cloud) whose minor over
        major principal variance is at most this has a clear major axis;
        when both have one, a resting pose is tried at the two rotations
        that lay the axes on each other instead of ``n_angles``.
    clear_ratio : float
        Once two distinct hypotheses are refined, hypotheses whose score is
        more than this factor above the best one's are not refined.
    ambiguity_ratio : float
        A distinct finalist whose score is within this factor of the best
        makes the result ambiguous.
    finalist_ratio, n_finalists : float, int
        Up to ``n_finalists`` candidates scoring within ``finalist_ratio`` of
        the best after coarse refinement are refined again on the CAD tree
        and compared.
    seed : int
    view_direction : (3,) float64, optional
        Direction from the part towards the sensor, data frame (+z for the
        rig). Every refinement then counts a point whose closest face is
        turned away from the sensor as an outlier (see :func:`register`), so
        that a thin part modelled as a solid is not fitted half onto its
        underside. Needs ``loss`` tukey or welsch.
    **register_kwargs
        Passed on to the final :func:`register` (which, having this search
        behind it, runs without its ``escape_deg`` scan unless given one).

    Returns
    -------
    Alignment

    Raises
    ------
    InvalidInput
        Bad points or parameters.
    InsufficientOverlap
        No hypothesis brings enough points near the CAD.
    """
    P = validate_points(points, min_points=30)
    view = validate_view(view_direction, loss)
    if n_angles < 1 or n_refine < 1 or min(sample_points, refine_points, score_points) < 30:
        raise InvalidInput(
            "n_angles and n_refine must be >= 1, sample_points, refine_points and "
            "score_points >= 30"
        )
    if not np.isfinite(ambiguity_ratio) or ambiguity_ratio < 1.0:
        raise InvalidInput(f"ambiguity_ratio must be >= 1, got {ambiguity_ratio!r}")
    if not 0.0 <= footprint_ratio <= 1.0:
        raise InvalidInput(f"footprint_ratio must be in [0, 1], got {footprint_ratio!r}")
    if not np.isfinite(clear_ratio) or clear_ratio < 1.0:
        raise InvalidInput(f"clear_ratio must be >= 1, got {clear_ratio!r}")
    if model is None:
        model = alignment_model(cad if cad is not None else tree, seed=seed)
    rng = np.random.default_rng(seed)
    # Random order: every prefix of the subsample is a random sample too.
    sub = P[rng.choice(len(P), size=min(sample_points, len(P)), replace=False)]
    c_data = sub.mean(axis=0)
    data_tree = cKDTree(sub)
    # Hypothesis scores saturate at a few per cent of the part size, so that a
    # hypothesis is judged by how much of its template lands on the cloud.
    trunc = 0.03 * model.size_mm
    scan = np.arange(n_angles) * (2.0 * np.pi / n_angles)
    axis_data, elongation_data = _footprint(sub[:, :2])
    # The cloud's principal directions in the plane (rows): a hypothesis puts
    # the middle of the template's extent along them on the middle of the
    # cloud's. The centroids would not do: the cloud's point density is
    # uneven (overlapping views), and a shift along a part's long axis is
    # the one the refinements correct most slowly.
    ca, sa = np.cos(axis_data), np.sin(axis_data)
    frame = np.array([[ca, sa], [-sa, ca]])
    mid_data = _mid_extent(sub[:, :2] @ frame.T)
    back = sub[:score_points]

    hyps: list[tuple[bool, float, int, float, np.ndarray]] = []
    # Poses whose hypotheses come from the footprints' axes: near enough to
    # be refined on the CAD tree directly (exact, and cheap near the surface).
    by_axes: set[int] = set()
    for k, pose in enumerate(model.poses):
        if max(pose.elongation, elongation_data) <= footprint_ratio:
            # Both footprints have a clear major axis: the rotation about the
            # vertical lays the template's axis on the cloud's, pointing one
            # way or the other (two hypotheses instead of a scan).
            a0 = (axis_data - pose.axis_rad) % (2.0 * np.pi)
            angles = np.array([a0, (a0 + np.pi) % (2.0 * np.pi)])
            by_axes.add(k)
        else:
            angles = scan
        c, s_ = np.cos(angles)[:, None], np.sin(angles)[:, None]
        # Per angle, the template turned about z (n, M) and the translation
        # t (n, 3) that maps it onto the cloud: x_data = Rz(theta) x_rest + t.
        full = pose.template
        rx = c * full[:, 0] - s_ * full[:, 1]
        ry = s_ * full[:, 0] + c * full[:, 1]
        mid_u = _mid_extent((rx * frame[0, 0] + ry * frame[0, 1]).T)
        mid_v = _mid_extent((rx * frame[1, 0] + ry * frame[1, 1]).T)
        shift = (mid_data[None, :] - np.stack([mid_u, mid_v], axis=1)) @ frame
        t = np.empty((len(angles), 3))
        t[:, :2] = shift
        t[:, 2] = c_data[2] - pose.centroid[2]
        # The template's points are independent samples: a prefix scores as
        # well as the whole, for less. Every angle in one query: (n, M, 3).
        tpl = full[:score_points]
        y = np.empty((len(angles), len(tpl), 3))
        y[:, :, 0] = c * tpl[:, 0] - s_ * tpl[:, 1] + t[:, :1]
        y[:, :, 1] = s_ * tpl[:, 0] + c * tpl[:, 1] + t[:, 1:2]
        y[:, :, 2] = tpl[:, 2] + t[:, 2:]
        d, _ = data_tree.query(y.reshape(-1, 3), distance_upper_bound=trunc)
        scores = np.mean(np.minimum(d, trunc).reshape(len(angles), -1) ** 2, axis=1)
        # And the other way round: the cloud turned into the resting frame,
        # against the whole template, so that a pose whose visible side covers
        # only part of the cloud (a panel on its edge) does not score well.
        bx = back[:, 0] - t[:, :1]
        by = back[:, 1] - t[:, 1:2]
        yb = np.empty((len(angles), len(back), 3))
        yb[:, :, 0] = c * bx + s_ * by
        yb[:, :, 1] = -s_ * bx + c * by
        yb[:, :, 2] = back[:, 2] - t[:, 2:]
        d, _ = cKDTree(full).query(yb.reshape(-1, 3), distance_upper_bound=trunc)
        scores += np.mean(np.minimum(d, trunc).reshape(len(angles), -1) ** 2, axis=1)
        # Hypotheses at neighbouring angles of a scan refine into the same
        # pose: the local minima of the score over the angle come first, so
        # that the refinement budget goes to distinct poses.
        if angles is scan:
            local_min = (scores <= np.roll(scores, 1)) & (scores <= np.roll(scores, -1))
        else:
            local_min = np.ones(len(angles), dtype=bool)
        for a in range(len(angles)):
            # T_data_cad = [Rz(theta) | t] T_rest_cad.
            T_dc = np.eye(4)
            T_dc[:3, :3] = _rot_z(angles[a])
            T_dc[:3, 3] = t[a]
            T_dc = T_dc @ pose.transform
            hyps.append(
                (
                    not local_min[a],
                    float(scores[a]),
                    k,
                    float(np.degrees(angles[a])),
                    np.linalg.inv(T_dc),
                )
            )
    hyps.sort(key=lambda h: (h[0], h[1], h[2], h[3]))
    best_hyp = hyps[0][1]
    log.debug("hypotheses: %s", [(h[2], round(h[3]), round(h[1], 2)) for h in hyps[:8]])

    # Coarse refinement of the best hypotheses (on the tree or the sampled surface).
    refined: list[Candidate] = []
    residuals: list[np.ndarray] = []
    tried = 0
    for _, score, k, ang, T in hyps:
        if tried >= 3 * n_refine or len(refined) >= n_refine:
            break
        if len(refined) >= 2 and score > clear_ratio * max(best_hyp, 1e-12 * trunc * trunc):
            # The rest place clearly less of their template on the cloud than
            # the best: two refined rivals are enough to judge ambiguity.
            break
        tried += 1
        # The search over the turn is this function's: its refinements run
        # without register's own scan of an unconstrained rotation.
        try:
            reg = register(
                tree if k in by_axes else model.surface,
                sub[:refine_points],
                init=T,
                loss="tukey",
                max_iterations=25,
                initial_subset=min(128, refine_points),
                max_subset=None,
                max_distance_mm=max(model.size_mm, 1.0),
                min_scale_mm=0.05,
                tolerance_rad=2e-4,
                tolerance_mm=2e-2,
                subset_tolerance_factor=10.0,
                seed=seed,
                view_direction=view,
                escape_deg=None,
            )
        except InsufficientOverlap:
            continue
        Tr = reg.transform
        if any(
            _pose_distance(Tr, c.transform, sub[:refine_points]) < 0.02 * model.size_mm
            for c in refined
        ):
            continue
        refined.append(Candidate(Tr, 0.0, k, ang))
        residuals.append(reg.residuals)
        log.debug(
            "hypothesis pose %d at %.0f deg: score %.3g -> rms %.3f", k, ang, score, reg.rms_mm
        )
    if not refined:
        raise InsufficientOverlap("no pose hypothesis brings the cloud near the CAD")

    scored = _score(refined, residuals, refined=False)

    # Finalists: the candidates that come close to the best are refined again
    # on the CAD tree (exact distances) and re-scored, so that a hypothesis
    # the coarse stage left a few degrees off is not mistaken for a rival.
    finalists: list[Candidate] = []
    final_res: list[np.ndarray] = []
    for cand in scored:
        if len(finalists) >= n_finalists or cand.score > finalist_ratio * scored[0].score:
            break
        try:
            reg = register(
                tree,
                sub[:refine_points],
                init=cand.transform,
                loss="tukey",
                max_iterations=40,
                initial_subset=refine_points,
                max_subset=None,
                max_distance_mm=max(model.size_mm, 1.0),
                seed=seed,
                view_direction=view,
                escape_deg=None,
            )
        except InsufficientOverlap:
            continue
        if any(
            _pose_distance(reg.transform, f.transform, sub[:refine_points]) < 0.02 * model.size_mm
            for f in finalists
        ):
            continue
        finalists.append(Candidate(reg.transform, 0.0, cand.pose_index, cand.angle_deg))
        final_res.append(reg.residuals)
    if finalists:
        ranked = _score(finalists, final_res, refined=True)
    else:
        ranked = scored[:1]
    best = ranked[0]
    ambiguous = len(ranked) > 1 and ranked[1].score <= ambiguity_ratio * best.score
    # The turn was searched here: the final fit scans no further unless asked.
    register_kwargs.setdefault("escape_deg", None)
    fine = register(
        tree,
        P,
        init=best.transform,
        loss=loss,
        weights=weights,
        seed=seed,
        view_direction=view,
        **register_kwargs,
    )
    log.debug(
        "align: %d candidates, %d finalists, best %.4g, runner-up %s, ambiguous %s",
        len(scored),
        len(ranked),
        best.score,
        f"{ranked[1].score:.4g}" if len(ranked) > 1 else "none",
        ambiguous,
    )
    finals = {(f.pose_index, f.angle_deg) for f in ranked}
    scored = ranked + [c for c in scored if (c.pose_index, c.angle_deg) not in finals]
    fields = {name: getattr(fine, name) for name in Registration.__dataclass_fields__}
    return Alignment(**fields, ambiguous=bool(ambiguous), candidates=tuple(scored))


def _score(
    cands: list[Candidate], residuals: list[np.ndarray], *, refined: bool
) -> list[Candidate]:
    """Re-score candidates with one truncation (3 robust scales of the best fit), best first."""
    sig = min(1.4826 * float(np.median(np.abs(r))) for r in residuals)
    tau = 3.0 * max(sig, 0.01)
    out = [
        Candidate(
            c.transform,
            float(np.mean(np.minimum(r * r, tau * tau))),
            c.pose_index,
            c.angle_deg,
            refined,
        )
        for c, r in zip(cands, residuals, strict=True)
    ]
    return sorted(out, key=lambda c: (c.score, c.pose_index, c.angle_deg))
