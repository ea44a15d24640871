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
The part's two tilts add a constant to it: robust least squares (Tukey
weights, so the dents do not pull) on ``g - G_cad - t``, with windows that
see a CAD step left out (there the phase difference jumps, and a speckle
straddling the jump moves by nothing the slopes predict), the CAD rendered
again at each update (ICP with the rendered CAD as the closest points).

**The in-plane shift** is not in the gradients of this part (its slope
changes only at its steps and at a facet's foot by the field's border, and
fitted there it is biased by a few tenths of a millimetre), but the steps
themselves are seen: the two lasers' speckles straddling a step differ by the
step's phase, so the phase difference's coherence drops along it. The shift
is where the measured incoherence correlates best with the CAD's step map
(:func:`step_shift`).

*Regularisation*: a Tikhonov penalty on the tilts' change from the start
(the prior: where the line put the part), and the shift's search bounded to
three of its prior sigmas. The tilts are observed by every window that lies
on the part away from a step; on a part that is mostly steps few are left,
the normal equations lose rank and the penalty keeps the start instead. The
bound keeps a CAD whose steps repeat from sending the part a period away. A
smoothness regularisation of integrating the gradients into heights would
not help: a height offset is the one thing gradients do not carry, and the
CAD already supplies the shape between the windows.

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
from .head import HoloHead
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
    """The coarse pose: the fitted pose, the tilts (slopes added, dz/dx and dz/dy) and
    the in-plane shift (mm, from the steps) it found from the start, whether the tilts'
    fit converged in how many CAD renderings, on how many windows, and their slope
    residual's RMS."""

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
    passes: int = 1,
) -> GradientField:
    """The gradient field of the surface in ``image`` from the displacements between
    the two lasers' speckles in the planes ``planes_mm`` (at least two distinct).

    Far planes give large displacements but average the slope over a wider disc
    (``NA dz``); a thousand millimetres is a few speckles at this head's NA. One
    refinement pass of the correlation (``passes``) is enough for a coarse pose: the
    whole-pixel pull of the later ones' subject is a small fraction of a pixel here,
    a slope of a few 1e-4.
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
        disp = correlate(a, b, window=window, passes=passes)
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
    iterations: int = 6,
    edge_jump_mm: float = 0.02,
) -> tuple[Transform, tuple[float, float], int, bool, int, float]:
    """Fit the part's two tilts to the gradient field.

    Parameters
    ----------
    gradients : GradientField, from :func:`gradient_field`
    calib : HoloCalibration (its head)
    mesh : the CAD, part frame, mm
    T_head_part : (4, 4) float64, the start
    sigma_slope : float
        The prior's spread: how far the start may be off in slope (dz/dx); the
        Tikhonov penalty is the change over it, squared.
    iterations : int
        CAD renderings at most.
    edge_jump_mm : float
        Height change between neighbouring CAD pixels that makes a step.

    Returns
    -------
    T_head_part, (slope_x, slope_y) added, iterations, converged, windows used,
    the slope residual's RMS.
    """
    head = calib.head
    g = gradients
    if not (sigma_slope > 0 and iterations >= 1):
        raise InvalidInput("sigma_slope must be > 0, iterations >= 1")
    T = np.array(T_head_part, dtype=np.float64)
    coords = np.stack([g.rows, g.cols])
    prior = np.eye(2) / sigma_slope**2
    total = np.zeros(2)
    converged = False
    used = 0
    rms = math.nan
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007
        depth = depth_map(head, mesh, T)
        nz = np.where(depth.hit, depth.normals[..., 2], 1.0)
        cover = _blur_at(depth.hit.astype(np.float64), g.sigma_px, coords)
        at = [
            _blur_at(np.where(depth.hit, -depth.normals[..., k] / nz, 0.0), g.sigma_px, coords)
            / np.maximum(cover, 1e-9)
            for k in (0, 1)
        ]
        # Across a CAD step the phase difference jumps: a speckle straddling it moves
        # by nothing the slopes predict. Windows that see a step are left out.
        steps = _blur_at(depth.edges(edge_jump_mm, 0).astype(np.float64), g.sigma_px, coords)
        use = g.good & (cover > 0.95) & (steps < 1e-3)
        used = int(use.sum())
        if used < 8:
            raise InvalidInput(f"only {used} gradient windows lie on the part: cannot align")
        r = np.concatenate([g.gx[use] - at[0][use], g.gy[use] - at[1][use]])
        J = np.zeros((2 * used, 2))
        J[:used, 0] = 1.0
        J[used:, 1] = 1.0
        # Robust scale of the slope noise, then Tukey weights (IRLS); the prior enters
        # the normal equations as the Tikhonov term.
        w = np.ones_like(r)
        step = np.zeros(2)
        for _ in range(5):
            res = r - J @ step
            scale = max(1.4826 * float(np.median(np.abs(res - np.median(res)))), 1e-4)
            u = res / (4.685 * scale)
            w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
            Jw = J * w[:, None]
            step = np.linalg.solve(Jw.T @ J / scale**2 + prior, Jw.T @ r / scale**2 - prior @ total)
        res = r - J @ step
        rms = float(np.sqrt(np.average(res**2, weights=np.maximum(w, 1e-12))))
        total += step
        log.debug("coarse tilt iteration %d: step %s, rms %.4f", it, step, rms)
        T = _update(np.array([step[0], step[1], 0.0, 0.0])) @ T
        if np.max(np.abs(step)) < 1e-4:
            converged = True
            break
    return T, (float(total[0]), float(total[1])), it, converged, used, rms


def _blur_at(image: F64, sigma: float, coords: F64) -> F64:
    """``image`` averaged by a Gaussian of ``sigma`` px, at the points ``coords`` (2, m)
    (rows, columns). The average is smooth on the scale of sigma: block means of a third
    of it first (their own spread, a ninth of sigma squared over 12, is negligible)
    make the filter cheap."""
    k = max(1, int(sigma / 3.0))
    n0, n1 = (d // k * k for d in image.shape)
    blocks = image[:n0, :n1].reshape(n0 // k, k, n1 // k, k).mean(axis=(1, 3))
    smooth = gaussian_filter(blocks, sigma / k)
    return map_coordinates(smooth, (coords - (k - 1) / 2.0) / k, order=1, mode="nearest")


def step_shift(
    calib: HoloCalibration,
    image: npt.ArrayLike,
    mesh: object,
    T_head_part: Transform,
    *,
    sigma_shift_mm: float = 0.5,
    smooth_speckles: float = 0.5,
    edge_jump_mm: float = 0.02,
) -> tuple[float, float] | None:
    """The part's in-plane shift (x, y mm, head frame) from where its steps are, or
    None when the CAD has no step in the field.

    A speckle straddling a step sees both sides, whose phase differences differ by
    the step's ``4 pi h / L``: the phase difference's coherence (its complex mean
    over ``smooth_speckles`` against the mean of its modulus) drops along every step
    not a whole number of intervals high. The CAD at the pose predicts the steps
    and how much each lowers the coherence;
    the shift is the peak of the cross-correlation of the measured incoherence with
    the predicted step map, blurred alike, refined by a parabola. The search is
    limited to three ``sigma_shift_mm`` (the prior: where the line put the part), so
    that a CAD whose steps repeat cannot send the part a period away.
    """
    head = calib.head
    if not sigma_shift_mm > 0:
        raise InvalidInput("sigma_shift_mm must be > 0")
    sigma = smooth_speckles * head.speckle_mm / head.pitch_mm
    gamma = calib.difference(image)
    mean = gaussian_filter(gamma.real, sigma) + 1j * gaussian_filter(gamma.imag, sigma)
    incoherence = 1.0 - np.abs(mean) / np.maximum(gaussian_filter(np.abs(gamma), sigma), 1e-300)
    depth = depth_map(head, mesh, T_head_part)
    template = gaussian_filter(_step_weights(depth.height_mm, edge_jump_mm, head), sigma)
    if template.std() < 1e-6 or not depth.hit.any():
        return None
    # A slope lowers the coherence a little all over (its phase varies within the
    # average): a facet beside a step would pull the step towards itself. The local
    # background, over a few times the average, is taken off both maps.
    incoherence = incoherence - gaussian_filter(incoherence, 3.0 * sigma, mode="wrap")
    template = template - gaussian_filter(template, 3.0 * sigma, mode="wrap")
    n = head.pixels
    corr = np.fft.irfft2(
        np.fft.rfft2(incoherence) * np.conj(np.fft.rfft2(template)),
        s=(n, n),
    )
    corr = np.fft.fftshift(corr)  # zero shift at (n/2, n/2)
    f = np.arange(n, dtype=np.float64) - n // 2
    reach = 3.0 * sigma_shift_mm / head.pitch_mm
    corr = np.where(f[:, None] ** 2 + f[None, :] ** 2 <= reach**2, corr, -np.inf)
    i, j = np.unravel_index(int(np.argmax(corr)), corr.shape)

    def vertex(cm: float, c0: float, cp: float) -> float:
        den = cm - 2.0 * c0 + cp
        return 0.0 if not np.isfinite(den) or den >= 0 else 0.5 * (cm - cp) / den

    di = vertex(corr[i - 1, j], corr[i, j], corr[(i + 1) % n, j])
    dj = vertex(corr[i, j - 1], corr[i, j], corr[i, (j + 1) % n])
    return (float(f[j] + dj) * head.pitch_mm, float(f[i] + di) * head.pitch_mm)


def _step_weights(height: F64, jump_mm: float, head: HoloHead) -> F64:
    """Per pixel, how much a step beside it lowers the coherence: two equal halves of a
    speckle whose phase differences differ by ``d = 4 pi h / L`` average to
    ``|cos(d / 2)|``, so a step weighs ``1 - |cos(2 pi h / L)|`` (nothing for a step of
    whole intervals); the part's outline weighs 1."""
    out = np.zeros(height.shape)
    for axis in (0, 1):
        d = np.abs(np.diff(height, axis=axis))
        w = np.where(np.isfinite(d), 1.0 - np.abs(np.cos(2.0 * np.pi * d / head.synthetic_mm)), 1.0)
        w = np.where(np.isfinite(d) & (d <= jump_mm), 0.0, w)
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis] = slice(None, -1)
        hi[axis] = slice(1, None)
        out[tuple(lo)] = np.maximum(out[tuple(lo)], w)
        out[tuple(hi)] = np.maximum(out[tuple(hi)], w)
    return np.where(np.isfinite(height), out, 0.0)


def coarse_pose(
    calib: HoloCalibration,
    image: npt.ArrayLike,
    mesh: object,
    T_head_part: Transform,
    *,
    shift: bool = True,
    edge_jump_mm: float = 0.02,
) -> CoarsePose:
    """The pose's in-plane shift from the steps (:func:`step_shift`, if ``shift``), then
    its tilts from the gradient field (:func:`gradient_field`, :func:`align_to_cad`)."""
    T = np.array(T_head_part, dtype=np.float64)
    moved = step_shift(calib, image, mesh, T, edge_jump_mm=edge_jump_mm) if shift else None
    if moved is not None:
        T = _update(np.array([0.0, 0.0, *moved])) @ T
    T, slope, it, converged, used, rms = align_to_cad(
        gradient_field(calib, image), calib, mesh, T, edge_jump_mm=edge_jump_mm
    )
    log.debug("coarse pose: shift %s mm, slope %s, %d windows", moved, slope, used)
    return CoarsePose(
        T_head_part=T,
        slope=slope,
        shift_mm=moved or (0.0, 0.0),
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
