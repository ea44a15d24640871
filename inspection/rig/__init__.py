"""The four-camera flash rig: cameras, pattern projector and conveyor in the rig frame.

The rig frame: origin at the centre of the measurement volume on the
conveyor surface, x along the conveyor's motion (the 800 mm side), y across
it (500 mm), z up (200 mm). Units are millimetres.

Layout of the rig as built (:meth:`Rig.nominal`), seen from above::

        y ^
          |   cam2 (-250, +300)        cam3 (+250, +300)
          |
          |               projector (0, 0)
          |        +---------------------------+
          |        |   measurement volume      |  500 mm across
          |        +---------------------------+
          |   cam0 (-250, -300)        cam1 (+250, -300)
          +-------------------------------------------> x (conveyor motion)

All four cameras hang 1300 mm above the belt and look at the centre of the
volume (0, 0, 100). Why this layout:

- **Two stereo pairs with baselines along x** (cam0-cam1 and cam2-cam3, 500 mm
  each, ~21° between the views at 1.35 m). Each pair is rectified with small
  rotations (the image x axes already point along rig x), so epipolar lines
  stay close to the image rows and SGBM's disparity search is short. The two
  pairs look from opposite sides in y, so a flange or a hole wall hidden from
  one pair is usually seen by the other: the pairs complement each other's
  occlusions. 500 mm of baseline at ~1.35 m gives ~2.2 mm of depth per
  pixel of disparity at the belt (z^2 / (f b)).
- **The ring pairs** cam0-cam2 and cam1-cam3 (600 mm baselines along y) are
  also usable (:attr:`Rig.ring_pairs`) where time allows: they see walls that
  face ±x, which the x pairs see at grazing angles.
- **8 mm lenses on 1280 x 1024 sensors with 4.8 µm pixels** (f ≈ 1667 px):
  the smallest standard focal length that still makes every camera see the
  whole 800 x 500 x 200 mm volume, including the top corners.
- **The projector** hangs in the middle, 1300 mm up, looking straight down, so
  it lights everything the cameras see except the far side of steep walls.

The pattern is a **random binary speckle** (:class:`Pattern`), not fringes:
the part moves at ~1 m/s and is captured in a single flash, and phase-shifted
fringes need several exposures of a still scene (or accept motion blur and
phase errors). A random speckle gives every pixel neighbourhood a unique
texture, which is exactly what single-shot stereo block matching (SGBM) needs,
on bare sheet metal that has no texture of its own. The speckle grain is set to
~3 camera pixels on the part, coarse enough to survive the lens blur, fine
enough for dense matching.

Cameras follow OpenCV's model (:mod:`.camera`). The rest: :mod:`.projector`
(the flash and its slide), :mod:`.conveyor` (the belt), :mod:`.assembly`
(the rig of the four cameras, projector and belt), :mod:`.toml` (the rig
file), :mod:`.poses` (rotations and rigid transforms of the rig frame),
:mod:`.checks` (input validators).
"""

from __future__ import annotations

from .assembly import DEFAULT_RIG_DATA, ENV_RIG, VOLUME_MM, Rig
from .camera import Camera, distort_normalized, undistort_normalized
from .conveyor import Conveyor
from .poses import belt_pose, look_at, rigid_align
from .projector import Pattern, Projector
from .toml import RIG_FORMAT

__all__ = [
    "DEFAULT_RIG_DATA",
    "ENV_RIG",
    "RIG_FORMAT",
    "VOLUME_MM",
    "Camera",
    "Conveyor",
    "Pattern",
    "Projector",
    "Rig",
    "belt_pose",
    "distort_normalized",
    "look_at",
    "rigid_align",
    "undistort_normalized",
]
