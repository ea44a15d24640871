"""One FrameSet in, one InspectionResult out: reconstruct, align, deviations.

The worker and replay call the same :meth:`Pipeline.run`, which is what lets
a replay reproduce a recorded result exactly. The stages are plain callables
collected in :class:`Stages`: :func:`flash_stages`, the four-camera flash rig
(``inspection.simulate`` / ``reconstruct`` / ``align`` / ``deviations``).
With a ``guide`` stage the frames are matched twice: the first cloud is
aligned, then the fine matching runs again (from the first pass's coarse
matching) with the part's CAD at that pose shaping its windows
(``inspection.Guide``); the windows on bends are matched once more with the
CAD where that cloud puts it, and the cloud is fitted from the first pose and
measured. The parts are the :class:`~service.parts.LoadedPart` objects of the station's
:class:`~service.parts.PartRegistry`: the worker and the REST API measure
with the same tree, alignment model and spec.

:meth:`Pipeline.run` never raises for a bad trigger: every failure becomes a
result with status ``error`` and a reason.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from inspection.errors import InspectionError

from .inspect import CloudFrame, Trigger, inspect_cloud, subsample
from .models import (
    InspectionResult,
    Status,
    make_result_id,
    missed_serial,
    software_version,
)
from .parts import LoadedPart
from .protocol import FrameSet

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- stages


@dataclass(frozen=True)
class Stages:
    """The computation behind the pipeline, as plain callables.

    The line measures with :func:`flash_stages`; the callables are separate so
    that a test can replace one (a crashing stage, an empty cloud) and see
    what the worker makes of it.

    Attributes
    ----------
    name : str
        Recorded with every run (``flash``).
    rig : object
        What ``reconstruct`` and ``render`` measure with.
    calibration_id : str
        Identifies ``rig``.
    reconstruct : callable(rig, frames) -> cloud
        ``cloud.points`` (N, 3) float64 rig frame mm.
    align : callable(part, points_rig) -> registration
        ``part`` is a :class:`~service.parts.LoadedPart`;
        ``registration.transform`` is T_cad_rig (4, 4); also ``rms_mm``,
        ``inlier_fraction``.
    deviations : callable(part, points_cad) -> deviations
        ``distances`` (N,) signed mm, ``comparison`` list with ``name``,
        ``deviation_mm``, ``support``, ``verdict``.
    render : callable(rig, mesh, T_rig_part, seed) -> list of images
        The simulator matching ``reconstruct`` (used by the ingest).
    calibrations : callable() -> list of dict
        One per camera, for the recorder (``name``, ``width``, ``height``,
        ``K``, ``D``, ``R``, ``P``).
    guide : callable(rig, cloud, part, T_rig_part) -> cloud, optional
        Matches the frames of ``cloud`` (what ``reconstruct`` returned) again
        with the part's CAD at ``T_rig_part`` guiding the matching (given with
        ``refit``; None: one pass). The flash rig's also fits that cloud and
        matches the windows on bends once more with the CAD at the fitted
        pose (``Reconstructor.rematch_bends``).
    refit : callable(part, points_rig, T_cad_rig) -> registration, optional
        Fits the guided cloud, starting from the first pass's pose.
    """

    name: str
    rig: Any
    calibration_id: str
    reconstruct: Callable[[Any, list[np.ndarray]], Any]
    align: Callable[[LoadedPart, np.ndarray], Any]
    deviations: Callable[[LoadedPart, np.ndarray], Any]
    render: Callable[[Any, trimesh.Trimesh, np.ndarray, int], list[np.ndarray]]
    calibrations: Callable[[], list[dict[str, Any]]] = list
    guide: Callable[[Any, Any, LoadedPart, np.ndarray], Any] | None = None
    refit: Callable[[LoadedPart, np.ndarray, np.ndarray], Any] | None = None

    def __post_init__(self) -> None:
        if (self.guide is None) != (self.refit is None):
            raise ValueError("Stages: give both guide and refit, or neither")


@dataclass(frozen=True, eq=False)
class FlashRig:
    """The four-camera flash rig: the nominal rig the simulator renders with (the truth)
    and the calibrated one the reconstruction measures with, plus its precomputed state."""

    nominal: Any
    calibrated: Any
    reconstructor: Any


def flash_stages(rig_calibration: str | Path | None = None, *, guided: bool = True) -> Stages:
    """The line's stages: ``inspection.simulate`` with ``Rig.nominal()`` renders,
    ``inspection.reconstruct`` with the calibrated rig measures, ``inspection.align``
    fits the cloud to the part's preloaded :class:`~inspection.grid.GridTree` and
    ``inspection.deviations`` measures against it.

    Parameters
    ----------
    rig_calibration : path, optional
        Calibrated rig (TOML, written by ``inspection calibrate``); absent or
        missing file: ``Rig.default()``.
    guided : bool
        With the CAD-guided second matching pass (``guide`` and ``refit``).
    """
    from inspection.alignment import align as inspection_align
    from inspection.deviations import deviations as inspection_deviations
    from inspection.reconstruct import Guide, Reconstructor
    from inspection.reconstruct import reconstruct as inspection_reconstruct
    from inspection.registration import register as inspection_register
    from inspection.rig import Rig
    from inspection.simulate import simulate

    from . import inspect as measure

    path = Path(rig_calibration) if rig_calibration else None
    calibrated = Rig.load(path) if path is not None and path.is_file() else Rig.default()
    rig = FlashRig(Rig.nominal(), calibrated, Reconstructor.build(calibrated))

    def reconstruct(r: FlashRig, frames: list[np.ndarray]) -> Any:
        # The matching is kept for the guided pass, which starts from it.
        return inspection_reconstruct(
            r.calibrated, frames, reconstructor=r.reconstructor, keep_matching=guided
        )

    def align(part: LoadedPart, points: np.ndarray) -> Any:
        return inspection_align(
            part.tree,
            points,
            model=part.alignment_model,
            cad=part.cad,
            **measure._registration_kwargs(part),
        )

    def refit(part: LoadedPart, points: np.ndarray, T_cad_rig: np.ndarray) -> Any:
        # From align's pose: the turn is searched already, no escape scan.
        return inspection_register(
            part.tree,
            points,
            init=T_cad_rig,
            escape_deg=None,
            **measure._registration_kwargs(part),
        )

    def guide(r: FlashRig, cloud: Any, part: LoadedPart, T: np.ndarray) -> Any:
        rec = r.reconstructor
        guided = rec.guided(cloud, Guide.from_cad(part.cad, T))
        # Then the windows on bends again, with the CAD where the guided cloud
        # puts it: a guide placed off pulls them towards it.
        try:
            fit = refit(part, guided.points, np.linalg.inv(T))
            return rec.rematch_bends(guided, Guide.from_cad(part.cad, np.linalg.inv(fit.transform)))
        except InspectionError as exc:
            log.debug("bends not matched again: the guided cloud did not fit: %s", exc)
            return guided

    def deviations(part: LoadedPart, points_cad: np.ndarray) -> Any:
        return inspection_deviations(part.tree, points_cad, measure.comparison_points(part.spec))

    def render(r: FlashRig, mesh: trimesh.Trimesh, T: np.ndarray, seed: int) -> list[np.ndarray]:
        return simulate(r.nominal, mesh, T, seed=seed)

    def calibrations() -> list[dict[str, Any]]:
        out = []
        for cam in calibrated.cameras:
            P = np.asarray(cam.K) @ np.hstack([np.asarray(cam.R), np.asarray(cam.t)[:, None]])
            out.append(
                {
                    "name": cam.name,
                    "width": cam.width,
                    "height": cam.height,
                    "K": np.asarray(cam.K).ravel().tolist(),
                    "D": np.asarray(cam.dist).ravel().tolist(),
                    "R": np.asarray(cam.R).ravel().tolist(),
                    "P": P.ravel().tolist(),
                }
            )
        return out

    return Stages(
        name="flash",
        rig=rig,
        calibration_id=calibrated.id,
        reconstruct=reconstruct,
        align=align,
        deviations=deviations,
        render=render,
        calibrations=calibrations,
        guide=guide if guided else None,
        refit=refit if guided else None,
    )


# --------------------------------------------------------------------------- results


@dataclass(frozen=True, eq=False)
class Outcome:
    """The result and the arrays behind it (for the recorder).

    Attributes
    ----------
    result : InspectionResult
    points_rig : (N, 3) float64 or None
        The reconstructed cloud, rig frame, mm (after subsampling to the part's ``max_points``).
    distances : (N,) float64 or None
        Signed deviation of each point from the CAD, mm.
    T_cad_rig : (4, 4) float64 or None
    """

    result: InspectionResult
    points_rig: np.ndarray | None = None
    distances: np.ndarray | None = None
    T_cad_rig: np.ndarray | None = None


@dataclass
class Pipeline:
    """Measures FrameSets of the parts it knows.

    Parameters
    ----------
    stages : Stages
    parts : mapping of part name to LoadedPart
    line, station : str
        Only FrameSets of this line and station are accepted (None: any).
    """

    stages: Stages
    parts: Mapping[str, LoadedPart]
    line: str | None = None
    station: str | None = None
    version: str = field(default_factory=software_version)

    def _base(self, fs: FrameSet) -> dict[str, Any]:
        part = self.parts.get(fs.part)
        return dict(
            id=make_result_id(fs.line, fs.station, fs.seq, fs.triggered_ns),
            line=fs.line,
            station=fs.station,
            part=fs.part,
            serial=fs.serial,
            seq=fs.seq,
            triggered_ns=fs.triggered_ns,
            calibration_id=fs.calibration_id or None,
            software_version=self.version,
            spec_version=part.spec.version if part else None,
            cad_hash=part.cad.hash if part else None,
            tree_hash=part.tree_hash if part else None,
        )

    def run(self, fs: FrameSet) -> Outcome:
        """Measure one FrameSet; never raises for bad data (status ``error`` instead)."""
        timings: dict[str, float] = {}
        t_start = time.perf_counter()
        base = self._base(fs)
        try:
            return self._run(fs, base, timings, t_start)
        except (InspectionError, ValueError, np.linalg.LinAlgError) as exc:
            reason = f"{type(exc).__name__}: {exc}"
        except Exception as exc:  # a bug in a stage must not take the worker down
            log.exception("pipeline failed on %s seq %d", fs.serial, fs.seq)
            reason = f"internal error: {type(exc).__name__}: {exc}"
        timings["total"] = (time.perf_counter() - t_start) * 1e3
        return Outcome(
            InspectionResult(status=Status.error, reason=reason[:2000], timings_ms=timings, **base)
        )

    def _error(
        self, base: dict[str, Any], reason: str, timings: dict[str, float], t0: float
    ) -> Outcome:
        timings["total"] = (time.perf_counter() - t0) * 1e3
        return Outcome(
            InspectionResult(status=Status.error, reason=reason, timings_ms=timings, **base)
        )

    def _guided(
        self, part: LoadedPart, cloud: Any, points: np.ndarray
    ) -> tuple[np.ndarray, Callable[[LoadedPart, np.ndarray], Any]] | None:
        """The CAD-guided second pass: the guided cloud and the fit that starts from the
        first pass's pose, or None (one pass) when the first alignment failed, is
        ambiguous or is not trusted; the usual fit then reports why."""
        assert self.stages.guide is not None and self.stages.refit is not None
        settings = part.spec.registration
        try:
            first = self.stages.align(part, subsample(points, settings.max_points))
        except InspectionError as exc:
            log.debug("no guided pass: the first alignment failed: %s", exc)
            return None
        T = np.asarray(first.transform, dtype=np.float64)
        trusted = (
            np.isfinite(T).all()
            and not getattr(first, "ambiguous", False)
            and first.inlier_fraction >= settings.min_inlier_fraction
            and first.rms_mm <= settings.max_rms_mm
        )
        if not trusted:
            log.debug("no guided pass: the first alignment is not trusted")
            return None
        guided = _finite_points(self.stages.guide(self.stages.rig, cloud, part, np.linalg.inv(T)))
        if guided is None or len(guided) == 0:
            return None
        refit = self.stages.refit

        def fit(p: LoadedPart, pts: np.ndarray) -> Any:
            return refit(p, pts, T)

        return guided, fit

    def _run(
        self, fs: FrameSet, base: dict[str, Any], timings: dict[str, float], t0: float
    ) -> Outcome:
        if self.line is not None and fs.line != self.line:
            return self._error(
                base, f"FrameSet of line {fs.line!r}, this is {self.line!r}", timings, t0
            )
        if self.station is not None and fs.station != self.station:
            return self._error(
                base, f"FrameSet of station {fs.station!r}, this is {self.station!r}", timings, t0
            )
        part = self.parts.get(fs.part)
        if part is None:
            known = ", ".join(sorted(self.parts)) or "none"
            return self._error(base, f"unknown part {fs.part!r} (known: {known})", timings, t0)
        if fs.calibration_id and fs.calibration_id != self.stages.calibration_id:
            return self._error(
                base,
                f"frames are for calibration {fs.calibration_id!r}, "
                f"this worker measures with {self.stages.calibration_id!r}",
                timings,
                t0,
            )
        t = time.perf_counter()
        cloud = self.stages.reconstruct(self.stages.rig, fs.images)
        timings["reconstruct"] = (time.perf_counter() - t) * 1e3
        points = _finite_points(cloud)
        if points is None:
            return self._error(
                base, f"reconstruction gave points of shape {np.shape(cloud.points)}", timings, t0
            )
        if len(points) == 0:
            return self._error(base, "empty cloud: no surface seen in the frames", timings, t0)
        fit = self.stages.align
        if self.stages.guide is not None:
            t = time.perf_counter()
            guided = self._guided(part, cloud, points)
            timings["guide"] = (time.perf_counter() - t) * 1e3
            if guided is not None:
                points, fit = guided
        # From here on the REST API's steps: align, deviations, verdict.
        trigger = Trigger(
            id=base["id"],
            line=fs.line,
            station=fs.station,
            serial=fs.serial,
            seq=fs.seq,
            triggered_ns=fs.triggered_ns,
            calibration_id=base["calibration_id"],
        )
        measured = inspect_cloud(
            part,
            points,
            trigger,
            frame=CloudFrame.rig,
            timings_ms=timings,
            fit=fit,
            measure=self.stages.deviations,
        )
        result = measured.result
        T = None if result.transform is None else np.asarray(result.transform, dtype=np.float64)
        return Outcome(result, points_rig=points, distances=measured.distances, T_cad_rig=T)


def _finite_points(cloud: Any) -> np.ndarray | None:
    """The cloud's finite points (N, 3), or None when its points are not (N, 3)."""
    points = np.asarray(cloud.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        return None
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        log.debug("dropping %d non-finite points", int((~finite).sum()))
        points = points[finite]
    return points


def missed_result(
    *,
    line: str,
    station: str,
    seq: int,
    triggered_ns: int,
    reason: str,
    part: str | None = None,
    serial: str | None = None,
    calibration_id: str | None = None,
    unknown_part: str = "unknown",
) -> InspectionResult:
    """The result of a trigger that was never inspected (dropped, or a gap in ``seq``)."""
    return _unmeasured(
        Status.missed, line, station, seq, triggered_ns, reason, part or unknown_part, serial,
        calibration_id,
    )  # fmt: skip


def error_result(
    *,
    line: str,
    station: str,
    seq: int,
    triggered_ns: int,
    reason: str,
    part: str | None = None,
    serial: str | None = None,
    calibration_id: str | None = None,
) -> InspectionResult:
    """The result of a FrameSet that could not even be decoded."""
    return _unmeasured(
        Status.error, line, station, seq, triggered_ns, reason[:2000], part or "unknown", serial,
        calibration_id,
    )  # fmt: skip


def _unmeasured(
    status: Status,
    line: str,
    station: str,
    seq: int,
    triggered_ns: int,
    reason: str,
    part: str,
    serial: str | None,
    calibration_id: str | None,
) -> InspectionResult:
    """A result with no measurement: its identity, status and reason only."""
    return InspectionResult(
        id=make_result_id(line, station, seq, triggered_ns),
        line=line,
        station=station,
        part=part,
        serial=serial or missed_serial(seq),
        seq=seq,
        triggered_ns=triggered_ns,
        status=status,
        reason=reason,
        calibration_id=calibration_id,
        software_version=software_version(),
    )
