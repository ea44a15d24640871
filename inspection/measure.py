"""The measuring sequence: from one trigger's frames, or a cloud, to the part's verdict.

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
6. measure signed deviations over the cloud and at the comparison points;
7. hold each comparison point's verdict against the pose's own uncertainty
   along its normal, and give the part its verdict.

Invalid input raises :class:`~inspection.errors.InvalidInput`; a valid
input that cannot be measured (no surface seen, no fit) gives a
:class:`Measurement` with ``verdict`` None and the reason.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

from .alignment import Alignment, AlignmentModel, align, alignment_model
from .cad import CadModel
from .deviations import (
    ComparisonPoint,
    ComparisonResult,
    Deviations,
    Verdict,
    check_comparison_points,
    deviations,
    part_verdict,
)
from .errors import InspectionError, InvalidInput
from .grid import GridTree
from .reconstruct import Cloud, Guide, Reconstructor
from .registration import LOSSES, Registration, StopReason, register, validate_view
from .rig import Rig

log = logging.getLogger(__name__)

__all__ = [
    "FitQuality",
    "Measurement",
    "MeasureParams",
    "Pass",
    "PartModel",
    "RegisterParams",
    "fit_quality",
    "measure_cloud",
    "measure_frames",
    "pose_sigma_mm",
]

MIN_POINTS = 10
"""Fewer measured points than this are not a cloud."""
MAX_POINTS = 20_000_000
"""Larger clouds are refused (memory), far above the rig's ~300k points."""

Frame = Literal["rig", "cad", "data"]
"""The frame a cloud is given in: ``rig`` (seen from above, anywhere on the
belt), ``data`` (any frame, anywhere), ``cad`` (already near the CAD frame:
only the fine registration runs)."""

# The names of the twist's components (omega L, t), in the CAD frame.
_DIRECTION_NAMES = (
    "rotation about x",
    "rotation about y",
    "rotation about z",
    "translation along x",
    "translation along y",
    "translation along z",
)
# A free direction that moves a point along its normal by more than this
# fraction of its own (unit) size leaves the point's deviation undetermined.
_FREE_MOVES = 1e-3


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class RegisterParams:
    """How a cloud is fitted to the CAD (the arguments of :func:`~inspection.register`).

    Attributes
    ----------
    loss : str
        M-estimator of the residuals (see :func:`~inspection.register`).
    max_iterations : int
    max_distance_mm : float
        Points farther than this from the CAD are outliers.
    seed : int
        Seeds the random subsets.
    view_direction : (3,) tuple of float or None
        Direction towards the sensor in the rig frame (+z for a rig looking
        down): a point is not fitted onto a face turned away from it. Used for
        clouds in the rig frame only. Needs ``loss`` tukey or welsch.
    """

    loss: str = "tukey"
    max_iterations: int = 50
    max_distance_mm: float = 10.0
    seed: int = 0
    view_direction: tuple[float, float, float] | None = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise InvalidInput(f"loss must be one of {sorted(LOSSES)}, got {self.loss!r}")
        if not (isinstance(self.max_iterations, int) and self.max_iterations >= 1):
            raise InvalidInput(f"max_iterations must be an integer >= 1, got {self.max_iterations}")
        if not (math.isfinite(self.max_distance_mm) and self.max_distance_mm > 0):
            raise InvalidInput(f"max_distance_mm must be positive, got {self.max_distance_mm}")
        if self.view_direction is not None:
            view = validate_view(np.asarray(self.view_direction, dtype=np.float64), self.loss)
            assert view is not None
            object.__setattr__(self, "view_direction", tuple(float(c) for c in view))

    def kwargs(self, frame: Frame) -> dict[str, object]:
        """Keyword arguments of ``align`` / ``register`` for a cloud in ``frame``."""
        out: dict[str, object] = {
            "loss": self.loss,
            "max_iterations": self.max_iterations,
            "max_distance_mm": self.max_distance_mm,
        }
        if self.seed:
            out["seed"] = self.seed
        if frame == "rig" and self.view_direction is not None:
            out["view_direction"] = self.view_direction
        return out


@dataclass(frozen=True)
class MeasureParams:
    """The measuring sequence's settings; the defaults are the line's.

    Attributes
    ----------
    path : {"cloud"}
        What is measured: the whole reconstructed cloud. (The comparison
        points' own path is refused until it exists.)
    guided : bool
        Match the frames a second time with the CAD at the first fit's pose.
    use_weights : bool
        Fit with the reconstruction's per-point quality as input weights.
    max_points : int
        Clouds are subsampled (evenly strided) to this size to fit.
    min_inlier_fraction : float
        A fit keeping fewer of the points is an error.
    max_rms_mm : float
        A fit with a larger residual is an error.
    ambiguous_is_error : bool
        A pose the global search calls ambiguous is an error (else measured,
        and the reason says so).
    min_support : int
        Points needed at a comparison point (unless it sets its own).
    uncertainty_fraction : float
        A comparison point whose deviation the pose leaves uncertain by more
        than this fraction of its tolerance band (3 sigma along its normal)
        is not measurable.
    register : RegisterParams
    """

    path: Literal["cloud", "comparison_points"] = "cloud"
    guided: bool = True
    use_weights: bool = False
    max_points: int = 50_000
    min_inlier_fraction: float = 0.5
    max_rms_mm: float = 1.0
    ambiguous_is_error: bool = False
    min_support: int = 10
    uncertainty_fraction: float = 0.1
    register: RegisterParams = field(default_factory=RegisterParams)

    def __post_init__(self) -> None:
        if self.path == "comparison_points":
            raise InvalidInput(
                "path 'comparison_points' (photogrammetry at the comparison points) is not "
                "available yet; measure with path 'cloud'"
            )
        if self.path != "cloud":
            raise InvalidInput(f"path must be 'cloud' or 'comparison_points', got {self.path!r}")
        if not (isinstance(self.max_points, int) and self.max_points >= 100):
            raise InvalidInput(f"max_points must be an integer >= 100, got {self.max_points}")
        if not 0.0 <= self.min_inlier_fraction <= 1.0:
            raise InvalidInput(
                f"min_inlier_fraction must lie in [0, 1], got {self.min_inlier_fraction}"
            )
        if not self.max_rms_mm > 0:
            raise InvalidInput(f"max_rms_mm must be positive, got {self.max_rms_mm}")
        if not (isinstance(self.min_support, int) and self.min_support >= 1):
            raise InvalidInput(f"min_support must be an integer >= 1, got {self.min_support}")
        if not self.uncertainty_fraction > 0:
            raise InvalidInput(
                f"uncertainty_fraction must be positive, got {self.uncertainty_fraction}"
            )
        if not isinstance(self.register, RegisterParams):
            raise InvalidInput(
                f"register must be RegisterParams, got {type(self.register).__name__}"
            )


# --------------------------------------------------------------------------- the part


@dataclass(frozen=True, eq=False)
class PartModel:
    """Everything measured against, built once per part type.

    Attributes
    ----------
    cad : CadModel
    tree : GridTree
        The closest-point grid of ``cad``.
    alignment : AlignmentModel or None
        Resting poses and templates of the global search; None: clouds can
        only be measured near the CAD frame (``frame="cad"``).
    comparison_points : tuple of ComparisonPoint
    """

    cad: CadModel
    tree: GridTree
    alignment: AlignmentModel | None
    comparison_points: tuple[ComparisonPoint, ...] = ()

    @classmethod
    def build(
        cls,
        cad: CadModel,
        comparison_points: Sequence[ComparisonPoint] = (),
        *,
        spacing_mm: float | None = None,
        band_mm: float | None = None,
        alignment: bool = True,
    ) -> PartModel:
        """Build the tree (``GridTree.build``) and the alignment model of ``cad``.

        Parameters
        ----------
        cad : CadModel
        comparison_points : sequence of ComparisonPoint
        spacing_mm, band_mm : float, optional
            The grid's build parameters; None: its defaults.
        alignment : bool
            Compute the global search's model (seconds; needed for clouds
            anywhere in the rig).
        """
        if not isinstance(cad, CadModel):
            raise InvalidInput(f"cad must be a CadModel, got {type(cad).__name__}")
        tree = GridTree.build(
            cad,
            **({} if spacing_mm is None else {"spacing_mm": spacing_mm}),  # type: ignore[arg-type]
            **({} if band_mm is None else {"band_mm": band_mm}),  # type: ignore[arg-type]
        )
        model = alignment_model(cad) if alignment else None
        return cls(cad, tree, model, check_comparison_points(comparison_points))

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "comparison_points", check_comparison_points(self.comparison_points)
        )

    def save(self, directory: str | Path) -> Path:
        """Write the tree, the alignment model and the comparison points into ``directory``."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        self.tree.save(d / "tree.npz")
        if self.alignment is not None:
            self.alignment.save(d / "alignment.npz", key=self.cad.hash)
        doc = {"points": [cp.to_dict() for cp in self.comparison_points]}
        (d / "points.json").write_text(json.dumps(doc, indent=2))
        return d

    @classmethod
    def load(cls, directory: str | Path, *, cad: CadModel) -> PartModel:
        """Read what :meth:`save` wrote; refuses a tree or model built from another CAD.

        Raises
        ------
        TreeMismatch
            The tree's CAD hash, parameters or format do not match ``cad``.
        InvalidInput
            A missing or unreadable file, or an alignment model of another CAD.
        """
        from .deviations import load_comparison_points

        d = Path(directory)
        tree = GridTree.load(d / "tree.npz", cad=cad)
        path = d / "alignment.npz"
        model = AlignmentModel.load(path, key=cad.hash) if path.is_file() else None
        return cls(cad, tree, model, load_comparison_points(d / "points.json"))


# --------------------------------------------------------------------------- the result


@dataclass(frozen=True, eq=False)
class Pass:
    """One matching pass: its cloud and the fit made to it.

    Attributes
    ----------
    name : str
        ``first``, ``guided`` or ``bends``.
    points : (N, 3) float64, mm, rig frame
    weights : (N,) float64
        Per-point quality of the reconstruction.
    fit : Registration or None
        The fit to this pass's cloud (None: not fitted, or the fit failed).
    """

    name: str
    points: np.ndarray = field(repr=False)
    weights: np.ndarray = field(repr=False)
    fit: Registration | None = field(default=None, repr=False)


@dataclass(frozen=True)
class FitQuality:
    """What the final fit says of itself.

    Attributes
    ----------
    converged : bool
    stop_reason : str
    iterations : int
    observability : float
        Smallest over largest eigenvalue of the fit's normal matrix (1: as
        well constrained in every direction; 0: a free direction).
    weak_directions : tuple of str
        The directions the data leave free, named in the CAD frame
        ("translation along x", "rotation about z", or a sum of them).
    ambiguous : bool or None
        The global search found another pose fitting almost as well (None:
        no global search ran).
    runner_up_score : float or None
        The best other pose's score over the chosen one's (1: fits as well).
    """

    converged: bool
    stop_reason: str
    iterations: int
    observability: float
    weak_directions: tuple[str, ...]
    ambiguous: bool | None = None
    runner_up_score: float | None = None


@dataclass(frozen=True, eq=False)
class Measurement:
    """One measured part.

    Attributes
    ----------
    verdict : Verdict or None
        ``pass``, ``fail`` or ``not_measurable``; None when the part could
        not be measured at all (see ``reason``).
    reason : str or None
        Why the verdict is not ``pass`` (the points that failed or could not
        be judged), why there is none, and any note of the fit.
    frame : {"rig", "cad", "data"}
        The frame the measured points were given in.
    transform : (4, 4) float64 or None
        ``T_cad_<frame>``: maps the measured points into the CAD frame.
    registration : Registration or None
        The final fit.
    quality : FitQuality or None
    deviations : Deviations or None
        Per point and at the comparison points (each comparison entry as
        judged against the pose's uncertainty); its ``verdict`` is the
        part's.
    points : (N, 3) float64, mm
        The cloud that was measured, in ``frame`` (the last pass's).
    passes : tuple of Pass
        Each matching pass's cloud and fit, in order (frames only).
    timings_ms : dict of str to float
        Per stage: ``reconstruct``, ``guide``, ``align``, ``deviations``, ``total``.
    """

    verdict: Verdict | None
    reason: str | None
    frame: Frame
    transform: np.ndarray | None = field(default=None, repr=False)
    registration: Registration | None = field(default=None, repr=False)
    quality: FitQuality | None = None
    deviations: Deviations | None = field(default=None, repr=False)
    points: np.ndarray = field(default_factory=lambda: np.empty((0, 3)), repr=False)
    passes: tuple[Pass, ...] = field(default=(), repr=False)
    timings_ms: dict[str, float] = field(default_factory=dict)

    def points_cad(self) -> np.ndarray | None:
        """``points`` mapped into the CAD frame (None without a transform)."""
        if self.transform is None:
            return None
        return _apply(self.transform, self.points)


# --------------------------------------------------------------------------- the sequence


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
    rec = rig if isinstance(rig, Reconstructor) else Reconstructor.build(rig)
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    kw = p.register.kwargs("rig")

    # 1. The cloud.
    t = time.perf_counter()
    cloud = rec(frames, keep_matching=p.guided)
    timings["reconstruct"] = _ms(t)
    first = _pass("first", cloud)
    if len(first.points) == 0:
        return _unmeasured("empty cloud: no surface seen in the frames", timings, t_start, first)

    # 2. and 3. The first fit and, from it, the guided passes.
    passes = [first]
    start: np.ndarray | None = None
    final: Registration | None = None
    if p.guided:
        t = time.perf_counter()
        fit = _try_align(part, first, p, kw)
        passes[0] = dataclasses.replace(first, fit=fit)
        if fit is not None and _trusted(fit, p):
            start = fit.transform
            guided = rec.guided(cloud, Guide.from_cad(part.cad, np.linalg.inv(start)))
            passes += _bends(part, rec, guided, start, p, kw)
            if len(passes[-1].points) == 0:
                log.debug("no guided cloud: measured from the first pass")
                passes, start = passes[:1], None
        else:
            log.debug("no guided pass: the first fit is not trusted")
            final = fit
        timings["guide"] = _ms(t)

    # 4. The final fit.
    last = passes[-1]
    t = time.perf_counter()
    try:
        if final is None:
            final = _fit(part, last.points, last.weights, p, kw, start=start)
    except InspectionError as exc:
        timings["align"] = _ms(t)
        return _unmeasured(f"alignment failed: {exc}", timings, t_start, *passes)
    timings["align"] = _ms(t)
    passes[-1] = dataclasses.replace(last, fit=final)
    search = passes[0].fit if start is not None else None
    return _judge(part, last.points, final, p, "rig", timings, t_start, tuple(passes), search)


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
        :data:`MIN_POINTS` points; bad weights; an unknown frame.
    """
    p = params if params is not None else MeasureParams()
    if frame not in ("rig", "cad", "data"):
        raise InvalidInput(f"frame must be 'rig', 'cad' or 'data', got {frame!r}")
    _check_part(part, frame)
    cloud = validate_cloud(points)
    w = np.ones(len(cloud)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(cloud),) or not np.isfinite(w).all() or (w < 0).any():
        raise InvalidInput(f"weights must be ({len(cloud)},) finite and >= 0")
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    t = time.perf_counter()
    try:
        fit = _fit(part, cloud, w, p, p.register.kwargs(frame), frame=frame)
    except InspectionError as exc:
        timings["align"] = _ms(t)
        return _unmeasured(f"alignment failed: {exc}", timings, t_start, frame=frame)
    timings["align"] = _ms(t)
    return _judge(part, cloud, fit, p, frame, timings, t_start, ())


# --------------------------------------------------------------------------- stages


def validate_cloud(points: object) -> np.ndarray:
    """``points`` as a C-contiguous (N, 3) float64 array, or raise InvalidInput.

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
    points: np.ndarray, weights: np.ndarray, p: MeasureParams
) -> tuple[np.ndarray, np.ndarray | None]:
    """The points a fit uses (subsampled to ``max_points``) and their weights, if used."""
    if len(points) > p.max_points:
        idx = _stride(len(points), p.max_points)
        points, weights = points[idx], weights[idx]
    return points, (weights if p.use_weights else None)


def _fit(
    part: PartModel,
    points: np.ndarray,
    weights: np.ndarray,
    p: MeasureParams,
    kw: dict[str, object],
    *,
    frame: Frame = "rig",
    start: np.ndarray | None = None,
) -> Registration:
    """The fit of a cloud: from ``start`` (no escape scan: the turn was searched),
    from the identity (``frame="cad"``), or by the global search."""
    pts, w = _fit_inputs(points, weights, p)
    if start is not None:
        return register(part.tree, pts, init=start, weights=w, escape_deg=None, **kw)  # type: ignore[arg-type]
    if frame == "cad":
        return register(part.tree, pts, init=np.eye(4), weights=w, **kw)  # type: ignore[arg-type]
    return align(part.tree, pts, model=part.alignment, cad=part.cad, weights=w, **kw)  # type: ignore[arg-type]


def _try_align(
    part: PartModel, first: Pass, p: MeasureParams, kw: dict[str, object]
) -> Registration | None:
    try:
        return _fit(part, first.points, first.weights, p, kw)
    except InspectionError as exc:
        log.debug("no guided pass: the first alignment failed: %s", exc)
        return None


def _trusted(fit: Registration, p: MeasureParams) -> bool:
    """Whether a first fit is good enough to guide the matching."""
    return bool(
        np.isfinite(fit.transform).all()
        and not (isinstance(fit, Alignment) and fit.ambiguous)
        and fit.inlier_fraction >= p.min_inlier_fraction
        and fit.rms_mm <= p.max_rms_mm
    )


def _bends(
    part: PartModel,
    rec: Reconstructor,
    guided: Cloud,
    start: np.ndarray,
    p: MeasureParams,
    kw: dict[str, object],
) -> list[Pass]:
    """The guided pass, fitted from ``start``, and the windows on bends matched once
    more with the CAD where that fit puts it; the guided pass alone when it cannot be fitted.

    A guided window takes its shape from the guide: placed off, it pulls the
    bends towards it, so they are matched again from the better pose.
    """
    g = _pass("guided", guided)
    if len(g.points) == 0:
        return [g]
    try:
        # Every guided point, not a subsample: the bends' guide is only as good as this fit.
        fit = register(
            part.tree, g.points, init=start, escape_deg=None,
            weights=g.weights if p.use_weights else None, **kw,  # type: ignore[arg-type]
        )  # fmt: skip
    except InspectionError as exc:
        log.debug("bends not matched again: the guided cloud did not fit: %s", exc)
        return [g]
    g = dataclasses.replace(g, fit=fit)
    bends = rec.rematch_bends(guided, Guide.from_cad(part.cad, np.linalg.inv(fit.transform)))
    return [g, _pass("bends", bends)]


def _judge(
    part: PartModel,
    points: np.ndarray,
    fit: Registration,
    p: MeasureParams,
    frame: Frame,
    timings: dict[str, float],
    t_start: float,
    passes: tuple[Pass, ...],
    search: Registration | None = None,
) -> Measurement:
    """5.-7.: the fit's quality, the deviations, and the verdict.

    ``search`` is the global search's fit when the final fit started from
    it (the guided passes): its ambiguity is the part's."""
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

    t = time.perf_counter()
    devs = deviations(
        part.tree,
        _apply(T, points),
        part.comparison_points,
        min_support=p.min_support,
        max_distance_mm=p.register.max_distance_mm,
    )
    devs = _held_to_the_pose(devs, part.comparison_points, fit, p)
    timings["deviations"] = _ms(t)
    timings["total"] = _ms(t_start)
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
        timings_ms=timings,
    )


def _fit_problem(fit: Registration, quality: FitQuality, p: MeasureParams) -> str | None:
    """Why the fit cannot be measured from, or None."""
    if not fit.converged:
        return (
            f"the fit did not converge ({fit.stop_reason.value} after {fit.iterations} iterations)"
        )
    if quality.ambiguous and p.ambiguous_is_error:
        return (
            "pose ambiguous: another pose fits almost as well "
            f"(score {quality.runner_up_score:.2f} of the chosen one's)"
        )
    if not fit.inlier_fraction >= p.min_inlier_fraction:
        return (
            f"fit kept {fit.inlier_fraction:.0%} of the points, "
            f"below the {p.min_inlier_fraction:.0%} required"
        )
    if not fit.rms_mm <= p.max_rms_mm:
        return f"fit residual {fit.rms_mm:.3f} mm above the {p.max_rms_mm} mm allowed"
    return None


def fit_quality(fit: Registration, search: Registration | None = None) -> FitQuality:
    """The diagnostics of ``fit``: convergence, observability, free directions, and
    the ambiguity of the global search (``fit`` itself, or ``search`` it started from)."""
    eig = np.asarray(fit.observability, dtype=np.float64)
    ratio = float(eig[0] / eig[-1]) if eig[-1] > 0 else 0.0
    ambiguous = runner_up = None
    found = search if search is not None else fit
    if isinstance(found, Alignment):
        ambiguous = bool(found.ambiguous)
        finalists = [c for c in found.candidates if c.refined]
        if len(finalists) > 1 and finalists[0].score > 0:
            runner_up = float(finalists[1].score / finalists[0].score)
    return FitQuality(
        converged=bool(fit.converged),
        stop_reason=StopReason(fit.stop_reason).value,
        iterations=int(fit.iterations),
        observability=ratio,
        weak_directions=tuple(_direction_name(u) for u in fit.degenerate_directions),
        ambiguous=ambiguous,
        runner_up_score=runner_up,
    )


def _direction_name(u: np.ndarray) -> str:
    a = np.abs(u)
    return " + ".join(_DIRECTION_NAMES[i] for i in np.flatnonzero(a >= 0.5 * a.max()))


def pose_sigma_mm(
    fit: Registration, position: npt.ArrayLike, normal: npt.ArrayLike
) -> tuple[float, tuple[str, ...]]:
    """How far the pose's uncertainty moves a CAD point along a direction (1 sigma, mm).

    The fit's twist ``(omega L, t)`` about ``fit.pose_center`` moves a point
    ``q`` along ``n`` by ``J . x`` with ``J = ((q - c) x n / L, n)``; its
    variance is ``J^T C J`` with ``C = fit.pose_covariance``. A direction the
    data leave free that moves the point along ``n`` makes it infinite.

    Returns
    -------
    sigma_mm : float
        ``inf`` when a free direction moves the point.
    free : tuple of str
        The names of the free directions that do.
    """
    q = np.asarray(position, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    L = float(fit.pose_radius_mm)
    J = np.concatenate([np.cross(q - fit.pose_center, n) / L, n])
    moving = tuple(
        _direction_name(u) for u in fit.degenerate_directions if abs(float(J @ u)) > _FREE_MOVES
    )
    if moving:
        return math.inf, moving
    return float(np.sqrt(max(float(J @ fit.pose_covariance @ J), 0.0))), ()


def _held_to_the_pose(
    devs: Deviations,
    points: Sequence[ComparisonPoint],
    fit: Registration,
    p: MeasureParams,
) -> Deviations:
    """The deviations with every judged point whose deviation the pose leaves
    uncertain (3 sigma along its normal above ``uncertainty_fraction`` of its
    tolerance band) made not measurable, with the reason."""
    by_name = {cp.name: cp for cp in points}
    out: list[ComparisonResult] = []
    for c in devs.comparison:
        if c.verdict is Verdict.NOT_MEASURABLE:
            out.append(c)
            continue
        cp = by_name[c.name]
        sigma, free = pose_sigma_mm(fit, cp.position, cp.normal)
        allowed = p.uncertainty_fraction * (cp.upper_mm - cp.lower_mm)
        if 3.0 * sigma <= allowed:
            out.append(c)
            continue
        if free:
            why = f"the fit leaves {', '.join(free)} free, which moves this point along its normal"
        else:
            why = (
                f"the pose leaves its deviation uncertain by {3 * sigma:.4f} mm (3 sigma), "
                f"over {allowed:.4f} mm allowed"
            )
        out.append(
            dataclasses.replace(
                c, verdict=Verdict.NOT_MEASURABLE, deviation_mm=math.nan, reason=why
            )
        )
    comparison = tuple(out)
    return dataclasses.replace(devs, comparison=comparison, verdict=part_verdict(comparison))


def _reason(devs: Deviations, note: str | None) -> str | None:
    """Which points made the verdict, and any note of the fit."""
    parts = []
    if devs.verdict is Verdict.FAIL:
        names = [c.name for c in devs.comparison if c.verdict is Verdict.FAIL]
        parts.append("out of tolerance at " + ", ".join(names))
    elif devs.verdict is Verdict.NOT_MEASURABLE:
        why = [
            f"{c.name} ({c.reason})" for c in devs.comparison if c.verdict is Verdict.NOT_MEASURABLE
        ]
        parts.append("not measurable at " + "; ".join(why))
    if note:
        parts.append(note)
    return "; ".join(parts) or None


def _unmeasured(
    reason: str, timings: dict[str, float], t_start: float, *passes: Pass, frame: Frame = "rig"
) -> Measurement:
    timings["total"] = _ms(t_start)
    log.debug("not measured: %s", reason)
    return Measurement(
        verdict=None,
        reason=reason,
        frame=frame,
        points=passes[-1].points if passes else np.empty((0, 3)),
        passes=passes,
        timings_ms=timings,
    )


def _check_part(part: PartModel, frame: Frame) -> None:
    if not isinstance(part, PartModel):
        raise InvalidInput(f"part must be a PartModel, got {type(part).__name__}")
    if frame != "cad" and part.alignment is None:
        raise InvalidInput(
            f"part {part.cad.name!r} has no alignment model: build it with alignment=True "
            "to measure clouds that lie anywhere"
        )


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
