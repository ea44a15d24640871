"""A dense sampling of the CAD surface that answers approximate closest-point queries."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..arrays import Faces, Points, Scalars, Vectors
from .sampling import sample_faces


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
        pts, f = sample_faces(
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
