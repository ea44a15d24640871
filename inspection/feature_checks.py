"""The features' comparison entries: holes, trim edges, gap/flush and character lines,
checked after the fit.

A feature comparison point becomes one entry per characteristic, named
``<point>.<characteristic>`` with the point's ``kind``: ``H1.x``, ``H1.y``
(the centre's offset along the hole's x and y), ``H1.d`` (the diameter's
deviation) and for a slot ``H1.len``; ``E3.trim`` (the edge's offset out
of the material: the mean offset of the curve fitted to its points) and
``E3.trim_max`` (that curve's largest offset, with where it lies); ``G2.gap``
and ``G2.flush`` (the gap to the mating part's nominal edge, and the
surface's height against it, as deviations from the nominal); ``C1.line`` and
``C1.line_max`` (a character line's mean offset across itself in the surface,
and its largest, with where). The outline is measured in the images
(:mod:`inspection.features`), a character line in the cloud
(:mod:`inspection.character_line`); given only a cloud, a hole is measured
from the cloud's rim, whose bias at edges the entry's reason states.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from .arrays import Image, Points, Scalars, Transform
from .cad import CadModel
from .character_line import measure_character_line
from .deviations import (
    FEATURE_KINDS,
    ComparisonPoint,
    ComparisonResult,
    Deviations,
    Verdict,
    part_verdict,
    robust_location,
)
from .features import (
    EdgeParams,
    Flash,
    HoleSpec,
    boundary_samples,
    hole_from_cloud,
    measure_hole,
    measure_trim_edge,
)
from .protocols import ClosestPointQuery
from .rig import Camera

__all__ = ["check_features", "hole_spec"]

# The surface's measured offset is pooled over this band around a feature's outline
# (beyond the half window the cloud loses at the edge).
_SURFACE_BAND_MM = (2.0, 8.0)
_SURFACE_MAX_MM = 1.0
_MIN_SURFACE_POINTS = 10


def hole_spec(cp: ComparisonPoint) -> HoleSpec:
    """The nominal hole of a ``kind="hole"`` comparison point."""
    n = np.asarray(cp.normal)
    axis = cp.axis if cp.axis is not None else (1.0, 0.0, 0.0)
    if cp.axis is None and abs(n[0]) > 0.9:
        axis = (0.0, 1.0, 0.0)
    return HoleSpec(cp.position, cp.normal, float(cp.diameter_mm or 0.0), cp.length_mm, axis)


def check_features(
    devs: Deviations,
    comparison_points: Sequence[ComparisonPoint],
    cad: CadModel,
    points_cad: Points,
    T_cad_rig: Transform | None = None,
    cameras: Sequence[Camera] = (),
    images: Sequence[Image] = (),
    *,
    tree: ClosestPointQuery,
    params: EdgeParams | None = None,
    line_points_cad: Points | None = None,
    flash: Flash | None = None,
) -> Deviations:
    """``devs`` with each feature point's placeholder entry replaced by its characteristics'
    entries, and the part's verdict given again.

    Parameters
    ----------
    devs : Deviations
        From :func:`~inspection.deviations.deviations` of ``points_cad``.
    comparison_points : the part's comparison points
    cad : the part's CAD
    points_cad : (N, 3) float64, mm, CAD frame
        The measured cloud after the fit.
    T_cad_rig : (4, 4) float64, optional
        The fit's pose; with ``cameras`` and ``images`` the outline is
        measured in the images.
    cameras, images : the calibrated cameras and their frames, in order
    tree : the CAD's closest points, as the deviations were measured (a
        character line is found against it)
    line_points_cad : (M, 3) float64, mm, CAD frame, optional
        The cloud character lines are found in (default ``points_cad``): one
        whose matching was not shaped by the CAD.
    flash : Flash, optional
        The flash's slide, which the edge model predicts on the material by an
        outline (without it, the material's light is taken as unpatterned).
    """
    by_name = {cp.name: cp for cp in comparison_points}
    out: list[ComparisonResult] = []
    d = np.asarray(devs.distances, dtype=np.float64)
    seen = T_cad_rig is not None and len(cameras) > 0 and len(images) == len(cameras)
    for c in devs.comparison:
        cp = by_name.get(c.name)
        if cp is None or cp.kind not in FEATURE_KINDS:
            out.append(c)
            continue
        offset, n_surface = _surface_offset(cp, points_cad, d)
        if cp.kind == "hole":
            out += _hole_entries(
                cp, points_cad, offset, T_cad_rig, cameras, images, seen, params, flash
            )
        elif cp.kind == "character_line":
            lines = points_cad if line_points_cad is None else line_points_cad
            out += _line_entries(cp, tree, lines)
        else:
            out += _edge_entries(
                cp, cad, offset, n_surface, T_cad_rig, cameras, images, seen, params, flash
            )
    comparison = tuple(out)
    return dataclasses.replace(
        devs, comparison=comparison, verdict=part_verdict(comparison, devs.failing_defects)
    )


def _surface_offset(cp: ComparisonPoint, P: Points, d: Scalars) -> tuple[float, int]:
    """The cloud's robust offset from the CAD around the feature (0 with too few points)."""
    reach = (cp.diameter_mm or 0.0) / 2 + max(cp.length_mm / 2 - (cp.diameter_mm or 0.0) / 2, 0)
    r = np.linalg.norm(P - np.asarray(cp.position), axis=1)
    lo, hi = _SURFACE_BAND_MM
    m = (r >= reach + lo) & (r <= reach + hi + cp.radius_mm) & (np.abs(d) <= _SURFACE_MAX_MM)
    if m.sum() < _MIN_SURFACE_POINTS:
        return 0.0, 0
    return robust_location(d[m])[0], int(m.sum())


def _entry(
    cp: ComparisonPoint,
    key: str,
    dev: float,
    sigma: float,
    support: int,
    spread: float,
    at: tuple[float, float, float] | None = None,
) -> ComparisonResult:
    lo, hi = cp.limits(key)
    verdict = Verdict.PASS if lo <= dev <= hi else Verdict.FAIL
    return ComparisonResult(
        f"{cp.name}.{key}", float(dev), support, verdict, lo, hi, spread, None, cp.kind, sigma, at
    )


def _unmeasured(cp: ComparisonPoint, reason: str, support: int = 0) -> list[ComparisonResult]:
    return [
        ComparisonResult(
            f"{cp.name}.{key}",
            math.nan,
            support,
            Verdict.NOT_MEASURABLE,
            *cp.limits(key),
            math.nan,
            reason,
            cp.kind,
        )  # fmt: skip
        for key in cp.characteristics()
    ]


def _hole_entries(cp, P, offset, T, cameras, images, seen, params, flash) -> list[ComparisonResult]:
    spec = hole_spec(cp)
    need = cp.min_support if cp.min_support is not None else 20
    if seen:
        m, why = measure_hole(
            spec, cameras, images, T, surface_offset_mm=offset, params=params,
            min_support=need, flash=flash,
        )  # fmt: skip
    else:
        m, why = hole_from_cloud(spec, P, min_support=min(need, 12))
        if m is not None:
            why = None
    if m is None:
        return _unmeasured(cp, why or "not measured")
    nominal_d = float(cp.diameter_mm or 0.0)
    values = {
        "x": (float(m.offset_mm[0]), float(m.sigma_mm[0])),
        "y": (float(m.offset_mm[1]), float(m.sigma_mm[1])),
        "d": (m.diameter_mm - nominal_d, float(m.sigma_mm[2])),
        "len": (m.length_mm - cp.length_mm, float(m.sigma_mm[3])),
    }
    return [_entry(cp, key, *values[key], m.support, m.rms_mm) for key in cp.characteristics()]


def _edge_entries(
    cp, cad, offset, n_surface, T, cameras, images, seen, params, flash
) -> list[ComparisonResult]:
    if not seen:
        return _unmeasured(cp, f"a {cp.kind} is measured in the images; none were given")
    p = params if params is not None else EdgeParams()
    samples, outward, normals = boundary_samples(
        cad.vertices, cad.faces, cad.face_normals, cp.position, cp.radius_mm, p.sample_mm
    )
    need = cp.min_support if cp.min_support is not None else 10
    m, why = measure_trim_edge(
        samples, outward, normals, cameras, images, T,
        surface_offset_mm=offset, params=p, min_support=need, flash=flash,
    )  # fmt: skip
    if m is None:
        return _unmeasured(cp, why or "not measured")
    if cp.kind == "trim_edge":
        return [
            _entry(cp, "trim", m.deviation_mm, m.sigma_mm, m.support, m.spread_mm),
            _entry(cp, "trim_max", m.max_mm, math.nan, m.support, m.spread_mm, m.at),
        ]
    # The gap to the mate's nominal edge shrinks by as much as the edge reaches out; the
    # flush is the surface's height at the edge against the mate's nominal surface.
    if n_surface == 0:
        return [
            _entry(cp, "gap", -m.deviation_mm, m.sigma_mm, m.support, m.spread_mm),
            *_unmeasured(cp, "too few cloud points on the surface by the edge")[1:],
        ]
    return [
        _entry(cp, "gap", -m.deviation_mm, m.sigma_mm, m.support, m.spread_mm),
        _entry(cp, "flush", offset, math.nan, n_surface, math.nan),
    ]


def _line_entries(
    cp: ComparisonPoint, tree: ClosestPointQuery, P: Points
) -> list[ComparisonResult]:
    need = cp.min_support if cp.min_support is not None else 10
    m, why = measure_character_line(
        tree, P, np.asarray(cp.position), np.asarray(cp.normal), cp.radius_mm, min_support=need
    )
    if m is None:
        return _unmeasured(cp, why or "not measured")
    return [
        _entry(cp, "line", m.offset_mm, m.sigma_mm, m.support, m.rms_mm),
        _entry(cp, "line_max", m.max_mm, math.nan, m.support, m.rms_mm, m.at),
    ]
