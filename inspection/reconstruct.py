"""Point clouds from the rig's four flash frames.

The algorithm, per stereo pair of :attr:`Rig.stereo_pairs` (cam0-cam1, cam2-cam3):

1. **Rectify** both frames to a common orientation that looks straight down at
   the belt (maps precomputed once per rig by :meth:`Reconstructor.build`), so
   that a horizontal surface has one disparity across the image and the search
   range follows from the heights of the measurement volume (or the part).
2. **Coarse matching**: OpenCV's StereoSGBM (3-way mode, left-right check) at
   half resolution over the predicted disparity range. Cheap, robust, but its
   1/16 px (here 1/8 px at full resolution, ~0.25 mm) is far from 0.1 mm.
3. **Region of the part**: coarse points more than ``z_min_mm`` above the belt;
   the conveyor background is dropped here, before the expensive steps.
4. **Sub-pixel refinement** at full resolution: a Gauss-Newton (Lucas-Kanade)
   fit of each pixel's window with gain and offset, on locally normalised
   images, with cubic B-spline interpolation (the least pixel locking; see
   :mod:`inspection._stereo`) and with saturated pixels (the
   flash's mirror reflections) given no weight. Pixels whose windows do not
   correlate (score below ``min_score``), move too far, or do not converge
   are dropped. Every ``stride``-th column is refined (windows overlap, so
   neighbouring columns add little information but cost as much).
   **Warped windows**: a square window assumes one disparity across it, which
   bends (edge radii, character lines) and walls seen at grazing angles break:
   there the fit came out up to ~0.5 mm off, with a sign that depends on the
   side of the part, and those are the points that fix a flat part in its
   plane (the pose's translation was 0.3-0.8 mm off from them alone). Where
   the refined disparity field bends or slopes, the window is fitted again
   warped by that field (smoothed), solving for its centre only, with samples
   off the field (across a depth edge) left out; two such passes.
5. **Triangulation** in the rectified frame (``Z = f B / d``), back to the rig frame.

Then the two pairs are **fused**: each point is looked up in the other pair's
refined disparity map. A point seen by both within ``consistency_mm`` is
confirmed and averaged with the other pair's surface on the same ray (full
weight; the two pairs' matching errors are independent); a point that lies in
front of the surface the other pair sees (a free-space violation: a wrong match
at a reflection or dirt, or a surface dragged past an outline by the matching
window, where the other pair's coarse matching sees the belt) is dropped; a
point the other pair cannot see keeps a reduced weight.

Weights in [0, 1] combine the match score and this cross-pair confirmation, so
that registration can down-weight doubtful points.

When a prior is given (:class:`Prior`, e.g. from the part's CAD model), the
disparity search covers only the heights the part can occupy, which makes the
coarse matching faster and less ambiguous.

**CAD-guided matching.** The warped windows above take their shape from the
measured field, which is itself smoothed where the surface bends: on the
panel's emboss walls and character line the surface comes out ~0.3 mm RMS
off, and those are the points that place the part in its plane. Once
the part is aligned, a :class:`Guide` (its CAD at the fitted pose) gives the
shape exactly: each pair's disparity field is rendered from the CAD (the
simulator's z-buffer, in the rectified view) and the windows are warped by
it, wherever it agrees with the measured field within ``guide_tolerance_px``
(elsewhere the part departs from its CAD and the measured shape is kept).
Only the shape comes from the CAD; each window's disparity is still measured,
so a dent is not guided away. :meth:`Reconstructor.guided` starts from the
first pass's matching (``keep_matching=True``), so the second pass costs only
its warped windows (~0.3 s), and the ring pairs it matches afresh (below;
~0.35 s more).

**Light that changes with the surface.** Bare metal reflects the flash as a
broad sheen as well as diffusely. The sheen depends on the view: each camera
of a pair sees it with another strength, and across a bend, where the
normal turns, it changes by a different amount in each view. A window's gain
and offset cannot absorb that, and the match moves: by up to 0.5 mm on the
panel's character line, which is what fixes its turn (the fitted pose came
out up to 0.06 deg and 0.16 mm off at one pose, against 0.01 deg and 0.05 mm
without the sheen). Where the guide shows that a window spans a bend (its
disparity slope varies by more than ``shading_bend`` across it), the window
also fits light that is a quadratic function of the surface's orientation:
five more unknowns, the monomials of the guide's two disparity slopes (a
function of the normal), with their coefficients fitted with the disparity
(:func:`_stereo.refine_warped_shaded`). The slopes come from the CAD, not
from the images, so they cannot mimic the speckle. On the demo panel the
points on bends come out a quarter closer to the surface, and over twelve poses
the fitted pose is within 0.027 deg and moves the part's corners by at most
0.20 mm (median 0.07, 0.15 after the first pass alone; ``make bench
BENCH=endtoend``); without the light's fit the worst pose was 0.064 deg and
0.46 mm off. The flat regions' windows are fitted as before. About one
window in six is on a bend; they cost ~0.1 s per frame set.

**The ring pairs in the guided pass.** The rig's two other pairs (cam0-cam2,
cam1-cam3, baselines along y) see the part with independent speckle windows
and the walls facing +-x head on. A coarse search for them would cost as
much as the first pass; with a guide there is no need: each is matched only
in the guided pass (``guided_ring_pairs``), started from the guide's
disparities where the CAD is seen, refined with square windows and then
warped like the other pairs. The cloud then has twice the points, and the
fusion confirms and averages more of them. Over 24 trials of the end-to-end
bench (seeds 11-14) the comparison points came out within 0.05 mm in 23
(20 without), the corners within 0.1 mm in 19 (18), the worst turn 0.024 deg
(0.027); for ~0.45 s more per part.

**Matching the bends again.** A guided window is fitted for its centre's
disparity only; its shape is the guide's. Where the guide sits a little
off, say 0.3 px across a bend, the bend's shape lands beside the real one
and the window's disparity comes out pulled towards the guide, by ~0.01 px
where the slope changes inside the window: ~0.02 mm on the panel's
character line, all along it, and that line fixes the part's turn in its
plane. With the guide at the true pose the fitted turn was up to twice
closer. :meth:`Reconstructor.rematch_bends` takes a guided cloud and a guide
at the pose fitted to it and matches again only the windows that span a
bend (the shaded ones) or reach the guide's outline, from their guided fit:
a sixth of the windows, ~0.2 s per part. Over the end-to-end bench's twelve
trials the worst turn fell from 0.021 to 0.016 deg, the corners' worst
displacement from 0.14 to 0.12 mm and their median from 0.07 to 0.06 mm
(within 0.1 mm: 11 of 12, from 8). A whole second guided pass gains no more
for three times the time.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from . import _stereo
from ._raster import rasterize
from .arrays import Points, Scalars, mesh_arrays
from .errors import InvalidInput
from .registration import validate_transform
from .rig import VOLUME_MM, Rig

log = logging.getLogger(__name__)

FLAG_TOO_DARK = "too_dark"
FLAG_SATURATED = "saturated"
FLAG_LOW_TEXTURE = "low_texture"
FLAG_EMPTY = "empty"
FLAG_PAIR_SKIPPED = "pair_skipped"

# Grey values at or above this are treated as saturated (the sensor clips at
# 255, and noise pulls clipped pixels a few DN down).
_SATURATION_DN = 250
# Light that changes with the surface (ReconstructParams.shading): the
# regressors are the guide's disparity slopes times this (O(1) on a bend),
# and this times a window's weight is added to their coefficients' diagonal.
_SHADING_SCALE = 10.0
_SHADING_RIDGE = 1e-3


@dataclass(frozen=True)
class ReconstructParams:
    """Parameters of :func:`reconstruct` (lengths in mm, image sizes in pixels).

    Attributes
    ----------
    z_min_mm : float
        Points lower than this above the belt are background and dropped.
    z_max_mm : float
        Top of the measurement volume searched without a prior.
    volume_margin_mm : float
        Margin added around the rig's measurement volume in x and y.
    coarse_block : int
        SGBM block size at half resolution (odd).
    norm_window : int
        Window of the local mean and contrast normalisation (odd).
    window : int
        Lucas-Kanade window at full resolution (odd).
    iterations : int
        Most Lucas-Kanade iterations per pixel (it stops earlier when converged).
    symmetric : bool
        Centre the matching windows in the cyclopean (mid-baseline) view
        rather than in the left image, which cancels the shift of edges and
        slopes towards the occluded side (see :func:`_stereo.refine_cyclopean`).
    converged_px : float
        Largest accepted last Gauss-Newton step (a pixel that still moves is dropped).
    free_space_mm : float
        A point this far in front of the surface another pair's coarse
        matching sees along the same ray (the belt, say) is dropped.
    ring_pairs : bool
        Also match the rig's ring pairs (baselines along y), which see the walls
        facing +-x that the stereo pairs see at grazing angles; doubles the time.
    guided_ring_pairs : bool
        With a :class:`Guide`, also match the ring pairs, started from the
        guide's disparities instead of a coarse search (see the module notes);
        ignored with ``ring_pairs``, which matches them in every pass.
    stride : int
        Refine every ``stride``-th column of the rectified left image (1: every pixel).
    warp_passes : int
        Passes of warped refinement after the square-window one (0: none):
        windows whose disparity field bends or slopes are fitted again with
        the window warped by the field of the previous pass (see
        :func:`_refine_warped`).
    warp_curvature_px : float
        A window is refitted when the mean of the field over it is off its
        centre's value by more than this (px): a bend inside the window.
    warp_slope : float
        ... or when the field's slope along the baseline exceeds this (px/px):
        a surface seen foreshortened differently by the two cameras.
    warp_iterations : int
        Gauss-Newton iterations per warped pass.
    warp_smooth : int
        Box (odd, px) over which the field is smoothed before it warps the windows.
    guide_passes : int
        Warped passes with a :class:`Guide` (instead of ``warp_passes``): a
        second one gains little (on the demo panel, the median displacement
        of the fitted part's corners over twelve poses is 0.073 mm instead of
        0.080) for ~70 ms more per frame set.
    guide_tolerance_px : float
        With a :class:`Guide`, a window follows the CAD's disparity field only
        where that is within this of the measured field at its centre (1 px is
        ~2 mm of depth: a pose error moves the field far less, a part that
        departs from its CAD more).
    shading : bool
        With a :class:`Guide`, a window that spans a bend also fits light that
        changes with the surface's slope across it (the sheen of bare metal,
        which each camera sees differently; see the module notes).
    shading_bend : float
        A window spans a bend when the slope of the guide's disparity field
        (px/px) varies by more than this over it.
    threads : int
        Stereo pairs matched at once (one thread each).
    max_shift_px : float
        Largest accepted change of a disparity during refinement.
    min_score : float
        Smallest accepted normalised cross-correlation of a refined match.
    score_full : float
        Match score at and above which a point gets full weight (the weight
        ramps up from ``min_score``).
    consistency_mm : float
        Depth tolerance of the cross-pair check.
    dark_dn : float
        A frame whose 99th percentile is below this is too dark.
    saturated_fraction : float
        A frame with more saturated pixels than this fraction is flagged (and
        not used when above twice the fraction).
    min_contrast_dn : float
        A frame whose local contrast (median absolute Laplacian-free
        deviation) is below this has too little texture to match.
    """

    z_min_mm: float = 3.0
    z_max_mm: float = 200.0
    volume_margin_mm: float = 20.0
    coarse_block: int = 5
    norm_window: int = 15
    window: int = 9
    iterations: int = 5
    stride: int = 2
    converged_px: float = 0.05
    symmetric: bool = False
    warp_passes: int = 2
    threads: int = 2
    score_full: float = 0.95
    warp_curvature_px: float = 0.03
    warp_slope: float = 0.1
    warp_iterations: int = 2
    warp_smooth: int = 5
    warp_window: int = 9
    guide_passes: int = 1
    guide_tolerance_px: float = 1.0
    shading: bool = True
    shading_bend: float = 0.01
    ring_pairs: bool = False
    guided_ring_pairs: bool = True
    free_space_mm: float = 2.0
    max_shift_px: float = 1.5
    min_score: float = 0.9
    consistency_mm: float = 0.6
    dark_dn: float = 25.0
    saturated_fraction: float = 0.25
    min_contrast_dn: float = 2.0

    def __post_init__(self) -> None:
        for name in ("coarse_block", "norm_window", "window", "warp_window"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 3 and v % 2 == 1):
                raise InvalidInput(f"ReconstructParams.{name} must be an odd int >= 3, got {v!r}")
        if not (isinstance(self.stride, int) and 1 <= self.stride <= 8):
            raise InvalidInput("ReconstructParams.stride must be an int in [1, 8]")
        if not (isinstance(self.iterations, int) and 1 <= self.iterations <= 50):
            raise InvalidInput("ReconstructParams.iterations must be an int in [1, 50]")
        for name, top in (
            ("warp_passes", 5),
            ("guide_passes", 5),
            ("warp_iterations", 50),
            ("threads", 8),
        ):
            v = getattr(self, name)
            low = 0 if name == "warp_passes" else 1
            if not (isinstance(v, int) and low <= v <= top):
                raise InvalidInput(f"ReconstructParams.{name} must be an int in [{low}, {top}]")
        if not (
            isinstance(self.warp_smooth, int) and self.warp_smooth >= 1 and self.warp_smooth % 2
        ):
            raise InvalidInput("ReconstructParams.warp_smooth must be an odd int >= 1")
        if not (0.0 <= self.z_min_mm < self.z_max_mm and math.isfinite(self.z_max_mm)):
            raise InvalidInput("ReconstructParams needs 0 <= z_min_mm < z_max_mm (finite)")
        for name in (
            "volume_margin_mm",
            "max_shift_px",
            "consistency_mm",
            "dark_dn",
            "min_contrast_dn",
            "converged_px",
            "free_space_mm",
            "warp_curvature_px",
            "warp_slope",
            "guide_tolerance_px",
            "shading_bend",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InvalidInput(f"ReconstructParams.{name} must be finite and >= 0")
        if not (self.min_score < self.score_full <= 1.0):
            raise InvalidInput("ReconstructParams needs min_score < score_full <= 1")
        if not (-1.0 <= self.min_score < 1.0 and 0.0 < self.saturated_fraction <= 1.0):
            raise InvalidInput(
                "ReconstructParams needs -1 <= min_score < 1 and 0 < saturated_fraction <= 1"
            )


@dataclass(frozen=True)
class Prior:
    """What is known about the part before matching: the band of heights it can occupy.

    Attributes
    ----------
    z_max_mm : float
        Highest point of the part above the belt (mm), with margin.
    """

    z_max_mm: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.z_max_mm) and self.z_max_mm > 0):
            raise InvalidInput(f"Prior.z_max_mm must be finite and > 0, got {self.z_max_mm!r}")

    @classmethod
    def from_cad(cls, cad: Any, *, margin_mm: float = 10.0) -> Prior:
        """The height band of a part lying on the belt on one of its large faces.

        The part's height is bounded by the smallest extent of its principal
        (inertia) box: a sheet-metal part rests on its flange or its face,
        never on an edge. Parts that may stand upright need an explicit
        :class:`Prior` (or none).

        Parameters
        ----------
        cad : CadModel or trimesh.Trimesh or (V, 3) array of vertices (mm)
        margin_mm : float
            Added to the height (tilt, warp, tolerance).
        """
        vertices = getattr(cad, "vertices", cad)
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or not np.all(np.isfinite(v)):
            raise InvalidInput("Prior.from_cad needs a mesh or an (N, 3) array of finite vertices")
        c = v - v.mean(axis=0)
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        extent = np.ptp(c @ vt.T, axis=0)
        return cls(float(extent.min()) + margin_mm)


@dataclass(frozen=True, eq=False)
class Guide:
    """The part's CAD at its fitted pose: the shape that the matching windows follow.

    See "CAD-guided matching" in the module notes. Build it with
    :meth:`from_cad` from the first alignment of an unguided cloud, and match
    the same frames again with it (:meth:`Reconstructor.guided`).

    Attributes
    ----------
    vertices : (V, 3) float64, mm, rig frame
        The CAD's vertices at the fitted pose.
    faces : (F, 3) int64
    """

    vertices: Points
    faces: npt.NDArray[np.int64]

    @classmethod
    def from_cad(cls, cad: Any, T_rig_part: npt.ArrayLike) -> Guide:
        """The guide of ``cad`` (CadModel or trimesh.Trimesh, part frame) posed by ``T_rig_part``.

        Parameters
        ----------
        cad : CadModel or trimesh.Trimesh
            Anything with ``vertices`` (V, 3) and ``faces`` (F, 3).
        T_rig_part : (4, 4) array
            Maps part-frame points into the rig frame: the inverse of a
            registration's ``transform`` (T_cad_rig).
        """
        v, f = mesh_arrays(cad)
        T = validate_transform(T_rig_part, name="T_rig_part")
        R = T[:3, :3]
        return cls(v @ R.T + T[:3, 3], f)


@dataclass(frozen=True)
class PairReport:
    """Counts of one stereo pair through the stages of :func:`reconstruct`.

    Attributes
    ----------
    pair : str
        "left-right" camera indices.
    coarse : int
        Full-resolution pixels with a coarse (SGBM) disparity.
    foreground : int
        Of those, pixels above the belt (the part's region).
    refined : int
        Pixels that passed refinement (score, shift, convergence).
    in_volume : int
        Triangulated points inside the measurement volume, above ``z_min_mm``.
    confirmed, unconfirmed, dropped : int
        Cross-pair check: seen by the other pair consistently, not seen by it,
        dropped as inconsistent.
    disparity_range : (float, float)
        Disparities searched (full-resolution pixels).
    skipped : str
        Why the pair was not used ("" when it was).
    """

    pair: str
    coarse: int = 0
    foreground: int = 0
    refined: int = 0
    in_volume: int = 0
    confirmed: int = 0
    unconfirmed: int = 0
    dropped: int = 0
    disparity_range: tuple[float, float] = (0.0, 0.0)
    skipped: str = ""


@dataclass(frozen=True)
class ReconstructionReport:
    """What happened in :func:`reconstruct`.

    Attributes
    ----------
    flags : tuple of str
        Sorted, e.g. ``"too_dark"``, ``"saturated"``, ``"low_texture"``,
        ``"empty"``, ``"pair_skipped"``.
    frame_flags : tuple of tuple of str
        Per camera, the flags of its frame.
    pairs : tuple of PairReport
    points : int
        Points in the cloud.
    timings_ms : dict of str to float
        Wall time per stage.
    """

    flags: tuple[str, ...]
    frame_flags: tuple[tuple[str, ...], ...]
    pairs: tuple[PairReport, ...]
    points: int
    timings_ms: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready summary."""
        return {
            "flags": list(self.flags),
            "frame_flags": [list(f) for f in self.frame_flags],
            "pairs": [vars(p) | {"disparity_range": list(p.disparity_range)} for p in self.pairs],
            "points": self.points,
            "timings_ms": dict(self.timings_ms),
        }


@dataclass(frozen=True, eq=False)
class Cloud:
    """A reconstructed point cloud in the rig frame.

    Attributes
    ----------
    points : (N, 3) float64, mm, rig frame
    weights : (N,) float64 in [0, 1]
        Per-point quality: match score times cross-pair confirmation.
    pair : (N,) int8
        Index of the pair that measured each point, into
        ``Reconstructor.pairs + Reconstructor.guide_pairs`` (the rig's stereo
        pairs, then its ring pairs when they are used).
    report : ReconstructionReport
    rig_id : str
        Calibration id of the rig used.
    matching : object or None
        What the matching found (``keep_matching=True``; ~35 MB per pair of
        1280 x 1024 frames), for :meth:`Reconstructor.guided`; None otherwise.
    """

    points: Points
    weights: Scalars
    pair: npt.NDArray[np.int8]
    report: ReconstructionReport
    rig_id: str = ""
    matching: _Matching | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def empty(self) -> bool:
        return len(self.points) == 0


@dataclass(frozen=True, eq=False)
class Reconstructor:
    """The per-rig state of :func:`reconstruct`: rectification maps of every stereo pair.

    Build once per rig with :meth:`build` (~0.1 s) and pass it to every call.

    Attributes
    ----------
    rig : Rig
    params : ReconstructParams
    pairs : tuple of _stereo.RectifiedPair
    volume_lo, volume_hi : (3,) float64, mm
        The box searched without a prior (rig frame).
    foreground_disparity : tuple of (H, W) float32
        Per pair, the coarse disparity above which a pixel is part, not belt.
    guide_pairs : tuple of _stereo.RectifiedPair
        Pairs matched only with a guide (``guided_ring_pairs``); their points
        follow those of ``pairs`` in :attr:`Cloud.pair`.
    """

    rig: Rig
    params: ReconstructParams
    pairs: tuple[_stereo.RectifiedPair, ...]
    volume_lo: npt.NDArray[np.float64]
    volume_hi: npt.NDArray[np.float64]
    foreground_disparity: tuple[npt.NDArray[np.float32], ...]
    guide_pairs: tuple[_stereo.RectifiedPair, ...] = ()

    @classmethod
    def build(cls, rig: Rig, params: ReconstructParams | None = None) -> Reconstructor:
        """Precompute the rectification of each of ``rig.stereo_pairs``."""
        if not isinstance(rig, Rig):
            raise InvalidInput(f"rig must be a Rig, got {type(rig).__name__}")
        params = params or ReconstructParams()
        if not isinstance(params, ReconstructParams):
            raise InvalidInput("params must be a ReconstructParams")
        m = params.volume_margin_mm
        lo = np.array([-VOLUME_MM[0] / 2 - m, -VOLUME_MM[1] / 2 - m, 0.0])
        hi = np.array([VOLUME_MM[0] / 2 + m, VOLUME_MM[1] / 2 + m, params.z_max_mm])
        wanted = rig.stereo_pairs + (rig.ring_pairs if params.ring_pairs else ())
        pairs = [_rectified(rig, a, b, lo, hi) for a, b in wanted]
        guided_only = params.guided_ring_pairs and not params.ring_pairs
        guide_pairs = tuple(_rectified(rig, a, b, lo, hi) for a, b in rig.ring_pairs if guided_only)
        # The belt at z = 0 seen through a rectified pixel has the disparity of
        # that depth; a part pixel is one whose coarse disparity is above that of
        # the plane z = z_min (less the coarse matching's own uncertainty, ~1 mm).
        z_fg = max(params.z_min_mm - 1.5, 0.0)
        fg = tuple(_belt_disparity(pair, z_fg) for pair in pairs)
        log.debug(
            "reconstructor built for rig %s: %s",
            rig.id,
            [(p.name, p.size, round(p.baseline_mm, 1)) for p in pairs],
        )
        return cls(rig, params, tuple(pairs), lo, hi, fg, guide_pairs)

    def __call__(
        self,
        frames: Sequence[npt.NDArray[np.uint8]],
        *,
        prior: Prior | None = None,
        guide: Guide | None = None,
        keep_matching: bool = False,
    ) -> Cloud:
        """Reconstruct one frame set; see :func:`reconstruct`.

        ``keep_matching=True`` keeps in the cloud what the matching found, so
        that :meth:`guided` can match the same frames again with a guide
        without starting over.
        """
        self._check_guide(guide)
        return _run(self, frames, prior, guide, keep_matching)

    def guided(self, cloud: Cloud, guide: Guide) -> Cloud:
        """Match the frames of ``cloud`` again, with the windows following ``guide``.

        Starts from the coarse and square-window matching kept in ``cloud``
        (made by this reconstructor with ``keep_matching=True``): only the
        warped passes, the triangulation and the fusion run again, about half
        the time of a whole reconstruction. The result is the cloud that
        ``self(frames, guide=guide)`` gives, to the bit, and keeps its
        matching as well.

        Raises
        ------
        InvalidInput
            ``cloud`` holds no matching of this reconstructor, or ``guide`` is
            not a :class:`Guide`.
        """
        if guide is None:
            raise InvalidInput("guided() needs a Guide")
        self._check_guide(guide)
        matching = cloud.matching if isinstance(cloud, Cloud) else None
        if matching is None or matching.reconstructor is not self:
            raise InvalidInput(
                "the cloud holds no matching of this reconstructor: reconstruct its frames with "
                "keep_matching=True (or pass guide= to the reconstruction)"
            )
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        n = len(self.pairs)

        def one_pair(k: int) -> _PairResult:
            if k >= n:
                return _guided_pair(self, k, matching.frames, matching.usable, guide, timings)
            res = matching.results[k]
            if res.state is None:  # skipped, or nothing of the part seen
                return res
            return _finish_pair(self.pairs[k], res.state, self.params, timings, k, guide)

        results = _per_pair(self, one_pair, n + len(self.guide_pairs))
        redone = replace(matching, results=tuple(results))
        return _assemble(redone, timings, t0, keep=True)

    def rematch_bends(self, cloud: Cloud, guide: Guide) -> Cloud:
        """Match the windows on bends of a guided cloud again, with ``guide`` at a better pose.

        A guided window takes its shape from the guide. Where the guide is
        placed a little off, a bend's shape lands beside the real one and
        the window's fit is pulled towards the guide (see "Matching the
        bends again" in the module notes). After the guided cloud has been
        fitted, this matches again only the windows that span a bend or
        reach the outline of the new guide, starting from the guided fit;
        every other window keeps its match. Triangulation and fusion run
        again.

        ``cloud`` is what :meth:`guided` (or this method) returned.

        Raises
        ------
        InvalidInput
            ``cloud`` is not a guided cloud of this reconstructor, or
            ``guide`` is not a :class:`Guide`.
        """
        if guide is None:
            raise InvalidInput("rematch_bends() needs a Guide")
        self._check_guide(guide)
        matching = cloud.matching if isinstance(cloud, Cloud) else None
        if (
            matching is None
            or matching.reconstructor is not self
            or not any(r.guided is not None for r in matching.results)
        ):
            raise InvalidInput(
                "the cloud holds no guided matching of this reconstructor: pass what "
                "guided() returned"
            )
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        pairs = self.pairs + self.guide_pairs

        def one_pair(k: int) -> _PairResult:
            res = matching.results[k]
            if res.state is None or res.guided is None:
                return res
            return _rematch_pair(pairs[k], res.state, res.guided, self.params, timings, k, guide)

        results = _per_pair(self, one_pair, len(matching.results))
        redone = replace(matching, results=tuple(results))
        return _assemble(redone, timings, t0, keep=True)

    def _check_guide(self, guide: Guide | None) -> None:
        if guide is not None and not isinstance(guide, Guide):
            raise InvalidInput(f"guide must be a Guide, got {type(guide).__name__}")
        if guide is not None and self.params.symmetric:
            raise InvalidInput("a guide warps the left view's windows: not with symmetric=True")


def reconstruct(
    rig: Rig,
    frames: Sequence[npt.NDArray[np.uint8]],
    *,
    prior: Prior | Any | None = None,
    params: ReconstructParams | None = None,
    reconstructor: Reconstructor | None = None,
    guide: Guide | None = None,
    keep_matching: bool = False,
) -> Cloud:
    """Reconstruct a point cloud of the part from the four flash frames.

    Parameters
    ----------
    rig : Rig
        The calibrated rig that took the frames (:meth:`Rig.default` on the line).
    frames : sequence of four (H, W) uint8
        One grey image per camera, in the rig's camera order, each of its
        camera's size.
    prior : Prior or CadModel or trimesh.Trimesh, optional
        What is known of the part: a mesh is turned into a :class:`Prior` with
        :meth:`Prior.from_cad` (the band of heights it can occupy).
    params : ReconstructParams, optional
        Only used when ``reconstructor`` is not given.
    reconstructor : Reconstructor, optional
        Precomputed per-rig state (build it once per rig; built here otherwise).
    guide : Guide, optional
        The part's CAD at its fitted pose: the matching windows follow its
        shape (see the module notes). Give it on a second pass over the same
        frames, after aligning the first cloud.
    keep_matching : bool
        Keep what the matching found in the cloud, for
        :meth:`Reconstructor.guided` (a guided pass without starting over).

    Returns
    -------
    Cloud
        Points in the rig frame (mm) with weights and a report. Frames that
        cannot give points (all dark, all saturated, no texture, no part)
        give an empty cloud flagged ``"empty"`` with the reason in its flags.

    Raises
    ------
    InvalidInput
        Wrong number of frames, wrong size, dtype or dimensions, or a
        reconstructor built for another rig.
    """
    if not isinstance(rig, Rig):
        raise InvalidInput(f"rig must be a Rig, got {type(rig).__name__}")
    if reconstructor is None:
        reconstructor = Reconstructor.build(rig, params)
    elif not isinstance(reconstructor, Reconstructor):
        raise InvalidInput("reconstructor must be a Reconstructor")
    elif reconstructor.rig.id != rig.id:
        raise InvalidInput(f"reconstructor was built for rig {reconstructor.rig.id}, not {rig.id}")
    if prior is not None and not isinstance(prior, Prior):
        prior = Prior.from_cad(prior)
    return reconstructor(frames, prior=prior, guide=guide, keep_matching=keep_matching)


# -- the pipeline -------------------------------------------------------------


def _check_frames(rig: Rig, frames: Any) -> list[npt.NDArray[np.uint8]]:
    if isinstance(frames, np.ndarray) and frames.ndim == 3:
        frames = list(frames)
    if not isinstance(frames, (list, tuple)):
        raise InvalidInput(
            f"frames must be a sequence of {len(rig.cameras)} images, got {type(frames).__name__}"
        )
    if len(frames) != len(rig.cameras):
        raise InvalidInput(f"need {len(rig.cameras)} frames (one per camera), got {len(frames)}")
    out = []
    for i, (img, cam) in enumerate(zip(frames, rig.cameras, strict=True)):
        if not isinstance(img, np.ndarray):
            raise InvalidInput(f"frame {i} must be a numpy array, got {type(img).__name__}")
        if img.dtype != np.uint8:
            raise InvalidInput(f"frame {i} must be uint8 (8-bit grey), got {img.dtype}")
        if img.ndim != 2:
            raise InvalidInput(f"frame {i} must be a 2-D grey image, got shape {img.shape}")
        if img.shape != cam.shape:
            raise InvalidInput(
                f"frame {i} has shape {img.shape}, camera {cam.name} takes {cam.shape} (H, W)"
            )
        out.append(np.ascontiguousarray(img))
    return out


def _frame_flags(img: npt.NDArray[np.uint8], p: ReconstructParams) -> tuple[set[str], bool]:
    """Flags of one frame, and whether it is usable at all."""
    flags: set[str] = set()
    usable = True
    small = img[::4, ::4]
    if np.percentile(small, 99) < p.dark_dn:
        flags.add(FLAG_TOO_DARK)
        usable = False
    sat = float(np.mean(small >= _SATURATION_DN))
    if sat > p.saturated_fraction:
        flags.add(FLAG_SATURATED)
        usable = usable and sat <= min(1.0, 2 * p.saturated_fraction) and sat < 0.99
    if usable:
        # Texture: median absolute difference of horizontal neighbours among
        # unsaturated pixels (the speckle gives tens of DN).
        row = small.astype(np.int16)
        diff = np.abs(np.diff(row, axis=1))[(small[:, 1:] < _SATURATION_DN)]
        if diff.size == 0 or float(np.median(diff)) < p.min_contrast_dn:
            flags.add(FLAG_LOW_TEXTURE)
            usable = False
    return flags, usable


_EXECUTORS: dict[int, ThreadPoolExecutor] = {}
_EXECUTOR_LOCK = threading.Lock()
# A forked child inherits the pool's bookkeeping but not its threads: it starts its own.
os.register_at_fork(after_in_child=_EXECUTORS.clear)


def _executor(threads: int) -> ThreadPoolExecutor:
    """A process-wide pool for the stereo pairs (threads are started once)."""
    with _EXECUTOR_LOCK:
        pool = _EXECUTORS.get(threads)
        if pool is None:
            pool = _EXECUTORS[threads] = ThreadPoolExecutor(threads, "reconstruct-pair")
        return pool


@dataclass
class _PairResult:
    report: PairReport
    points: npt.NDArray[np.float64]
    score: npt.NDArray[np.float32]
    disparity: npt.NDArray[np.float32] | None = None  # full rectified size, NaN where none
    coarse: npt.NDArray[np.float32] | None = None  # SGBM's, belt included, NaN where none
    state: _PairState | None = None  # what a guided pass starts from (not symmetric)
    # The guided pass's fit (crop coordinates: d_ref, score, step): what
    # Reconstructor.rematch_bends starts from.
    guided: tuple[npt.NDArray[np.float32], ...] | None = None


def _run(
    rec: Reconstructor,
    frames: Any,
    prior: Prior | None,
    guide: Guide | None,
    keep_matching: bool = False,
) -> Cloud:
    p = rec.params
    rig = rec.rig
    imgs = _check_frames(rig, frames)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    frame_flags = []
    usable = []
    for img in imgs:
        f, ok = _frame_flags(img, p)
        frame_flags.append(tuple(sorted(f)))
        usable.append(ok)
    all_flags = set().union(*[set(f) for f in frame_flags])
    timings["check"] = (time.perf_counter() - t0) * 1e3

    z_hi = min(p.z_max_mm, prior.z_max_mm) if prior is not None else p.z_max_mm
    lo = rec.volume_lo.copy()
    hi = rec.volume_hi.copy()
    hi[2] = max(z_hi, p.z_min_mm + 1.0)

    n = len(rec.pairs)

    def one_pair(k: int) -> _PairResult:
        if k >= n:
            assert guide is not None  # such pairs are only asked for with a guide
            return _guided_pair(rec, k, imgs, usable, guide, timings)
        pair = rec.pairs[k]
        t1 = time.perf_counter()
        if not (usable[pair.left] and usable[pair.right]):
            return _skipped(rec, pair, usable)
        out = _match_pair(
            pair,
            rec.foreground_disparity[k],
            imgs[pair.left],
            imgs[pair.right],
            lo,
            hi,
            p,
            timings,
            k,
            guide,
        )
        timings[f"pair{pair.name}"] = (time.perf_counter() - t1) * 1e3
        return out

    # The pairs are independent and their heavy steps (OpenCV, the numba
    # kernels) release the GIL: one thread per pair, each kernel on one thread,
    # uses two cores without nesting numba's parallel layer.
    results = _per_pair(rec, one_pair, n + (len(rec.guide_pairs) if guide is not None else 0))
    if any(r.report.skipped for r in results):
        all_flags.add(FLAG_PAIR_SKIPPED)
    # The pairs matched only with a guide need the frames again.
    kept = tuple(img.copy() for img in imgs) if keep_matching and rec.guide_pairs else ()
    matching = _Matching(
        rec, tuple(results), tuple(frame_flags), frozenset(all_flags), kept, tuple(usable)
    )
    return _assemble(matching, timings, t0, keep_matching)


def _crops(
    left: npt.NDArray[np.float32],
    right: npt.NDArray[np.float32],
    sat_l: npt.NDArray[np.bool_],
    sat_r: npt.NDArray[np.bool_],
    region: npt.NDArray[np.bool_],
    d_min: float,
    d_max: float,
    p: ReconstructParams,
) -> tuple[Any, ...]:
    """The crops a pair's refinement works on: around ``region`` of the left view
    (padded by the windows), and of the right view where disparities in
    [d_min, d_max] send it. Returns the left crop's slices, its origin (x0, y0),
    the right crop's first column, both crops locally normalised (the right one
    as row spline coefficients, which the kernels sample between pixels) and
    their weights (0 where saturated)."""
    ys, xs = np.nonzero(region)
    pad = p.window + p.norm_window
    h_img, w_img = region.shape
    y0 = max(int(ys.min()) - pad, 0)
    y1 = min(int(ys.max()) + pad + 1, h_img)
    x0 = max(int(xs.min()) - pad, 0)
    x1 = min(int(xs.max()) + pad + 1, w_img)
    roi = (slice(y0, y1), slice(x0, x1))
    rx0 = max(int(math.floor(x0 - d_max)) - pad, 0)
    rx1 = min(int(math.ceil(x1 - d_min)) + pad, w_img)
    left_n = _stereo.local_normalise(left[roi], p.norm_window)
    right_n = _stereo.spline_rows(_stereo.local_normalise(right[y0:y1, rx0:rx1], p.norm_window))
    wl = (~sat_l[roi]).astype(np.float32)
    wr = (~sat_r[y0:y1, rx0:rx1]).astype(np.float32)
    return roi, x0, y0, rx0, left_n, right_n, wl, wr


def _skipped(
    rec: Reconstructor, pair: _stereo.RectifiedPair, usable: Sequence[bool]
) -> _PairResult:
    """The result of a pair not matched because one of its frames cannot be used."""
    bad = [rec.rig.cameras[i].name for i in (pair.left, pair.right) if not usable[i]]
    return _PairResult(
        PairReport(pair.name, skipped=f"unusable frame(s): {', '.join(bad)}"),
        np.zeros((0, 3)),
        np.zeros(0, np.float32),
    )


def _guided_pair(
    rec: Reconstructor,
    k: int,
    frames: Sequence[npt.NDArray[np.uint8]],
    usable: Sequence[bool],
    guide: Guide,
    timings: dict[str, float],
) -> _PairResult:
    """Pair ``k`` of ``rec.pairs + rec.guide_pairs``, one matched only with a guide:
    started from the guide's disparities where the CAD is seen (no coarse search),
    a square-window refinement, then the guided passes of the other pairs."""
    p = rec.params
    pair = rec.guide_pairs[k - len(rec.pairs)]
    if not (usable[pair.left] and usable[pair.right]):
        return _skipped(rec, pair, usable)
    t = time.perf_counter()
    left = _rectify(frames[pair.left], pair.maps_left)
    right = _rectify(frames[pair.right], pair.maps_right)
    sat_l = left >= _SATURATION_DN - 0.5
    sat_r = right >= _SATURATION_DN - 0.5
    g = _guide_disparity(pair, guide)
    seen = np.isfinite(g)
    if not seen.any():
        return _PairResult(PairReport(pair.name), np.zeros((0, 3)), np.zeros(0, np.float32))
    d_min, d_max = float(g[seen].min()), float(g[seen].max())
    report = PairReport(pair.name, foreground=int(seen.sum()), disparity_range=(d_min, d_max))
    frame = _PairFrame(g.shape, rec.volume_lo, rec.volume_hi, report, None)
    roi, x0, y0, rx0, left_n, right_n, wl, wr = _crops(
        left, right, sat_l, sat_r, seen, d_min, d_max, p
    )
    cols = np.arange(roi[1].start, roi[1].stop) % p.stride == 0
    py, px = np.nonzero(seen[roi] & ~sat_l[roi] & cols[None, :])
    d_init = g[roi][py, px].astype(np.float32)
    shift = float(rx0 - x0)
    d_sq = np.empty(len(px), np.float32)
    score = np.empty(len(px), np.float32)
    step = np.empty(len(px), np.float32)
    fit = (p.window // 2, p.iterations, d_sq, score, step)
    start = (d_init + shift).astype(np.float32)
    _stereo.refine_pixels(
        left_n, right_n, wl, wr, px.astype(np.int64), py.astype(np.int64), start, *fit
    )
    timings[f"refine{k}"] = (time.perf_counter() - t) * 1e3
    state = _PairState(
        left_n, right_n, wl, wr, px, py, d_init, d_sq, score, step, shift, x0, y0, roi, frame
    )
    return _finish_pair(pair, state, p, timings, k, guide, g)


def _per_pair(
    rec: Reconstructor, one_pair: Callable[[int], _PairResult], n: int | None = None
) -> list[_PairResult]:
    """``one_pair(k)`` for the first ``n`` pairs (default: ``rec.pairs``)."""
    # The pairs are independent and their heavy steps (OpenCV, the numba
    # kernels) release the GIL: one thread per pair, each kernel on one thread,
    # uses two cores without nesting numba's parallel layer.
    n = len(rec.pairs) if n is None else n
    if rec.params.threads > 1 and n > 1:
        return list(_executor(rec.params.threads).map(one_pair, range(n)))
    return [one_pair(k) for k in range(n)]


@dataclass(frozen=True, eq=False)
class _Matching:
    """What one frame set's matching found, pair by pair: kept in a :class:`Cloud`
    (``keep_matching=True``) so that :meth:`Reconstructor.guided` can start from it."""

    reconstructor: Reconstructor
    results: tuple[_PairResult, ...]
    frame_flags: tuple[tuple[str, ...], ...]
    flags: frozenset[str]
    # The frames, for the pairs matched only with a guide (Reconstructor.guide_pairs).
    frames: tuple[npt.NDArray[np.uint8], ...] = ()
    usable: tuple[bool, ...] = ()


def _assemble(matching: _Matching, timings: dict[str, float], t0: float, keep: bool) -> Cloud:
    """Fuse the pairs' points into the cloud."""
    rec = matching.reconstructor
    t = time.perf_counter()
    points, weights, which, reports = _fuse(rec, list(matching.results), rec.params)
    timings["fuse"] = (time.perf_counter() - t) * 1e3
    timings["total"] = (time.perf_counter() - t0) * 1e3
    flags = set(matching.flags)
    if len(points) == 0:
        flags.add(FLAG_EMPTY)
    report = ReconstructionReport(
        tuple(sorted(flags)), matching.frame_flags, tuple(reports), len(points), timings
    )
    log.debug(
        "reconstructed %d points in %.0f ms, flags %s", len(points), timings["total"], report.flags
    )
    return Cloud(points, weights, which, report, rec.rig.id, matching if keep else None)


def _match_pair(
    pair: _stereo.RectifiedPair,
    fg_disparity: npt.NDArray[np.float32],
    img_l: npt.NDArray[np.uint8],
    img_r: npt.NDArray[np.uint8],
    lo: npt.NDArray[np.float64],
    hi: npt.NDArray[np.float64],
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
    guide: Guide | None = None,
) -> _PairResult:
    t = time.perf_counter()
    # Rectify in float32 so that the refinement sees no second quantisation.
    left = _rectify(img_l, pair.maps_left)
    right = _rectify(img_r, pair.maps_right)
    sat_l = left >= _SATURATION_DN - 0.5
    sat_r = right >= _SATURATION_DN - 0.5
    left_u8 = np.clip(left + 0.5, 0, 255).astype(np.uint8)
    right_u8 = np.clip(right + 0.5, 0, 255).astype(np.uint8)
    timings[f"rectify{k}"] = (time.perf_counter() - t) * 1e3

    t = time.perf_counter()
    d_min, d_max = pair.disparity_range(lo, hi)
    d_coarse = _stereo.coarse_disparity(left_u8, right_u8, d_min, d_max, p.coarse_block)
    coarse_ok = np.isfinite(d_coarse)
    n_coarse = int(coarse_ok.sum())
    timings[f"sgbm{k}"] = (time.perf_counter() - t) * 1e3
    rep = PairReport(pair.name, coarse=n_coarse, disparity_range=(d_min, d_max))
    empty = _PairResult(rep, np.zeros((0, 3)), np.zeros(0, np.float32))
    if n_coarse == 0:
        return empty

    t = time.perf_counter()
    # The part's region: coarse depth above the belt (conveyor background removed).
    fg = coarse_ok & (d_coarse > fg_disparity)
    n_fg = int(fg.sum())
    if n_fg == 0:
        return _PairResult(
            PairReport(pair.name, coarse=n_coarse, disparity_range=(d_min, d_max)),
            np.zeros((0, 3)),
            np.zeros(0, np.float32),
            None,
            d_coarse,
        )
    roi, x0, y0, rx0, left_n, right_n, wl, wr = _crops(
        left, right, sat_l, sat_r, fg, d_min, d_max, p
    )
    todo = fg[roi] & ~sat_l[roi]
    py, px = np.nonzero(todo)
    d_init = d_coarse[roi][py, px]
    report = PairReport(pair.name, coarse=n_coarse, foreground=n_fg, disparity_range=(d_min, d_max))
    frame = _PairFrame(fg.shape, lo, hi, report, d_coarse)
    if p.symmetric:
        # Points on the cyclopean view's grid: c = x_left - d / 2 (full-image
        # columns), every stride-th column; the coarse disparity of each comes
        # from the left pixel that maps to it.
        c = np.rint((px + x0) - 0.5 * d_init).astype(np.int64)
        sel = c % p.stride == 0
        c, py_, d_init = c[sel], py[sel], d_init[sel]
        cl = (c - x0).astype(np.float64)
        cr = (c - rx0).astype(np.float64)
        n = len(c)
        d_ref = np.empty(n, np.float32)
        score = np.empty(n, np.float32)
        step = np.empty(n, np.float32)
        _stereo.refine_cyclopean(
            _stereo.spline_rows(left_n),  # sampled between pixels too
            right_n,
            wl,
            wr,
            cl,
            cr,
            py_.astype(np.int64),
            d_init.astype(np.float32),
            p.window // 2,
            p.iterations,
            d_ref,
            score,
            step,
        )
        x_left = c + 0.5 * d_ref.astype(np.float64)
        rows = py_ + y0
    else:
        if p.stride > 1:
            # Refine every stride-th column only (the windows overlap anyway).
            sel = (px + x0) % p.stride == 0
            px, py, d_init = px[sel], py[sel], d_init[sel]
        # In the crops, a left pixel x matches right x - d', with d' = d - x0 + rx0.
        shift = float(rx0 - x0)
        n = len(px)
        d_ref = np.empty(n, np.float32)
        score = np.empty(n, np.float32)
        step = np.empty(n, np.float32)
        _stereo.refine_pixels(
            left_n,
            right_n,
            wl,
            wr,
            px.astype(np.int64),
            py.astype(np.int64),
            (d_init + shift).astype(np.float32),
            p.window // 2,
            p.iterations,
            d_ref,
            score,
            step,
        )
        timings[f"refine{k}"] = (time.perf_counter() - t) * 1e3
        state = _PairState(
            left_n,
            right_n,
            wl,
            wr,
            px,
            py,
            d_init,
            d_ref,
            score,
            step,
            shift,
            x0,
            y0,
            roi,
            frame,
        )
        return _finish_pair(pair, state, p, timings, k, guide)
    timings[f"refine{k}"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    out = _triangulate_pair(pair, x_left, rows, d_ref, score, step, d_init, frame, p)
    timings[f"triangulate{k}"] = (time.perf_counter() - t) * 1e3
    return out


@dataclass(frozen=True, eq=False)
class _PairFrame:
    """What one pair's triangulation needs besides its matches: the rectified image
    size, the volume searched, the report so far and the coarse (SGBM) disparities."""

    shape: tuple[int, ...]
    lo: npt.NDArray[np.float64]
    hi: npt.NDArray[np.float64]
    report: PairReport
    coarse: npt.NDArray[np.float32] | None  # None: matched only with a guide


@dataclass(frozen=True, eq=False)
class _PairState:
    """One pair's matching up to its square-window refinement (crop coordinates):
    what the warped passes, with or without a guide, start from."""

    left_n: npt.NDArray[np.float32]
    right_n: npt.NDArray[np.float32]  # row B-spline coefficients (_stereo.spline_rows)
    wl: npt.NDArray[np.float32]
    wr: npt.NDArray[np.float32]
    px: npt.NDArray[np.intp]
    py: npt.NDArray[np.intp]
    d_init: npt.NDArray[np.float32]  # coarse, full-image disparities
    d_square: npt.NDArray[np.float32]  # square-window refinement, crop disparities
    score: npt.NDArray[np.float32]
    step: npt.NDArray[np.float32]
    shift: float  # crop disparity = full-image disparity + shift
    x0: int
    y0: int
    roi: tuple[slice, slice]
    frame: _PairFrame


def _finish_pair(
    pair: _stereo.RectifiedPair,
    st: _PairState,
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
    guide: Guide | None,
    guide_field: npt.NDArray[np.float32] | None = None,
) -> _PairResult:
    """The warped passes (guided or not) and the triangulation of one pair
    (``guide_field``: the guide's disparities, :func:`_guide_disparity`, when
    already drawn)."""
    t = time.perf_counter()
    shape = None
    if guide is not None:
        if guide_field is None:
            guide_field = _guide_disparity(pair, guide)
        shape = guide_field[st.roi] + np.float32(st.shift)
        timings[f"guide{k}"] = (time.perf_counter() - t) * 1e3
    d_ref, score, step = st.d_square, st.score, st.step
    if p.warp_passes or shape is not None:
        d_ref, score, step = _refine_warped(
            st.left_n,
            st.right_n,
            st.wl,
            st.wr,
            st.px,
            st.py,
            st.d_init + st.shift,
            d_ref,
            score,
            step,
            p,
            shape,
        )
    timings[f"warp{k}"] = (time.perf_counter() - t) * 1e3
    return _triangulate_state(pair, st, (d_ref, score, step), p, timings, k, shape is not None)


def _triangulate_state(
    pair: _stereo.RectifiedPair,
    st: _PairState,
    fit: tuple[npt.NDArray[np.float32], ...],
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
    guided: bool,
) -> _PairResult:
    """The pair's result from its warped fit ``(d_ref, score, step)`` (crop
    coordinates), kept with the state it started from (and, ``guided``, the fit)."""
    t = time.perf_counter()
    d_ref, score, step = fit
    x_left = (st.px + st.x0).astype(np.float64)
    rows = st.py + st.y0
    d_full = d_ref - np.float32(st.shift)
    out = _triangulate_pair(pair, x_left, rows, d_full, score, step, st.d_init, st.frame, p)
    timings[f"triangulate{k}"] = (time.perf_counter() - t) * 1e3
    out.state = st
    if guided:
        out.guided = fit
    return out


def _rematch_pair(
    pair: _stereo.RectifiedPair,
    st: _PairState,
    guided: tuple[npt.NDArray[np.float32], ...],
    p: ReconstructParams,
    timings: dict[str, float],
    k: int,
    guide: Guide,
) -> _PairResult:
    """One pair of :meth:`Reconstructor.rematch_bends`: the guided windows that span a
    bend or reach the outline of ``guide``, warped by it again from their guided fit."""
    t = time.perf_counter()
    shape = _guide_disparity(pair, guide)[st.roi] + np.float32(st.shift)
    d_ref, score, step = (a.copy() for a in guided)
    g_field, g_mask, shade, bent = _guide_maps(shape, p)
    px, py = st.px, st.py
    ok = (
        np.isfinite(d_ref)
        & (score >= p.min_score)
        & (np.abs(d_ref - (st.d_init + st.shift)) <= p.max_shift_px)
        & (g_mask[py, px] > 0.0)
        & (np.abs(g_field[py, px] - d_ref) <= p.guide_tolerance_px)
    )
    kw = (p.warp_window, p.warp_window)
    inside = cv2.boxFilter(g_mask, cv2.CV_32F, kw, normalize=False, borderType=cv2.BORDER_CONSTANT)
    outline = inside < p.warp_window * p.warp_window - 0.5
    images = (st.left_n, st.right_n, st.wl, st.wr, g_field, g_mask, px, py)
    if bent is not None:
        _warp(*images, ok & bent[py, px], d_ref, score, step, p, shade)
        plain = ok & ~bent[py, px] & outline[py, px]
    else:
        plain = ok & (_bends(g_field, g_mask, px, py, p) | outline[py, px])
    _warp(*images, plain, d_ref, score, step, p)
    timings[f"rematch{k}"] = (time.perf_counter() - t) * 1e3
    return _triangulate_state(pair, st, (d_ref, score, step), p, timings, k, True)


def _triangulate_pair(
    pair: _stereo.RectifiedPair,
    x_left: npt.NDArray[np.float64],
    rows: npt.NDArray[np.intp],
    d_ref: npt.NDArray[np.float32],
    score: npt.NDArray[np.float32],
    step: npt.NDArray[np.float32],
    d_init: npt.NDArray[np.float32],
    frame: _PairFrame,
    p: ReconstructParams,
) -> _PairResult:
    """Accepted matches of one pair as rig-frame points, and its disparity map."""
    lo, hi = frame.lo, frame.hi
    good = (
        np.isfinite(d_ref)
        & (score >= p.min_score)
        & (np.abs(d_ref - d_init) <= p.max_shift_px)
        & (np.abs(step) < p.converged_px)
    )
    w_img = frame.shape[1]
    xg = x_left[good]
    yg = rows[good].astype(np.float64)
    d = d_ref[good].astype(np.float64)
    xi = np.clip(np.rint(xg).astype(np.int64), 0, w_img - 1)
    yi = rows[good]
    pts = pair.triangulate(xg, yg, d)
    inside = np.all((pts >= lo) & (pts <= hi), axis=1) & (pts[:, 2] >= p.z_min_mm)
    pts = pts[inside]
    score = score[good][inside]
    # The disparity map of the left view, for the other pair's consistency check.
    full = np.full(frame.shape, np.nan, np.float32)
    full[yi[inside], xi[inside]] = d[inside]
    _fill_gaps(full, p.stride)
    rep = replace(frame.report, refined=int(good.sum()), in_volume=len(pts))
    return _PairResult(rep, pts, score, full, frame.coarse)


def _rectified(
    rig: Rig, a: int, b: int, lo: npt.NDArray[np.float64], hi: npt.NDArray[np.float64]
) -> _stereo.RectifiedPair:
    """The rectified pair of cameras a and b; its "left" camera is the one at the
    lower end of the baseline's main direction (rectified x grows along it)."""
    ca, cb = rig.cameras[a], rig.cameras[b]
    base = cb.centre - ca.centre
    k = int(np.argmax(np.abs(base[:2])))
    if base[k] < 0:
        a, b, ca, cb = b, a, cb, ca
    return _stereo.rectify_pair(ca, cb, a, b, lo, hi)


def _rectify(
    img: npt.NDArray[np.uint8], maps: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]
) -> npt.NDArray[np.float32]:
    out = cv2.remap(
        img.astype(np.float32), maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )
    return np.asarray(out, dtype=np.float32)


def _refine_warped(
    left_n: npt.NDArray[np.float32],
    right_n: npt.NDArray[np.float32],
    wl: npt.NDArray[np.float32],
    wr: npt.NDArray[np.float32],
    px: npt.NDArray[np.intp],
    py: npt.NDArray[np.intp],
    d_init: npt.NDArray[np.float32],
    d_ref: npt.NDArray[np.float32],
    score: npt.NDArray[np.float32],
    step: npt.NDArray[np.float32],
    p: ReconstructParams,
    guide: npt.NDArray[np.float32] | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Refine again, with windows warped by the disparity field found so far.

    A square window assumes one disparity across it. Where the surface bends
    (the panel's edge radii, character lines, the walls of the flange seen at
    grazing angles) that is far from true, and the fit comes out up to half a
    millimetre off, with a sign that depends on the side of the part: those
    are the very points that fix a flat part in its plane. The refined
    disparities (smoothed over ``warp_smooth`` pixels) give the shape of the
    surface; the warped fit (:func:`_stereo.refine_warped`) then only solves
    for each window's centre. Only windows whose field is far from constant
    are refitted (mean over the window off its centre by more than
    ``warp_curvature_px``, a slope above ``warp_slope``, or a window reaching
    a hole in the field); elsewhere the square window is already right.
    Each pass starts from the previous one's field.

    With ``guide`` (the CAD's disparity field over the crop, NaN off the
    part; see :class:`Guide`), every window whose centre lies on it, within
    ``guide_tolerance_px`` of the measured field, is warped by the guide
    instead, in ``guide_passes`` passes.

    Inputs are the crops and pixel lists of :func:`_match_pair` (disparities
    in crop coordinates); returns new ``d_ref``, ``score``, ``step``.
    """
    ks = (p.warp_smooth, p.warp_smooth)
    guided = shade = bent = None
    if guide is not None:
        g_field, g_mask, shade, bent = _guide_maps(guide, p)
        guided = (g_field, g_mask)
    passes = p.warp_passes if guide is None else p.guide_passes
    for _ in range(passes):
        ok = (
            np.isfinite(d_ref) & (score >= p.min_score) & (np.abs(d_ref - d_init) <= p.max_shift_px)
        )
        field_ = np.full(left_n.shape, np.nan, np.float32)
        field_[py[ok], px[ok]] = d_ref[ok]
        _fill_gaps(field_, p.stride)
        known = np.isfinite(field_)
        mask = known.astype(np.float32)
        v = np.where(known, field_, 0.0).astype(np.float32)
        num = cv2.boxFilter(v, cv2.CV_32F, ks, normalize=False, borderType=cv2.BORDER_CONSTANT)
        den = cv2.boxFilter(mask, cv2.CV_32F, ks, normalize=False, borderType=cv2.BORDER_CONSTANT)
        smooth = np.where(known, num / np.maximum(den, 1.0), 0.0).astype(np.float32)
        sel = ok & _bends(smooth, mask, px, py, p)
        d_ref, score, step = d_ref.copy(), score.copy(), step.copy()
        if guided is not None:
            g_field, g_mask = guided
            follow = (
                ok
                & (g_mask[py, px] > 0.0)
                & (np.abs(g_field[py, px] - smooth[py, px]) <= p.guide_tolerance_px)
            )
            shaded = follow & bent[py, px] if bent is not None else np.zeros_like(follow)
            images = (left_n, right_n, wl, wr, g_field, g_mask, px, py)
            _warp(*images, follow & ~shaded, d_ref, score, step, p)
            if shaded.any():
                _warp(*images, shaded, d_ref, score, step, p, shade)
            sel &= ~follow
        _warp(left_n, right_n, wl, wr, smooth, mask, px, py, sel, d_ref, score, step, p)
    return d_ref, score, step


def _bends(
    field_: npt.NDArray[np.float32],
    mask: npt.NDArray[np.float32],
    px: npt.NDArray[np.intp],
    py: npt.NDArray[np.intp],
    p: ReconstructParams,
) -> npt.NDArray[np.bool_]:
    """Windows over which ``field_`` (0 where ``mask`` is 0) is far from constant: its
    mean off the centre's value by more than ``warp_curvature_px``, a slope along the
    baseline above ``warp_slope``, or a hole in the field inside the window."""
    kw = (p.window, p.window)
    num_w = cv2.boxFilter(field_, cv2.CV_32F, kw, normalize=False, borderType=cv2.BORDER_CONSTANT)
    den_w = cv2.boxFilter(mask, cv2.CV_32F, kw, normalize=False, borderType=cv2.BORDER_CONSTANT)
    cnt = den_w[py, px]
    off = np.abs(num_w[py, px] / np.maximum(cnt, 1.0) - field_[py, px])
    right = field_[py, np.minimum(px + 1, field_.shape[1] - 1)]
    slope = np.abs(right - field_[py, np.maximum(px - 1, 0)]) * 0.5
    bends: npt.NDArray[np.bool_] = (
        (off > p.warp_curvature_px) | (slope > p.warp_slope) | (cnt < p.window * p.window - 0.5)
    )
    return bends


def _warp(
    left_n: npt.NDArray[np.float32],
    right_n: npt.NDArray[np.float32],
    wl: npt.NDArray[np.float32],
    wr: npt.NDArray[np.float32],
    shape: npt.NDArray[np.float32],
    mask: npt.NDArray[np.float32],
    px: npt.NDArray[np.intp],
    py: npt.NDArray[np.intp],
    sel: npt.NDArray[np.bool_],
    d_ref: npt.NDArray[np.float32],
    score: npt.NDArray[np.float32],
    step: npt.NDArray[np.float32],
    p: ReconstructParams,
    shade: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] | None = None,
) -> None:
    """Refit the selected windows warped by ``shape``, in place: with
    :func:`_stereo.refine_warped`, or with ``shade`` (the surface
    coordinates of :func:`_shading`) :func:`_stereo.refine_warped_shaded`."""
    idx = np.nonzero(sel)[0]
    d2 = np.empty(len(idx), np.float32)
    s2 = np.empty(len(idx), np.float32)
    st2 = np.empty(len(idx), np.float32)
    pixels = (px[idx].astype(np.int64), py[idx].astype(np.int64), d_ref[idx].astype(np.float32))
    fit = (p.warp_window // 2, p.warp_iterations, d2, s2, st2)
    if shade is None:
        _stereo.refine_warped(left_n, right_n, wl, wr, shape, mask, *pixels, *fit)
    else:
        _stereo.refine_warped_shaded(
            left_n, right_n, wl, wr, shape, mask, *shade, _SHADING_RIDGE, *pixels, *fit
        )
    d_ref[idx], score[idx], step[idx] = d2, s2, st2


def _guide_maps(guide: npt.NDArray[np.float32], p: ReconstructParams) -> tuple[Any, ...]:
    """What the warped kernels take of a guide's disparity field over a crop
    (NaN off the part): the field with 0 off the part, its mask (1 on the
    part), and with ``p.shading`` the surface coordinates and the windows on
    bends of :func:`_shading` (else None, None)."""
    on_part = np.isfinite(guide)
    g_field = np.where(on_part, guide, 0.0).astype(np.float32)
    g_mask = on_part.astype(np.float32)
    if not p.shading:
        return g_field, g_mask, None, None
    su, sv, bent = _shading(guide, on_part, p)
    return g_field, g_mask, (su, sv), bent


def _shading(
    field_: npt.NDArray[np.float32], on_part: npt.NDArray[np.bool_], p: ReconstructParams
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Surface coordinates for light that changes with the surface, and the windows on bends.

    The slopes ``(a, b)`` of the guide's disparity field (px/px, one-sided at
    its outline) are a function of the surface normal: scaled by
    ``_SHADING_SCALE`` (to about 1 on a bend), they are the coordinates whose
    quadratic monomials :func:`_stereo.refine_warped_shaded` fits the light
    with. A window spans a bend where either slope varies, over the window's
    on-part pixels, by more than ``p.shading_bend``.
    """
    a, b = (_slope(field_, on_part, axis) for axis in (1, 0))
    k = np.ones((p.warp_window, p.warp_window), np.uint8)
    bent = np.zeros(on_part.shape, bool)
    for g in (a, b):
        hi = cv2.dilate(np.where(on_part, g, np.float32(-1e30)), k)
        lo = cv2.erode(np.where(on_part, g, np.float32(1e30)), k)
        bent |= hi - lo > p.shading_bend
    scale = np.float32(_SHADING_SCALE)
    return scale * a, scale * b, bent


def _slope(
    field_: npt.NDArray[np.float32], on_part: npt.NDArray[np.bool_], axis: int
) -> npt.NDArray[np.float32]:
    """Derivative of ``field_`` along ``axis``: the mean of the differences to
    both neighbours that are on the part (one-sided at its outline, 0 alone)."""
    f = np.moveaxis(np.where(on_part, field_, np.float32(0.0)), axis, -1)
    on = np.moveaxis(on_part, axis, -1)
    both = on[..., 1:] & on[..., :-1]
    diff = np.where(both, f[..., 1:] - f[..., :-1], np.float32(0.0))
    total = np.zeros_like(f)
    count = np.zeros(f.shape, np.int8)
    for side in (np.s_[..., 1:], np.s_[..., :-1]):
        total[side] += diff
        count[side] += both
    return np.ascontiguousarray(np.moveaxis(total / np.maximum(count, 1), -1, axis), np.float32)


def _guide_disparity(pair: _stereo.RectifiedPair, guide: Guide) -> npt.NDArray[np.float32]:
    """The guide's disparity at every rectified left pixel of ``pair`` (NaN: not on the part).

    The CAD is drawn into the rectified left view with the simulator's
    z-buffer rasteriser (exact for planar faces: 1/z is interpolated).
    """
    q = pair.to_rect(guide.vertices)
    z = q[:, 2]
    w, h = pair.size
    zbuf = np.full((h, w), np.inf, np.float32)
    fbuf = np.full((h, w), -1, np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = pair.f_px * q[:, 0] / z + pair.cx_left
        sy = pair.f_px * q[:, 1] / z + pair.cy
    rasterize(sx, sy, z, guide.faces, zbuf, fbuf)
    seen = np.isfinite(zbuf)
    out = np.full((h, w), np.nan, np.float32)
    out[seen] = pair.fb / zbuf[seen].astype(np.float64) + pair.offset_px
    return out


def _fill_gaps(disparity: npt.NDArray[np.float32], stride: int) -> None:
    """Fill short gaps along rows (the columns not refined), in place, from measured neighbours."""
    # A row scan in numba: three box filters per pass over the whole image cost ~50x more.
    _stereo.fill_row_gaps(disparity, stride)


def _belt_disparity(pair: _stereo.RectifiedPair, z_mm: float) -> npt.NDArray[np.float32]:
    """Disparity of the plane z = ``z_mm`` (rig frame) at every rectified left pixel."""
    w, h = pair.size
    # Rectified ray through pixel (x, y): r = R^T [(x - cx)/f, (y - cy)/f, 1]; it meets
    # z = z_mm at depth Z = (z_mm - C_z) / r_z along the rectified axis.
    R = pair.R_rect_rig
    xn = (np.arange(w, dtype=np.float64) - pair.cx_left) / pair.f_px
    yn = (np.arange(h, dtype=np.float64) - pair.cy) / pair.f_px
    rz = R[0, 2] * xn[None, :] + R[1, 2] * yn[:, None] + R[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (z_mm - pair.centre_left[2]) / rz
        d = pair.fb / depth + pair.offset_px
    return np.where(depth > 0, d, np.inf).astype(np.float32)


def _fuse(
    rec: Reconstructor, results: list[_PairResult], p: ReconstructParams
) -> tuple[Points, Scalars, npt.NDArray[np.int8], list[PairReport]]:
    """Cross-pair check, averaging and weights (see the module docstring).

    A point confirmed by the other pair is replaced by the mean of itself and
    the other pair's surface point on the same viewing ray of the other pair:
    the two pairs' matching errors are independent, so this halves their
    variance where both see the part.
    """
    pairs = rec.pairs + rec.guide_pairs

    def one(k: int) -> tuple[Points, Scalars, PairReport] | PairReport:
        res = results[k]
        if len(res.points) == 0:
            return res.report
        quality = np.clip(
            (res.score.astype(np.float64) - p.min_score) / (p.score_full - p.min_score), 0.0, 1.0
        )
        factor = np.full(len(res.points), 0.6)
        drop = np.zeros(len(res.points), bool)
        confirmed = np.zeros(len(res.points), bool)
        fused = res.points.copy()
        for j, other in enumerate(results):
            if j == k:
                continue
            pair = pairs[j]
            if other.coarse is not None:
                # Free space seen by the other pair's coarse matching, belt included:
                # a point well in front of what the other pair sees there would
                # have hidden it. This removes the surfaces that windows drag past
                # an outline facing this pair, where the other pair sees the belt.
                z, z_coarse = _depth_in_other(pair, other.coarse, res.points)
                seen_c = np.isfinite(z_coarse)
                drop |= seen_c & (z_coarse - z > p.free_space_mm)
            if other.disparity is None:
                continue
            z, z_other = _depth_in_other(pair, other.disparity, res.points)
            seen = np.isfinite(z_other)
            dz = np.where(seen, z_other - z, 0.0)
            ok = seen & (np.abs(dz) <= p.consistency_mm) & ~confirmed
            # The other pair's surface point on the ray from its left centre
            # through this point: scale the ray by the depth ratio.
            ratio = z_other[ok] / z[ok]
            other_pt = pair.centre_left + (res.points[ok] - pair.centre_left) * ratio[:, None]
            fused[ok] = 0.5 * (res.points[ok] + other_pt)
            confirmed |= ok
            # dz > 0: the point lies in front of (nearer the camera than) the
            # surface the other pair sees through it, which would have hidden that surface.
            drop |= seen & (dz > p.consistency_mm)
        factor[confirmed] = 1.0
        drop &= ~confirmed
        keep = ~drop
        r = res.report
        report = PairReport(
            r.pair,
            r.coarse,
            r.foreground,
            r.refined,
            r.in_volume,
            int(confirmed.sum()),
            int((~confirmed & keep).sum()),
            int(drop.sum()),
            r.disparity_range,
            r.skipped,
        )
        return fused[keep], (quality * factor)[keep], report

    # Each pair's points are checked against the others' maps independently.
    if p.threads > 1 and len(results) > 1:
        done = list(_executor(p.threads).map(one, range(len(results))))
    else:
        done = [one(k) for k in range(len(results))]
    pts_out, w_out, which_out, reports = [], [], [], []
    for k, out in enumerate(done):
        if isinstance(out, PairReport):
            reports.append(out)
            continue
        pts, w, report = out
        pts_out.append(pts)
        w_out.append(w)
        which_out.append(np.full(len(pts), k, np.int8))
        reports.append(report)
    if not pts_out:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int8), reports
    return np.concatenate(pts_out), np.concatenate(w_out), np.concatenate(which_out), reports


def _depth_in_other(
    pair: _stereo.RectifiedPair, disparity: npt.NDArray[np.float32], points: Points
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Depth of points, and of the other pair's surface on the same rays, in the other pair's frame.

    The other pair's disparity map is interpolated bilinearly where the four
    neighbours are measured, else taken from the nearest pixel.

    Returns
    -------
    z : (N,) float64, mm
        Depth of each point along the other pair's rectified axis.
    z_other : (N,) float64, mm
        Depth of the other pair's surface through the same pixel (NaN: not measured there).
    """
    n = len(points)
    z, z_other = np.empty(n), np.empty(n)
    _stereo.depth_in_view(
        np.ascontiguousarray(points, dtype=np.float64),
        pair.centre_left,
        pair.R_rect_rig,
        pair.f_px,
        pair.cx_left,
        pair.cy,
        pair.fb,
        pair.offset_px,
        disparity,
        z,
        z_other,
    )
    return z, z_other


# -- pictures -----------------------------------------------------------------


def deviation_colours(values: npt.ArrayLike, limit_mm: float) -> npt.NDArray[np.uint8]:
    """Diverging colours for signed deviations: blue (-limit) - white (0) - red (+limit).

    Parameters
    ----------
    values : (N,) float64, mm
        NaN gives grey.
    limit_mm : float
        Deviation shown at full saturation.

    Returns
    -------
    (N, 3) uint8 RGB
    """
    v = np.asarray(values, dtype=np.float64)
    t = np.clip(v / limit_mm, -1.0, 1.0)
    rgb = np.empty((len(v), 3))
    pos = t >= 0
    # Towards red: keep R, lower G and B; towards blue: keep B, lower R and G.
    rgb[:, 0] = np.where(pos, 1.0, 1.0 + t)
    rgb[:, 1] = 1.0 - np.abs(t)
    rgb[:, 2] = np.where(pos, 1.0 - t, 1.0)
    rgb[~np.isfinite(v)] = 0.5
    return np.rint(rgb * 255).astype(np.uint8)


def write_deviation_ply(
    path: str | os.PathLike[str],
    points: npt.ArrayLike | Cloud,
    deviations: npt.ArrayLike | None = None,
    *,
    limit_mm: float = 0.5,
) -> Path:
    """Write a point cloud as binary PLY coloured by deviation, for people to look at.

    (:func:`inspection.cloud_io.write_ply` writes plain points and scalars for
    programs; this one adds the colours a viewer shows directly.)

    Any PLY viewer (MeshLab, CloudCompare, Open3D) shows it. Each vertex has
    x, y, z (float32, mm), red, green, blue (uint8), and, with deviations, a
    ``deviation`` scalar (float32, mm) that viewers can map themselves.

    Parameters
    ----------
    path : path-like
    points : (N, 3) float64, mm, or Cloud
        Points in any frame (the caller's choice: rig or CAD).
    deviations : (N,) float64, mm, optional
        Signed deviation of each point; without it, points are coloured by
        their weight (dark = doubtful) when ``points`` is a Cloud, else grey.
    limit_mm : float
        Deviation at full colour (blue below -limit, red above +limit).

    Returns
    -------
    Path
    """
    weights = None
    if isinstance(points, Cloud):
        weights = points.weights
        pts = points.points
    else:
        pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInput(f"points must have shape (N, 3), got {pts.shape}")
    if not (math.isfinite(limit_mm) and limit_mm > 0):
        raise InvalidInput("limit_mm must be finite and > 0")
    n = len(pts)
    dev = None
    if deviations is not None:
        dev = np.asarray(deviations, dtype=np.float64)
        if dev.shape != (n,):
            raise InvalidInput(f"deviations must have shape ({n},), got {dev.shape}")
        rgb = deviation_colours(dev, limit_mm)
    elif weights is not None:
        g = np.rint(60 + 195 * np.clip(weights, 0, 1)).astype(np.uint8)
        rgb = np.stack([g, g, g], axis=1)
    else:
        rgb = np.full((n, 3), 200, np.uint8)
    fields = [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
    ]
    if dev is not None:
        fields.append(("deviation", "<f4"))
    rec = np.empty(n, dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    if dev is not None:
        rec["deviation"] = dev
    ply_types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment units mm", f"element vertex {n}"]
    header += [f"property {ply_types[t]} {name}" for name, t in fields]
    header.append("end_header")
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    return out


__all__ = [
    "Cloud",
    "PairReport",
    "Prior",
    "ReconstructParams",
    "ReconstructionReport",
    "Reconstructor",
    "deviation_colours",
    "reconstruct",
    "write_deviation_ply",
]
