"""The diverging colour scale of signed deviations: blue below the CAD, white on it, red above."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

NOT_MEASURED = 0.5
"""The grey (relative intensity, all three channels) of a point without a deviation (NaN)."""


def deviation_colours(values: npt.ArrayLike, limit_mm: float) -> npt.NDArray[np.uint8]:
    """Colours of signed deviations: blue (-limit) - white (0) - red (+limit).

    Parameters
    ----------
    values : (N,) float64, mm
        Signed deviations; NaN gives the grey :data:`NOT_MEASURED` (128).
    limit_mm : float
        Deviation shown at full saturation (> 0); beyond it the colour stays.

    Returns
    -------
    (N, 3) uint8 RGB
    """
    v = np.asarray(values, dtype=np.float64)
    t = np.clip(v / limit_mm, -1.0, 1.0)
    rgb = np.empty((len(v), 3))
    pos = t >= 0
    # Towards red: keep R, lower G and B; towards blue: keep B, lower R and G.
    rgb[:, 0] = np.where(pos, 1.0, 1.0 + t)
    rgb[:, 1] = 1.0 - np.abs(t)
    rgb[:, 2] = np.where(pos, 1.0 - t, 1.0)
    rgb[~np.isfinite(v)] = NOT_MEASURED
    return np.rint(rgb * 255).astype(np.uint8)
