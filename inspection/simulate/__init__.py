"""The rig simulator: four flash frames of a part on the belt, and calibration boards.

What a frame set contains, and why (each is a way real frames are hard):

- The **projected speckle** (the rig's only texture on bare sheet metal), cut
  off by **projector shadows** behind walls and flanges (a shadow map rendered
  from the projector, filtered over four texels so shadow edges are soft).
- **Flash shading**: Lambert with inverse-square fall-off from the projector,
  plus two Blinn-Phong lobes: a broad sheen (each camera sees the metal with a
  different brightness) and a sharp mirror lobe, the flash's own reflection,
  which **saturates** in blobs that carry no pattern.
- **Dirt on the part** (matte dark spots that move with the part) and **on the
  lens** (soft dark out-of-focus blobs fixed in the image).
- A **textured belt** (periodic along x, so it can move) and a dark floor
  beyond it, lit by the same flash.
- **Lens distortion** exactly as OpenCV models it (every pixel's ray is
  undistorted once per rig), vignetting (cos^4), optical blur, and **sensor
  noise** (shot noise with variance proportional to the signal, read noise,
  8-bit quantisation).
- **Motion blur**: the belt carries the part along +x by
  ``rig.conveyor.speed_mm_s * flash_us`` during the flash, so the frame is the
  average of sub-exposures of the part (and the belt) shifted along x, while
  the projector and the cameras stay put: part edges, dirt and the belt's
  texture smear along the belt; the speckle on a face that moves within its
  own plane does not.
- **Pixel area**: a pixel collects the light over its whole area, so the
  projected speckle is averaged over each pixel's footprint on the part (3 x 3
  samples placed through the footprint's Jacobian; ``pixel_samples``). Taken
  at the pixel's centre alone, the speckle's fine grain aliases, and
  differently in each camera: an error no real sensor makes. A pixel on the
  part's outline (a hole's rim, the part against the belt, a flange over the
  floor) is the mean of ``edge_samples`` x ``edge_samples`` rays through it,
  each meeting its own surface: outlines fall between pixel centres, as the
  features' edge search measures them.

Rendering: a numba z-buffer per camera into an undistorted buffer, then exact
ray-plane intersections per real pixel (see :mod:`inspection._raster`); the
cameras render in parallel threads (as many as ``NUMBA_NUM_THREADS`` allows). The
per-rig set-up (rays, pattern, belt texture) is done once by
:meth:`Simulator.build`; :func:`simulate` keeps the last two simulators, keyed
by the rig's content id.

Everything is deterministic for a seed.
"""

from __future__ import annotations

import threading
from typing import Any, Literal, overload

import numpy.typing as npt

from ..arrays import Image
from ..board import CharucoSpec
from ..errors import InvalidInput
from ..rig import Rig
from .exposure import MIN_SMEAR_PX, SUB_EXPOSURE_PX
from .options import CameraTruth, RenderOptions
from .simulator import Simulator

__all__ = [
    "MIN_SMEAR_PX",
    "SUB_EXPOSURE_PX",
    "CameraTruth",
    "RenderOptions",
    "Simulator",
    "simulate",
    "simulate_board",
    "simulator_for",
]

_CACHE: dict[str, Simulator] = {}
_CACHE_LOCK = threading.Lock()
_CACHE_SIZE = 2


def simulator_for(rig: Rig) -> Simulator:
    """The :class:`Simulator` of a rig, built once and kept (the last two rigs, by content id)."""
    if not isinstance(rig, Rig):
        raise InvalidInput(f"rig must be a Rig, got {type(rig).__name__}")
    key = rig.id
    with _CACHE_LOCK:
        sim = _CACHE.get(key)
    if sim is None:
        sim = Simulator.build(rig)
        with _CACHE_LOCK:
            _CACHE[key] = sim
            while len(_CACHE) > _CACHE_SIZE:
                _CACHE.pop(next(iter(_CACHE)))
    return sim


@overload
def simulate(
    rig: Rig,
    mesh: Any,
    T_rig_part: npt.ArrayLike,
    *,
    seed: int = ...,
    options: RenderOptions | None = ...,
    return_truth: Literal[False] = ...,
) -> list[Image]: ...
@overload
def simulate(
    rig: Rig,
    mesh: Any,
    T_rig_part: npt.ArrayLike,
    *,
    seed: int = ...,
    options: RenderOptions | None = ...,
    return_truth: Literal[True],
) -> tuple[list[Image], list[CameraTruth]]: ...
def simulate(
    rig: Rig,
    mesh: Any,
    T_rig_part: npt.ArrayLike,
    *,
    seed: int = 0,
    options: RenderOptions | None = None,
    return_truth: bool = False,
) -> list[Image] | tuple[list[Image], list[CameraTruth]]:
    """Render the four flash frames of a part lying on the belt.

    Parameters
    ----------
    rig : Rig
        The rig to render with: the truth (normally :meth:`Rig.nominal`).
    mesh : trimesh.Trimesh, CadModel, or anything with ``vertices`` (V, 3)
        and ``faces`` (F, 3)
        The part in its own frame, mm.
    T_rig_part : (4, 4) float64
        Pose of the part: maps part-frame points into the rig frame.
    seed : int
        Seeds the faults (dirt) and the sensor noise; the same seed gives the
        same images, bit for bit.
    options : RenderOptions, optional
        Photometry and faults (default: :class:`RenderOptions` ()).
    return_truth : bool
        Also return what each camera really saw.

    Returns
    -------
    images : list of four (H, W) uint8
        In the order of ``rig.cameras``.
    truths : list of four CameraTruth
        Only with ``return_truth=True``.

    Raises
    ------
    InvalidInput
        For a mesh without faces or with non-finite vertices, a transform that
        is not a finite rigid 4 x 4 matrix, or a bad seed.
    """
    return simulator_for(rig).render(
        mesh, T_rig_part, seed=seed, options=options, return_truth=return_truth
    )


def simulate_board(
    rig: Rig,
    T_rig_board: npt.ArrayLike,
    board: CharucoSpec | None = None,
    *,
    seed: int = 0,
    options: RenderOptions | None = None,
    supersample: int = 5,
) -> list[Image]:
    """Render a printed ChArUco board in any pose, under even calibration lighting.

    Parameters
    ----------
    rig : Rig
        The rig (the truth).
    T_rig_board : (4, 4) float64
        Maps board-frame points (see :mod:`inspection.board`) into the rig frame.
    board : CharucoSpec, optional
        Board layout (default :class:`CharucoSpec` ()).
    seed : int
        Seeds the sensor noise.
    options : RenderOptions, optional
        Sensor parameters (noise, blur, belt shift).
    supersample : int
        Rays per pixel along each axis: area sampling, as a sensor's pixels
        integrate light. With 3 the board's edges alias: its corners were
        found 0.12 px RMS off on the board lying on the belt (0.09 px with 5),
        and the calibrated rig frame came out tilted by up to 0.012 deg.

    Returns
    -------
    list of four (H, W) uint8
    """
    return simulator_for(rig).render_board(
        T_rig_board, board, seed=seed, options=options, supersample=supersample
    )
