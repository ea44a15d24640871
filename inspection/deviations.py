"""Signed deviations of a registered cloud from the CAD, and the part's verdict.

Every measured point (already in the CAD frame) gets its signed distance to
the CAD surface (positive on the outer side). At each named comparison point
the measured points within its support radius are pooled and their signed
distances, taken along the comparison point's normal, are averaged robustly
(a Tukey-biweight M-estimate of location with a MAD scale, so that a stray
reflection in the support does not move the result). The deviation is checked against
the point's signed tolerance; a comparison point with too few points in its
support cannot be judged (``not_measurable``). Given the part's
:class:`~inspection.surface.SurfaceModel`, the whole surface is judged too:
the field's statistics count only the points the surface measured (not the
edge points, the fit's outliers or the background), and regions of the
surface out of the band are surface defects
(:class:`~inspection.surface.SurfaceDefect`).
"""

from __future__ import annotations

import enum
import json
import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from numba import njit

from .arrays import Points, Scalars
from .errors import InvalidInput
from .protocols import ClosestPointQuery
from .surface import PointClasses, SurfaceDefect, SurfaceModel, SurfaceParams
from .validate import validate_points

log = logging.getLogger(__name__)

__all__ = [
    "CHARACTERISTICS",
    "FEATURE_KINDS",
    "ComparisonPoint",
    "ComparisonResult",
    "Deviations",
    "FieldSummary",
    "Verdict",
    "deviations",
    "check_comparison_points",
    "load_comparison_points",
    "part_verdict",
    "robust_location",
    "warmup",
]

KINDS = ("surface", "hole", "trim_edge", "gap_flush", "character_line")
"""Kinds of comparison point a spec may name."""
MEASURED_KINDS = ("surface",)
"""Kinds measured from the cloud's signed distances here; the others are features of
the outline (:data:`FEATURE_KINDS`), measured after the fit (:mod:`inspection.feature_checks`)."""
FEATURE_KINDS = ("hole", "trim_edge", "gap_flush", "character_line")
CHARACTERISTICS = {
    "surface": (),
    "hole": ("x", "y", "d"),
    "trim_edge": ("trim", "trim_max"),
    "gap_flush": ("gap", "flush"),
    "character_line": ("line", "line_max"),
}
"""Each feature kind's characteristics: one comparison entry ``<point>.<characteristic>`` each
(a slot adds ``len``). A curve's ``_max`` is the largest deviation along the curve fitted to
its measured points, the other its mean offset."""

# Points whose CAD normal turns more than ~60 degrees away from the
# comparison point's normal lie on another surface (a flange, the far side
# of a thin wall) and are not pooled.
_MIN_NORMAL_COS = 0.5
# Tukey's biweight constant (95 % efficiency under Gaussian noise).
_TUKEY_C = 4.685


class Verdict(enum.StrEnum):
    """Outcome of a check."""

    PASS = "pass"
    FAIL = "fail"
    NOT_MEASURABLE = "not_measurable"


@dataclass(frozen=True)
class ComparisonPoint:
    """A named point on the CAD surface where the deviation is checked.

    Attributes
    ----------
    name : str
    position : (3,) tuple of float, mm, CAD frame
        Nominal point on the surface.
    normal : (3,) tuple of float
        Direction along which the deviation is measured (normalised on
        construction); the outward surface normal for ``kind="surface"``.
    lower_mm, upper_mm : float
        Signed tolerance: the deviation must lie in [lower_mm, upper_mm].
    radius_mm : float
        Measured points within this distance of ``position`` are pooled.
    kind : str
        ``"surface"``; or a feature of the outline: ``"hole"`` (``position``
        its centre on the surface, ``normal`` its axis towards the cameras),
        ``"trim_edge"`` and ``"gap_flush"`` (``position`` on the CAD's edge,
        ``normal`` in the surface's plane, normal to the edge, out of the
        material); ``"character_line"`` (``position`` on the crease of the
        CAD's surface, ``normal`` in the surface, across the line: the
        direction of a positive offset; ``radius_mm`` the half length of the
        line measured).
    min_support : int or None
        Points needed for a verdict at this point; None: the ``min_support``
        given to :func:`deviations`.
    diameter_mm : float or None
        A hole's nominal diameter (needed for ``kind="hole"``).
    length_mm : float
        A slot's nominal overall length (0: a round hole).
    axis : (3,) tuple of float or None
        A hole's in-plane x (a slot's long axis); None: the CAD's x made normal
        to the hole's axis.
    mate : (3,) tuple of float or None
        For ``gap_flush``: the mating part's nominal edge point, in this part's
        CAD frame (the gap along ``normal``, the flush along the surface normal).
    tolerances : tuple of (characteristic, lower_mm, upper_mm)
        Limits of single characteristics (``d``, ``flush``, ...); the others
        take ``lower_mm`` and ``upper_mm``.
    """

    name: str
    position: tuple[float, float, float]
    normal: tuple[float, float, float]
    lower_mm: float
    upper_mm: float
    radius_mm: float
    kind: str = "surface"
    min_support: int | None = None
    diameter_mm: float | None = None
    length_mm: float = 0.0
    axis: tuple[float, float, float] | None = None
    mate: tuple[float, float, float] | None = None
    tolerances: tuple[tuple[str, float, float], ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise InvalidInput("a comparison point needs a non-empty name")
        pos = _vec3(self.position, f"{self.name}: position")
        nrm = _vec3(self.normal, f"{self.name}: normal")
        length = math.sqrt(sum(c * c for c in nrm))
        if length < 1e-12:
            raise InvalidInput(f"{self.name}: normal must not be zero")
        for label, val in (("lower_mm", self.lower_mm), ("upper_mm", self.upper_mm)):
            if not isinstance(val, int | float) or not math.isfinite(val):
                raise InvalidInput(f"{self.name}: {label} must be a finite number, got {val!r}")
        if self.lower_mm > self.upper_mm:
            raise InvalidInput(f"{self.name}: lower_mm {self.lower_mm} > upper_mm {self.upper_mm}")
        r = self.radius_mm
        if not isinstance(r, int | float) or not math.isfinite(r) or r <= 0:
            raise InvalidInput(
                f"{self.name}: radius_mm must be a finite positive number, got {r!r}"
            )
        if self.kind not in KINDS:
            raise InvalidInput(f"{self.name}: unknown kind {self.kind!r}; expected one of {KINDS}")
        ms = self.min_support
        if ms is not None and (
            isinstance(ms, bool) or not isinstance(ms, int | np.integer) or ms < 1
        ):
            raise InvalidInput(f"{self.name}: min_support must be an integer >= 1, got {ms!r}")
        self._check_feature()
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "normal", tuple(c / length for c in nrm))
        object.__setattr__(self, "lower_mm", float(self.lower_mm))
        object.__setattr__(self, "upper_mm", float(self.upper_mm))
        object.__setattr__(self, "radius_mm", float(r))

    def _check_feature(self) -> None:
        name = self.name
        if self.kind == "hole":
            d = self.diameter_mm
            if not isinstance(d, int | float) or not math.isfinite(d) or d <= 0:
                raise InvalidInput(f"{name}: a hole needs a positive diameter_mm, got {d!r}")
        elif self.diameter_mm is not None:
            raise InvalidInput(f"{name}: diameter_mm applies to holes only")
        ln = self.length_mm
        if not isinstance(ln, int | float) or not math.isfinite(ln) or ln < 0:
            raise InvalidInput(f"{name}: length_mm must be >= 0, got {ln!r}")
        if self.axis is not None:
            object.__setattr__(self, "axis", _vec3(self.axis, f"{name}: axis"))
        if self.kind == "gap_flush":
            if self.mate is None:
                raise InvalidInput(f"{name}: a gap_flush point needs the mating edge point 'mate'")
            object.__setattr__(self, "mate", _vec3(self.mate, f"{name}: mate"))
        elif self.mate is not None:
            raise InvalidInput(f"{name}: mate applies to gap_flush points only")
        known = set(self.characteristics())
        tol = []
        for item in self.tolerances:
            try:
                key, lo, hi = item
            except (TypeError, ValueError) as exc:
                raise InvalidInput(
                    f"{name}: a tolerance is (characteristic, lower, upper)"
                ) from exc
            if key not in known:
                raise InvalidInput(
                    f"{name}: no characteristic {key!r} for kind {self.kind!r}; "
                    f"expected one of {sorted(known)}"
                )
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise InvalidInput(f"{name}.{key}: limits must be finite and ordered")
            tol.append((str(key), float(lo), float(hi)))
        object.__setattr__(self, "tolerances", tuple(tol))

    def characteristics(self) -> tuple[str, ...]:
        """The characteristics this point is checked by (empty for a surface point)."""
        base = CHARACTERISTICS[self.kind]
        if self.kind == "hole" and self.length_mm > (self.diameter_mm or 0.0):
            return (*base, "len")
        return base

    def limits(self, characteristic: str) -> tuple[float, float]:
        """The tolerance of one characteristic."""
        for key, lo, hi in self.tolerances:
            if key == characteristic:
                return lo, hi
        return self.lower_mm, self.upper_mm

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> ComparisonPoint:
        """Build from a mapping with the field names (as in a JSON or TOML spec)."""
        if not isinstance(d, Mapping):
            raise InvalidInput(f"a comparison point must be a mapping, got {type(d).__name__}")
        known = {f.name for f in fields(cls)}
        extra = set(d) - known
        if extra:
            raise InvalidInput(f"comparison point: unknown keys {sorted(extra)}")
        missing = known - set(d) - {
            "kind", "min_support", "diameter_mm", "length_mm", "axis", "mate", "tolerances"
        }  # fmt: skip
        if missing:
            raise InvalidInput(
                f"comparison point {d.get('name', '?')!r}: missing {sorted(missing)}"
            )
        args = dict(d)
        tol = args.get("tolerances")
        if isinstance(tol, Mapping):
            args["tolerances"] = tuple((k, *v) for k, v in tol.items())
        elif isinstance(tol, list):
            args["tolerances"] = tuple(tuple(t) for t in tol)
        return cls(**args)  # type: ignore[arg-type]

    def to_dict(self) -> dict[str, object]:
        return {
            "name": self.name,
            "position": list(self.position),
            "normal": list(self.normal),
            "lower_mm": self.lower_mm,
            "upper_mm": self.upper_mm,
            "radius_mm": self.radius_mm,
            "kind": self.kind,
            "min_support": self.min_support,
            "diameter_mm": self.diameter_mm,
            "length_mm": self.length_mm,
            "axis": None if self.axis is None else list(self.axis),
            "mate": None if self.mate is None else list(self.mate),
            "tolerances": {k: [lo, hi] for k, lo, hi in self.tolerances},
        }


def _vec3(v: object, label: str) -> tuple[float, float, float]:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{label} must be three numbers: {exc}") from exc
    if a.shape != (3,) or not np.isfinite(a).all():
        raise InvalidInput(f"{label} must be three finite numbers, got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


def load_comparison_points(path: str | Path) -> tuple[ComparisonPoint, ...]:
    """Read comparison points from JSON: a list, or ``{"points": [...]}``.

    Raises
    ------
    InvalidInput
        Unreadable file, malformed JSON, bad or duplicate entries.
    """
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except OSError as exc:
        raise InvalidInput(f"{p}: cannot read: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise InvalidInput(f"{p}: not valid JSON: {exc}") from exc
    items = doc.get("points") if isinstance(doc, dict) else doc
    if not isinstance(items, list):
        raise InvalidInput(f"{p}: expected a list of comparison points or {{'points': [...]}}")
    points = tuple(ComparisonPoint.from_dict(it) for it in items)
    _check_unique(points)
    return points


def check_comparison_points(points: Iterable[object]) -> tuple[ComparisonPoint, ...]:
    """``points`` as a tuple, checked to be ComparisonPoints with distinct names.

    Raises
    ------
    InvalidInput
    """
    out = tuple(points)
    for cp in out:
        if not isinstance(cp, ComparisonPoint):
            raise InvalidInput(f"expected ComparisonPoint, got {type(cp).__name__}")
    _check_unique(out)  # type: ignore[arg-type]
    return out  # type: ignore[return-value]


def _check_unique(points: Sequence[ComparisonPoint]) -> None:
    seen: set[str] = set()
    for cp in points:
        if cp.name in seen:
            raise InvalidInput(f"duplicate comparison point name {cp.name!r}")
        seen.add(cp.name)


@dataclass(frozen=True)
class ComparisonResult:
    """The deviation at one comparison point.

    Attributes
    ----------
    name : str
    deviation_mm : float
        Robust average of the signed distances along the point's normal, mm;
        NaN when not measurable.
    support : int
        Measured points pooled.
    verdict : Verdict
    lower_mm, upper_mm : float
        The tolerance it was checked against.
    spread_mm : float
        Robust standard deviation (MAD x 1.4826) of the pooled distances, mm;
        NaN when not measurable.
    reason : str or None
        Why the point is not measurable.
    kind : str
        The comparison point's kind (a feature's entries are named
        ``<point>.<characteristic>``).
    sigma_mm : float
        1 sigma of ``deviation_mm`` where the measurement gives it (features), else NaN.
    at_mm : (3,) tuple of float or None
        Where a curve's largest deviation lies (the ``_max`` entries of trim
        edges and character lines), on the nominal, CAD frame, mm.
    """

    name: str
    deviation_mm: float
    support: int
    verdict: Verdict
    lower_mm: float
    upper_mm: float
    spread_mm: float
    reason: str | None = None
    kind: str = "surface"
    sigma_mm: float = math.nan
    at_mm: tuple[float, float, float] | None = None

    def to_dict(self) -> dict[str, object]:
        return {
            "name": self.name,
            "deviation_mm": None if math.isnan(self.deviation_mm) else self.deviation_mm,
            "lower_mm": self.lower_mm,
            "upper_mm": self.upper_mm,
            "support": self.support,
            "verdict": self.verdict.value,
            "spread_mm": None if math.isnan(self.spread_mm) else self.spread_mm,
            "reason": self.reason,
            "kind": self.kind,
            "sigma_mm": None if math.isnan(self.sigma_mm) else self.sigma_mm,
            "at_mm": None if self.at_mm is None else list(self.at_mm),
        }


@dataclass(frozen=True)
class FieldSummary:
    """Statistics of the signed distances of the points the surface measured, mm.

    Attributes
    ----------
    n : int
        Points measured.
    inliers : int
        Points counted in the statistics: the others are counted apart below.
    edge : int
        Edge points: off the CAD's edge, or near a boundary or an occlusion edge.
    outliers : int
        Points the fit rejects (beyond its rejection distance).
    far : int
        Points beyond the correspondence distance (background, gross outliers).
    mean_mm, std_mm, rms_mm, min_mm, max_mm, max_abs_mm : float
    median_mm, mad_mm : float
        Median and median absolute deviation from it.
    p001_mm, p01_mm, p05_mm, p95_mm, p99_mm, p999_mm : float
        Percentiles (0.1, 1, 5, 95, 99, 99.9). Every statistic is NaN when no
        point is counted.
    """

    n: int
    inliers: int
    edge: int
    outliers: int
    far: int
    mean_mm: float
    std_mm: float
    rms_mm: float
    min_mm: float
    max_mm: float
    max_abs_mm: float
    median_mm: float
    mad_mm: float
    p001_mm: float
    p01_mm: float
    p05_mm: float
    p95_mm: float
    p99_mm: float
    p999_mm: float

    @classmethod
    def of(
        cls, d: Scalars, counted: np.ndarray | None = None, classes: PointClasses | None = None
    ) -> FieldSummary:
        """The statistics of ``d[counted]`` (every finite value when ``counted`` is None);
        ``classes`` gives the counts set apart."""
        d = np.asarray(d, dtype=np.float64)
        keep = np.isfinite(d) if counted is None else np.asarray(counted, bool) & np.isfinite(d)
        x = d[keep]
        apart = (0, 0, 0)
        if classes is not None:
            apart = (
                int(classes.edge.sum()), int(classes.outlier.sum()), int(classes.far.sum())
            )  # fmt: skip
        elif counted is not None:
            apart = (0, 0, int(len(d) - keep.sum()))
        if len(x) == 0:
            return cls(len(d), 0, *apart, *([math.nan] * 14))
        p001, p01, p05, p50, p95, p99, p999 = np.percentile(x, [0.1, 1, 5, 50, 95, 99, 99.9])
        return cls(
            len(d),
            len(x),
            *apart,
            mean_mm=float(x.mean()),
            std_mm=float(x.std()),
            rms_mm=float(np.sqrt(np.mean(x * x))),
            min_mm=float(x.min()),
            max_mm=float(x.max()),
            max_abs_mm=float(np.abs(x).max()),
            median_mm=float(p50),
            mad_mm=float(np.median(np.abs(x - p50))),
            p001_mm=float(p001),
            p01_mm=float(p01),
            p05_mm=float(p05),
            p95_mm=float(p95),
            p99_mm=float(p99),
            p999_mm=float(p999),
        )

    def to_dict(self) -> dict[str, float | int | None]:
        return {
            k: (None if isinstance(v, float) and math.isnan(v) else v)
            for k, v in self.__dict__.items()
        }


@dataclass(frozen=True, eq=False)
class Deviations:
    """Signed deviations of a cloud from the CAD.

    Attributes
    ----------
    distances : (N,) float64, mm
        Signed distance of every point (positive on the outer side).
    inliers : (N,) bool
        Points within ``max_distance_mm`` of the CAD (the others are background).
    comparison : tuple of ComparisonResult
        One per comparison point, in the given order.
    summary : FieldSummary
        Statistics of the field over the points the surface measured.
    verdict : Verdict
        The part's verdict by :func:`part_verdict`.
    defects : tuple of SurfaceDefect or None
        Regions of the surface out of the surface band, largest first (empty
        without a surface model; None: the surface was not checked).
    defects_fail : bool
        Whether the defects fail the part (the spec's ``fails_part``).
    classes : PointClasses or None
        What each point is (None without a surface model).
    """

    distances: Scalars
    inliers: np.ndarray
    comparison: tuple[ComparisonResult, ...]
    summary: FieldSummary
    verdict: Verdict
    defects: tuple[SurfaceDefect, ...] | None = ()
    defects_fail: bool = True
    classes: PointClasses | None = None

    @property
    def failing_defects(self) -> tuple[SurfaceDefect, ...]:
        """The defects that fail the part."""
        return self.defects if self.defects_fail and self.defects is not None else ()


def part_verdict(
    comparison: Iterable[ComparisonResult], failing_defects: Sequence[SurfaceDefect] = ()
) -> Verdict:
    """``fail`` if any comparison point fails or a surface defect fails the part, else
    ``not_measurable`` if any comparison point cannot be judged, else ``pass``."""
    verdicts = {r.verdict for r in comparison}
    if Verdict.FAIL in verdicts or len(failing_defects):
        return Verdict.FAIL
    if Verdict.NOT_MEASURABLE in verdicts:
        return Verdict.NOT_MEASURABLE
    return Verdict.PASS


@njit(cache=True, nogil=True, inline="always")
def _in_ball(points, i, centres, j, r2):  # pragma: no cover - compiled
    """Whether point i lies within ball j (squared radii ``r2``); x first, as a cheap reject."""
    dx = points[i, 0] - centres[j, 0]
    if dx * dx > r2[j]:
        return False
    dy = points[i, 1] - centres[j, 1]
    dz = points[i, 2] - centres[j, 2]
    return dx * dx + dy * dy + dz * dz <= r2[j]


@njit(cache=True, nogil=True)
def _gather_balls(
    points: np.ndarray, centres: np.ndarray, radii: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Indices of the points within each ball, in point order, as CSR (start, index).

    One pass over the points counts, a second fills: cheaper than building a
    kd-tree over the whole cloud for a handful of small balls.
    """
    n, k = points.shape[0], centres.shape[0]
    r2 = radii * radii
    counts = np.zeros(k + 1, dtype=np.int64)
    for i in range(n):
        for j in range(k):
            if _in_ball(points, i, centres, j, r2):
                counts[j + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    index = np.empty(start[-1], dtype=np.int64)
    for i in range(n):
        for j in range(k):
            if _in_ball(points, i, centres, j, r2):
                index[fill[j]] = i
                fill[j] += 1
    return start, index


def warmup() -> None:
    """Compile (or load from numba's cache) the support search, off the first part."""
    _gather_balls(np.zeros((2, 3)), np.zeros((1, 3)), np.ones(1))


def robust_location(
    x: Scalars, *, c: float = _TUKEY_C, iterations: int = 50
) -> tuple[float, float]:
    """Tukey-biweight M-estimate of location with a fixed MAD scale.

    Starts from the median, so a minority of gross outliers (a reflection in
    the support) get zero weight instead of pulling the mean.

    Parameters
    ----------
    x : (n,) float64
    c : float
        Tukey's constant in units of the scale.

    Returns
    -------
    location : float
    scale : float
        1.4826 x MAD about the median.
    """
    x = np.asarray(x, dtype=np.float64)
    mu = float(np.median(x))
    scale = 1.482602218505602 * float(np.median(np.abs(x - mu)))
    if scale <= 1e-12:
        return mu, scale
    for _ in range(iterations):
        # IRLS with the biweight w = (1 - (r / c s)^2)^2 inside c s, 0 outside.
        u = (x - mu) / (c * scale)
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        new = float(np.sum(w * x) / np.sum(w))
        if abs(new - mu) <= 1e-9 * scale:
            mu = new
            break
        mu = new
    return mu, scale


def deviations(
    tree: ClosestPointQuery,
    points_cad: Points,
    comparison_points: Iterable[ComparisonPoint] = (),
    *,
    min_support: int = 10,
    max_distance_mm: float = math.inf,
    surface: SurfaceModel | None = None,
    surface_params: SurfaceParams | None = None,
    outlier_mm: float = math.inf,
    viewpoints: Points | None = None,
    view_directions: Points | None = None,
) -> Deviations:
    """Signed deviations of every point, at each comparison point, and over the surface.

    Parameters
    ----------
    tree : ClosestPointQuery
        The CAD's closest-point structure (``GridTree``).
    points_cad : (N, 3) float64, mm, CAD frame
        The measured points after registration (``T_cad_data`` applied).
    comparison_points : iterable of ComparisonPoint
    min_support : int
        A comparison point with fewer pooled points is ``not_measurable``
        (unless the point sets its own ``min_support``); so is a node of the
        defect search.
    max_distance_mm : float
        Points farther than this from the CAD are background, left out of the
        field (the registration's correspondence distance).
    surface : SurfaceModel, optional
        The part's surface model (``PartModel.surface``): with it, edge points
        and outliers are counted apart and surface defects are searched.
    surface_params : SurfaceParams, optional
        The surface band (default: ``SurfaceParams()``).
    outlier_mm : float
        The fit's rejection distance: farther points are outliers.
    viewpoints : (K, 3) float64, mm, CAD frame, optional
        The cameras' centres, whose silhouettes of the CAD are occlusion edges.
    view_directions : (K, 3) float64, CAD frame, optional
        Views from far away (towards the sensor), when the centres are not known.

    Returns
    -------
    Deviations

    Raises
    ------
    InvalidInput
        Bad points, duplicate comparison point names, ``min_support < 1``.
    """
    P = validate_points(points_cad, name="points_cad")
    cps = check_comparison_points(comparison_points)
    if min_support < 1:
        raise InvalidInput(f"min_support must be >= 1, got {min_support}")
    if not max_distance_mm > 0:
        raise InvalidInput(f"max_distance_mm must be positive, got {max_distance_mm}")
    if not outlier_mm > 0:
        raise InvalidInput(f"outlier_mm must be positive, got {outlier_mm}")
    cl = tree.query(P)
    d = np.asarray(cl.distances, dtype=np.float64)
    normals = np.asarray(cl.normals, dtype=np.float64)
    results = _at_comparison_points(P, d, normals, cps, min_support)
    inliers = np.abs(d) <= max_distance_mm
    defects: tuple[SurfaceDefect, ...] = ()
    sp = surface_params if surface_params is not None else SurfaceParams()
    classes = None
    if surface is not None:
        classes, defects = surface.assess(
            P, np.asarray(cl.points, dtype=np.float64), normals, d, sp,
            outlier_mm=outlier_mm, max_distance_mm=max_distance_mm, min_support=min_support,
            viewpoints=viewpoints, directions=view_directions,
            comparison=tuple((cp.name, cp.position) for cp in cps),
        )  # fmt: skip
        summary = FieldSummary.of(d, classes.surface, classes)
    else:
        summary = FieldSummary.of(d, inliers & (np.abs(d) <= outlier_mm))
    failing = defects if sp.fails_part else ()
    verdict = part_verdict(results, failing)
    log.debug(
        "deviations: %d points, %d comparison points, %d defects, verdict %s",
        len(P), len(cps), len(defects), verdict,
    )  # fmt: skip
    return Deviations(
        distances=d,
        inliers=inliers,
        comparison=tuple(results),
        summary=summary,
        verdict=verdict,
        defects=defects,
        defects_fail=sp.fails_part,
        classes=classes,
    )


def _at_comparison_points(
    P: np.ndarray,
    d: np.ndarray,
    normals: np.ndarray,
    cps: tuple[ComparisonPoint, ...],
    min_support: int,
) -> list[ComparisonResult]:
    """Each comparison point's pooled, robust deviation and its verdict."""
    results = []
    measured = [cp for cp in cps if cp.kind in MEASURED_KINDS]
    if measured:
        start, index = _gather_balls(
            P,
            np.array([cp.position for cp in measured], dtype=np.float64).reshape(-1, 3),
            np.array([cp.radius_mm for cp in measured], dtype=np.float64),
        )
        support_of = {cp.name: index[start[j] : start[j + 1]] for j, cp in enumerate(measured)}
    for cp in cps:
        need = cp.min_support if cp.min_support is not None else min_support
        if cp.kind not in MEASURED_KINDS:
            # A feature of the outline: its entries come from the images after the fit.
            results.append(
                ComparisonResult(
                    cp.name, math.nan, 0, Verdict.NOT_MEASURABLE, cp.lower_mm, cp.upper_mm,
                    math.nan, f"a {cp.kind} is measured from the images after the fit",
                    cp.kind,
                )
            )  # fmt: skip
            continue
        idx = support_of[cp.name]
        n_cp = np.asarray(cp.normal)
        cos = normals[idx] @ n_cp if len(idx) else np.empty(0)
        keep = np.abs(cos) >= _MIN_NORMAL_COS
        # The field's sign is "outward"; along the comparison normal it flips
        # where that normal points inwards.
        x = d[idx[keep]] * np.sign(cos[keep])
        support = len(x)
        if support < need:
            results.append(
                ComparisonResult(
                    cp.name,
                    math.nan,
                    support,
                    Verdict.NOT_MEASURABLE,
                    cp.lower_mm,
                    cp.upper_mm,
                    math.nan,
                    f"{support} points in its support, {need} needed",
                )
            )
            continue
        dev, spread = robust_location(x)
        ok = cp.lower_mm <= dev <= cp.upper_mm
        results.append(
            ComparisonResult(
                cp.name,
                dev,
                support,
                Verdict.PASS if ok else Verdict.FAIL,
                cp.lower_mm,
                cp.upper_mm,
                spread,
            )
        )
    return results
