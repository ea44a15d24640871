"""The sensor: shot and read noise from a counter-based generator, clipped and quantised."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .._jit import NO_RUNTIME


@njit(cache=True, nogil=True, inline="always")
def _splitmix64(x):  # pragma: no cover - compiled
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@njit(cache=True, nogil=True, **NO_RUNTIME)
def sensor_noise(img, key, shot, read2, out):  # pragma: no cover - compiled
    """Add shot and read noise, clip and quantise to 8 bits.

    The noise is a counter-based generator (splitmix64 of the key and the
    pixel index), so every pixel's noise depends only on the
    seed and its position: deterministic whatever the number of threads.

    Parameters
    ----------
    img : (H, W) float32
        Noise-free signal in DN.
    key : uint64
        Derived from the seed and the camera.
    shot : float
        Shot-noise variance per DN of signal.
    read2 : float
        Read-noise variance, DN^2.
    out : (H, W) uint8
        Written.
    """
    H, W = img.shape
    for i in range(H):
        for j in range(W):
            s = img[i, j]
            if s < 0.0:
                s = 0.0
            var = s * shot + read2
            if var > 0.0:
                # Irwin-Hall: the sum of four 16-bit uniforms from one hash,
                # centred and scaled to unit variance (a Gaussian to within
                # 1 % out to 3 sigma; sensor noise needs no better).
                h = _splitmix64(key ^ np.uint64(i * W + j))
                acc = 0.0
                for _ in range(4):
                    acc += float(h & np.uint64(0xFFFF))
                    h = h >> np.uint64(16)
                g = (acc * (1.0 / 65536.0) - 2.0) * 1.7320508075688772
                s += math.sqrt(var) * g
            s = math.floor(s + 0.5)
            if s < 0.0:
                s = 0.0
            elif s > 255.0:
                s = 255.0
            out[i, j] = np.uint8(s)
