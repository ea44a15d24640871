"""Rectified stereo pairs of the rig: geometry, coarse matching and sub-pixel refinement.

Internal module of :mod:`inspection.reconstruct`; callers are trusted.

Rectification is chosen for this rig, not left to ``cv2.stereoRectify``: both
rectified cameras of a pair look straight down at the belt (the rectified z
axis is the rig's -z made orthogonal to the baseline). A horizontal surface
then has one disparity everywhere in the image, so the disparity range that
SGBM must search is set by the heights in the measurement volume alone
(``d = f B / Z``) and does not grow with the convergence of the cameras. The
principal points of the two rectified images are shifted so that the volume
fills both and its disparities are small numbers.

Refinement is a Lucas-Kanade (Gauss-Newton) fit of each pixel's own window,
with a gain and an offset, on images normalised by their local mean and
contrast, so that the different brightness of the metal seen from two sides
does not bias the match. A dense variant that aggregates per-pixel updates
with box filters (one ``cv2.remap`` per iteration for the whole field) was
tried first: it is not a consistent model (neighbours shift by different
amounts) and its iteration amplifies the frequencies where the box filter's
response is negative, so it did not converge below ~0.1 px.

Where the surface bends or slopes inside a window, :func:`refine_warped`
fits the window again warped by the disparity field found so far.

**Interpolation.** The right image is sampled between its pixels by a cubic
B-spline through them (its coefficients along the rows: :func:`spline_rows`).
Any interpolator smooths the image by an amount that depends on where between
two pixels it samples, and the fit then prefers the disparities whose
fraction the smoothing favours: the "pixel locking" of window matchers. With
Catmull-Rom's cubic convolution the disparity came out biased by up to
0.014 px on clean rendered speckle (0.02 px with the simulator's faults),
as a sine of the disparity's fraction; over a flat region the fraction
changes slowly, so a comparison point's whole support radius took the same
bias, ~0.03 mm. The B-spline's response is much flatter: 0.003 px
(0.008 px with the faults). The coefficients cost one recursive filter pass
per row; the kernels' cost is the same (four taps either way).

The kernels run on one thread each (no ``prange``): the caller matches the
two stereo pairs on two threads, which uses both cores without nesting
numba's parallel layer inside Python threads (the workqueue layer aborts on
that).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from numba import njit
from scipy import ndimage

from ._linalg import cholesky_solve
from .rig import Camera

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class RectifiedPair:
    """One stereo pair rectified to a common, belt-facing orientation.

    Attributes
    ----------
    left, right : int
        Camera indices in the rig.
    R_rect_rig : (3, 3) float64
        Rotation rig -> rectified frame (rows: x along the baseline, y, z down).
    centre_left : (3,) float64, mm
        Optical centre of the left camera in the rig frame (the rectified frame's origin).
    baseline_mm : float
        Distance between the two optical centres.
    f_px : float
        Focal length of both rectified images.
    cx_left, cx_right, cy : float
        Principal points of the rectified images (pixels).
    size : (int, int)
        (width, height) of both rectified images.
    maps_left, maps_right : tuple of two (H, W) float32
        ``cv2.remap`` maps from rectified pixels to the original (distorted) image.
    """

    left: int
    right: int
    R_rect_rig: F64
    centre_left: F64
    baseline_mm: float
    f_px: float
    cx_left: float
    cx_right: float
    cy: float
    size: tuple[int, int]
    maps_left: tuple[F32, F32]
    maps_right: tuple[F32, F32]

    @property
    def name(self) -> str:
        return f"{self.left}-{self.right}"

    @property
    def fb(self) -> float:
        """f * B (px mm): disparity times depth."""
        return self.f_px * self.baseline_mm

    @property
    def offset_px(self) -> float:
        """Disparity of a point at infinite depth (the principal point shift)."""
        return self.cx_left - self.cx_right

    # -- geometry -----------------------------------------------------------
    def to_rect(self, points_rig: F64) -> F64:
        """Rig-frame points (N, 3) -> rectified left-camera frame (N, 3), mm."""
        return (points_rig - self.centre_left) @ self.R_rect_rig.T

    def project(self, points_rig: F64) -> tuple[F64, F64, F64]:
        """Rig-frame points -> rectified left pixel (x, y) and depth Z (mm)."""
        p = self.to_rect(points_rig)
        z = p[:, 2]
        return self.f_px * p[:, 0] / z + self.cx_left, self.f_px * p[:, 1] / z + self.cy, z

    def disparity_of_depth(self, z: F64 | float) -> F64 | float:
        """Rectified disparity (px) of a point at depth ``z`` (mm) along the rectified axis."""
        return self.fb / z + self.offset_px

    def triangulate(self, x: F64, y: F64, d: F64) -> F64:
        """Rectified left pixels and disparities (N,) -> rig-frame points (N, 3), mm."""
        z = self.fb / (d - self.offset_px)
        p = np.empty((len(x), 3))
        p[:, 0] = (x - self.cx_left) * z / self.f_px
        p[:, 1] = (y - self.cy) * z / self.f_px
        p[:, 2] = z
        return p @ self.R_rect_rig + self.centre_left

    def disparity_range(self, lo: F64, hi: F64) -> tuple[float, float]:
        """Disparities spanned by the box ``lo``..``hi`` (rig frame, mm)."""
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        z = self.to_rect(corners)[:, 2]
        d = self.fb / z + self.offset_px
        return float(d.min()), float(d.max())


def rectify_pair(
    cam_l: Camera, cam_r: Camera, left: int, right: int, lo: F64, hi: F64, margin_px: int = 8
) -> RectifiedPair:
    """Build the belt-facing rectification of one pair (see the module docstring).

    Parameters
    ----------
    cam_l, cam_r : Camera
        Left (lower x) and right camera.
    left, right : int
        Their indices in the rig.
    lo, hi : (3,) float64, mm
        The measurement volume (rig frame) that the rectified images must cover.
    margin_px : int
        Extra pixels around the projected volume.
    """
    c_l = cam_l.centre
    c_r = cam_r.centre
    base = c_r - c_l
    baseline = float(np.linalg.norm(base))
    ex = base / baseline
    down = np.array([0.0, 0.0, -1.0])
    ez = down - ex * (ex @ down)
    ez /= np.linalg.norm(ez)
    ey = np.cross(ez, ex)
    R = np.stack([ex, ey, ez])
    f = float(np.mean([cam_l.K[0, 0], cam_l.K[1, 1], cam_r.K[0, 0], cam_r.K[1, 1]]))
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    # Ideal (principal-point-free) rectified coordinates of the volume in both views.
    xs, ys = [], []
    for c in (c_l, c_r):
        p = (corners - c) @ R.T
        xs.append(f * p[:, 0] / p[:, 2])
        ys.append(f * p[:, 1] / p[:, 2])
    cx_l = margin_px - float(xs[0].min())
    cx_r = margin_px - float(xs[1].min())
    width = (
        int(math.ceil(max(xs[0].max() - xs[0].min(), xs[1].max() - xs[1].min()))) + 2 * margin_px
    )
    y_all = np.concatenate(ys)
    cy = margin_px - float(y_all.min())
    height = int(math.ceil(y_all.max() - y_all.min())) + 2 * margin_px
    maps = []
    for cam, cx in ((cam_l, cx_l), (cam_r, cx_r)):
        K_new = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        R_cam_rect = R @ cam.R.T  # camera -> rectified (OpenCV's R argument)
        m1, m2 = cv2.initUndistortRectifyMap(
            cam.K, cam.dist, R_cam_rect, K_new, (width, height), cv2.CV_32FC1
        )
        maps.append((np.asarray(m1, np.float32), np.asarray(m2, np.float32)))
    R.setflags(write=False)
    return RectifiedPair(
        left, right, R, c_l.copy(), baseline, f, cx_l, cx_r, cy, (width, height), maps[0], maps[1]
    )


def local_normalise(img: F32, window: int) -> F32:
    """Subtract the local mean and divide by the local standard deviation (box window)."""
    k = (window, window)
    mean = cv2.boxFilter(img, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    sq = cv2.boxFilter(img * img, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    var = np.maximum(sq - mean * mean, 0.0)
    # The floor keeps flat, dark regions (shadows) from being amplified into noise.
    return ((img - mean) / np.sqrt(var + 4.0)).astype(np.float32)


def spline_rows(img: F32) -> F32:
    """Cubic B-spline coefficients of each row of ``img`` (mirror boundary).

    What the refinement kernels sample: the spline with these coefficients
    passes through the pixels, and its values and slopes in between come from
    four coefficients (:func:`_bspline`).
    """
    out = ndimage.spline_filter1d(img, order=3, axis=1, mode="mirror", output=np.float32)
    return np.ascontiguousarray(out, dtype=np.float32)


def coarse_disparity(
    left_u8: npt.NDArray[np.uint8],
    right_u8: npt.NDArray[np.uint8],
    d_min: float,
    d_max: float,
    block: int,
) -> F32:
    """SGBM (3-way) disparity at half resolution, returned at full resolution (px, NaN = none).

    Parameters
    ----------
    left_u8, right_u8 : (H, W) uint8
        Rectified images at full resolution.
    d_min, d_max : float
        Disparity range to search, full-resolution pixels.
    block : int
        SGBM block size at half resolution (odd).
    """
    h, w = left_u8.shape
    lh = cv2.pyrDown(left_u8)
    rh = cv2.pyrDown(right_u8)
    lo = int(math.floor(d_min / 2.0)) - 2
    num = int(math.ceil((d_max / 2.0 - lo + 2) / 16.0)) * 16
    sgbm = cv2.StereoSGBM.create(
        minDisparity=lo,
        numDisparities=num,
        blockSize=block,
        P1=8 * block * block,
        P2=32 * block * block,
        disp12MaxDiff=1,
        preFilterCap=31,
        uniquenessRatio=10,
        speckleWindowSize=40,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    raw = sgbm.compute(lh, rh)
    disp = raw.astype(np.float32) * np.float32(2.0 / 16.0)
    disp[raw <= (lo - 1) * 16] = np.nan
    # Half-resolution pixel i sits at full-resolution pixel 2i (pyrDown's sampling).
    return np.asarray(cv2.resize(disp, (w, h), interpolation=cv2.INTER_NEAREST), dtype=np.float32)


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _gauss_newton_step(a11, a12, a13, a22, a23, a33, b1, b2, b3):  # pragma: no cover
    """One Gauss-Newton step of the window fits: the symmetric 3x3 system
    A x = b solved by Cramer's rule, its first (disparity) component clamped
    to +-1 px. Returns (ok, x1, x2, x3); ok is False for a singular A."""
    c11 = a22 * a33 - a23 * a23
    c12 = a13 * a23 - a12 * a33
    c13 = a12 * a23 - a13 * a22
    det = a11 * c11 + a12 * c12 + a13 * c13
    if abs(det) < 1e-12:
        return False, 0.0, 0.0, 0.0
    c22 = a11 * a33 - a13 * a13
    c23 = a12 * a13 - a11 * a23
    c33 = a11 * a22 - a12 * a12
    dd = (c11 * b1 + c12 * b2 + c13 * b3) / det
    dg = (c12 * b1 + c22 * b2 + c23 * b3) / det
    do = (c13 * b1 + c23 * b2 + c33 * b3) / det
    if dd > 1.0:
        dd = 1.0
    elif dd < -1.0:
        dd = -1.0
    return True, dd, dg, do


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _bspline(a):  # pragma: no cover
    """Cubic B-spline weights of the coefficients at columns i-1 .. i+2 for a
    sample at i + a (0 <= a < 1), and their derivatives in a."""
    b = 1.0 - a
    a2 = a * a
    a3 = a2 * a
    return (
        b * b * b / 6.0,
        0.5 * a3 - a2 + 2.0 / 3.0,
        -0.5 * a3 + 0.5 * a2 + 0.5 * a + 1.0 / 6.0,
        a3 / 6.0,
        -0.5 * b * b,
        1.5 * a2 - 2.0 * a,
        -1.5 * a2 + a + 0.5,
        0.5 * a2,
    )


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _ncc(s1, st, sw, stt, sww, stw):  # pragma: no cover
    """Normalised cross-correlation of a window's samples t and r from their weighted
    sums: of the weights, t, r, t^2, r^2 and t r."""
    mt = st / s1
    mw = sw / s1
    ctw = stw / s1 - mt * mw
    ctt = stt / s1 - mt * mt
    cww = sww / s1 - mw * mw
    return ctw / math.sqrt(max(ctt * cww, 1e-12))


@njit(cache=True, nogil=True, inline="always")
def _store(i, ok, d, score, step, out_d, out_score, out_step):  # pragma: no cover
    """Row i of a window fit's outputs: its disparity, score and last step, or
    NaN / -1 / 99 for a fit that failed."""
    if ok:
        out_d[i] = d
        out_score[i] = score
        out_step[i] = step
    else:
        out_d[i] = np.nan
        out_score[i] = -1.0
        out_step[i] = 99.0


@njit(cache=True, nogil=True, fastmath=True)
def refine_pixels(
    left, right, wl, wr, px, py, d0, radius, iterations, out_d, out_score, out_step
):  # pragma: no cover
    """Sub-pixel disparity of each listed pixel: Gauss-Newton on its own window.

    For each pixel the window of the left image is matched against the right
    image shifted by a constant disparity ``d`` (cubic B-spline
    interpolation, see the module notes), with a gain and an offset:
    ``L ≈ g R(x - d) + o``. Three unknowns, normal equations solved in closed
    form; samples are weighted by ``wl`` and ``wr`` (0 where saturated).

    Parameters
    ----------
    left : (H, W) float32
        Locally normalised rectified left image.
    right : (H, W) float32
        The same of the right image, as row B-spline coefficients
        (:func:`spline_rows`).
    wl, wr : (H, W) float32
        Sample weights (0: saturated or outside).
    px, py : (N,) int64
        Pixels to refine (left image).
    d0 : (N,) float32
        Initial disparities.
    radius : int
        Half window (window = 2 radius + 1).
    iterations : int
    out_d, out_score, out_step : (N,) float32
        Refined disparity, weighted normalised correlation, last step (written).
    """
    H, W = left.shape
    n = px.shape[0]
    for i in range(n):
        x = px[i]
        y = py[i]
        d = float(d0[i])
        g = 1.0
        o = 0.0
        score = -1.0
        step = 99.0
        ok = True
        for _ in range(iterations):
            xr = x - d
            xi = int(math.floor(xr))
            a = xr - xi
            if xi - radius - 1 < 0 or xi + radius + 2 >= W or y - radius < 0 or y + radius >= H:
                ok = False
                break
            w0, w1, w2, w3, g0, g1, g2, g3 = _bspline(a)
            s1 = 0.0
            sw = 0.0
            sg = 0.0
            sww = 0.0
            sgg = 0.0
            sgw = 0.0
            st = 0.0
            stt = 0.0
            stw = 0.0
            stg = 0.0
            for v in range(-radius, radius + 1):
                yy = y + v
                # Row slices (1-D, unit stride) halve the time of 2-D indexing
                # here: the compiler keeps one base pointer per row.
                lrow = left[yy, x - radius : x + radius + 1]
                wlrow = wl[yy, x - radius : x + radius + 1]
                rrow = right[yy, xi - radius - 1 : xi + radius + 3]
                wrrow = wr[yy, xi - radius : xi + radius + 2]
                for u in range(2 * radius + 1):
                    # No branch on zero weights: the loop stays vectorisable.
                    wt = wlrow[u] * wrrow[u] * wrrow[u + 1]
                    r0 = rrow[u]
                    r1 = rrow[u + 1]
                    r2 = rrow[u + 2]
                    r3 = rrow[u + 3]
                    rv = w0 * r0 + w1 * r1 + w2 * r2 + w3 * r3
                    gv = g0 * r0 + g1 * r1 + g2 * r2 + g3 * r3
                    t = lrow[u]
                    s1 += wt
                    sw += wt * rv
                    sg += wt * gv
                    sww += wt * rv * rv
                    sgg += wt * gv * gv
                    sgw += wt * gv * rv
                    st += wt * t
                    stt += wt * t * t
                    stw += wt * t * rv
                    stg += wt * t * gv
            if s1 < 0.5 * (2 * radius + 1) ** 2:
                ok = False
                break
            # Weighted normalised cross-correlation at the current shift.
            score = _ncc(s1, st, sw, stt, sww, stw)
            # Gauss-Newton for (Δ, g, o) with residual e = t - g r - o and
            # d(g r)/dΔ = -g dr/dx (the image moves left when d grows).
            # Normal matrix A = J^T J, J = [-g gv, rv, 1]; rhs b = J^T e.
            a11 = g * g * sgg
            a12 = -g * sgw
            a13 = -g * sg
            a22 = sww
            a23 = sw
            a33 = s1
            se = st - g * sw - o * s1
            b1 = -g * (stg - g * sgw - o * sg)
            b2 = stw - g * sww - o * sw
            b3 = se
            ok, dd, dg, do = _gauss_newton_step(a11, a12, a13, a22, a23, a33, b1, b2, b3)
            if not ok:
                break
            d += dd
            g += dg
            o += do
            step = dd
            if abs(dd) < 0.002:
                break
        _store(i, ok, d, score, step, out_d, out_score, out_step)


@njit(cache=True, nogil=True, fastmath=True)
def refine_cyclopean(
    left, right, wl, wr, cl, cr, py, d0, radius, iterations, out_d, out_score, out_step
):  # pragma: no cover
    """Sub-pixel disparity at points of the cyclopean (mid-baseline) view.

    The window is centred half-way between the two views: the left image is
    sampled at ``c + d/2 + u`` and the right one at ``c - d/2 + u``. Matching
    from one view only (the left window against the shifted right image)
    shifts every depth edge and every slope towards the occluded side (the
    "fattening" of window matchers), and with both pairs' baselines along x
    that shift is the same for the whole cloud, an in-plane bias of the part's
    position; the symmetric window cancels it to first order.

    Model ``L(c + d/2 + u) ≈ g R(c - d/2 + u) + o`` per window, three
    unknowns (d, g, o) by Gauss-Newton, cubic B-spline interpolation of both
    images, samples weighted by ``wl`` and ``wr`` (0 where saturated).

    Parameters
    ----------
    left, right : (H, Wl), (H, Wr) float32
        Locally normalised rectified images (crops), both as row B-spline
        coefficients (:func:`spline_rows`).
    wl, wr : float32, same shapes
        Sample weights.
    cl, cr : (N,) float64
        Cyclopean x of each point in the left and in the right crop's columns.
    py : (N,) int64
        Row of each point (both crops).
    d0 : (N,) float32
        Initial disparities.
    radius : int
    iterations : int
    out_d, out_score, out_step : (N,) float32
        Refined disparity (NaN: failed), normalised correlation, last step.
    """
    H = left.shape[0]
    Wl = left.shape[1]
    Wr = right.shape[1]
    n = py.shape[0]
    for i in range(n):
        y = py[i]
        d = float(d0[i])
        g = 1.0
        o = 0.0
        score = -1.0
        step = 99.0
        ok = y - radius >= 0 and y + radius < H
        for _ in range(iterations):
            if not ok:
                break
            xl = cl[i] + 0.5 * d
            xr = cr[i] - 0.5 * d
            il = int(math.floor(xl))
            ir = int(math.floor(xr))
            if (
                il - radius - 1 < 0
                or il + radius + 2 >= Wl
                or ir - radius - 1 < 0
                or ir + radius + 2 >= Wr
            ):
                ok = False
                break
            lw0, lw1, lw2, lw3, lg0, lg1, lg2, lg3 = _bspline(xl - il)
            rw0, rw1, rw2, rw3, rg0, rg1, rg2, rg3 = _bspline(xr - ir)
            s1 = 0.0
            sl = 0.0
            sr = 0.0
            sll = 0.0
            srr = 0.0
            slr = 0.0
            # Sums for the normal equations with j = dL/dd + g dR/dd... see below.
            sj = 0.0
            sjj = 0.0
            sjr = 0.0
            sje = 0.0
            sre = 0.0
            se = 0.0
            for v in range(-radius, radius + 1):
                yy = y + v
                for u in range(-radius, radius + 1):
                    xa = il + u
                    xb = ir + u
                    wt = wl[yy, xa] * wl[yy, xa + 1] * wr[yy, xb] * wr[yy, xb + 1]
                    l0 = left[yy, xa - 1]
                    l1 = left[yy, xa]
                    l2 = left[yy, xa + 1]
                    l3 = left[yy, xa + 2]
                    r0 = right[yy, xb - 1]
                    r1 = right[yy, xb]
                    r2 = right[yy, xb + 1]
                    r3 = right[yy, xb + 2]
                    lv = lw0 * l0 + lw1 * l1 + lw2 * l2 + lw3 * l3
                    lgr = lg0 * l0 + lg1 * l1 + lg2 * l2 + lg3 * l3
                    rv = rw0 * r0 + rw1 * r1 + rw2 * r2 + rw3 * r3
                    rgr = rg0 * r0 + rg1 * r1 + rg2 * r2 + rg3 * r3
                    # e = L(c + d/2) - g R(c - d/2) - o;  de/dd = (L' + g R') / 2.
                    e = lv - g * rv - o
                    j = 0.5 * (lgr + g * rgr)
                    s1 += wt
                    sl += wt * lv
                    sr += wt * rv
                    sll += wt * lv * lv
                    srr += wt * rv * rv
                    slr += wt * lv * rv
                    sj += wt * j
                    sjj += wt * j * j
                    sjr += wt * j * rv
                    sje += wt * j * e
                    sre += wt * rv * e
                    se += wt * e
            if s1 < 0.5 * (2 * radius + 1) ** 2:
                ok = False
                break
            ml = sl / s1
            mr = sr / s1
            score = (slr / s1 - ml * mr) / math.sqrt(
                max((sll / s1 - ml * ml) * (srr / s1 - mr * mr), 1e-12)
            )
            # Gauss-Newton on Σ e² in (Δd, Δg, Δo): de = j Δd - r Δg - Δo, so
            # [ Σjj  -Σjr  -Σj ] [Δd]     [ Σje ]
            # [-Σjr   Σrr   Σr ] [Δg] = - [-Σre ]
            # [ -Σj   Σr    Σ1 ] [Δo]     [ -Σe ]
            a11 = sjj
            a12 = -sjr
            a13 = -sj
            a22 = srr
            a23 = sr
            a33 = s1
            b1 = -sje
            b2_ = sre
            b3_ = se
            ok, dd, dg, do = _gauss_newton_step(a11, a12, a13, a22, a23, a33, b1, b2_, b3_)
            if not ok:
                break
            d += dd
            g += dg
            o += do
            step = dd
            if abs(dd) < 0.002:
                break
        _store(i, ok, d, score, step, out_d, out_score, out_step)


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _warped_sample(rrow, wrrow, xr, wr_cols):  # pragma: no cover
    """Right-image row ``rrow`` (B-spline coefficients) at column ``xr``: the
    spline's value, its derivative, and the sample's weight (the right weights
    ``wrrow`` of the two nearest pixels). Branch-free: a column off the row is
    clamped to a valid one and weighted 0, rather than skipped."""
    xf = math.floor(xr)
    a = xr - xf
    xb0 = int(xf)
    xb = min(max(xb0, 1), wr_cols - 3)
    inside = 1.0 if xb == xb0 else 0.0
    w0, w1, w2, w3, g0, g1, g2, g3 = _bspline(a)
    r0 = rrow[xb - 1]
    r1 = rrow[xb]
    r2 = rrow[xb + 1]
    r3 = rrow[xb + 2]
    rv = w0 * r0 + w1 * r1 + w2 * r2 + w3 * r3
    gv = g0 * r0 + g1 * r1 + g2 * r2 + g3 * r3
    return rv, gv, inside * wrrow[xb] * wrrow[xb + 1]


@njit(cache=True, nogil=True, inline="always")
def _warp_centre(shape, mask, x, y, radius):  # pragma: no cover
    """Whether a warped window at (x, y) fits in the crop and is centred on the
    field, and the field's value there (0 off the crop)."""
    H, W = shape.shape
    if not (y - radius >= 0 and y + radius < H and x - radius >= 0 and x + radius < W):
        return False, 0.0
    return mask[y, x] > 0.0, float(shape[y, x])


@njit(cache=True, nogil=True)
def depth_in_view(
    points, centre, R, f_px, cx, cy, fb, offset_px, disparity, z_out, z_other
):  # pragma: no cover
    """Each rig-frame point's depth along a rectified view's axis (``z_out``) and the
    depth of the surface that view's ``disparity`` map measures on the same ray
    (``z_other``; NaN where not measured there): the map is interpolated
    bilinearly where its four neighbours are measured, else taken from the
    nearest pixel. ``R``, ``centre``: the view's rotation rig -> rectified and
    optical centre."""
    h, w = disparity.shape
    for i in range(points.shape[0]):
        a = points[i, 0] - centre[0]
        b = points[i, 1] - centre[1]
        c = points[i, 2] - centre[2]
        z = R[2, 0] * a + R[2, 1] * b + R[2, 2] * c
        z_out[i] = z
        z_other[i] = np.nan
        if not z > 0.0:
            continue
        x = f_px * (R[0, 0] * a + R[0, 1] * b + R[0, 2] * c) / z + cx
        y = f_px * (R[1, 0] * a + R[1, 1] * b + R[1, 2] * c) / z + cy
        xf = math.floor(x)
        yf = math.floor(y)
        if not (xf >= 0 and xf < w - 1 and yf >= 0 and yf < h - 1):
            continue
        xi = int(xf)
        yi = int(yf)
        fx = x - xf
        fy = y - yf
        d = (
            disparity[yi, xi] * (1.0 - fx) * (1.0 - fy)
            + disparity[yi, xi + 1] * fx * (1.0 - fy)
            + disparity[yi + 1, xi] * (1.0 - fx) * fy
            + disparity[yi + 1, xi + 1] * fx * fy
        )
        if not math.isfinite(d):
            d = disparity[yi + int(round(fy)), xi + int(round(fx))]
        if math.isfinite(d):
            z_other[i] = fb / (d - offset_px)


@njit(cache=True, nogil=True, fastmath=True)
def refine_warped(
    left, right, wl, wr, shape, mask, px, py, d0, radius, iterations, out_d, out_score, out_step
):  # pragma: no cover
    """Sub-pixel disparity with the window warped by a known disparity shape.

    As :func:`refine_pixels`, but the right-image sample of window offset
    (u, v) is taken at ``x + u - d - (S[y + v, x + u] - S[y, x])``: the
    window follows the surface's disparity field ``S`` (a previous estimate),
    so slanted and curved surfaces (walls seen at a grazing angle, bends)
    are compared with the right image stretched as the surface stretches it,
    and only the centre's disparity ``d`` (with gain and offset) is fitted.
    Samples where ``S`` is NaN (not part of the surface: across a depth edge)
    get no weight, so windows do not drag a surface past its outline.

    Parameters
    ----------
    shape : (H, W) float32
        Disparity field of the left crop (px; any finite value where none).
    mask : (H, W) float32
        1 where ``shape`` is known, 0 elsewhere.
    Others as :func:`refine_pixels`.
    """
    wr_cols = right.shape[1]
    n = px.shape[0]
    nw = (2 * radius + 1) ** 2
    for i in range(n):
        x = px[i]
        y = py[i]
        d = float(d0[i])
        g = 1.0
        o = 0.0
        score = -1.0
        step = 99.0
        ok, s0 = _warp_centre(shape, mask, x, y, radius)
        for _ in range(iterations):
            if not ok:
                break
            s1 = 0.0
            sw = 0.0
            sg = 0.0
            sww = 0.0
            sgg = 0.0
            sgw = 0.0
            st = 0.0
            stt = 0.0
            stw = 0.0
            stg = 0.0
            for v in range(-radius, radius + 1):
                yy = y + v
                lrow = left[yy, x - radius : x + radius + 1]
                wlrow = wl[yy, x - radius : x + radius + 1]
                srow = shape[yy, x - radius : x + radius + 1]
                mrow = mask[yy, x - radius : x + radius + 1]
                rrow = right[yy]
                wrrow = wr[yy]
                for u in range(2 * radius + 1):
                    xr = (x - radius + u) - d - (srow[u] - s0)
                    rv, gv, wrt = _warped_sample(rrow, wrrow, xr, wr_cols)
                    wt = mrow[u] * wlrow[u] * wrt
                    t = lrow[u]
                    s1 += wt
                    sw += wt * rv
                    sg += wt * gv
                    sww += wt * rv * rv
                    sgg += wt * gv * gv
                    sgw += wt * gv * rv
                    st += wt * t
                    stt += wt * t * t
                    stw += wt * t * rv
                    stg += wt * t * gv
            if s1 < 0.5 * nw:
                ok = False
                break
            score = _ncc(s1, st, sw, stt, sww, stw)
            a11 = g * g * sgg
            a12 = -g * sgw
            a13 = -g * sg
            a22 = sww
            a23 = sw
            a33 = s1
            b1 = -g * (stg - g * sgw - o * sg)
            b2 = stw - g * sww - o * sw
            b3 = st - g * sw - o * s1
            ok, dd, dg, do = _gauss_newton_step(a11, a12, a13, a22, a23, a33, b1, b2, b3)
            if not ok:
                break
            d += dd
            g += dg
            o += do
            step = dd
            if abs(dd) < 0.002:
                break
        _store(i, ok, d, score, step, out_d, out_score, out_step)


# Regressors of :func:`refine_warped_shaded` (the quadratic monomials of two
# surface coordinates), and its unknowns (disparity, gain, offset and their
# coefficients): constants, so that the compiler unrolls the accumulation of
# the normal equations.
SHADE_TERMS = 5
_SHADED_UNKNOWNS = 3 + SHADE_TERMS


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _monomials(u, v, out):  # pragma: no cover
    """The regressors of :func:`refine_warped_shaded` at surface coordinates (u, v)."""
    out[0] = u
    out[1] = v
    out[2] = u * u
    out[3] = u * v
    out[4] = v * v


@njit(cache=True, nogil=True, fastmath=True)
def refine_warped_shaded(
    left,
    right,
    wl,
    wr,
    shape,
    mask,
    su,
    sv,
    ridge,
    px,
    py,
    d0,
    radius,
    iterations,
    out_d,
    out_score,
    out_step,
):  # pragma: no cover
    """:func:`refine_warped` with light that varies with the surface across the window.

    The model is ``L ≈ g R(x') + o + sum_k c_k (q_k - q_k(centre))``: besides
    the gain and offset, an additive term linear in ``SHADE_TERMS``
    regressors, the quadratic monomials ``u, v, u^2, u v, v^2`` of two
    coordinates of the surface known at every pixel (such as its slopes),
    whose coefficients ``c`` are fitted with the disparity: light that is a
    smooth function of the surface's orientation.
    Gauss-Newton on all the unknowns, normal equations solved by Cholesky;
    ``ridge`` times the window's weight is added to the coefficients'
    diagonal, which keeps a regressor that does not vary in the window from
    making the system singular.

    Parameters
    ----------
    su, sv : (H, W) float32
        The surface coordinates ``u`` and ``v`` at every left-crop pixel.
    ridge : float
    Others as :func:`refine_warped`.
    """
    wr_cols = right.shape[1]
    n = px.shape[0]
    nw = (2 * radius + 1) ** 2
    A = np.empty((_SHADED_UNKNOWNS, _SHADED_UNKNOWNS))
    b = np.empty(_SHADED_UNKNOWNS)
    J = np.empty(_SHADED_UNKNOWNS)
    c = np.empty(SHADE_TERMS)
    q0 = np.empty(SHADE_TERMS)
    q = np.empty(SHADE_TERMS)
    for i in range(n):
        x = px[i]
        y = py[i]
        d = float(d0[i])
        g = 1.0
        o = 0.0
        c[:] = 0.0
        score = -1.0
        step = 99.0
        ok, s0 = _warp_centre(shape, mask, x, y, radius)
        if ok:
            _monomials(su[y, x], sv[y, x], q0)
        for _ in range(iterations):
            if not ok:
                break
            A[:, :] = 0.0
            b[:] = 0.0
            s1 = 0.0
            sw = 0.0
            sww = 0.0
            st = 0.0
            stt = 0.0
            stw = 0.0
            for v in range(-radius, radius + 1):
                yy = y + v
                lrow = left[yy, x - radius : x + radius + 1]
                wlrow = wl[yy, x - radius : x + radius + 1]
                srow = shape[yy, x - radius : x + radius + 1]
                mrow = mask[yy, x - radius : x + radius + 1]
                urow = su[yy, x - radius : x + radius + 1]
                vrow = sv[yy, x - radius : x + radius + 1]
                rrow = right[yy]
                wrrow = wr[yy]
                for u in range(2 * radius + 1):
                    xr = (x - radius + u) - d - (srow[u] - s0)
                    rv, gv, wrt = _warped_sample(rrow, wrrow, xr, wr_cols)
                    wt = mrow[u] * wlrow[u] * wrt
                    if wt == 0.0:
                        continue
                    t = lrow[u]
                    e = t - g * rv - o
                    J[0] = -g * gv
                    J[1] = rv
                    J[2] = 1.0
                    _monomials(urow[u], vrow[u], q)
                    for k in range(SHADE_TERMS):
                        qk = q[k] - q0[k]
                        J[3 + k] = qk
                        e -= c[k] * qk
                    for r in range(_SHADED_UNKNOWNS):
                        wj = wt * J[r]
                        b[r] += wj * e
                        for m in range(r, _SHADED_UNKNOWNS):
                            A[r, m] += wj * J[m]
                    s1 += wt
                    sw += wt * rv
                    sww += wt * rv * rv
                    st += wt * t
                    stt += wt * t * t
                    stw += wt * t * rv
            if s1 < 0.5 * nw:
                ok = False
                break
            score = _ncc(s1, st, sw, stt, sww, stw)
            for r in range(_SHADED_UNKNOWNS):
                for m in range(r):
                    A[r, m] = A[m, r]
            for k in range(SHADE_TERMS):
                A[3 + k, 3 + k] += ridge * s1
            sol, ok = cholesky_solve(A, b)
            if not ok:
                break
            dd = min(max(sol[0], -1.0), 1.0)
            d += dd
            g += sol[1]
            o += sol[2]
            for k in range(SHADE_TERMS):
                c[k] += sol[3 + k]
            step = dd
            if abs(dd) < 0.002:
                break
        _store(i, ok, d, score, step, out_d, out_score, out_step)


@njit(cache=True, nogil=True)
def fill_row_gaps(disparity, passes):  # pragma: no cover
    """Fill NaN pixels from their measured row neighbours, in place, ``passes`` times.

    Each pass sets every NaN pixel with a measured left or right neighbour
    to the mean of the measured ones (values of the previous pass), so gaps
    of up to ``2 * passes`` columns between measured pixels close and
    outlines grow by ``passes`` columns.

    Parameters
    ----------
    disparity : (H, W) float32
        NaN where not measured; modified in place.
    passes : int
    """
    H, W = disparity.shape
    prev = np.empty(W, np.float32)
    for _ in range(passes):
        for y in range(H):
            row = disparity[y]
            for x in range(W):
                prev[x] = row[x]
            for x in range(W):
                if not np.isnan(prev[x]):
                    continue
                s = np.float32(0.0)
                c = 0
                if x > 0 and not np.isnan(prev[x - 1]):
                    s += prev[x - 1]
                    c += 1
                if x + 1 < W and not np.isnan(prev[x + 1]):
                    s += prev[x + 1]
                    c += 1
                if c > 0:
                    row[x] = s / np.float32(c)
