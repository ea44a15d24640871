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
   (:func:`~inspection.holography.unwrap.orders`).
5. **Deviations** along the CAD normal, ``(z - z_cad) n_z`` (exact on each
   planar facet), where measured.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy.ndimage import binary_dilation, gaussian_filter

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
    pose_iterations: int = 6
    pose_tolerance_um: float = 0.05
    tukey_mm: float = 0.02
    """Tukey's constant of the pose fit: deviations beyond it do not pull the pose."""
    coarse_pose: bool = False
    """First align the pose's tilts to the gradient field from the speckle displacements
    (:mod:`.gradient`): the phase-based pose alone fails from a start tilted by more than
    about two degrees. Off by default: a start from the line's registration is far
    closer, and the gradient field costs more than the rest of the measurement."""
    coarse_shift: bool = True
    """With ``coarse_pose``, find the in-plane shift first, from where the CAD's steps
    lower the phase difference's coherence."""

    def __post_init__(self) -> None:
        for name in ("smooth_speckles", "edge_jump_mm", "tukey_mm", "pose_tolerance_um"):
            if not getattr(self, name) > 0:
                raise InvalidInput(f"{name} must be > 0")
        if not 0 <= self.min_coherence < 1 or self.pose_iterations < 0:
            raise InvalidInput("min_coherence must be in [0, 1), pose_iterations >= 0")


@dataclass(frozen=True)
class FlaggedRegion:
    """A region deviating from the CAD by more than a quarter of the synthetic
    wavelength: its size, where it is, its order (how many phase intervals off)
    and the deviation the order suggests (an estimate, not a measurement)."""

    pixels: int
    area_mm2: float
    centroid_mm: tuple[float, float]
    order: int
    estimate_mm: float


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
    measured, flagged : (n, n) bool
        Where the shape is measured; where it is beyond the unwrapping limit.
    regions : the flagged regions, largest first.
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
    plane = np.zeros(3)  # dz, slope_x, slope_y of the prediction's correction
    converged = params.pose_iterations == 0
    iterations = 0
    for iterations in range(1, params.pose_iterations + 1):  # noqa: B007
        predicted = depth.height_mm + plane[0] + plane[1] * x + plane[2] * y
        residual, coherence = _residual(gamma, norm, predicted, scale, sigma)
        usable = ~edges & (coherence >= params.min_coherence)
        # Only the pixels of order 0 tell the pose: inside a region beyond the
        # limit the wrapped residual looks small and would pull it.
        o = orders(residual, usable, min_region_px=min_region)
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
    usable = ~depth.edges(params.edge_jump_mm, band) & (coherence >= params.min_coherence)
    t2 = time.perf_counter()
    timings["unwrap_ms"] = (t2 - t1) * 1e3 - timings.get("coarse_ms", 0.0)

    # 4. Orders: what lies beyond a quarter of the synthetic wavelength.
    o = orders(residual, usable, min_region_px=min_region)
    flagged = o.known & (o.order != 0)
    # A speckle straddling a region's rim mixes both orders: the rim, a speckle
    # wide, is not measured either.
    rim = binary_dilation(flagged, iterations=band) if flagged.any() else flagged
    measured = o.known & (o.order == 0) & ~rim
    regions = _regions(o, flagged, residual, scale, head.pitch_mm, x, y)

    # 5. Deviations along the normal.
    cad = depth.height_mm
    height = np.where(measured, cad + residual * scale, np.nan)
    deviation = (height - cad) * depth.normals[..., 2]
    timings["deviations_ms"] = (time.perf_counter() - t2) * 1e3
    timings["total_ms"] = (time.perf_counter() - t0) * 1e3
    log.debug("hologram measured: %d px, %d flagged regions", int(measured.sum()), len(regions))
    shape = HoloShape(
        height_mm=height,
        cad_height_mm=cad,
        deviation_mm=deviation,
        wrapped_phase=np.angle(_smooth(gamma, sigma)),
        coherence=coherence,
        measured=measured,
        flagged=flagged,
        regions=regions,
        T_head_part=T,
        pose_iterations=iterations,
        pose_converged=converged,
        calibration_id=calib.id,
        timings_ms=timings,
        limit_mm=head.synthetic_mm / 4.0,
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
    for label in np.unique(o.region[flagged]):
        sel = flagged & (o.region == label)
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
    return tuple(sorted(out, key=lambda r: -r.pixels))
