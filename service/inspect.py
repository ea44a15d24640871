"""One point cloud and one part in, one :class:`~service.models.InspectionResult` out.

The steps read like the algorithm: validate the cloud, align it to the
part's CAD tree (global search then robust fine registration, or only the
fine registration when the cloud is already near the CAD frame), measure
signed deviations at every point and at the comparison points, and give the
part its status. Invalid clouds raise :class:`~inspection.errors.InvalidInput`
(the API answers 422, the worker publishes an error result); a cloud that is
valid but cannot be fitted gives a result with status ``error`` and the reason.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np

from inspection.errors import InspectionError, InvalidInput

from .config import PartSpec
from .models import (
    FieldStats,
    InspectionResult,
    PointResult,
    Status,
    Verdict,
    finite_or_none,
    software_version,
)
from .parts import LoadedPart

log = logging.getLogger(__name__)

MAX_POINTS = 20_000_000
"""Larger clouds are refused (memory), far above the rig's ~300k points."""

MIN_POINTS = 10


class CloudFrame(StrEnum):
    """The frame a cloud is given in.

    ``rig``: anywhere on the conveyor; a global alignment finds the part.
    ``cad``: already close to the CAD frame; only the fine registration runs.
    """

    rig = "rig"
    cad = "cad"


@dataclass(frozen=True)
class Trigger:
    """Where a cloud comes from: the metadata a result carries.

    ``id`` is the result's id (``make_result_id`` for triggers).
    """

    id: str
    line: str
    station: str
    serial: str
    seq: int
    triggered_ns: int
    calibration_id: str | None = None


@dataclass(frozen=True)
class Inspection:
    """A result and the per-point arrays behind it.

    Attributes
    ----------
    result : InspectionResult
    points_cad : (N, 3) float64, mm, or None
        The cloud in the CAD frame (None when no fit was made).
    distances : (N,) float64, mm, or None
        Signed deviation per point (positive on the outer side); NaN where
        the point was not measured.
    """

    result: InspectionResult
    points_cad: np.ndarray | None = field(default=None, repr=False)
    distances: np.ndarray | None = field(default=None, repr=False)


def comparison_points(spec: PartSpec) -> list[Any]:
    """The spec's comparison points as ``inspection.ComparisonPoint`` objects."""
    from inspection.deviations import ComparisonPoint

    out = []
    for p in spec.points:
        kwargs: dict[str, Any] = dict(
            name=p.name,
            position=np.asarray(p.position_mm, dtype=np.float64),
            normal=np.asarray(p.normal, dtype=np.float64),
            lower_mm=p.lower_mm,
            upper_mm=p.upper_mm,
            radius_mm=p.radius_mm,
        )
        fields = getattr(ComparisonPoint, "__dataclass_fields__", {})
        if "kind" in fields:
            kwargs["kind"] = p.kind.value
        if "min_support" in fields:
            kwargs["min_support"] = p.min_support
        out.append(ComparisonPoint(**kwargs))
    return out


def validate_cloud(points: Any) -> np.ndarray:
    """Return ``points`` as a C-contiguous (N, 3) float64 array, or raise InvalidInput.

    Refuses wrong shapes, fewer than :data:`MIN_POINTS` points, more than
    :data:`MAX_POINTS`, and any non-finite coordinate (a NaN would silently
    poison the fit).
    """
    a = np.asarray(points)
    if a.dtype.kind not in "fiu":
        raise InvalidInput(f"point coordinates must be numbers, got dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] != 3:
        raise InvalidInput(f"a point cloud is an (N, 3) array, got shape {a.shape}")
    if len(a) < MIN_POINTS:
        raise InvalidInput(f"the cloud has {len(a)} points; at least {MIN_POINTS} are needed")
    if len(a) > MAX_POINTS:
        raise InvalidInput(f"the cloud has {len(a)} points; at most {MAX_POINTS} are accepted")
    a = np.ascontiguousarray(a, dtype=np.float64)
    finite = np.isfinite(a).all(axis=1)
    if not finite.all():
        raise InvalidInput(
            f"{int((~finite).sum())} of {len(a)} points have non-finite coordinates (NaN or inf)"
        )
    return a


def subsample(points: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` of ``points``, evenly strided (deterministic, order kept)."""
    if len(points) <= max_points:
        return points
    idx = np.linspace(0, len(points) - 1, max_points).round().astype(np.int64)
    return points[idx]


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def _registration_kwargs(part: LoadedPart, *, rig_frame: bool = True) -> dict[str, Any]:
    """Keyword arguments of ``align``/``register`` from the part's settings; the
    direction towards the sensor is known only for clouds in the rig frame."""
    r = part.spec.registration
    kwargs: dict[str, Any] = {
        "loss": r.loss.value,
        "max_iterations": r.max_iterations,
        "max_distance_mm": r.max_correspondence_mm,
    }
    if rig_frame and (view := r.view_direction()) is not None:
        kwargs["view_direction"] = view
    return kwargs


def _field_stats(distances: np.ndarray, inliers: np.ndarray) -> FieldStats:
    d = distances[inliers & np.isfinite(distances)]
    if len(d) == 0:
        return FieldStats(points=len(distances), inliers=0)
    p05, p95 = np.percentile(d, [5.0, 95.0])
    return FieldStats(
        points=len(distances),
        inliers=len(d),
        mean_mm=finite_or_none(d.mean()),
        std_mm=finite_or_none(d.std()),
        rms_mm=finite_or_none(np.sqrt(np.mean(d * d))),
        min_mm=finite_or_none(d.min()),
        max_mm=finite_or_none(d.max()),
        p05_mm=finite_or_none(p05),
        p95_mm=finite_or_none(p95),
    )


def _point_results(part: LoadedPart, devs: Any) -> list[PointResult]:
    specs = {p.name: p for p in part.spec.points}
    out = []
    for c in devs.comparison:
        spec = specs[c.name]
        dev = finite_or_none(c.deviation_mm)
        verdict = Verdict(str(getattr(c.verdict, "value", c.verdict)))
        out.append(
            PointResult(
                name=c.name,
                deviation_mm=dev if verdict != Verdict.not_measurable else None,
                lower_mm=spec.lower_mm,
                upper_mm=spec.upper_mm,
                support=int(c.support),
                verdict=verdict,
            )
        )
    return out


def _reason(status: Status, comparison: list[PointResult], note: str | None) -> str | None:
    """Which points made the status, and any note of the fit."""
    parts = []
    if status == Status.fail:
        names = [c.name for c in comparison if c.verdict == Verdict.fail]
        parts.append("out of tolerance at " + ", ".join(names))
    elif status == Status.not_measurable:
        names = [c.name for c in comparison if c.verdict == Verdict.not_measurable]
        parts.append("not enough support at " + ", ".join(names))
    if note:
        parts.append(note)
    return "; ".join(parts) or None


def part_status(points: list[PointResult]) -> Status:
    """The part's status: any point failed, else any not measurable, else pass."""
    verdicts = {p.verdict for p in points}
    if Verdict.fail in verdicts:
        return Status.fail
    if Verdict.not_measurable in verdicts:
        return Status.not_measurable
    return Status.passed


def inspect_cloud(
    part: LoadedPart,
    points: Any,
    trigger: Trigger,
    *,
    frame: CloudFrame | str = CloudFrame.rig,
    timings_ms: dict[str, float] | None = None,
    fit: Callable[[LoadedPart, np.ndarray], Any] | None = None,
    measure: Callable[[LoadedPart, np.ndarray], Any] | None = None,
) -> Inspection:
    """Align a cloud to ``part`` and measure it.

    Parameters
    ----------
    part : LoadedPart
    points : (N, 3) array, mm
        In the rig frame (``frame="rig"``) or near the CAD frame (``"cad"``).
    trigger : Trigger
    frame : {"rig", "cad"}
    timings_ms : dict, optional
        Timings of earlier stages (e.g. ``reconstruct``) to carry into the result.
    fit, measure : callable(part, points) -> registration / deviations, optional
        Replace the global alignment (``frame="rig"``) and the deviation
        measurement; the line's pipeline passes its stages here, so the REST
        API and the line turn a cloud into a result by the same steps.

    Returns
    -------
    Inspection
        ``result.transform`` is T_cad_rig (T_cad_data for ``frame="cad"``).

    Raises
    ------
    InvalidInput
        The cloud is not an (N, 3) array of finite numbers with enough points.
    """
    from inspection.alignment import align
    from inspection.deviations import deviations
    from inspection.registration import register

    frame = CloudFrame(frame)
    t_start = time.perf_counter()
    timings = dict(timings_ms or {})
    cloud = validate_cloud(points)
    spec = part.spec
    base: dict[str, Any] = dict(
        id=trigger.id,
        line=trigger.line,
        station=trigger.station,
        part=spec.name,
        serial=trigger.serial,
        seq=trigger.seq,
        triggered_ns=trigger.triggered_ns,
        spec_version=spec.version,
        cad_hash=part.cad.hash,
        tree_hash=part.tree_hash,
        calibration_id=trigger.calibration_id,
        software_version=software_version(),
    )

    def error(reason: str, **extra: Any) -> Inspection:
        timings["total"] = (time.perf_counter() - t_start) * 1e3 + sum(
            v for k, v in timings.items() if k != "total"
        )
        log.info("part %s serial %s: error: %s", spec.name, trigger.serial, reason)
        return Inspection(
            InspectionResult(
                **base, status=Status.error, reason=reason, timings_ms=timings, **extra
            )
        )

    # 1. Fit: global search + robust registration, or only the registration.
    t0 = time.perf_counter()
    fit_points = subsample(cloud, spec.registration.max_points)
    reg: Any
    try:
        if frame == CloudFrame.rig and fit is not None:
            reg = fit(part, fit_points)
        elif frame == CloudFrame.rig:
            reg = align(
                part.tree, fit_points, model=part.alignment_model, cad=part.cad,
                **_registration_kwargs(part),
            )  # fmt: skip
        else:
            reg = register(
                part.tree,
                fit_points,
                init=np.eye(4),
                **_registration_kwargs(part, rig_frame=False),
            )
    except InspectionError as exc:
        timings["align"] = (time.perf_counter() - t0) * 1e3
        return error(f"alignment failed: {exc}")
    timings["align"] = (time.perf_counter() - t0) * 1e3
    T = np.asarray(reg.transform, dtype=np.float64)
    if not np.isfinite(T).all():
        return error("registration gave a non-finite transform")
    fitted: dict[str, Any] = dict(
        transform=T.tolist(),
        rms_mm=finite_or_none(reg.rms_mm),
        inlier_fraction=finite_or_none(reg.inlier_fraction),
    )
    note = None
    if getattr(reg, "ambiguous", False):
        note = "pose ambiguous: another pose fits almost as well (a symmetric-looking part)"
        if spec.registration.ambiguous_is_error:
            return error(note, **fitted)
    if not reg.inlier_fraction >= spec.registration.min_inlier_fraction:
        return error(
            f"fit kept {reg.inlier_fraction:.0%} of the points, "
            f"below the {spec.registration.min_inlier_fraction:.0%} required",
            **fitted,
        )
    if not reg.rms_mm <= spec.registration.max_rms_mm:
        return error(
            f"fit residual {reg.rms_mm:.3f} mm above the {spec.registration.max_rms_mm} mm allowed",
            **fitted,
        )

    # 2. Deviations of every point and at the comparison points, in the CAD frame.
    t0 = time.perf_counter()
    points_cad = _apply(T, cloud)
    try:
        if measure is not None:
            devs = measure(part, points_cad)
        else:
            devs = deviations(part.tree, points_cad, comparison_points(spec))
    except InspectionError as exc:
        timings["deviations"] = (time.perf_counter() - t0) * 1e3
        return error(f"deviations failed: {exc}", **fitted)
    distances = np.asarray(devs.distances, dtype=np.float64)
    inliers = np.abs(distances) <= spec.registration.max_correspondence_mm
    comparison = _point_results(part, devs)
    timings["deviations"] = (time.perf_counter() - t0) * 1e3

    # 3. The verdict.
    status = part_status(comparison)
    timings["total"] = (time.perf_counter() - t_start) * 1e3 + sum(
        v for k, v in timings.items() if k not in ("total", "align", "deviations")
    )
    result = InspectionResult(
        **base,
        status=status,
        reason=_reason(status, comparison, note),
        comparison=comparison,
        field=_field_stats(distances, inliers),
        timings_ms=timings,
        **fitted,
    )
    kept = np.where(inliers, distances, np.nan)
    return Inspection(result=result, points_cad=points_cad, distances=kept)


def warm_up(part: LoadedPart, *, points: int = 3000) -> float:
    """Run the whole measurement once on points of the part's own surface; returns seconds.

    The numerical kernels compile on their first call (seconds); doing it
    while the part loads keeps that off the first inspected part.
    """
    t0 = time.perf_counter()
    cad = part.cad
    up = cad.faces[cad.face_normals[:, 2] > 0.3]
    if len(up) == 0:
        up = cad.faces
    # Points spread evenly over the faces looking up: a cloud like the rig's.
    tri = cad.vertices[up]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(0)
    pick = rng.choice(len(tri), size=points, p=area / area.sum())
    a, b = rng.random((2, points))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[pick]
    cloud = t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])
    if len(cloud) < MIN_POINTS:
        return 0.0
    trigger = Trigger(id="warm-up", line="warm-up", station="warm-up", serial="warm-up",
                      seq=0, triggered_ns=0)  # fmt: skip
    for frame in (CloudFrame.rig, CloudFrame.cad):
        try:
            r = inspect_cloud(part, cloud, trigger, frame=frame).result
        except (InspectionError, ModuleNotFoundError) as exc:
            log.info("warm-up of %s incomplete: %s", part.name, exc)
            break
        if r.status == Status.error:
            log.info("warm-up of %s (%s frame): %s", part.name, frame.value, r.reason)
    return time.perf_counter() - t0
