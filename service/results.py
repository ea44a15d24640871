"""An :class:`~inspection.measure.Measurement` as the service publishes it: an InspectionResult.

The measuring sequence decides everything about the part (its verdict, the
reason, the fit's diagnostics, the field's statistics); this module only
maps that onto the pydantic model, adding the trigger's identity and what
makes the result traceable.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from inspection.deviations import Deviations, Verdict
from inspection.measure import Frame, Measurement, measure_cloud
from inspection.transforms import apply

from .models import (
    FieldStats,
    InspectionResult,
    PointResult,
    Status,
    SurfaceDefectResult,
    finite_or_none,
    software_version,
)
from .parts import LoadedPart


@dataclass(frozen=True)
class Trigger:
    """Where a measurement comes from: the identity a result carries.

    ``id`` is the result's id (``make_result_id`` for triggers).
    """

    id: str
    line: str
    station: str
    part: str
    serial: str
    seq: int
    triggered_ns: int
    calibration_id: str | None = None
    spec_version: str | None = None
    cad_hash: str | None = None
    tree_hash: str | None = None
    software_version: str = ""


@dataclass(frozen=True, eq=False)
class Outcome:
    """The result and the arrays behind it (for the recorder and the deviation archive).

    Attributes
    ----------
    result : InspectionResult
    points : (N, 3) float64 or None
        The measured cloud, in the frame it was given in (rig for frames), mm.
    distances : (N,) float64 or None
        Signed deviation of each point from the CAD, mm; NaN for points that
        are not inliers.
    transform : (4, 4) float64 or None
        T_cad_<frame> of ``points``.
    maps : dict of str to (H, W) float64
        The sensor's own maps (``inspection.Measurement.maps``), for the recordings.
    """

    result: InspectionResult
    points: np.ndarray | None = field(default=None, repr=False)
    distances: np.ndarray | None = field(default=None, repr=False)
    transform: np.ndarray | None = field(default=None, repr=False)
    maps: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def points_cad(self) -> np.ndarray | None:
        """``points`` in the CAD frame (None without a fit)."""
        if self.points is None or self.transform is None:
            return None
        return apply(self.transform, self.points)


def upload_trigger(
    part: LoadedPart, *, id: str, line: str, station: str, serial: str, triggered_ns: int
) -> Trigger:
    """The identity of a cloud measured outside the line (an API upload, a CLI file)."""
    return Trigger(
        id=id,
        line=line,
        station=station,
        part=part.name,
        serial=serial,
        seq=0,
        triggered_ns=triggered_ns,
        spec_version=part.spec.version,
        cad_hash=part.cad.hash,
        tree_hash=part.tree_hash,
        software_version=software_version(),
    )


def measure_upload(
    part: LoadedPart, points: np.ndarray, trigger: Trigger, *, frame: Frame = "rig"
) -> Outcome:
    """Measure an uploaded cloud with the part's own parameters (``inspection.measure_cloud``).

    Raises
    ------
    inspection.InvalidInput
        The cloud is not an (N, 3) array of finite numbers with enough points.
    """
    return outcome(measure_cloud(part.model, points, part.params, frame=frame), trigger)


def outcome(m: Measurement, trigger: Trigger) -> Outcome:
    """The result of ``m`` for ``trigger``, with the per-point arrays behind it."""
    status = Status.error if m.verdict is None else Status(m.verdict.value)
    fit: dict[str, object] = {}
    if m.transform is not None and np.isfinite(m.transform).all():
        fit["transform"] = np.asarray(m.transform, dtype=np.float64).tolist()
    if m.registration is not None:
        fit["rms_mm"] = finite_or_none(m.registration.rms_mm)
        fit["inlier_fraction"] = finite_or_none(m.registration.inlier_fraction)
    if m.quality is not None:
        q = m.quality
        fit |= dict(
            converged=q.converged,
            stop_reason=q.stop_reason,
            iterations=q.iterations,
            observability=finite_or_none(q.observability),
            weak_directions=list(q.weak_directions),
            ambiguous=q.ambiguous,
            runner_up_score=finite_or_none(q.runner_up_score),
        )
    devs = m.deviations
    measured: dict[str, object] = {}
    distances = None
    if devs is not None:
        measured = dict(
            comparison=point_results(devs), defects=defect_results(devs), field=field_stats(devs)
        )
        distances = np.where(devs.inliers, devs.distances, np.nan)
    measured["path"] = m.path
    result = InspectionResult(
        **dataclasses.asdict(trigger),
        status=status,
        reason=None if m.reason is None else m.reason[:2000],
        timings_ms=dict(m.timings_ms),
        **fit,  # type: ignore[arg-type]
        **measured,  # type: ignore[arg-type]
    )
    points = m.points if len(m.points) else None
    T = None if "transform" not in fit else np.asarray(m.transform, dtype=np.float64)
    return Outcome(result, points=points, distances=distances, transform=T, maps=dict(m.maps))


def point_results(devs: Deviations) -> list[PointResult]:
    return [
        PointResult(
            name=c.name,
            deviation_mm=None
            if c.verdict is Verdict.NOT_MEASURABLE
            else finite_or_none(c.deviation_mm),
            lower_mm=c.lower_mm,
            upper_mm=c.upper_mm,
            support=int(c.support),
            verdict=c.verdict,
            reason=c.reason,
            kind=c.kind,
            at_mm=None if c.at_mm is None else list(c.at_mm),
        )
        for c in devs.comparison
    ]


def defect_results(devs: Deviations) -> list[SurfaceDefectResult] | None:
    """The surface defects found; None where the surface was not checked."""
    if devs.defects is None:
        return None
    return [
        SurfaceDefectResult(
            kind=f.kind,  # type: ignore[arg-type]
            center_mm=[float(v) for v in f.center_mm],
            area_mm2=f.area_mm2,
            peak_mm=f.peak_mm,
            mean_mm=f.mean_mm,
            nearest_point=f.nearest_point,
            points=f.points,
        )
        for f in devs.defects
    ]


def field_stats(devs: Deviations) -> FieldStats:
    s = devs.summary
    counts = dict(points=s.n, inliers=s.inliers, edge=s.edge, outliers=s.outliers, far=s.far)
    if s.inliers == 0:
        return FieldStats(**counts)

    def f(x: float) -> float | None:
        return None if math.isnan(x) else finite_or_none(x)

    return FieldStats(
        **counts,
        mean_mm=f(s.mean_mm),
        std_mm=f(s.std_mm),
        rms_mm=f(s.rms_mm),
        min_mm=f(s.min_mm),
        max_mm=f(s.max_mm),
        median_mm=f(s.median_mm),
        p001_mm=f(s.p001_mm),
        p05_mm=f(s.p05_mm),
        p95_mm=f(s.p95_mm),
        p999_mm=f(s.p999_mm),
    )
