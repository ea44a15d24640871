"""The lobe cut chosen by the speckle displacements it leaves.

A lobe cut out of the spectrum and moved to the origin by its centre ``c``
(the field multiplied by ``exp(-i 2 pi c . x)``) keeps whatever carrier the
centre misses: the lobe's power-weighted mean frequency minus ``c``. Refocused
from ``-dz`` to ``+dz``, a speckle field with a carrier ``f`` moves by
``2 dz lambda f`` (the Fourier shift theorem on the angular spectrum), so the
mean speckle displacement between the two planes measures the centre's error
directly, in any direction, and is zero only for the cut centred on its lobe.
The displacement is linear in the error: each step moves the centre by what
the displacement says, the disc moves with it, and a few steps settle it
(a Newton search on the mean displacement, sub-bin, since the carrier is
continuous even where the disc's bins are not).

The two lasers' reconstructions then move alike: their displacement against
each other in a defocused plane (``dz lambda`` times the difference of their
centres' errors) is what decides how alike their speckles are, hence the
coherence of the phase difference; it is reported before and after.

:func:`~inspection.holography.spectrum.find_lobes` starts the search: its
window around the design's carrier clips a lobe whose reference wave is far
off the design, and the centroid of what is left is biased towards the design.
The cut follows the lobe wherever it is. Its radius is kept: the mean
displacement does not depend on it once the disc holds the lobe.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from ..errors import CalibrationError, InvalidInput
from .correlation import Displacement, correlate
from .head import HoloHead
from .propagate import propagate
from .spectrum import Field, Lobe, find_lobes, lobe_field, spectrum

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LobeCut:
    """The two lobes as cut, and the speckle displacements that chose them (px).

    Attributes
    ----------
    lobes : the two lobes, in the head's order.
    start : the lobes the search started from.
    refocus_px : per laser, the mean displacement left between ``-dz`` and ``+dz``.
    between_px, start_between_px : float
        The mean displacement between the two lasers' reconstructions in the plane
        ``+dz``, at the end and at the start.
    iterations : int
    converged : bool
    """

    lobes: tuple[Lobe, Lobe]
    start: tuple[Lobe, Lobe]
    refocus_px: tuple[float, float]
    between_px: float
    start_between_px: float
    iterations: int
    converged: bool


def minimise_cut(
    head: HoloHead,
    image: npt.ArrayLike,
    lobes: tuple[Lobe, Lobe] | None = None,
    *,
    dz_mm: float | None = None,
    window: int = 64,
    iterations: int = 6,
    tolerance_bins: float = 0.05,
    min_peak: float = 0.3,
) -> LobeCut:
    """Centre each lobe's cut where the speckles of its reconstruction do not move
    between the planes ``-dz_mm`` and ``+dz_mm``.

    Parameters
    ----------
    head : HoloHead
    image : (n, n) hologram
    lobes : the start (default: :func:`~inspection.holography.spectrum.find_lobes`)
    dz_mm : float, optional
        Half the distance between the two planes, mm; default 0.15 of the depth of
        focus ``lambda / NA^2``: far enough that a bin moves the speckles by a
        twentieth of a pixel or more, near enough that they still correlate (at half
        the depth of focus they no longer do).
    window : int
        Correlation window side, px.
    iterations : int
        Steps at most.
    tolerance_bins : float
        A step smaller than this (FFT bins) ends the search.

    Raises
    ------
    CalibrationError
        Too few windows correlate to measure a displacement.
    """
    dz_mm = dz_mm if dz_mm is not None else 0.15 * head.wavelength_mm / head.na**2
    if not (math.isfinite(dz_mm) and dz_mm > 0 and iterations >= 1 and tolerance_bins > 0):
        raise InvalidInput("dz_mm and tolerance_bins must be > 0, iterations >= 1")
    spec = spectrum(image)
    n = head.pixels
    if spec.shape != (n, n):
        raise InvalidInput(f"the head has {n} x {n} pixels, the image {spec.shape}")
    start = lobes or find_lobes(head, image)
    window = min(window, n // 4 * 2)
    current = list(start)
    refocus = [math.nan, math.nan]
    converged = False
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007
        worst = 0.0
        for i, wavelength in enumerate(head.wavelengths_mm):
            field = _demodulated(spec, current[i])
            a = propagate(field, -dz_mm, wavelength, head.pitch_mm)
            b = propagate(field, dz_mm, wavelength, head.pitch_mm)
            disp = correlate(np.abs(a) ** 2, np.abs(b) ** 2, window=window)
            dy, dx = _mean_displacement(disp, n, min_peak)
            refocus[i] = math.hypot(dy, dx)
            # 2 dz lambda f mm for a carrier f = bins / field_mm.
            per_bin = 2.0 * dz_mm * wavelength / head.field_mm / head.pitch_mm  # px per bin
            step = (dy / per_bin, dx / per_bin)
            worst = max(worst, math.hypot(*step))
            current[i] = replace(current[i], row=current[i].row + step[0],
                                 col=current[i].col + step[1])  # fmt: skip
        log.debug("lobe cut step %d: %s, largest move %.3f bins", it, current, worst)
        if worst < tolerance_bins:
            converged = True
            break
    cut = (current[0], current[1])
    return LobeCut(
        lobes=cut,
        start=(start[0], start[1]),
        refocus_px=(refocus[0], refocus[1]),
        between_px=between(head, spec, cut, dz_mm, window, min_peak),
        start_between_px=between(head, spec, (start[0], start[1]), dz_mm, window, min_peak),
        iterations=it,
        converged=converged,
    )


def between(
    head: HoloHead,
    spec: Field,
    lobes: tuple[Lobe, Lobe],
    dz_mm: float,
    window: int = 64,
    min_peak: float = 0.3,
) -> float:
    """The mean displacement (px) of laser 2's reconstruction against laser 1's in the
    plane ``dz_mm``, each lobe moved to the origin by its centre."""
    fields = [
        propagate(_demodulated(spec, lobe), dz_mm, wavelength, head.pitch_mm)
        for lobe, wavelength in zip(lobes, head.wavelengths_mm, strict=True)
    ]
    disp = correlate(np.abs(fields[0]) ** 2, np.abs(fields[1]) ** 2, window=window)
    return math.hypot(*_mean_displacement(disp, head.pixels, min_peak))


def _demodulated(spec: Field, lobe: Lobe) -> Field:
    """The lobe's field with its centre's carrier removed: the cut moved to the origin,
    by a fraction of a bin too."""
    n = spec.shape[0]
    k = np.arange(n, dtype=np.float64)
    carrier = np.exp(-2j * np.pi * (lobe.row * k[:, None] + lobe.col * k[None, :]) / n)
    return lobe_field(spec, lobe) * carrier


def _mean_displacement(disp: Displacement, n: int, min_peak: float) -> tuple[float, float]:
    """The displacement at the field's centre (px), from a least-squares plane through
    the good windows: a reference wave's curvature adds a displacement growing across
    the field, which the plane keeps apart from the carrier's."""
    good = disp.good(min_peak=min_peak)
    if good.sum() < 6:
        raise CalibrationError(f"only {int(good.sum())} speckle windows correlate")
    c = (n - 1) / 2.0
    A = np.stack([np.ones(int(good.sum())), disp.cols[good] - c, disp.rows[good] - c], axis=1)
    dy = np.linalg.lstsq(A, disp.dy[good], rcond=None)[0][0]
    dx = np.linalg.lstsq(A, disp.dx[good], rcond=None)[0][0]
    return float(dy), float(dx)
