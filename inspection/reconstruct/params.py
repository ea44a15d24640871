"""The parameters of the reconstruction: one frozen record, checked when it is made.

Lengths are in millimetres, image sizes and disparities in pixels of the
rectified images. :class:`ReconstructParams` is built once (the service maps
its configuration onto it) and handed to :meth:`Reconstructor.build
<inspection.reconstruct.Reconstructor.build>`; every stage reads its own
fields from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import InvalidInput

SATURATION_DN = 250
"""Grey values at or above this are saturated (the sensor clips at 255, and
noise pulls clipped pixels a few DN down)."""


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
        slopes towards the occluded side (see :func:`.kernels.refine_cyclopean`).
    converged_px : float
        Largest accepted last Gauss-Newton step (a pixel that still moves is dropped).
    free_space_mm : float
        A point this far in front of the surface another pair's coarse
        matching sees along the same ray (the belt, say) is dropped.
    ring_pairs : bool
        Also match the rig's ring pairs (baselines along y), which see the walls
        facing +-x that the stereo pairs see at grazing angles, with a coarse
        search of their own in every pass.
    guided_ring_pairs : bool
        With a :class:`Guide`, also match the ring pairs, started from the
        guide's disparities instead of a coarse search (see :mod:`.guided`);
        ignored with ``ring_pairs``, which matches them in every pass.
    stride : int
        Refine every ``stride``-th column of the rectified left image (1: every pixel).
    row_stride : int
        Refine every ``row_stride``-th row of the rectified left image (1:
        every row); the rows between are filled from their measured
        neighbours. The windows span ``window`` rows, so the rows left out
        cost the averages at the comparison points little; the fitted pose,
        which rests on the bends and outlines, loses more.
    warp_passes : int
        Passes of warped refinement after the square-window one (0: none):
        windows whose disparity field bends or slopes are fitted again with
        the window warped by the field of the previous pass (see
        :func:`.warping.warped_passes`).
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
        Warped passes with a :class:`Guide` (instead of ``warp_passes``).
    guide_tolerance_px : float
        With a :class:`Guide`, a window follows the CAD's disparity field only
        where that is within this of the measured field at its centre (1 px is
        ~2 mm of depth: a pose error moves the field far less, a part that
        departs from its CAD more).
    shading : bool
        With a :class:`Guide`, a window that spans a bend also fits light that
        changes with the surface's slope across it (the sheen of bare metal,
        which each camera sees differently; see :mod:`.warping`).
    shading_bend : float
        A window spans a bend when the slope of the guide's disparity field
        (px/px) varies by more than this over it.
    sparse_rows : int
        A sparse first pass (:meth:`Reconstructor.match
        <inspection.reconstruct.Reconstructor.match>` with ``sparse=True``)
        gives points from every ``sparse_rows``-th rectified row only;
        :meth:`Reconstructor.sparse_cloud
        <inspection.reconstruct.Reconstructor.sparse_cloud>` matches those
        rows alone.
    sparse_cloud_warp_slope, sparse_cloud_warp_passes : float, int
        ``warp_slope`` and ``warp_passes`` of :meth:`Reconstructor.sparse_cloud
        <inspection.reconstruct.Reconstructor.sparse_cloud>`. That cloud
        places the part alone, with no guided pass after it to fit the
        windows on slopes to the surface's shape, so it warps the windows on
        gentler slopes than the first pass does, in one pass.
    threads : int
        Stereo pairs matched at once (one thread each, from the pool the
        :class:`Reconstructor` owns; 1: no pool, the pairs one after the other).
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
    row_stride: int = 1
    converged_px: float = 0.05
    symmetric: bool = False
    warp_passes: int = 2
    threads: int = 2
    sparse_rows: int = 4
    sparse_cloud_warp_slope: float = 0.02
    sparse_cloud_warp_passes: int = 1
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
            ("sparse_cloud_warp_passes", 5),
            ("guide_passes", 5),
            ("warp_iterations", 50),
            ("threads", 8),
            ("sparse_rows", 16),
            ("row_stride", 8),
        ):
            v = getattr(self, name)
            low = 0 if name in ("warp_passes", "sparse_cloud_warp_passes") else 1
            if not (isinstance(v, int) and low <= v <= top):
                raise InvalidInput(f"ReconstructParams.{name} must be an int in [{low}, {top}]")
        if self.sparse_rows % self.row_stride:
            raise InvalidInput(
                "ReconstructParams.sparse_rows must be a multiple of row_stride (the rows refined)"
            )
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
            "sparse_cloud_warp_slope",
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


__all__ = ["SATURATION_DN", "ReconstructParams"]
