"""The measuring sequence, step by step: from one trigger's frames, or a cloud, to a verdict.

This module is the only place where the stages are put in order; the
worker, the CLI, the REST API, the benchmarks and the tests all measure
through :func:`measure_frames` and :func:`measure_cloud`. The sequence for
the four-camera flash rig:

1. reconstruct the frames into a cloud in the rig frame;
2. align the cloud to the CAD (global search over the resting poses, then
   robust fine registration);
3. when the first fit can be trusted (``guided``): match the frames again
   with the CAD at that pose shaping the matching windows, fit, match the
   windows on bends once more with the CAD at that fit;
4. fit the final cloud, starting from the first pose;
5. judge the fit (converged, inliers, residual, ambiguity);
6. measure signed deviations over the cloud and at the comparison points,
   set apart the points at edges and the fit's outliers, and search the
   surface for defects;
7. hold each comparison point's verdict against the pose's own uncertainty
   along its normal, and give the part its verdict (a surface defect fails
   it when the spec says so);
   and measure the features of the outline (holes, trim edges, gap and flush)
   in the frames at the fit's pose, one entry per characteristic;
8. where the part has a datum scheme (RPS), align it by its measured datums
   (alone, or holding them on the best fit) and measure it again at that pose.

The comparison-point path (``path="comparison_points"``,
:func:`_measure_at_points`) is a branch of the same sequence: step 1 as a
sparse pass, step 2, then, instead of steps 3 and 6, local photogrammetry
at each comparison point with the CAD at the fitted pose shaping its
windows (:mod:`inspection.cadpoints`), and step 7; the surface between the
points is not checked.

Invalid input raises :class:`~inspection.errors.InvalidInput`; a valid
input that cannot be measured (no surface seen, no fit) gives a
:class:`Measurement` with ``verdict`` None and the reason.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ..alignment import align
from ..alignment.rps import rps_align
from ..cadpoints import LocalModel, measure_points
from ..deviations import (
    FEATURE_KINDS,
    ComparisonPoint,
    Deviations,
    FieldSummary,
    Verdict,
    deviations,
    part_verdict,
)
from ..errors import InspectionError, InvalidInput
from ..feature_checks import check_features, hole_spec
from ..features import Flash, hole_frame
from ..reconstruct import Cloud, Guide, Matching, Reconstructor
from ..registration import LOSSES, Registration, register
from ..rig import Camera, Projector, Rig
from ..transforms import apply
from .judging import _fit_problem, _held_to_the_pose, _reason, fit_quality, judge_points
from .params import Frame, MeasureParams
from .part import PartModel
from .result import Measurement, Pass

log = logging.getLogger(__name__)

MIN_POINTS = 10
"""Fewer measured points than this are not a cloud."""
MAX_POINTS = 20_000_000
"""Larger clouds are refused (memory), far above the rig's ~300k points."""
MAX_COORDINATE_MM = 1e7
"""Coordinates beyond +-10 km are refused: no part is that large, and the fit's
squares of them would overflow."""


def measure_frames(
    part: PartModel,
    rig: Rig | Reconstructor,
    frames: Sequence[npt.NDArray[np.uint8]],
    params: MeasureParams | None = None,
) -> Measurement:
    """Measure one trigger's frames of ``part``.

    Parameters
    ----------
    part : PartModel
    rig : Rig or Reconstructor
        The calibrated rig the frames were taken with; pass its
        ``Reconstructor`` (``Reconstructor.build(rig)``) to reuse the
        precomputed rectification across parts.
    frames : sequence of (H, W) uint8 images, one per camera
    params : MeasureParams, optional
        Default: the line's.

    Returns
    -------
    Measurement
        ``transform`` is T_cad_rig; ``passes`` holds each matching pass.

    Raises
    ------
    InvalidInput
        Frames that do not fit the rig, a part without an alignment model.
    """
    p = params if params is not None else MeasureParams()
    _check_part(part, "rig")
    if isinstance(rig, Reconstructor):
        return _measure_frames(part, rig, frames, p)
    with Reconstructor.build(rig) as rec:  # its threads end with this call
        return _measure_frames(part, rec, frames, p)


def _measure_frames(
    part: PartModel, rec: Reconstructor, frames: Sequence[npt.NDArray[np.uint8]], p: MeasureParams
) -> Measurement:
    if p.path == "comparison_points":
        return _measure_at_points(part, rec, frames, p)
    timings = _Laps()
    t_start = _mark()

    # 1. The cloud, and (guided) what its matching found: where the guided pass starts.
    t = _mark()
    cloud, matching = rec.match(frames) if p.guided else (rec(frames), None)
    _lap(timings, "reconstruct", t)
    first = _pass("first", cloud)
    if len(first.points) == 0:
        return _unmeasured("empty cloud: no surface seen in the frames", timings, t_start, first)

    # 2. and 3. The first fit and, from it, the guided passes.
    passes = [first]
    start: np.ndarray | None = None
    final: Registration | None = None
    if matching is not None:  # p.guided
        t = _mark()
        fit = _try_align(part, first, p)
        passes[0] = dataclasses.replace(first, fit=fit)
        if fit is not None and _trusted(fit, p):
            start = fit.transform
            guide = Guide.from_cad(part.cad, np.linalg.inv(start))
            guided, matching = rec.guided(matching, guide)
            passes += _bends(part, rec, guided, matching, start, p)
            if len(passes[-1].points) == 0:
                log.debug("no guided cloud: measured from the first pass")
                passes, start = passes[:1], None
        else:
            log.debug("no guided pass: the first fit is not trusted")
            final = fit
        _lap(timings, "guide", t)

    # 4. The final fit.
    last = passes[-1]
    t = _mark()
    try:
        if final is None:
            final = _fit(part, last.points, last.weights, p, start=start)
    except InspectionError as exc:
        _lap(timings, "align", t)
        return _unmeasured(f"alignment failed: {exc}", timings, t_start, *passes)
    _lap(timings, "align", t)
    passes[-1] = dataclasses.replace(last, fit=final)
    search = passes[0].fit if start is not None else None
    cameras = np.array([cam.centre for cam in rec.rig.cameras], dtype=np.float64)
    # The outlines' edge model predicts the flash's speckle on the material by them.
    flash = None
    if any(cp.kind in FEATURE_KINDS and cp.kind != "character_line"
           for cp in part.comparison_points):  # fmt: skip
        t = _mark()
        flash = _flash(rec.rig.projector)
        _lap(timings, "flash", t)
    return _judge(
        part, last.points, final, p, "rig", timings, t_start, tuple(passes), search,
        cameras=cameras, views=(tuple(rec.rig.cameras), tuple(frames)), unguided=first.points,
        flash=flash,
    )  # fmt: skip


def _measure_at_points(
    part: PartModel, rec: Reconstructor, frames: Sequence[npt.NDArray[np.uint8]], p: MeasureParams
) -> Measurement:
    """The comparison-point path: a sparse first pass places the part, and each comparison
    point is measured by local photogrammetry around it alone."""
    timings = _Laps()
    t_start = _mark()
    path = "comparison_points"

    # 1. A sparse pass (every few rows, and nothing more): enough to place the part.
    t = _mark()
    cloud = rec.sparse_cloud(frames)
    _lap(timings, "reconstruct", t)
    first = _pass("first", cloud)
    if len(first.points) == 0:
        return _unmeasured("empty cloud: no surface seen in the frames", timings, t_start,
                           first, path=path)  # fmt: skip

    # 2. Its global alignment and fine fit.
    t = _mark()
    try:
        fit = _fit(part, first.points, first.weights, p, max_points=p.pose_points)
    except InspectionError as exc:
        _lap(timings, "align", t)
        return _unmeasured(f"alignment failed: {exc}", timings, t_start, first, path=path)
    _lap(timings, "align", t)
    passes = (dataclasses.replace(first, fit=fit),)
    T = np.asarray(fit.transform, dtype=np.float64)
    quality = fit_quality(fit)
    problem = "registration gave a non-finite transform" if not np.isfinite(T).all() else None
    problem = problem or _fit_problem(fit, quality, p)
    if problem is not None:
        return dataclasses.replace(
            _unmeasured(problem, timings, t_start, *passes, path=path),
            transform=T, registration=fit, quality=quality,
        )  # fmt: skip

    # 3. Each comparison point, by local photogrammetry with the CAD at the pose.
    t = _mark()
    assert part.caster is not None
    model = LocalModel.build(part.cad, part.comparison_points, rec, caster=part.caster)
    local = measure_points(model, frames, T, p.local)
    _lap(timings, "points", t)

    # 4. The verdicts, held to the pose's uncertainty as well as their own.
    devs = _held_to_the_pose(judge_points(part.comparison_points, local, p),
                             part.comparison_points, fit, p)  # fmt: skip
    note = None
    if quality.ambiguous:
        note = (
            "pose ambiguous: another pose fits almost as well "
            f"(score {quality.runner_up_score:.2f} of the chosen one's; a symmetric-looking part)"
        )
    _lap(timings, "total", t_start)
    return Measurement(
        verdict=devs.verdict,
        reason=_reason(devs, note),
        frame="rig",
        transform=T,
        registration=fit,
        quality=quality,
        deviations=devs,
        points=first.points,
        passes=passes,
        timings_ms=dict(timings),
        cpu_ms=dict(timings.cpu),
        path=path,
        local=local,
    )


def measure_cloud(
    part: PartModel,
    points: npt.ArrayLike,
    params: MeasureParams | None = None,
    *,
    frame: Frame = "rig",
    weights: npt.ArrayLike | None = None,
) -> Measurement:
    """Measure a cloud of ``part``.

    Parameters
    ----------
    part : PartModel
    points : (N, 3) float64, mm
        In ``frame``.
    params : MeasureParams, optional
        Default: the line's (``guided`` does not apply to a cloud).
    frame : {"rig", "cad", "data"}
        ``rig``: seen from above (the view direction applies), anywhere on
        the belt; ``data``: any frame, anywhere (no view direction);
        ``cad``: near the CAD frame, only the fine registration runs.
    weights : (N,) float64, optional
        Per-point quality, used when ``params.use_weights``.

    Returns
    -------
    Measurement
        ``transform`` is T_cad_<frame>.

    Raises
    ------
    InvalidInput
        Not an (N, 3) array of finite numbers with at least
        :data:`MIN_POINTS` points; bad weights; an unknown frame; a path other
        than ``cloud``.
    """
    p = params if params is not None else MeasureParams()
    if p.path != "cloud":
        raise InvalidInput(
            f"path {p.path!r} measures a trigger's frames (measure_frames); a cloud is "
            "measured by path 'cloud'"
        )
    if frame not in ("rig", "cad", "data"):
        raise InvalidInput(f"frame must be 'rig', 'cad' or 'data', got {frame!r}")
    _check_part(part, frame)
    cloud = validate_cloud(points)
    w = np.ones(len(cloud)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(cloud),) or not np.isfinite(w).all() or (w < 0).any():
        raise InvalidInput(f"weights must be ({len(cloud)},) finite and >= 0")
    timings = _Laps()
    t_start = _mark()
    t = _mark()
    try:
        fit = _fit(part, cloud, w, p, frame=frame)
    except InspectionError as exc:
        _lap(timings, "align", t)
        return _unmeasured(f"alignment failed: {exc}", timings, t_start, frame=frame)
    _lap(timings, "align", t)
    return _judge(part, cloud, fit, p, frame, timings, t_start, ())


# --------------------------------------------------------------------------- stages


def validate_cloud(points: object) -> np.ndarray:
    """``points`` as a C-contiguous (N, 3) float64 array, or raise InvalidInput.

    Refuses wrong shapes, fewer than :data:`MIN_POINTS` points, more than
    :data:`MAX_POINTS`, any non-finite coordinate (a NaN would silently
    poison the fit) and any beyond :data:`MAX_COORDINATE_MM`.
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
    far = (np.abs(a) > MAX_COORDINATE_MM).any(axis=1)
    if far.any():
        raise InvalidInput(
            f"{int(far.sum())} of {len(a)} points lie beyond +-{MAX_COORDINATE_MM:g} mm"
        )
    return a


def subsample(points: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` of ``points``, evenly strided (deterministic, order kept)."""
    if len(points) <= max_points:
        return points
    return points[_stride(len(points), max_points)]


def _stride(n: int, k: int) -> np.ndarray:
    return np.linspace(0, n - 1, k).round().astype(np.int64)


def _pass(name: str, cloud: Cloud) -> Pass:
    """A pass of ``cloud``'s finite points and their weights."""
    points = np.asarray(cloud.points, dtype=np.float64)
    weights = np.asarray(cloud.weights, dtype=np.float64)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        log.debug("dropping %d non-finite points", int((~finite).sum()))
        points, weights = points[finite], weights[finite]
    return Pass(name, points, weights)


def _fit_inputs(
    points: np.ndarray, weights: np.ndarray, p: MeasureParams, max_points: int | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The points a fit uses (subsampled to ``max_points``, default the params') and their
    weights, if used."""
    n = p.max_points if max_points is None else max_points
    if len(points) > n:
        idx = _stride(len(points), n)
        points, weights = points[idx], weights[idx]
    return points, (weights if p.use_weights else None)


def _fit(
    part: PartModel,
    points: np.ndarray,
    weights: np.ndarray,
    p: MeasureParams,
    *,
    frame: Frame = "rig",
    start: np.ndarray | None = None,
    max_points: int | None = None,
) -> Registration:
    """The fit of a cloud: from ``start`` (no escape scan: the turn was searched),
    from the identity (``frame="cad"``), or by the global search (which searches the turn)."""
    pts, w = _fit_inputs(points, weights, p, max_points)
    rp = p.fit_params(frame)
    if start is not None:
        rp = dataclasses.replace(rp, escape_deg=None)
        return register(part.tree, pts, rp, init=start, weights=w, faces=part.faces)
    if frame == "cad":
        return register(part.tree, pts, rp, init=np.eye(4), weights=w, faces=part.faces)
    rp = dataclasses.replace(rp, escape_deg=None)
    return align(
        part.tree, pts, rp, model=part.alignment, cad=part.cad, weights=w, faces=part.faces
    )


def _try_align(part: PartModel, first: Pass, p: MeasureParams) -> Registration | None:
    try:
        return _fit(part, first.points, first.weights, p, max_points=p.guide_points)
    except InspectionError as exc:
        log.debug("no guided pass: the first alignment failed: %s", exc)
        return None


def _trusted(fit: Registration, p: MeasureParams) -> bool:
    """Whether a first fit is good enough to guide the matching.

    An ambiguous pose guides too: the guide is the CAD at the pose the part
    is measured at either way, and the ambiguity is reported from the search.
    """
    return bool(
        np.isfinite(fit.transform).all()
        and fit.inlier_fraction >= p.min_inlier_fraction
        and fit.rms_mm <= p.max_rms_mm
    )


def _bends(
    part: PartModel,
    rec: Reconstructor,
    guided: Cloud,
    matching: Matching,
    start: np.ndarray,
    p: MeasureParams,
) -> list[Pass]:
    """The guided pass (``guided``, its ``matching``), fitted from ``start``, and the windows
    on bends matched once more with the CAD where that fit puts it; the guided pass alone
    when it cannot be fitted.

    A guided window takes its shape from the guide: placed off, it pulls the
    bends towards it, so they are matched again from the better pose.
    """
    g = _pass("guided", guided)
    if len(g.points) == 0:
        return [g]
    try:
        pts, w = _fit_inputs(g.points, g.weights, p, p.guide_points)
        fit = register(
            part.tree, pts, dataclasses.replace(p.fit_params("rig"), escape_deg=None),
            init=start, weights=w, faces=part.faces,
        )  # fmt: skip
    except InspectionError as exc:
        log.debug("bends not matched again: the guided cloud did not fit: %s", exc)
        return [g]
    g = dataclasses.replace(g, fit=fit)
    bends, _ = rec.rematch_bends(matching, Guide.from_cad(part.cad, np.linalg.inv(fit.transform)))
    return [g, _pass("bends", bends)]


def _judge(
    part: PartModel,
    points: np.ndarray,
    fit: Registration,
    p: MeasureParams,
    frame: Frame,
    timings: _Laps,
    t_start: tuple[float, float],
    passes: tuple[Pass, ...],
    search: Registration | None = None,
    *,
    cameras: np.ndarray | None = None,
    views: tuple[tuple[Camera, ...], tuple[npt.NDArray[np.uint8], ...]] = ((), ()),
    unguided: np.ndarray | None = None,
    flash: Flash | None = None,
) -> Measurement:
    """5.-8.: the fit's quality, the deviations over the cloud and the surface, the features,
    the datum alignment, and the verdict.

    ``search`` is the global search's fit when the final fit started from
    it (the guided passes): its ambiguity is the part's. ``cameras`` are the
    rig's camera centres (rig frame), whose view of the CAD has its occlusion edges;
    ``views`` the calibrated cameras and their frames, in which the features'
    outlines are measured, with ``flash``'s slide; ``unguided`` the first pass's cloud
    (``frame``), in which character lines are found (None: ``points``)."""
    T = np.asarray(fit.transform, dtype=np.float64)
    quality = fit_quality(fit, search)
    if not np.isfinite(T).all():
        return _unmeasured("registration gave a non-finite transform", timings, t_start,
                           *passes, frame=frame)  # fmt: skip
    problem = _fit_problem(fit, quality, p)
    if problem is not None:
        return dataclasses.replace(
            _unmeasured(problem, timings, t_start, *passes, frame=frame),
            transform=T, registration=fit, quality=quality, points=points,
        )  # fmt: skip
    note = None
    if quality.ambiguous:
        note = (
            "pose ambiguous: another pose fits almost as well "
            f"(score {quality.runner_up_score:.2f} of the chosen one's; a symmetric-looking part)"
        )

    lines = points if unguided is None else unguided
    at = functools.partial(
        _deviations_at, part, points, fit=fit, p=p, frame=frame, cameras=cameras, views=views,
        timings=timings, lines=lines, flash=flash,
    )  # fmt: skip

    # 8. The datum alignment, where the part has one: its datums measured at the fit's pose
    # place it, and the whole part is measured once, at the pose the datums give.
    rps = None
    if part.rps is not None:
        t = _mark()
        names = {d.name for d in part.rps.datums}
        datums = at(T, only=[cp for cp in part.comparison_points if cp.name in names])
        measured, why = _datums_measured(part, datums, T)
        if measured is None:
            _lap(timings, "rps", t)
            return dataclasses.replace(
                _unmeasured(why or "", timings, t_start, *passes, frame=frame),
                transform=T, registration=fit, quality=quality, deviations=at(T), points=points,
            )  # fmt: skip
        rps = rps_align(part.rps.datums, measured, init=T, hold=part.rps.mode == "best_fit_rps")
        T = rps.transform
        _lap(timings, "rps", t)
    if rps is None:
        devs = at(T)
    else:
        # A datum on a dent or a bump tilts the part by its height, and in the datums'
        # frame the whole surface would read as one defect. Defects are local shapes, and
        # points are edges or outliers whatever the frame: the surface is assessed with
        # the part placed by its best fit, which spreads no datum's error. The comparison
        # points, the features and the field's values are the datums'.
        devs = at(T, surface=False)
        t = _mark()
        # Each defect names its nearest comparison point: those are measured here too,
        # at little cost (the features are not).
        T_fit = np.asarray(fit.transform, dtype=np.float64)
        shape = _deviations_of(part, apply(T_fit, points), T_fit, part.comparison_points,
                               surface=True, fit=fit, p=p, frame=frame,
                               cameras=cameras)  # fmt: skip
        _lap(timings, "deviations", t, add=True)
        classes, summary = devs.classes, devs.summary
        if shape.classes is not None:
            classes = shape.classes
            summary = FieldSummary.of(devs.distances, classes.surface, classes)
        devs = dataclasses.replace(
            devs, classes=classes, summary=summary, defects=shape.defects,
            defects_fail=shape.defects_fail,
            verdict=part_verdict(devs.comparison, shape.failing_defects),
        )  # fmt: skip
    _lap(timings, "total", t_start)
    return Measurement(
        verdict=devs.verdict,
        reason=_reason(devs, note),
        frame=frame,
        transform=T,
        registration=fit,
        quality=quality,
        deviations=devs,
        points=points,
        passes=passes,
        timings_ms=dict(timings),
        cpu_ms=dict(timings.cpu),
        rps=rps,
    )


def _deviations_at(
    part: PartModel,
    points: np.ndarray,
    T: np.ndarray,
    *,
    fit: Registration,
    p: MeasureParams,
    frame: Frame,
    cameras: np.ndarray | None,
    views: tuple[tuple[Camera, ...], tuple[npt.NDArray[np.uint8], ...]],
    timings: _Laps,
    lines: np.ndarray,
    flash: Flash | None = None,
    only: Sequence[ComparisonPoint] | None = None,
    surface: bool = True,
) -> Deviations:
    """6., 7. and the features: the deviations of ``points`` placed by ``T`` (laps
    ``deviations`` and ``features``); character lines in ``lines`` placed by ``T``.

    ``only``: these comparison points alone, and no search of the surface (the
    datums that place the part before it is measured); ``surface`` False: no search
    of the surface either.

    A guided pass takes its windows' shape from the CAD, which pulls a crease
    towards its drawn place: lines are found in the unguided first pass."""
    comparison_points = part.comparison_points if only is None else tuple(only)
    t = _mark()
    points_cad = apply(T, points)
    devs = _deviations_of(part, points_cad, T, comparison_points,
                          surface=only is None and surface, fit=fit, p=p, frame=frame,
                          cameras=cameras)  # fmt: skip
    devs = _held_to_the_pose(devs, comparison_points, fit, p)
    _lap(timings, "deviations", t)
    if any(cp.kind in FEATURE_KINDS for cp in comparison_points):
        t = _mark()
        devs = check_features(
            devs, comparison_points, part.cad, points_cad, T, *views, tree=part.exact,
            line_points_cad=points_cad if lines is points else apply(T, lines), flash=flash,
        )  # fmt: skip
        _lap(timings, "features", t)
    return devs


def _deviations_of(
    part: PartModel,
    points_cad: np.ndarray,
    T: np.ndarray,
    comparison_points: Sequence[ComparisonPoint],
    *,
    surface: bool,
    fit: Registration,
    p: MeasureParams,
    frame: Frame,
    cameras: np.ndarray | None,
) -> Deviations:
    """:func:`~inspection.deviations.deviations` of ``points_cad`` (placed by ``T``) at
    ``comparison_points``, and with ``surface`` the surface's classes and defects; the
    cameras' places, or the direction they look from, in the CAD frame of ``T`` give the
    surface model its occlusion edges."""
    viewpoints = directions = None
    if cameras is not None:
        viewpoints = apply(T, cameras)
    elif frame == "rig" and p.register.view_direction is not None:
        directions = (T[:3, :3] @ np.asarray(p.register.view_direction, dtype=np.float64))[None]
    return deviations(
        part.exact,
        points_cad,
        comparison_points,
        min_support=p.min_support,
        max_distance_mm=p.register.max_distance_mm,
        surface=part.surface if surface else None,
        surface_params=p.surface,
        outlier_mm=rejection_mm(fit),
        viewpoints=viewpoints,
        view_directions=directions,
    )


def _datums_measured(
    part: PartModel, devs: Deviations, T: np.ndarray
) -> tuple[np.ndarray | None, str | None]:
    """The datums as measured, in the measured points' frame (placed by ``T``), or why not."""
    assert part.rps is not None
    entries = {c.name: c for c in devs.comparison}
    named = {cp.name: cp for cp in part.comparison_points}
    out = []
    for d in part.rps.datums:
        cp = named[d.name]
        keys = ("x", "y") if cp.kind == "hole" else ("",)
        found = [entries[f"{d.name}.{k}" if k else d.name] for k in keys]
        bad = [c for c in found if c.verdict is Verdict.NOT_MEASURABLE]
        if bad:
            return None, f"RPS datum {d.name} not measurable: {bad[0].reason}"
        q = np.asarray(cp.position, dtype=np.float64)
        if cp.kind == "hole":
            x, y, _ = hole_frame(cp.normal, hole_spec(cp).axis)
            q = q + found[0].deviation_mm * x + found[1].deviation_mm * y
        else:
            q = q + found[0].deviation_mm * np.asarray(cp.normal)
        out.append(q)
    return apply(np.linalg.inv(T), np.array(out)), None


def rejection_mm(fit: Registration) -> float:
    """The distance beyond which the fit gives a point no weight: where Tukey's biweight
    reaches zero at the fit's scale (the same distance for losses that never reach zero)."""
    return float(LOSSES["tukey"][1] * fit.scale_mm) if fit.scale_mm > 0 else math.inf


def _unmeasured(
    reason: str,
    timings: _Laps,
    t_start: tuple[float, float],
    *passes: Pass,
    frame: Frame = "rig",
    path: str = "cloud",
) -> Measurement:
    _lap(timings, "total", t_start)
    log.debug("not measured: %s", reason)
    return Measurement(
        verdict=None,
        reason=reason,
        frame=frame,
        points=passes[-1].points if passes else np.empty((0, 3)),
        passes=passes,
        timings_ms=dict(timings),
        cpu_ms=dict(timings.cpu),
        path=path,
    )


def _check_part(part: PartModel, frame: Frame) -> None:
    if not isinstance(part, PartModel):
        raise InvalidInput(f"part must be a PartModel, got {type(part).__name__}")
    if frame != "cad" and part.alignment is None:
        raise InvalidInput(
            f"part {part.cad.name!r} has no alignment model: build it with alignment=True "
            "to measure clouds that lie anywhere"
        )


@functools.lru_cache(maxsize=4)
def _flash(projector: Projector) -> Flash:
    """The projector's slide, rendered once: it is the rig's, the same for every part
    (a projector is one object per rig, hashed by identity)."""
    return Flash.build(projector)


class _Laps(dict[str, float]):
    """Wall time per stage, ms, and beside it (``cpu``) the process's CPU time, ms."""

    def __init__(self) -> None:
        super().__init__()
        self.cpu: dict[str, float] = {}


def _mark() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()


def _lap(laps: _Laps, stage: str, since: tuple[float, float], *, add: bool = False) -> None:
    """The stage's time since ``since``; ``add``: added to what the stage already took."""
    laps[stage] = (time.perf_counter() - since[0]) * 1e3 + (laps.get(stage, 0.0) if add else 0.0)
    laps.cpu[stage] = (time.process_time() - since[1]) * 1e3 + (
        laps.cpu.get(stage, 0.0) if add else 0.0
    )
