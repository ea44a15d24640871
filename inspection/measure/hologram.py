"""The measuring sequence's branch for the holographic head: one hologram to a verdict.

The same sequence as the flash rig's from the cloud on; what differs is how
the cloud is made, and that the head's phase needs the CAD before it can be
turned into heights at all:

1. **shape against the CAD** at the pose the part is known to lie at
   (:func:`inspection.holography.measure_shape`): the phase difference of
   the two lasers, unwrapped with the CAD's prediction, the out-of-plane
   pose fitted from it, and the regions beyond a quarter of the synthetic
   wavelength flagged instead of measured;
2. the measured pixels as points of the head frame, weighted by the phase's
   coherence;
3. the **fine registration** of those points to the CAD (the line's robust
   point-to-surface fit), from the pose the phase gave;
4. judged as every cloud is: the fit's quality, the deviations over the
   points and at the comparison points, the verdict;
5. a region beyond the range (a known order off, of unknown order, or
   measured within its uncertainty of the limit), or a judged deviation
   beyond it by more than its uncertainty, is a deviation larger than any
   tolerance the head is used for: it fails a part that would otherwise
   pass, and the reason names it;
6. the phase and the judged deviations as maps on the head's pixel grid,
   for the recordings.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import numpy.typing as npt

from ..arrays import Transform
from ..deviations import Verdict
from ..errors import InspectionError, InvalidInput
from ..holography import HoloCalibration, ShapeParams, measure_shape
from ..holography.shape import FlaggedRegion, HoloShape
from ..registration import register
from .params import MeasureParams
from .part import PartModel
from .result import Measurement, Pass
from .sequence import _check_part, _fit_inputs, _judge, _lap, _Laps, _mark, _unmeasured

log = logging.getLogger(__name__)


def measure_hologram(
    part: PartModel,
    calib: HoloCalibration,
    image: npt.ArrayLike,
    T_head_cad: Transform,
    params: MeasureParams | None = None,
    *,
    shape: ShapeParams | None = None,
) -> Measurement:
    """Measure one hologram of ``part``.

    Parameters
    ----------
    part : PartModel
        Needs no alignment model: the pose is known to the head's range.
    calib : HoloCalibration
        The head's calibration.
    image : (n, n) uint16 hologram
    T_head_cad : (4, 4) float64
        Where the part lies under the head (its fixture), to well within a
        quarter of the synthetic wavelength in height.
    params : MeasureParams, optional
        The line's (registration, tolerances, fit-quality limits).
    shape : ShapeParams, optional
        How the phase is turned into a shape.

    Returns
    -------
    Measurement
        ``frame`` "data": the head frame; ``transform`` is T_cad_head;
        ``passes`` holds the one pass ("hologram") and its fit.

    Raises
    ------
    InvalidInput
        An image that does not fit the calibration, a bad pose.
    """
    p = params if params is not None else MeasureParams()
    _check_part(part, "cad")
    T0 = np.asarray(T_head_cad, dtype=np.float64)
    if T0.shape != (4, 4) or not np.isfinite(T0).all():
        raise InvalidInput(f"T_head_cad must be a finite (4, 4) array, got shape {T0.shape}")
    timings = _Laps()
    t_start = _mark()

    # 1. The shape against the CAD.
    t = _mark()
    holo = measure_shape(calib, image, part.cad, T0, shape)
    _lap(timings, "hologram", t)

    # 2. Its points.
    points, weights = _points(calib, holo)
    first = Pass("hologram", points, weights)
    if len(points) < max(p.register.min_points, 6):
        return _unmeasured(
            f"only {len(points)} pixels measured", timings, t_start, first, frame="data"
        )

    # 3. The fine registration, from the pose the phase gave.
    t = _mark()
    rp = dataclasses.replace(p.fit_params("data"), escape_deg=None)
    pts, w = _fit_inputs(points, weights, p)
    try:
        init = np.asarray(np.linalg.inv(holo.T_head_part), dtype=np.float64)
        fit = register(part.tree, pts, rp, init=init, weights=w, faces=part.faces)
    except InspectionError as exc:
        _lap(timings, "align", t)
        return _unmeasured(f"alignment failed: {exc}", timings, t_start, first, frame="data")
    _lap(timings, "align", t)

    # 4. Judged as every cloud.
    passes = (dataclasses.replace(first, fit=fit),)
    m = _judge(part, points, fit, p, "data", timings, t_start, passes)
    m = dataclasses.replace(m, maps=_maps(holo, m))

    # 5. What lies beyond the range.
    judged = _judged_beyond(holo, m.maps["deviation"], shape)
    if not holo.regions and not judged:
        return m
    notes = []
    if holo.regions:
        listed = "; ".join(_describe(r) for r in holo.regions)
        n = len(holo.regions)
        notes.append(
            f"{n} region{'s' if n > 1 else ''} beyond the holographic range "
            f"(+-{holo.limit_mm:.3f} mm) or possibly so: {listed}"
        )
    if judged:
        notes.append(
            f"{judged} measured pixel{'s' if judged > 1 else ''} deviating beyond the "
            f"holographic range (+-{holo.limit_mm:.3f} mm) by more than their uncertainty"
        )
    note = "; ".join(notes)
    verdict = Verdict.FAIL if m.verdict in (Verdict.PASS, Verdict.FAIL) else m.verdict
    reason = note if not m.reason else f"{m.reason}; {note}"
    log.debug("hologram: %s", note)
    return dataclasses.replace(m, verdict=verdict, reason=reason)


def _describe(r: FlaggedRegion) -> str:
    x, y = r.centroid_mm
    where = f"{r.area_mm2:.1f} mm^2 at ({x:.1f}, {y:.1f}) mm of the head"
    if r.kind == "unknown_order":
        return f"{where}, of unknown order (cut off by unmeasurable pixels): may exceed the range"
    if r.kind == "unmeasured":
        return f"{where}, not measurable (a slope too steep for the head?): may exceed the range"
    if r.kind == "at_limit":
        return (
            f"{where}, {r.estimate_mm:+.3f} mm with the aperture's blur taken back: "
            "at the limit within its uncertainty"
        )
    return f"{where}, about {r.estimate_mm:+.2f} mm"


def _judged_beyond(
    holo: HoloShape, deviation: npt.NDArray[np.float64], shape: ShapeParams | None
) -> int:
    """Measured pixels whose judged deviation (after the fine registration) exceeds the
    range by more than their expanded uncertainty: the fit can move the part against
    the phase's pose, and a deviation measured beyond the range is not one the
    unwrapping vouches for."""
    k = (shape or ShapeParams()).limit_coverage
    with np.errstate(invalid="ignore"):
        over = np.abs(deviation) - k * holo.uncertainty_mm > holo.limit_mm
    return int(np.count_nonzero(over & holo.measured))


def _maps(holo: HoloShape, m: Measurement) -> dict[str, npt.NDArray[np.float64]]:
    deviation = np.full(holo.measured.shape, np.nan)
    if m.deviations is not None:
        # The judged distances, one per measured pixel in row-major order; the fit's
        # outliers stay NaN as they do in the cloud.
        d = m.deviations
        deviation[holo.measured] = np.where(d.inliers, d.distances, np.nan)
    phase = np.where(holo.measured | holo.flagged, holo.wrapped_phase, np.nan)
    return {"phase": phase, "deviation": deviation}


def _points(
    calib: HoloCalibration, holo: HoloShape
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    x, y = calib.head.grid()
    sel = holo.measured
    points = np.stack([x[sel], y[sel], holo.height_mm[sel]], axis=1)
    return np.ascontiguousarray(points), np.ascontiguousarray(holo.coherence[sel])
