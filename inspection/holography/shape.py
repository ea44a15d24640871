"""The shape of a part from one hologram, against its CAD.

``measure_shape`` reads like the method:

1. **Phase difference**: both lobes cut and corrected by the calibration,
   ``O1 O2*`` (phase ``4 pi z / L``).
2. **Against the CAD**: the CAD at the pose predicts ``z_cad``; the product
   ``O1 O2* exp(-i 4 pi z_cad / L)`` holds only the deviation's phase, which
   is continuous across the CAD's steps, so it can be averaged over a speckle
   or so (amplitude-weighted complex mean) without mixing the two sides of a
   step. Pixels next to the CAD's edges (where a speckle sees both sides) and
   of low coherence are left out.
3. **The pose, iterated**: optionally first the in-plane shift from the
   steps and the tilts from the unwrapped gradient field of the speckle
   displacements (:mod:`.gradient`); then the part's out-of-plane pose (height and two
   tilts) is fitted to the deviation's phase by robust least squares (Tukey
   weights, so dents do not pull it), the prediction redone, until the update
   stops moving; then the CAD is rendered again at the fitted pose.
4. **Orders**: regions that 2 pi jumps separate from the main field deviate
   by more than a quarter of the synthetic wavelength: flagged, not measured,
   nor is their rim, a speckle wide
   (:func:`~inspection.holography.unwrap.orders`). So is a region that
   unmeasurable pixels cut off from the rest of its CAD surface (a steep
   dent's core inside the ring its flank blurs out): its order is unknown,
   and the deviation may exceed the range. An unmeasurable area of a CAD
   surface, away from its edges and larger than speckle noise leaves, is
   reported as well: inside a surface, what the CAD's prediction leaves of
   the phase turns that fast only on a steep deviation, and the path that
   its order would be read along is missing.
5. **Deviations** along the CAD normal, ``(z - z_cad) n_z`` (exact on each
   planar facet), where measured, with each pixel's standard uncertainty
   from its coherence. Measured regions whose height lies within their
   expanded uncertainty of the limit are reported too: a phase that close
   to pi may as well be one order further. The aperture and the average
   blur a dent's bottom shallower than it is: to second order a Gaussian
   blur of variance ``s^2`` adds ``s^2 / 2`` times the Laplacian, which the
   check takes back before comparing with the limit, counting the
   correction's size as uncertain too.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.ndimage import (
    binary_closing,
    binary_dilation,
    binary_fill_holes,
    gaussian_filter,
    label,
)

from ..arrays import Transform
from ..errors import InvalidInput
from .calibration import HoloCalibration
from .depth import depth_map
from .gradient import CoarsePose, coarse_pose
from .unwrap import Orders, orders

log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ShapeParams:
    """How to measure a shape. Lengths relative to the speckle are in mean speckle
    diameters of the head."""

    smooth_speckles: float = 0.5
    """Sigma of the Gaussian complex average of the deviation's phase."""
    min_coherence: float = 0.5
    """Least coherence (|mean| / mean |.|) of that average for a pixel to count."""
    edge_jump_mm: float = 0.02
    """Height change between neighbouring CAD pixels that makes an edge."""
    edge_band_speckles: float = 1.0
    """Pixels this close to a CAD edge are not measured."""
    min_region_speckles: float = 1.0
    """Regions smaller than this many speckle areas are noise, not deviations."""
    phase_samples: float = 20.0
    """Independent samples of the phase difference that the average holds, for each
    pixel's standard uncertainty: the phase spread ``sqrt(-2 ln coherence)`` (the spread
    that leaves that mean resultant length) over its square root. The speckle's phase
    noise is finer than the speckle (dark spots), so there are more than the average
    holds speckles."""
    min_hole_speckles: float = 2.0
    """An unmeasurable area of a CAD surface (away from its edges) of this many speckle
    areas is reported: speckle noise leaves smaller ones."""
    limit_coverage: float = 2.0
    """Coverage factor of the uncertainty against the range's limit: a measured height
    (its blur taken back) within this many standard uncertainties (the phase's and the
    blur correction's) of a quarter of the synthetic wavelength is reported as possibly
    beyond it."""
    pose_iterations: int = 6
    pose_tolerance_um: float = 0.05
    tukey_mm: float = 0.02
    """Tukey's constant of the pose fit: deviations beyond it do not pull the pose."""
    coarse_pose: bool = False
    """First align the pose's tilts to the gradient field from the speckle displacements
    (:mod:`.gradient`): the phase-based pose alone fails from a start tilted by more than
    about two degrees. Off here, for a caller whose start is known to be closer (it costs
    about as much as the rest of the measurement); the line's stations turn it on
    (``[holography] coarse_pose``), and it changes nothing for a well-placed part."""
    coarse_shift: bool = True
    """With ``coarse_pose``, find the in-plane shift first, from where the CAD's steps
    lower the phase difference's coherence."""

    def __post_init__(self) -> None:
        for name in (
            "smooth_speckles",
            "edge_jump_mm",
            "tukey_mm",
            "pose_tolerance_um",
            "phase_samples",
            "min_hole_speckles",
        ):
            if not getattr(self, name) > 0:
                raise InvalidInput(f"{name} must be > 0")
        if not 0 <= self.min_coherence < 1 or self.pose_iterations < 0:
            raise InvalidInput("min_coherence must be in [0, 1), pose_iterations >= 0")
        if not self.limit_coverage >= 0:
            raise InvalidInput("limit_coverage must be >= 0")


RegionKind = Literal["beyond", "unknown_order", "unmeasured", "at_limit"]


@dataclass(frozen=True)
class FlaggedRegion:
    """A region that may deviate from the CAD by more than a quarter of the synthetic
    wavelength: its size and where it is (head frame), and why.

    ``kind``:

    - ``"beyond"``: 2 pi jumps separate it from its surface's main region; ``order``
      (how many phase intervals off) is known, ``estimate_mm`` the height deviation
      it suggests (an estimate, not a measurement). Not measured.
    - ``"unknown_order"``: unmeasurable pixels cut it off from the rest of its CAD
      surface; ``order`` is None and ``estimate_mm`` NaN. Not measured.
    - ``"unmeasured"``: an area of a CAD surface, away from its edges, that is not
      measured; ``order`` is None and ``estimate_mm`` NaN.
    - ``"at_limit"``: measured in order 0, but its height deviation ``estimate_mm``
      (the largest, its blur taken back) lies within its expanded uncertainty of the
      limit.
    """

    pixels: int
    area_mm2: float
    centroid_mm: tuple[float, float]
    order: int | None
    estimate_mm: float
    kind: RegionKind = "beyond"


@dataclass(frozen=True)
class HoloShape:
    """One hologram measured against the CAD (head frame, mm).

    Attributes
    ----------
    height_mm : (n, n) float64
        Measured z; NaN where not measured.
    cad_height_mm : (n, n) float64
        The CAD's z at the fitted pose.
    deviation_mm : (n, n) float64
        Deviation along the CAD normal; NaN where not measured.
    wrapped_phase : (n, n) float64
        The phase difference, averaged as in step 2, wrapped (rad).
    coherence : (n, n) float64
    uncertainty_mm : (n, n) float64
        Standard uncertainty of each measured pixel's height; NaN where not measured.
    measured, flagged : (n, n) bool
        Where the shape is measured; where it is not, being beyond the unwrapping
        limit or of unknown order.
    regions : the regions beyond, of unknown order and at the limit, largest first.
    T_head_part : (4, 4) float64, the fitted pose.
    pose_iterations : int; pose_converged : bool
    calibration_id : str
    limit_mm : float
    timings_ms : per stage
    """

    height_mm: F64
    cad_height_mm: F64
    deviation_mm: F64
    wrapped_phase: F64
    coherence: F64
    uncertainty_mm: F64
    measured: npt.NDArray[np.bool_]
    flagged: npt.NDArray[np.bool_]
    regions: tuple[FlaggedRegion, ...]
    T_head_part: Transform
    pose_iterations: int
    pose_converged: bool
    calibration_id: str
    limit_mm: float
    """The largest deviation the CAD-based unwrapping tells: a quarter of the
    synthetic wavelength."""
    timings_ms: dict[str, float] = field(default_factory=dict)
    coarse: CoarsePose | None = None
    """The pose from the gradient field, when ``ShapeParams.coarse_pose`` asked for it."""


def measure_shape(
    calib: HoloCalibration,
    image: npt.ArrayLike,
    mesh: object,
    T_head_part: Transform,
    params: ShapeParams | None = None,
) -> HoloShape:
    """Measure the part in ``image`` against its CAD ``mesh`` near the pose ``T_head_part``.

    Parameters
    ----------
    calib : HoloCalibration
    image : (n, n) integer or float hologram
    mesh : trimesh mesh (or vertices and faces), part frame, mm
    T_head_part : (4, 4) float64
        The pose the part is known to lie at, to well within a quarter of the
        synthetic wavelength in height.
    params : ShapeParams, optional
    """
    params = params or ShapeParams()
    head = calib.head
    scale = head.synthetic_mm / (4.0 * np.pi)  # mm of height per rad of phase difference
    speckle_px = head.speckle_mm / head.pitch_mm
    sigma = params.smooth_speckles * speckle_px
    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    # 1. The phase difference.
    gamma = calib.difference(image)
    norm = gaussian_filter(np.abs(gamma), sigma)
    t1 = time.perf_counter()
    timings["phase_ms"] = (t1 - t0) * 1e3

    # 2-3. Against the CAD, the pose iterated; the tilts first from the gradient field.
    T = np.array(T_head_part, dtype=np.float64)
    coarse = None
    if params.coarse_pose:
        coarse = coarse_pose(
            calib, image, mesh, T, shift=params.coarse_shift, edge_jump_mm=params.edge_jump_mm
        )
        T = coarse.T_head_part
        timings["coarse_ms"] = (time.perf_counter() - t1) * 1e3
    depth = depth_map(head, mesh, T)
    x, y = head.grid()
    band = max(1, int(round(params.edge_band_speckles * speckle_px)))
    min_region = max(4, int(params.min_region_speckles * np.pi / 4.0 * speckle_px**2))
    edges = depth.edges(params.edge_jump_mm, band)
    groups = _surfaces(edges)
    plane = np.zeros(3)  # dz, slope_x, slope_y of the prediction's correction
    converged = params.pose_iterations == 0
    iterations = 0
    for iterations in range(1, params.pose_iterations + 1):  # noqa: B007
        predicted = depth.height_mm + plane[0] + plane[1] * x + plane[2] * y
        residual, coherence = _residual(gamma, norm, predicted, scale, sigma)
        usable = ~edges & (coherence >= params.min_coherence)
        # Only the pixels of order 0 tell the pose: inside a region beyond the
        # limit the wrapped residual looks small and would pull it.
        o = orders(residual, usable, min_region_px=min_region, groups=groups)
        fit = o.known & (o.order == 0)
        step = _fit_plane(residual[fit] * scale, x[fit], y[fit], params.tukey_mm)
        plane += step
        if (
            abs(step[0]) * 1e3 < params.pose_tolerance_um
            and np.max(np.abs(step[1:])) * head.field_mm * 1e3 < params.pose_tolerance_um
        ):
            converged = True
            break
    T = _pose_update(plane) @ T
    depth = depth_map(head, mesh, T)
    residual, coherence = _residual(gamma, norm, depth.height_mm, scale, sigma)
    edges = depth.edges(params.edge_jump_mm, band)
    usable = ~edges & (coherence >= params.min_coherence)
    t2 = time.perf_counter()
    timings["unwrap_ms"] = (t2 - t1) * 1e3 - timings.get("coarse_ms", 0.0)

    # 4. Orders: what lies beyond a quarter of the synthetic wavelength, and what
    # unmeasurable pixels cut off so that its order is unknown.
    o = orders(residual, usable, min_region_px=min_region, groups=_surfaces(edges))
    beyond = o.known & (o.order != 0)
    flagged = beyond | o.unreached
    # A speckle straddling a region's rim mixes both orders: the rim, a speckle
    # wide, is not measured either.
    rim = binary_dilation(flagged, iterations=band) if flagged.any() else flagged
    measured = o.known & (o.order == 0) & ~rim

    min_hole = max(4, int(params.min_hole_speckles * np.pi / 4.0 * speckle_px**2))
    holes, holed, enclosed = _holes(
        ~edges & ~o.known & ~o.unreached, flagged, min_hole, band, head.pitch_mm, x, y
    )
    flagged |= enclosed
    # The phase next to such a hole turns nearly as fast: its rim is not measured either.
    measured &= ~binary_dilation(holed, iterations=band) if holed.any() else ~holed

    # 5. Deviations along the normal, and what lies within its uncertainty of the limit.
    cad = depth.height_mm
    height = np.where(measured, cad + residual * scale, np.nan)
    deviation = (height - cad) * depth.normals[..., 2]
    spread = np.sqrt(-2.0 * np.log(np.clip(coherence, 1e-12, 1.0)))
    uncertainty = np.where(measured, scale * spread / math.sqrt(params.phase_samples), np.nan)
    limit = head.synthetic_mm / 4.0
    # The blur: the average's Gaussian and the aperture's (an Airy spot's intensity,
    # sigma 0.21 lambda / NA), in pixels squared.
    blur = sigma**2 + (0.21 * head.wavelength_mm / head.na / head.pitch_mm) ** 2
    # The Laplacian averaged over half the phase's sigma: enough against its noise, and
    # less blurred again than over the whole. Measured on the blurred surface, it falls
    # short of the true one on a dent a few blurs wide: the correction is uncertain by
    # its own size.
    correction = 0.5 * blur * _laplacian(residual, measured, 0.5 * sigma) * scale
    unblurred = residual * scale - correction
    spread_mm = np.hypot(uncertainty, correction)
    near = measured & (np.abs(unblurred) + params.limit_coverage * spread_mm >= limit)
    regions = (
        _regions(o, beyond, residual, scale, head.pitch_mm, x, y)
        + _cut_off(o.unreached, head.pitch_mm, x, y)
        + holes
        + _at_limit(near, min_region, unblurred, head.pitch_mm, x, y)
    )
    regions = tuple(sorted(regions, key=lambda r: -r.pixels))
    timings["deviations_ms"] = (time.perf_counter() - t2) * 1e3
    timings["total_ms"] = (time.perf_counter() - t0) * 1e3
    log.debug("hologram measured: %d px, %d regions reported", int(measured.sum()), len(regions))
    shape = HoloShape(
        height_mm=height,
        cad_height_mm=cad,
        deviation_mm=deviation,
        wrapped_phase=np.angle(_smooth(gamma, sigma)),
        coherence=coherence,
        uncertainty_mm=uncertainty,
        measured=measured,
        flagged=flagged,
        regions=regions,
        T_head_part=T,
        pose_iterations=iterations,
        pose_converged=converged,
        calibration_id=calib.id,
        timings_ms=timings,
        limit_mm=limit,
        coarse=coarse,
    )
    return shape


def _smooth(z: npt.NDArray[np.complex128], sigma: float) -> npt.NDArray[np.complex128]:
    return gaussian_filter(z.real, sigma) + 1j * gaussian_filter(z.imag, sigma)


def _residual(
    gamma: npt.NDArray[np.complex128], norm: F64, predicted: F64, scale: float, sigma: float
) -> tuple[F64, F64]:
    """The deviation's phase (the CAD's prediction removed, then averaged) and its
    coherence, per pixel; off the CAD, phase 0 and coherence 0."""
    on = np.isfinite(predicted)
    demodulated = np.where(on, gamma * np.exp(-1j * np.where(on, predicted, 0.0) / scale), 0.0)
    mean = _smooth(demodulated, sigma)
    coherence = np.abs(mean) / np.maximum(norm, 1e-300)
    return np.where(on, np.angle(mean), 0.0), np.where(on, coherence, 0.0)


def _fit_plane(dz: F64, x: F64, y: F64, c: float) -> F64:
    """Robust fit of ``dz ~ p0 + p1 x + p2 y`` (IRLS with Tukey's biweight, constant c)."""
    if len(dz) < 3:
        raise InvalidInput("too few measurable pixels to fit the pose")
    A = np.stack([np.ones_like(x), x, y], axis=1)
    w = np.ones_like(dz)
    p: F64 = np.zeros(3)
    for _ in range(10):
        Aw = A * w[:, None]
        p = np.asarray(np.linalg.solve(Aw.T @ A + 1e-12 * np.eye(3), Aw.T @ dz), np.float64)
        u = (dz - A @ p) / c
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        if w.sum() < 3:
            break
    return np.asarray(p, dtype=np.float64)


def _pose_update(plane: F64) -> Transform:
    """The small rigid motion whose height change is ``p0 + p1 x + p2 y``: a lift of p0
    and rotations about the head's y axis (by -p1) and x axis (by p2)."""
    ry = -math.atan(plane[1])
    rx = math.atan(plane[2])
    cx, sx, cy, sy = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    T = np.eye(4)
    T[:3, :3] = Rx @ Ry
    T[2, 3] = plane[0]
    return T


def _regions(
    o: Orders,
    flagged: npt.NDArray[np.bool_],
    residual: F64,
    scale: float,
    pitch: float,
    x: F64,
    y: F64,
) -> tuple[FlaggedRegion, ...]:
    out = []
    for region in np.unique(o.region[flagged]):
        sel = flagged & (o.region == region)
        k = int(np.bincount(o.order[sel] - o.order[sel].min()).argmax() + o.order[sel].min())
        est = (residual[sel] + 2.0 * np.pi * k) * scale
        out.append(
            FlaggedRegion(
                pixels=int(sel.sum()),
                area_mm2=float(sel.sum()) * pitch * pitch,
                centroid_mm=(float(x[sel].mean()), float(y[sel].mean())),
                order=k,
                estimate_mm=float(est[np.argmax(np.abs(est))]),
            )
        )
    return tuple(out)


def _surfaces(edges: npt.NDArray[np.bool_]) -> npt.NDArray[np.int64]:
    """Each piece of CAD surface that no CAD edge cuts, labelled (4-connected, as the
    orders' graph); -1 on the edges and off the part."""
    labels, _ = label(~edges)
    return np.asarray(labels, dtype=np.int64) - 1


def _components(mask: npt.NDArray[np.bool_], min_px: int) -> list[npt.NDArray[np.bool_]]:
    labels, count = label(mask)
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    return [labels == k for k in range(1, count + 1) if sizes[k] >= min_px]


def _laplacian(phase: F64, where: npt.NDArray[np.bool_], sigma: float) -> F64:
    """The Laplacian of a wrapped phase (rad per pixel squared) from its wrapped
    differences where all five pixels of the stencil are in ``where``, averaged over
    ``sigma`` (normalised: pixels without one count for nothing); 0 where none is near."""
    lap = np.zeros(phase.shape)
    ok = np.zeros(phase.shape, dtype=bool)
    c = (slice(1, -1), slice(1, -1))
    for axis in (0, 1):
        d = np.angle(np.exp(1j * np.diff(phase, axis=axis)))
        second = np.diff(d, axis=axis)
        lap[c] += second[:, 1:-1] if axis == 0 else second[1:-1, :]
    ok[c] = (
        where[1:-1, 1:-1] & where[:-2, 1:-1] & where[2:, 1:-1] & where[1:-1, :-2] & where[1:-1, 2:]
    )
    weight = gaussian_filter(ok.astype(np.float64), sigma)
    mean = gaussian_filter(np.where(ok, lap, 0.0), sigma)
    return np.where(weight > 1e-3, mean / np.maximum(weight, 1e-3), 0.0)


def _cut_off(
    unreached: npt.NDArray[np.bool_], pitch: float, x: F64, y: F64
) -> tuple[FlaggedRegion, ...]:
    return tuple(_unknown(sel, "unknown_order", pitch, x, y) for sel in _components(unreached, 1))


def _holes(
    hole: npt.NDArray[np.bool_],
    flagged: npt.NDArray[np.bool_],
    min_px: int,
    band: int,
    pitch: float,
    x: F64,
    y: F64,
) -> tuple[tuple[FlaggedRegion, ...], npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """The unmeasured areas of the CAD's surfaces that no flagged region explains (the
    flank around a region beyond the range is unmeasured too), each with what it
    encloses but for a neck narrower than ``2 band`` px: a measured island that only
    such a neck joins to the rest has its order carried along a path a speckle or so
    wide, through the hole's edge, where nothing vouches for it. Returns the regions,
    their pixels and the enclosed ones."""
    near = binary_dilation(flagged, iterations=band + 1) if flagged.any() else flagged
    out = []
    holed = np.zeros(hole.shape, dtype=bool)
    enclosed = np.zeros(hole.shape, dtype=bool)
    for sel in _components(hole, min_px):
        if (sel & near).any():
            continue
        closed = binary_fill_holes(binary_closing(sel, iterations=band, border_value=0))
        inside = np.asarray(closed, dtype=bool) & ~sel & ~hole
        enclosed |= inside
        holed |= sel | inside
        out.append(_unknown(sel | inside, "unmeasured", pitch, x, y))
    return tuple(out), holed, enclosed


def _unknown(
    sel: npt.NDArray[np.bool_], kind: RegionKind, pitch: float, x: F64, y: F64
) -> FlaggedRegion:
    return FlaggedRegion(
        pixels=int(sel.sum()),
        area_mm2=float(sel.sum()) * pitch * pitch,
        centroid_mm=(float(x[sel].mean()), float(y[sel].mean())),
        order=None,
        estimate_mm=math.nan,
        kind=kind,
    )


def _at_limit(
    near: npt.NDArray[np.bool_], min_px: int, dz: F64, pitch: float, x: F64, y: F64
) -> tuple[FlaggedRegion, ...]:
    out = []
    for sel in _components(near, min_px):
        d = dz[sel]
        out.append(
            FlaggedRegion(
                pixels=int(sel.sum()),
                area_mm2=float(sel.sum()) * pitch * pitch,
                centroid_mm=(float(x[sel].mean()), float(y[sel].mean())),
                order=0,
                estimate_mm=float(d[np.argmax(np.abs(d))]),
                kind="at_limit",
            )
        )
    return tuple(out)
