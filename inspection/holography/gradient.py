"""The surface's gradient field from speckle displacements, and the coarse pose it gives.

**The gradient field.** Where the surface slopes, the two lasers' fields
differ by the phase difference ``dphi = 4 pi z / L`` (L the synthetic
wavelength), which varies across the field: locally, laser 2's field is laser
1's with the carrier ``-grad(dphi) / 2 pi``. Propagated to a plane ``dz`` out
of focus, a speckle pattern with a carrier moves by ``dz lambda`` times it
(the Fourier shift theorem on the angular spectrum), so laser 2's speckles
move against laser 1's by ``A(dz) = -2 dz (lambda / L) grad z``: proportional
to the distance to the focus plane, zero in it, and the phase gradient is what
generates the movement (a speckle pattern of a single laser, fully diffuse,
does not move: its light fills the aperture whatever the slope). Both fields
are propagated to several planes, correlated window by window
(:func:`~inspection.holography.correlation.correlate`), and the slope of
``A`` over the planes gives ``grad z`` per window. It is never wrapped: a tilt
of several phase intervals over the field is read as directly as a small one.

**Alignment to the CAD.** The CAD at a pose predicts the gradient (its
normals), averaged as the windows and the defocus average the measurement.
The part's two tilts add a constant to the gradient; an in-plane shift moves
the CAD's features (where its slope changes: a facet's rim), so the fit is
Gauss-Newton on ``g - G_cad(x - s) - t`` with Tukey weights (the steps' rims,
where a speckle sees both sides, and dents do not pull it), the CAD rendered
again at each update (ICP with the rendered CAD as the closest points).

*Regularisation*: a Tikhonov penalty on the pose's change from the start
(the prior: where the line put the part). The in-plane shift is observed
only through the CAD's slope features, weakly on a part with few (on a flat
part, not at all): without a prior its normal equations are near singular
and the shift would wander with the noise; the penalty holds an unobserved
direction at the start and is small against the data where the data tell.
A smoothness regularisation of integrating the gradients into heights would
not help here: a height offset is the one thing gradients do not carry, and
the CAD already supplies the shape between the windows.

The height is not fitted: the gradient field does not see it, nor does
anything else in an image-plane hologram of a diffuse surface under normal
illumination (a lift by one phase interval changes each laser's field by a
constant phase only; the head's depth of focus, ``lambda / NA^2``, is
hundreds of millimetres). The phase-based pose then fits the height within
the interval the start lies in.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.ndimage import gaussian_filter, map_coordinates

from ..arrays import Transform
from ..errors import InvalidInput
from .calibration import HoloCalibration
from .correlation import correlate
from .depth import depth_map
from .propagate import propagate

log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class GradientField:
    """The surface's slope per correlation window (head frame).

    Attributes
    ----------
    rows, cols : (m,) float64, px
        Window centres.
    gx, gy : (m,) float64
        ``dz/dx`` and ``dz/dy`` of the surface there.
    good : (m,) bool
        Windows that correlated in every plane.
    sigma_px : float
        How far (Gaussian sigma, px) the window and the defocus average the slope.
    """

    rows: F64
    cols: F64
    gx: F64
    gy: F64
    good: npt.NDArray[np.bool_]
    sigma_px: float


@dataclass(frozen=True)
class CoarsePose:
    """The pose from the gradient field: the fitted pose, the tilts (slopes) and the
    in-plane shift (mm) it found from the start, why it stopped, and on how many
    windows."""

    T_head_part: Transform
    slope: tuple[float, float]
    shift_mm: tuple[float, float]
    iterations: int
    converged: bool
    windows: int
    residual_rms: float


def gradient_field(
    calib: HoloCalibration,
    image: npt.ArrayLike,
    *,
    planes_mm: tuple[float, ...] = (-1000.0, 1000.0),
    window: int | None = None,
    min_peak: float = 0.5,
) -> GradientField:
    """The gradient field of the surface in ``image`` from the displacements between
    the two lasers' speckles in the planes ``planes_mm`` (at least two distinct).

    Far planes give large displacements but average the slope over a wider disc
    (``NA dz``); a thousand millimetres is a few speckles at this head's NA.
    """
    head = calib.head
    dz = np.asarray(planes_mm, dtype=np.float64)
    if dz.ndim != 1 or len(np.unique(dz)) < 2 or not np.all(np.isfinite(dz)):
        raise InvalidInput("planes_mm must hold at least two distinct finite planes")
    # A window of an eighth of the field: enough speckles to correlate, and enough
    # windows to see where the CAD's slope changes.
    window = window or max(16, head.pixels // 8 // 2 * 2)
    o1, o2 = calib.object_fields(image)
    x, y = head.grid()
    # The calibration's residual belongs to laser 2's field: O1 (O2 e^{im})* is the
    # phase difference that measures 4 pi z / L.
    o2 = o2 * np.exp(1j * calib.residual.phase(x, y))
    l1, l2 = head.wavelengths_mm
    dxs, dys, ok = [], [], None
    for d in dz:
        a = np.abs(propagate(o1, float(d), l1, head.pitch_mm)) ** 2
        b = np.abs(propagate(o2, float(d), l2, head.pitch_mm)) ** 2
        disp = correlate(a, b, window=window)
        dxs.append(disp.dx)
        dys.append(disp.dy)
        good = disp.good(min_peak=min_peak)
        ok = good if ok is None else ok & good
    assert ok is not None
    # Least-squares slope of A over the planes, per window: A = -2 dz (lambda / L) grad z.
    c = dz - dz.mean()
    to_slope = -head.synthetic_mm / (2.0 * l2) * head.pitch_mm / float(c @ c)
    gx = to_slope * (c @ np.array(dxs))
    gy = to_slope * (c @ np.array(dys))
    footprint = head.na * float(np.max(np.abs(dz))) / head.pitch_mm
    # A Hann-tapered window averages over a sigma of about 0.11 of its side; the
    # defocused field at a point gathers a disc of radius NA dz (sigma: half of it).
    sigma = math.hypot(0.11 * window, 0.5 * footprint)
    return GradientField(
        rows=disp.rows, cols=disp.cols, gx=gx, gy=gy, good=ok, sigma_px=float(sigma)
    )


def align_to_cad(
    gradients: GradientField,
    calib: HoloCalibration,
    mesh: object,
    T_head_part: Transform,
    *,
    sigma_slope: float = 0.1,
    sigma_shift_mm: float = 0.5,
    iterations: int = 6,
    edge_jump_mm: float = 0.02,
    fit_shift: bool = True,
) -> CoarsePose:
    """Fit the part's two tilts and in-plane shift to the gradient field.

    Parameters
    ----------
    gradients : GradientField, from :func:`gradient_field`
    calib : HoloCalibration (its head)
    mesh : the CAD, part frame, mm
    T_head_part : (4, 4) float64, the start
    sigma_slope, sigma_shift_mm : float
        The prior's spread: how far the start may be off in slope (dz/dx) and in
        shift (mm). The Tikhonov penalty is the change over these, squared.
    iterations : int
        CAD renderings at most.
    edge_jump_mm : float
        Height change between neighbouring CAD pixels that makes a step.
    fit_shift : bool
        Fit the in-plane shift too (else the tilts alone).
    """
    head = calib.head
    g = gradients
    if not (sigma_slope > 0 and sigma_shift_mm > 0 and iterations >= 1):
        raise InvalidInput("sigma_slope and sigma_shift_mm must be > 0, iterations >= 1")
    T = np.array(T_head_part, dtype=np.float64)
    coords = np.stack([g.rows, g.cols])
    prior = np.diag([1 / sigma_slope**2] * 2 + [1 / sigma_shift_mm**2] * 2)
    total = np.zeros(4)  # slope_x, slope_y, shift_x, shift_y from the start
    free = [0, 1, 2, 3] if fit_shift else [0, 1]
    converged = False
    used = 0
    rms = math.nan
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007
        depth = depth_map(head, mesh, T)
        hit = depth.hit.astype(np.float64)
        nz = np.where(depth.hit, depth.normals[..., 2], 1.0)
        grads = [np.where(depth.hit, -depth.normals[..., k] / nz, 0.0) for k in (0, 1)]
        cover = gaussian_filter(hit, g.sigma_px)
        smooth = [gaussian_filter(v, g.sigma_px) / np.maximum(cover, 1e-9) for v in grads]
        at = [map_coordinates(v, coords, order=1, mode="nearest") for v in smooth]
        # d G / d(x, y) in 1/mm: the CAD's slope features, what tells the shift.
        jac = [
            [
                map_coordinates(d, coords, order=1, mode="nearest") / head.pitch_mm
                for d in np.gradient(v)[::-1]  # (d/dx, d/dy)
            ]
            for v in smooth
        ]
        inside = map_coordinates(cover, coords, order=1, mode="nearest") > 0.95
        # Across a CAD step the phase difference jumps: a speckle straddling it moves
        # by nothing the slopes predict. Windows that see a step are left out.
        steps = gaussian_filter(depth.edges(edge_jump_mm, 0).astype(np.float64), g.sigma_px)
        clear = map_coordinates(steps, coords, order=1, mode="nearest") < 1e-3
        use = g.good & inside & clear
        used = int(use.sum())
        if used < 8:
            raise InvalidInput(f"only {used} gradient windows lie on the part: cannot align")
        m = used
        r = np.concatenate([g.gx[use] - at[0][use], g.gy[use] - at[1][use]])
        J = np.zeros((2 * m, 4))
        J[:m, 0] = 1.0
        J[m:, 1] = 1.0
        for k in (0, 1):  # shift s moves the CAD's slope map: G(x - s) = G - dG/dx s
            J[:m, 2 + k] = -jac[0][k][use]
            J[m:, 2 + k] = -jac[1][k][use]
        # Robust scale of the slope noise, then Tukey weights (IRLS).
        w = np.ones_like(r)
        step = np.zeros(4)
        for _ in range(5):
            res = r - J @ step
            scale = max(1.4826 * float(np.median(np.abs(res - np.median(res)))), 1e-4)
            u = res / (4.685 * scale)
            w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
            Jw = J * w[:, None]
            A = Jw.T @ J / scale**2 + prior
            step = np.zeros(4)
            step[free] = np.linalg.solve(
                A[np.ix_(free, free)], (Jw.T @ r / scale**2 - prior @ total)[free]
            )
        res = r - J @ step
        rms = float(np.sqrt(np.average(res**2, weights=np.maximum(w, 1e-12))))
        total += step
        log.debug("coarse pose iteration %d: step %s, rms %.4f", it, step, rms)
        T = _update(step) @ T
        if np.max(np.abs(step[:2])) < 1e-4 and np.max(np.abs(step[2:])) < 0.01:
            converged = True
            break
    log.debug("coarse pose: slope %s, shift %s mm, %d windows", total[:2], total[2:], used)
    return CoarsePose(
        T_head_part=T,
        slope=(float(total[0]), float(total[1])),
        shift_mm=(float(total[2]), float(total[3])),
        iterations=it,
        converged=converged,
        windows=used,
        residual_rms=rms,
    )


def _update(step: F64) -> Transform:
    """The rigid motion adding the slopes ``step[:2]`` to the surface (rotations about
    the head's y and x axes) and moving it by ``step[2:]`` mm in the head's plane."""
    ry = -math.atan(step[0])
    rx = math.atan(step[1])
    cx, sx, cy, sy = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    U = np.eye(4)
    U[:3, :3] = Rx @ Ry
    U[0, 3] = step[2]
    U[1, 3] = step[3]
    return U
