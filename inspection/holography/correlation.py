"""Sub-pixel displacement of one image against another, window by window.

Plain image correlation, as in particle-image and speckle velocimetry: each
interrogation window of ``a`` is cross-correlated (zero-mean, normalised,
by FFT) with the window of ``b`` at the same place; the integer peak is
refined by a three-point Gaussian fit along each axis. That fit pulls a
broad peak (large speckles) towards the whole pixel, so further passes
resample each window of ``b`` (cubic interpolation) at the displacement found
so far and correlate again: the peak left is near zero, where the fit is
symmetric, and its small remainder is added (image-deformation refinement).

Every window reports its correlation-peak quality: the normalised
correlation coefficient at the peak (1 for identical patterns, near 0 for
unrelated ones) and the ratio of the highest peak to the second-highest
local maximum (a ratio near 1 means the displacement is a guess).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import sliding_window_view
from scipy.ndimage import map_coordinates, maximum_filter

from ..errors import InvalidInput

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Displacement:
    """Per-window displacement of ``b`` against ``a``: ``b(p) ~ a(p - d)``.

    Attributes
    ----------
    rows, cols : (m,) float64, px
        Window centres in ``a``.
    dy, dx : (m,) float64, px
        Displacement along rows and columns.
    peak : (m,) float64
        Normalised correlation coefficient at the peak, -1 .. 1.
    ratio : (m,) float64
        Highest correlation peak over the second-highest local maximum (>= 1).
    """

    rows: F64
    cols: F64
    dy: F64
    dx: F64
    peak: F64
    ratio: F64

    def good(self, min_peak: float = 0.3, min_ratio: float = 1.3) -> npt.NDArray[np.bool_]:
        """Windows whose displacement can be trusted."""
        return (self.peak >= min_peak) & (self.ratio >= min_ratio)


def correlate(
    a: npt.ArrayLike,
    b: npt.ArrayLike,
    *,
    window: int = 64,
    step: int | None = None,
    passes: int = 3,
) -> Displacement:
    """Displacements of ``b`` against ``a`` on a grid of square windows.

    Parameters
    ----------
    a, b : (h, w) float, same shape
    window : int
        Window side, px (even, >= 8).
    step : int, optional
        Spacing of the windows, px; default half a window.
    passes : int
        Refinement passes after the first (each resamples ``b`` at the
        displacement found so far).
    """
    A = np.asarray(a, dtype=np.float64)
    B = np.asarray(b, dtype=np.float64)
    if A.ndim != 2 or A.shape != B.shape:
        raise InvalidInput(f"a and b must be 2-D of one shape, got {A.shape} and {B.shape}")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
        raise InvalidInput("a and b must be finite")
    if window < 8 or window % 2 or window > min(A.shape):
        raise InvalidInput(f"window must be even, >= 8 and fit the image, got {window}")
    step = step or window // 2
    if step < 1 or passes < 0:
        raise InvalidInput(f"step must be >= 1 and passes >= 0, got {step}, {passes}")
    r0 = np.arange(0, A.shape[0] - window + 1, step)
    c0 = np.arange(0, A.shape[1] - window + 1, step)
    R0, C0 = (g.ravel() for g in np.meshgrid(r0, c0, indexing="ij"))
    wa = _windows(A, R0, C0, window)
    dy, dx, peak, ratio = _peak(wa, _windows(B, R0, C0, window))
    grid = np.arange(window, dtype=np.float64)
    for _ in range(passes):
        # b's window moved by the displacement so far, clamped to stay inside b.
        ty = np.clip(R0 + dy, 0, A.shape[0] - window) - R0
        tx = np.clip(C0 + dx, 0, A.shape[1] - window) - C0
        rows = (R0 + ty)[:, None, None] + grid[None, :, None]
        cols = (C0 + tx)[:, None, None] + grid[None, None, :]
        wb = map_coordinates(B, [rows + 0 * cols, cols + 0 * rows], order=3, mode="nearest")
        wb -= wb.mean(axis=(1, 2), keepdims=True)
        ry, rx, peak, ratio = _peak(wa, wb)
        dy, dx = ty + ry, tx + rx
    half = (window - 1) / 2.0
    return Displacement(rows=R0 + half, cols=C0 + half, dy=dy, dx=dx, peak=peak, ratio=ratio)


def _windows(img: F64, r0: npt.NDArray[np.int64], c0: npt.NDArray[np.int64], w: int) -> F64:
    view = sliding_window_view(img, (w, w))
    out = view[r0, c0].astype(np.float64)
    out -= out.mean(axis=(1, 2), keepdims=True)
    return out


def _taper(w: int) -> F64:
    # A window's borders sit at the same place in a and b: untapered, their edges
    # correlate with each other and pull every peak towards zero displacement.
    t = np.hanning(w + 2)[1:-1]
    return np.outer(t, t)


def _peak(wa: F64, wb: F64) -> tuple[F64, F64, F64, F64]:
    w = wa.shape[1]
    taper = _taper(w)
    wa = wa * taper
    wb = wb * taper
    norm = np.sqrt((wa**2).sum(axis=(1, 2)) * (wb**2).sum(axis=(1, 2)))
    corr = np.fft.irfft2(np.conj(np.fft.rfft2(wa)) * np.fft.rfft2(wb), s=(w, w))
    corr /= np.where(norm > 0, norm, np.inf)[:, None, None]
    corr = np.fft.fftshift(corr, axes=(1, 2))  # zero shift at (w/2, w/2)
    m = len(corr)
    flat = corr.reshape(m, -1).argmax(axis=1)
    iy, ix = np.divmod(flat, w)
    idx = np.arange(m)
    c0 = corr[idx, iy, ix]

    def fit(cm: F64, cp: F64) -> F64:
        # Three-point Gaussian: the peak of the parabola through the logs.
        lm, l0, lp = (np.log(np.maximum(v, 1e-9)) for v in (cm, c0, cp))
        den = 2.0 * (lm - 2.0 * l0 + lp)
        return np.where(np.abs(den) > 1e-12, (lm - lp) / np.where(den == 0, 1.0, den), 0.0)

    fy = fit(corr[idx, (iy - 1) % w, ix], corr[idx, (iy + 1) % w, ix])
    fx = fit(corr[idx, iy, (ix - 1) % w], corr[idx, iy, (ix + 1) % w])
    local = (corr == maximum_filter(corr, size=(1, 3, 3), mode="wrap")) & (corr > 0)
    local[idx, iy, ix] = False
    second = np.where(local, corr, 0.0).reshape(m, -1).max(axis=1)
    ratio = c0 / np.maximum(second, 1e-9)
    half = w // 2
    return (
        iy - half + np.clip(fy, -0.5, 0.5),
        ix - half + np.clip(fx, -0.5, 0.5),
        c0,
        np.maximum(ratio, 1.0),
    )
