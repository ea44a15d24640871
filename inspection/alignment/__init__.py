"""Global alignment: find the pose of a part lying anywhere on the conveyor.

The sensor looks down (+z of the data frame is up) at a part resting in one
of its stable poses, turned by any angle about the vertical and placed
anywhere in the measurement volume. The search (:func:`align`, in
:mod:`.search`) runs in three stages:

1. *Hypotheses.* For every stable resting pose of the CAD (from the convex
   hull: trimesh's ``compute_stable_poses``), the side that faces the sensor
   is sampled once (an :class:`AlignmentModel`, :mod:`.model`, built
   explicitly and reused for every part). Each pose is tried at a few
   rotations about the vertical, with the centroid of its visible side put on
   the centroid of the measured cloud: the two that lay the major axis of the
   template's footprint on the cloud's when both footprints are elongated,
   else ``n_angles`` evenly spread. Each hypothesis is scored by truncated
   nearest-neighbour distances both ways, template to a subsample of the
   cloud and that subsample to the template (kd-trees, so scoring never
   touches the CAD); refinement stops once two distinct hypotheses are
   refined and the rest score clearly worse.
2. *Coarse refinement.* The best few distinct hypotheses are refined by
   :func:`inspection.registration.register` on a subsample of the cloud
   and re-scored with one common truncated residual cost: against the CAD
   tree when the rotation came from the footprints' axes (such hypotheses
   start within a few mm), else against a dense sampling of the CAD surface
   (:class:`SampledSurface`, :mod:`.surface`), as cheap far from the surface
   as near it (point-to-plane against the samples' face normals). Two
   distinct poses that fit equally well (a box turned by 180 degrees, a disc
   at any angle) make the result *ambiguous*.
3. *Fine registration* of every point from the best pose with
   :func:`~inspection.registration.register` on the CAD tree.

:mod:`.sampling` spreads points over the faces a sensor sees.
"""

from __future__ import annotations

from .model import MODEL_FORMAT_VERSION, AlignmentModel, RestingPose, alignment_model
from .sampling import DEFAULT_MIN_COS, sample_faces, sample_facing
from .search import Alignment, Candidate, align
from .surface import SampledSurface

# The name bench/bench_registration.py imports.
_sample_faces = sample_faces

__all__ = [
    "DEFAULT_MIN_COS",
    "MODEL_FORMAT_VERSION",
    "Alignment",
    "AlignmentModel",
    "Candidate",
    "RestingPose",
    "SampledSurface",
    "align",
    "alignment_model",
    "sample_faces",
    "sample_facing",
]
