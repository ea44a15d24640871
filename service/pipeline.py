"""One FrameSet in, one InspectionResult out, through the measuring sequence.

The worker and replay call the same :meth:`Pipeline.run`, which is what lets
a replay reproduce a recorded result exactly. What the pipeline measures
with is collected in :class:`Stages`: the one ``measure`` callable that an
executor runs (``inspection.measure_frames`` on the calibrated rig, for the
flash rig of :func:`flash_stages`; ``inspection.measure_hologram`` on the
calibrated head, for the holographic head of :func:`holography_stages`), and
the simulator that renders the frames of the simulated line. The parts are the
:class:`~service.parts.LoadedPart` objects of the station's
:class:`~service.parts.PartRegistry`: the worker and the REST API measure
with the same tree, alignment model and spec.

:meth:`Pipeline.run` never raises for a bad trigger: every failure becomes a
result with status ``error`` and a reason.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh

from inspection.errors import InspectionError
from inspection.measure import Measurement, MeasurePath

from .models import (
    InspectionResult,
    Status,
    make_result_id,
    missed_serial,
    software_version,
)
from .parts import LoadedPart
from .protocol import FrameSet
from .results import Outcome, Trigger, outcome

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- stages


@dataclass(frozen=True)
class Stages:
    """What a station measures with: one measuring callable and the simulator.

    Attributes
    ----------
    name : str
        Recorded with every run (``flash``, ``holography``).
    rig : object
        What ``render`` renders with.
    calibration_id : str
        Identifies the calibrated rig ``measure`` measures with.
    measure : callable(part, frames) -> inspection.Measurement
        The whole measuring sequence for one trigger's images; the one call
        an executor runs. ``part`` is a :class:`~service.parts.LoadedPart`.
    render : callable(rig, mesh, T_rig_part, seed) -> list of images
        The simulator matching ``measure`` (used by the ingest).
    calibrations : callable() -> list of dict
        One per camera, for the recorder (``name``, ``width``, ``height``,
        ``K``, ``D``, ``T_camera_rig``: see :class:`~service.recorder.Recorder`).
    guided : bool
        Whether ``measure`` matches the frames a second time, guided by the CAD.
    path : {"cloud", "comparison_points"}
        What ``measure`` measures (``inspection.MeasureParams.path``).
    calibration_toml : str or None
        The calibrated rig itself, for the recordings.
    remake : callable(threads) -> Stages, or None
        Builds the same measuring stages in another process (a Dask worker),
        matching stereo pairs on ``threads`` threads; picklable. None: these
        stages exist in this process only.
    sensor : str
        The FrameSet ``sensor`` these stages measure (``flash`` or
        ``holography``); a FrameSet of another is refused.
    """

    name: str
    rig: Any
    calibration_id: str
    measure: Callable[[LoadedPart, list[np.ndarray]], Measurement]
    render: Callable[[Any, trimesh.Trimesh, np.ndarray, int], list[np.ndarray]]
    calibrations: Callable[[], list[dict[str, Any]]] = list
    guided: bool = True
    calibration_toml: str | None = None
    path: MeasurePath = "cloud"
    remake: Callable[[int], Stages] | None = None
    sensor: str = "flash"


@dataclass(frozen=True)
class FlashRender:
    """A :attr:`Stages.render`: the simulator with the line's render options (the flash)."""

    options: Any
    """inspection.RenderOptions"""

    def __call__(
        self, rig: Any, mesh: trimesh.Trimesh, T_rig_part: np.ndarray, seed: int
    ) -> list[np.ndarray]:
        from inspection.simulate import simulate

        return simulate(rig, mesh, T_rig_part, seed=seed, options=self.options)


@dataclass(frozen=True)
class FlashRemake:
    """A :attr:`Stages.remake` for :func:`flash_stages`: the calibrated rig as TOML text
    the matching mode and the path, which is all a process elsewhere needs to measure the
    same way."""

    calibration_toml: str
    guided: bool
    path: MeasurePath = "cloud"

    def __call__(self, threads: int) -> Stages:
        from inspection.rig import Rig

        return flash_stages(
            Rig.from_toml(self.calibration_toml), guided=self.guided, threads=threads,
            path=self.path,
        )  # fmt: skip


def flash_stages(
    rig_calibration: Any = None,
    *,
    guided: bool = True,
    truth: Any = None,
    render_options: Any = None,
    threads: int | None = None,
    path: MeasurePath = "cloud",
) -> Stages:
    """The line's stages: ``inspection.simulate`` renders with the rig as built;
    ``inspection.measure_frames`` with the calibrated rig measures.

    Parameters
    ----------
    rig_calibration : path or inspection.Rig, optional
        Calibrated rig (TOML, written by ``inspection calibrate``, or the rig
        itself); absent: ``Rig.default()``. A named file that does not exist
        is an error.
    guided : bool
        With the CAD-guided second matching pass.
    truth : inspection.Rig, optional
        The rig the simulator renders with; default ``Rig.nominal()``.
    render_options : inspection.RenderOptions, optional
        The simulator's options (the flash); default its own.
    threads : int, optional
        Stereo pairs matched at once (``ReconstructParams.threads``; default
        its own). The pairs are matched the same whatever the count.
    path : {"cloud", "comparison_points"}
        What is measured: the whole cloud, or the comparison points alone.
    """
    from inspection.measure import measure_frames
    from inspection.reconstruct import Reconstructor, ReconstructParams
    from inspection.rig import Rig
    from inspection.simulate import RenderOptions

    if isinstance(rig_calibration, Rig):
        calibrated = rig_calibration
    else:
        calibrated = Rig.load(rig_calibration) if rig_calibration else Rig.default()
    nominal = truth if truth is not None else Rig.nominal()
    params = ReconstructParams() if threads is None else ReconstructParams(threads=threads)
    reconstructor = Reconstructor.build(calibrated, params)

    def measure(part: LoadedPart, frames: list[np.ndarray]) -> Measurement:
        params = dataclasses.replace(part.params, guided=guided, path=path)
        return measure_frames(part.model, reconstructor, frames, params)

    def calibrations() -> list[dict[str, Any]]:
        out = []
        for cam in calibrated.cameras:
            T_camera_rig = np.eye(4)
            T_camera_rig[:3, :3], T_camera_rig[:3, 3] = cam.R, np.ravel(cam.t)
            out.append(
                {
                    "name": cam.name,
                    "width": cam.width,
                    "height": cam.height,
                    "K": np.asarray(cam.K).ravel().tolist(),
                    "D": np.asarray(cam.dist).ravel().tolist(),
                    "T_camera_rig": T_camera_rig.ravel().tolist(),
                }
            )
        return out

    return Stages(
        name="flash",
        rig=nominal,
        calibration_id=calibrated.id,
        measure=measure,
        render=FlashRender(render_options if render_options is not None else RenderOptions()),
        calibrations=calibrations,
        guided=guided,
        calibration_toml=calibrated.to_toml(),
        path=path,
        remake=FlashRemake(calibrated.to_toml(), guided, path),
    )


@dataclass(frozen=True)
class HoloRig:
    """The simulated holographic head as built: its design, the reference waves it really
    records with and its noise (what :attr:`Stages.rig` is for :func:`holography_stages`)."""

    head: Any
    """inspection.holography.HoloHead"""
    references: tuple[Any, Any]
    """inspection.holography.ReferenceWave, two"""
    noise: Any = None
    """inspection.holography.HoloNoise, or None: its defaults"""

    @classmethod
    def simulated(cls, head: Any) -> HoloRig:
        """``head`` with the reference waves of :meth:`~inspection.holography.HoloHead.as_built`."""
        return cls(head, head.as_built())

    def record(
        self, mesh: Any, T_head_part: np.ndarray, deviation_mm: np.ndarray | None, seed: int
    ) -> np.ndarray:
        """One hologram, (n, n) uint16, of ``mesh`` at ``T_head_part`` with ``deviation_mm``."""
        from inspection.holography import simulate_hologram

        image, _ = simulate_hologram(
            self.head, mesh, T_head_part, deviation_mm=deviation_mm,
            references=self.references, noise=self.noise, seed=seed,
        )  # fmt: skip
        return image

    def calibrate(self, seed: int = 1) -> Any:
        """The head calibrated from one simulated hologram of a flat plate at z = 0."""
        from inspection.holography import calibrate_head

        plate = trimesh.creation.box((1.5 * self.head.field_mm, 1.5 * self.head.field_mm, 3.0))
        plate.apply_translation((0.0, 0.0, -1.5))
        return calibrate_head(self.head, self.record(plate, np.eye(4), None, seed))


@dataclass(frozen=True)
class HoloRender:
    """A :attr:`Stages.render` for :func:`holography_stages`: one hologram, no deviation."""

    def __call__(
        self, rig: Any, mesh: trimesh.Trimesh, T_head_part: np.ndarray, seed: int
    ) -> list[np.ndarray]:
        return [rig.record(mesh, T_head_part, None, seed)]


@dataclass(frozen=True)
class HoloRemake:
    """A :attr:`Stages.remake` for :func:`holography_stages`: the calibration as TOML text,
    the fixture's pose and whether the pose starts from the gradient field, which is all a
    process elsewhere needs to measure the same way."""

    calibration_toml: str
    T_head_cad: tuple[float, ...]
    coarse_pose: bool

    def __call__(self, threads: int) -> Stages:
        from inspection.holography import HoloCalibration

        calib = HoloCalibration.from_toml(self.calibration_toml)
        return holography_stages(
            calib, T_head_cad=np.reshape(self.T_head_cad, (4, 4)), coarse_pose=self.coarse_pose
        )


def holo_shape_params(*, coarse_pose: bool) -> Any:
    """The measuring sequence's shape parameters for a holographic station: with
    ``coarse_pose``, the part's tilts are first aligned from the gradient field of the
    speckle displacements (``ShapeParams.coarse_pose``). The in-plane shift from the CAD's
    steps stays off: the fixture holds the part in the plane, and the shift only moves a
    well-held part by a pixel or so along the steps."""
    from inspection.holography import ShapeParams

    return ShapeParams(coarse_pose=coarse_pose, coarse_shift=False)


def holography_stages(
    calibration: Any,
    *,
    T_head_cad: np.ndarray,
    truth: HoloRig | None = None,
    coarse_pose: bool = True,
) -> Stages:
    """The holographic head's stages: ``inspection.measure_hologram`` with the calibrated head
    measures one ``mono16`` hologram per trigger of a part held at ``T_head_cad``; the
    simulator records with ``truth`` (default: the calibration's head as built).

    Parameters
    ----------
    calibration : inspection.holography.HoloCalibration
    T_head_cad : (4, 4) float64
        Where the fixture holds the part (its CAD frame in the head frame).
    truth : HoloRig, optional
    coarse_pose : bool
        Align the part's tilts to the gradient field first (``[holography] coarse_pose``):
        a part tilted more than about two degrees off ``T_head_cad`` is found only so.
    """
    from inspection.errors import InvalidInput
    from inspection.measure import measure_hologram

    shape = holo_shape_params(coarse_pose=coarse_pose)

    T_fixture = np.array(T_head_cad, dtype=np.float64)
    if T_fixture.shape != (4, 4) or not np.isfinite(T_fixture).all():
        raise ValueError("T_head_cad must be a finite (4, 4) array")
    n = calibration.head.pixels

    def measure(part: LoadedPart, frames: list[np.ndarray]) -> Measurement:
        if len(frames) != 1 or frames[0].dtype != np.uint16 or frames[0].shape != (n, n):
            shown = ", ".join(f"{f.shape[1]}x{f.shape[0]} {f.dtype}" for f in frames)
            raise InvalidInput(
                f"the holographic head takes one {n}x{n} mono16 image per trigger, got {shown}"
            )
        return measure_hologram(
            part.model, calibration, frames[0], T_fixture, part.params, shape=shape
        )

    toml = calibration.to_toml()
    return Stages(
        name="holography",
        rig=truth if truth is not None else HoloRig.simulated(calibration.head),
        calibration_id=calibration.id,
        measure=measure,
        render=HoloRender(),
        guided=False,
        calibration_toml=toml,
        remake=HoloRemake(toml, tuple(T_fixture.ravel().tolist()), coarse_pose),
        sensor="holography",
    )


# --------------------------------------------------------------------------- results


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

    def _trigger(self, fs: FrameSet, part: LoadedPart | None) -> Trigger:
        return Trigger(
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
        t_start = time.perf_counter()
        # Looked up once: a part replaced meanwhile (a new revision) is measured and
        # reported as one revision, not half of each.
        part = self.parts.get(fs.part)
        trigger = self._trigger(fs, part)
        try:
            refused = self._refusal(fs, part)
            if refused is not None or part is None:
                return self._error(trigger, refused or "unknown part", t_start)
            measured = self.stages.measure(part, fs.images)
            return outcome(measured, trigger)
        except (InspectionError, ValueError, np.linalg.LinAlgError) as exc:
            reason = f"{type(exc).__name__}: {exc}"
        except Exception as exc:  # a bug in a stage must not take the worker down
            log.exception("pipeline failed on %s seq %d", fs.serial, fs.seq)
            reason = f"internal error: {type(exc).__name__}: {exc}"
        return self._error(trigger, reason, t_start)

    def refusal(self, fs: FrameSet) -> str | None:
        """Why this pipeline does not measure ``fs`` (wrong station, unknown part, other
        calibration), or None."""
        return self._refusal(fs, self.parts.get(fs.part))

    def _refusal(self, fs: FrameSet, part: LoadedPart | None) -> str | None:
        if self.line is not None and fs.line != self.line:
            return f"FrameSet of line {fs.line!r}, this is {self.line!r}"
        if self.station is not None and fs.station != self.station:
            return f"FrameSet of station {fs.station!r}, this is {self.station!r}"
        if fs.sensor != self.stages.sensor:
            return f"FrameSet of the {fs.sensor} sensor, this station measures {self.stages.sensor}"
        if part is None:
            known = ", ".join(sorted(self.parts)) or "none"
            return f"unknown part {fs.part!r} (known: {known})"
        if fs.calibration_id and fs.calibration_id != self.stages.calibration_id:
            return (
                f"frames are for calibration {fs.calibration_id!r}, "
                f"this worker measures with {self.stages.calibration_id!r}"
            )
        return None

    def _error(self, trigger: Trigger, reason: str, t_start: float) -> Outcome:
        timings = {"total": (time.perf_counter() - t_start) * 1e3}
        fields = dataclasses.asdict(trigger)
        return Outcome(
            InspectionResult(
                status=Status.error, reason=reason[:2000], timings_ms=timings, **fields
            )
        )


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
