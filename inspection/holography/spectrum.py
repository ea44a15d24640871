"""The hologram's spectrum: finding the two lobes and cutting each out.

Each laser's hologram term ``O R*`` is a disc (the lobe) in the spectrum of
the image, centred at minus its reference wave's carrier; its twin ``O* R``
sits opposite, the object's autocorrelation at the centre. A lobe is found
as the brightest region of the smoothed power spectrum near where the head's
design puts it, its centre as the power-weighted centroid, its radius as
where its radial power profile falls to a tenth of its plateau.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.ndimage import gaussian_filter

from ..errors import InvalidInput
from .head import HoloHead

Field = npt.NDArray[np.complex128]
"""(n, n) complex128, a complex field on the pixel grid."""


@dataclass(frozen=True)
class Lobe:
    """A lobe in the image's (unshifted) FFT, in frequency bins (row, column),
    signed: bin (u, v) is the frequency (v, u) / field_mm cycles/mm along (x, y)."""

    row: float
    col: float
    radius: float

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.row, self.col, self.radius)):
            raise InvalidInput("a lobe's centre and radius must be finite")
        if self.radius <= 0:
            raise InvalidInput(f"a lobe's radius must be > 0, got {self.radius}")

    def mask(self, n: int) -> npt.NDArray[np.bool_]:
        f = np.fft.fftfreq(n, d=1.0 / n)
        return (f[:, None] - self.row) ** 2 + (f[None, :] - self.col) ** 2 <= self.radius**2


def spectrum(image: npt.ArrayLike) -> Field:
    """The image's 2-D FFT (mean removed), complex128, unshifted."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or img.shape[0] != img.shape[1] or not np.all(np.isfinite(img)):
        raise InvalidInput(f"a hologram must be a finite square 2-D image, got {img.shape}")
    return np.fft.fft2(img - img.mean())


def find_lobes(head: HoloHead, image: npt.ArrayLike) -> tuple[Lobe, Lobe]:
    """The two lobes ``O R*`` of the hologram, one per laser, in the head's order.

    Each is searched within the design lobe radius (plus half) of where the
    design's reference wave puts it; the search never reaches the twin or the
    centre, so a lobe is never confused with them.

    Raises
    ------
    InvalidInput
        The image does not match the head, or a lobe holds no power.
    """
    spec = spectrum(image)
    n = head.pixels
    if spec.shape != (n, n):
        raise InvalidInput(f"the head has {n} x {n} pixels, the image {spec.shape}")
    power = gaussian_filter(np.fft.fftshift(np.abs(spec) ** 2), sigma=2.0, mode="wrap")
    f = np.arange(n, dtype=np.float64) - n // 2  # shifted bins
    bins_per = head.field_mm  # bins per cycle/mm
    lobes = []
    for wavelength, ref in zip(head.wavelengths_mm, head.references, strict=True):
        # The carrier of O R*: minus the reference's tilt, in cycles/mm, then bins.
        c_col = -ref.tilt_x_mrad * 1e-3 / wavelength * bins_per
        c_row = -ref.tilt_y_mrad * 1e-3 / wavelength * bins_per
        search = 1.5 * head.lobe_radius * bins_per
        d2 = (f[:, None] - c_row) ** 2 + (f[None, :] - c_col) ** 2
        window = d2 <= search**2
        p = np.where(window, power, 0.0)
        if not np.any(p > 0):
            raise InvalidInput("no power where the design puts a lobe")
        # The plateau is flat: its power-weighted centroid above half the peak is the centre.
        strong = p >= 0.5 * p.max()
        w = p * strong
        row = float((w.sum(axis=1) @ f) / w.sum())
        col = float((w.sum(axis=0) @ f) / w.sum())
        r = np.sqrt((f[:, None] - row) ** 2 + (f[None, :] - col) ** 2)
        edges = np.arange(0.0, search + 1.0, 1.0)
        idx = np.digitize(r[window], edges)
        total = np.bincount(idx, weights=power[window], minlength=len(edges) + 1)
        cnt = np.bincount(idx, minlength=len(edges) + 1)
        prof = total[1 : len(edges)] / np.maximum(cnt[1 : len(edges)], 1)
        plateau = float(np.median(prof[: max(3, len(prof) // 3)]))
        below = np.nonzero(prof < 0.1 * plateau)[0]
        radius = float(edges[below[0]]) if len(below) else float(search)
        lobes.append(Lobe(row=row, col=col, radius=radius + 1.0))
    return lobes[0], lobes[1]


def lobe_field(spec: Field, lobe: Lobe) -> Field:
    """The field of one lobe on the full pixel grid, carrier kept: the inverse FFT of
    the spectrum inside the lobe's disc."""
    return np.fft.ifft2(np.where(lobe.mask(spec.shape[0]), spec, 0.0))
