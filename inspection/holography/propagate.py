"""Numerical refocusing: the angular-spectrum propagation of a complex field."""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInput
from .spectrum import Field


def propagate(field: Field, dz_mm: float, wavelength_mm: float, pitch_mm: float) -> Field:
    """The field ``dz_mm`` further along z (negative: back), by the angular spectrum.

    Each plane wave of the field's spectrum (fx, fy) advances by the phase
    ``2 pi dz sqrt(1 / lambda^2 - fx^2 - fy^2)``; evanescent waves are dropped.
    Exact for band-limited fields, apart from the wrap-around of the FFT at the
    borders.

    Parameters
    ----------
    field : (n, m) complex128
    dz_mm, wavelength_mm, pitch_mm : float, mm
    """
    u = np.asarray(field)
    if u.ndim != 2 or not np.iscomplexobj(u):
        raise InvalidInput(f"field must be a 2-D complex array, got {u.dtype} {u.shape}")
    if not (np.isfinite(dz_mm) and wavelength_mm > 0 and pitch_mm > 0):
        raise InvalidInput("dz_mm must be finite, wavelength_mm and pitch_mm > 0")
    fy = np.fft.fftfreq(u.shape[0], d=pitch_mm)
    fx = np.fft.fftfreq(u.shape[1], d=pitch_mm)
    arg = 1.0 / wavelength_mm**2 - fy[:, None] ** 2 - fx[None, :] ** 2
    # Subtract the common phase 2 pi dz / lambda: it moves nothing.
    kz = np.sqrt(np.maximum(arg, 0.0)) - 1.0 / wavelength_mm
    kernel = np.where(arg > 0, np.exp(2j * np.pi * dz_mm * kz), 0.0)
    return np.fft.ifft2(np.fft.fft2(u) * kernel)
