"""The ingest adapter: a trigger at the line rate, a frame source, FrameSets on zenoh.

A :class:`FrameSource` turns one trigger into one :class:`FrameSet`. The
default is :class:`SimulatedRig`: it places the station's part on the
conveyor in a resting pose with a random in-plane rotation and position,
gives it a random serial, now and then presses a dent into it
(:mod:`inspection.defects`; the truth goes into the FrameSet header), and
renders the rig's images. :class:`SimulatedHead` is its counterpart for a
holographic station: the part in its fixture, one hologram per trigger. A
real-camera source implements the same one-method protocol. :func:`line_rig` makes the
simulator's rig the line as configured: its belt speed and slide.

:class:`Ingest` fires the trigger every ``trigger_period_s`` (on an absolute
schedule, so a slow capture does not make the line drift), numbers the
triggers per station from 0, and publishes each FrameSet with congestion
control BLOCK. With a :class:`SeqState` the numbering survives a restart:
each seq is on disk before its FrameSet leaves, so none is used twice.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np
import trimesh

from inspection.cad import CadModel
from inspection.defects import Dent, press, random_dent
from inspection.panel import HoleShift, PanelSpec, sheet_metal_panel, vary_holes
from inspection.rig import Rig
from inspection.transforms import apply

from .pipeline import HoloRig, Stages
from .protocol import FrameSet, Truth, encode_frameset

log = logging.getLogger(__name__)


def simulated_serial(part: str, seq: int, rng: np.random.Generator) -> str:
    """A simulated part's serial: its part's name, the seq and four hex digits drawn from
    the trigger's own stream (so that the same seed gives the same serials)."""
    return f"{part[:8].upper()}-{seq:06d}-{rng.integers(16**4):04x}"


class FrameSource(Protocol):
    """Turns a trigger into a FrameSet."""

    def capture(self, seq: int, triggered_ns: int) -> FrameSet:
        """Fire the flash and the cameras; ``seq`` and ``triggered_ns`` go into the FrameSet."""


@dataclass(frozen=True)
class Drift:
    """A dent pressed at ``center_mm`` (part frame) into every part after seq ``after_seq``,
    ``mm_per_part`` deeper at each: a tool wearing, a die drifting."""

    center_mm: tuple[float, float, float]
    normal: tuple[float, float, float]
    after_seq: int = 0
    mm_per_part: float = 0.02
    radius_mm: float = 20.0
    flat_mm: float = 12.0

    def dent(self, seq: int) -> Dent | None:
        if seq <= self.after_seq:
            return None
        depth = (seq - self.after_seq) * self.mm_per_part
        return Dent(self.center_mm, self.normal, depth, self.radius_mm, self.flat_mm)


@dataclass(frozen=True)
class SimulationSettings:
    """What the simulated rig varies from part to part.

    Attributes
    ----------
    defect_rate : float
        Fraction of parts that get a dent, 0..1.
    dent_depth_mm, dent_radius_mm : (float, float)
        Ranges of an injected dent's depth (its size: ``dent_bump_fraction``
        of them are bumps) and radius, mm, drawn uniformly
        (:func:`inspection.defects.random_dent`).
    dent_flat_mm : float
        Radius of its flat bottom, mm.
    dent_bump_fraction : float
        Share of the dents that are bumps, 0..1.
    position_range_mm : (float, float)
        Half-ranges of the random x, y position of the part's centre on the conveyor.
    yaw_range_deg : float
        Half-range of the random in-plane rotation about the part's long axis
        lying along the conveyor; 180 (the default) allows any rotation, which
        keeps a part of up to about 400 x 260 mm inside the 800 x 500 mm volume
        when its centre stays within 10 mm of the belt's middle across it.
    flip : bool
        Also turn half of the parts by a half turn (arriving either way round).
    hole_shift_mm, hole_radius_mm : float
        A generated panel's holes are made off their drawn place by up to
        ``hole_shift_mm`` in x and y and with radii off by up to
        ``hole_radius_mm`` (:func:`inspection.panel.vary_holes`); 0: as drawn.
    seed : int
        With ``seq``, fixes everything about a part: the same (seed, seq)
        gives the same part, pose, serial and images.
    drift : Drift, optional
        A dent that grows part by part at one place (a process drifting).
    """

    defect_rate: float = 0.1
    dent_depth_mm: tuple[float, float] = (0.2, 2.0)
    dent_radius_mm: tuple[float, float] = (12.0, 20.0)
    dent_flat_mm: float = 7.0
    dent_bump_fraction: float = 0.5
    position_range_mm: tuple[float, float] = (60.0, 10.0)
    yaw_range_deg: float = 180.0
    flip: bool = False
    hole_shift_mm: float = 0.0
    hole_radius_mm: float = 0.0
    seed: int = 0
    drift: Drift | None = None

    def __post_init__(self) -> None:
        if not 0 <= self.defect_rate <= 1:
            raise ValueError("defect_rate must lie in [0, 1]")
        (d_lo, d_hi), (r_lo, r_hi) = self.dent_depth_mm, self.dent_radius_mm
        if not (0 < d_lo <= d_hi and 0 <= self.dent_flat_mm < r_lo <= r_hi):
            raise ValueError("a dent needs 0 < depth lo <= hi and 0 <= flat < radius lo <= hi")
        if not 0 <= self.dent_bump_fraction <= 1:
            raise ValueError("dent_bump_fraction must lie in [0, 1]")
        if not (self.hole_shift_mm >= 0 and self.hole_radius_mm >= 0):
            raise ValueError("hole_shift_mm and hole_radius_mm must be >= 0")


def line_rig(rig: Rig, *, conveyor_speed_mm_s: float, pattern_seed: int) -> Rig:
    """The rig as built (``rig``, e.g. ``Rig.nominal()``) running on a line: its belt at
    ``conveyor_speed_mm_s`` and its projector's speckle slide drawn with ``pattern_seed``."""
    projector = replace(rig.projector, pattern=replace(rig.projector.pattern, seed=pattern_seed))
    conveyor = replace(rig.conveyor, speed_mm_s=conveyor_speed_mm_s)
    return replace(rig, projector=projector, conveyor=conveyor)


@dataclass(frozen=True, eq=False)
class SimPart:
    """A part the simulator can place: its CAD, mesh, resting poses and their probabilities."""

    name: str
    cad: CadModel
    mesh: trimesh.Trimesh
    resting_poses: np.ndarray
    """(K, 4, 4): T_conveyor_part of each stable resting pose (part centre above the origin)."""
    probabilities: np.ndarray
    panel: PanelSpec | None = None
    """The generated panel's design, whose holes the simulator can make off their place."""

    @classmethod
    def from_cad(
        cls, name: str, cad: CadModel, *, flat: bool = True, panel: PanelSpec | None = None
    ) -> SimPart:
        """``flat``: the part rests as modelled (z up, lowest point on z = 0), e.g. the panel.

        Otherwise trimesh's stable poses of the convex hull are used. ``panel``: the
        design ``cad`` was generated from.
        """
        mesh = trimesh.Trimesh(cad.vertices, cad.faces, process=False)
        if flat:
            T = np.eye(4)
            centre = (cad.vertices.min(axis=0) + cad.vertices.max(axis=0)) / 2
            T[:3, 3] = [-centre[0], -centre[1], -cad.vertices[:, 2].min()]
            poses, probs = T[None], np.ones(1)
        else:
            poses, probs = mesh.convex_hull.compute_stable_poses(n_samples=1)
            poses, probs = np.asarray(poses)[:6], np.asarray(probs)[:6]
            for T in poses:
                v = apply(T, cad.vertices)
                centre = (v.min(axis=0) + v.max(axis=0)) / 2
                T[:2, 3] -= centre[:2]
        return cls(name, cad, mesh, poses, probs / probs.sum(), panel)


class SimulatedRig:
    """The default :class:`FrameSource`: renders the station's parts with the stages' simulator.

    Parameters
    ----------
    stages : Stages
        Its ``render`` and ``rig`` make the images, ``calibration_id`` is stamped on them.
    parts : sequence of SimPart
        The part types this station sees (chosen uniformly).
    line, station : str
    settings : SimulationSettings
    """

    def __init__(
        self,
        stages: Stages,
        parts: Sequence[SimPart],
        *,
        line: str,
        station: str,
        settings: SimulationSettings | None = None,
    ) -> None:
        if not parts:
            raise ValueError("the simulated rig needs at least one part")
        self.stages = stages
        self.parts = list(parts)
        self.line = line
        self.station = station
        self.settings = settings or SimulationSettings()

    def capture(self, seq: int, triggered_ns: int) -> FrameSet:
        s = self.settings
        rng = np.random.default_rng([s.seed, seq])
        part = self.parts[int(rng.integers(len(self.parts)))]
        rest = part.resting_poses[rng.choice(len(part.resting_poses), p=part.probabilities)]
        angle = np.deg2rad(rng.uniform(-s.yaw_range_deg, s.yaw_range_deg))
        if s.flip and rng.random() < 0.5:
            angle += np.pi
        c, si = np.cos(angle), np.sin(angle)
        place = np.eye(4)
        place[:2, :2] = [[c, -si], [si, c]]
        place[:2, 3] = rng.uniform(-1, 1, 2) * np.asarray(s.position_range_mm)
        T_rig_part = place @ rest
        serial = simulated_serial(part.name, seq, rng)
        defects: tuple[Dent, ...] = ()
        mesh = part.mesh
        holes: tuple[HoleShift, ...] = ()
        if part.panel is not None and part.panel.holes and (s.hole_shift_mm or s.hole_radius_mm):
            # Its own stream, so that turning this on changes nothing else about a part.
            made, holes = vary_holes(
                part.panel, np.random.default_rng([s.seed, seq, 1]),
                shift_mm=s.hole_shift_mm, radius_mm=s.hole_radius_mm,
            )  # fmt: skip
            m = sheet_metal_panel(made)
            mesh = trimesh.Trimesh(m.vertices, m.faces, process=False)
        if rng.random() < s.defect_rate:
            defects = (self._random_dent(part, T_rig_part, rng),)
        drifted = s.drift.dent(seq) if s.drift is not None and part is self.parts[0] else None
        if drifted is not None:
            defects = (*defects, drifted)
        if defects:
            mesh = press(mesh, defects)
        images = self.stages.render(self.stages.rig, mesh, T_rig_part, int(rng.integers(2**31)))
        return FrameSet(
            line=self.line,
            station=self.station,
            part=part.name,
            serial=serial,
            seq=seq,
            triggered_ns=triggered_ns,
            calibration_id=self.stages.calibration_id,
            images=images,
            cameras=[f"cam{i}" for i in range(len(images))],
            truth=Truth(T_rig_part, defects, holes),
        )

    def _random_dent(self, part: SimPart, T_rig_part: np.ndarray, rng: np.random.Generator) -> Dent:
        """A dent at a random point of the surface the cameras see (normal up in the rig)."""
        s = self.settings
        return random_dent(
            part.mesh, rng, up=T_rig_part[:3, :3].T @ np.array([0.0, 0.0, 1.0]),
            depth_mm=s.dent_depth_mm, radius_mm=s.dent_radius_mm, flat_mm=s.dent_flat_mm,
            bump_fraction=s.dent_bump_fraction,
        )  # fmt: skip


@dataclass(frozen=True)
class FixtureSettings:
    """How a part lies under the holographic head, and the dents it may carry.

    Attributes
    ----------
    T_head_cad : (4, 4) float64
        The fixture's pose: where the part's frame lies in the head's.
    height_range_mm, tilt_range_mrad : float
        Half-ranges of the part's random height about it and of its tilts about x and y.
    defect_rate : float
        Fraction of parts given a dent, 0..1.
    dent_depth_mm, dent_radius_mm : (float, float)
        Ranges of a dent's depth (into the material) and of where it blends back, mm.
    seed : int
        With ``seq``, fixes everything about a part.
    """

    T_head_cad: np.ndarray
    height_range_mm: float = 0.05
    tilt_range_mrad: float = 2.0
    defect_rate: float = 0.1
    dent_depth_mm: tuple[float, float] = (0.03, 0.15)
    dent_radius_mm: tuple[float, float] = (2.5, 4.0)
    seed: int = 0


class SimulatedHead:
    """The :class:`FrameSource` of a holographic station: the part in its fixture, placed
    within the fixture's play, now and then dented, recorded by the simulated head.

    A dent (``inspection.defects.Dent``, part frame, along the part's z) moves the
    surface by ``-depth * profile(r)`` along its normal; it goes into the FrameSet's
    truth, with the part's pose in the head frame as ``T_rig_part``.

    Parameters
    ----------
    stages : Stages
        Holographic stages: ``rig`` is the :class:`~service.pipeline.HoloRig` that records.
    parts : sequence of SimPart
    line, station : str
    settings : FixtureSettings
    """

    def __init__(
        self,
        stages: Stages,
        parts: Sequence[SimPart],
        *,
        line: str,
        station: str,
        settings: FixtureSettings,
    ) -> None:
        if not isinstance(stages.rig, HoloRig):
            raise ValueError("the simulated head needs holographic stages")
        if not parts:
            raise ValueError("the simulated head needs at least one part")
        self.stages = stages
        self.rig: HoloRig = stages.rig
        self.parts = list(parts)
        self.line = line
        self.station = station
        self.settings = settings

    def capture(self, seq: int, triggered_ns: int) -> FrameSet:
        from scipy.spatial.transform import Rotation

        s = self.settings
        rng = np.random.default_rng([s.seed, seq])
        part = self.parts[int(rng.integers(len(self.parts)))]
        play = np.eye(4)
        tilts = rng.uniform(-1, 1, 2) * s.tilt_range_mrad * 1e-3
        play[:3, :3] = Rotation.from_rotvec([tilts[0], tilts[1], 0.0]).as_matrix()
        play[2, 3] = rng.uniform(-1, 1) * s.height_range_mm
        T_head_part = np.asarray(s.T_head_cad, dtype=np.float64) @ play
        serial = simulated_serial(part.name, seq, rng)
        defects: tuple[Dent, ...] = ()
        if rng.random() < s.defect_rate:
            defects = (self._random_dent(T_head_part, rng),)
        deviation = self._deviation(T_head_part, defects)
        image = self.rig.record(part.mesh, T_head_part, deviation, int(rng.integers(2**31)))
        return FrameSet(
            line=self.line,
            station=self.station,
            part=part.name,
            serial=serial,
            seq=seq,
            triggered_ns=triggered_ns,
            calibration_id=self.stages.calibration_id,
            images=[image],
            cameras=["holo"],
            truth=Truth(T_head_part, defects),
            sensor="holography",
        )

    def _random_dent(self, T_head_part: np.ndarray, rng: np.random.Generator) -> Dent:
        """A dent within the middle half of the field, its axis along the part's z."""
        s = self.settings
        half = 0.25 * self.rig.head.field_mm
        x, y = rng.uniform(-half, half, 2)
        centre = np.linalg.inv(T_head_part) @ np.array([x, y, 0.0, 1.0])
        return Dent(
            (float(centre[0]), float(centre[1]), 0.0),
            (0.0, 0.0, 1.0),
            float(rng.uniform(*s.dent_depth_mm)),
            float(rng.uniform(*s.dent_radius_mm)),
        )

    def _deviation(self, T_head_part: np.ndarray, defects: Sequence[Dent]) -> np.ndarray | None:
        if not defects:
            return None
        x, y = self.rig.head.grid()
        pixels = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
        in_part = apply(np.linalg.inv(T_head_part), pixels)
        out = np.zeros(x.size)
        for d in defects:
            out -= d.depth_mm * d.profile(d.axis_distance(in_part))
        return out.reshape(x.shape)


class SeqState:
    """The ingest's next seq, in a file: written (and synced) before each trigger fires.

    Parameters
    ----------
    path : str or Path
        Created with its folder on the first save; absent: counting starts at 0.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def load(self) -> int:
        """The next seq to use (0 without a file; a damaged file is an error)."""
        try:
            text = self.path.read_text().strip()
        except FileNotFoundError:
            return 0
        if not text.isdigit():
            raise ValueError(f"{self.path.name}: not a seq number: {text[:40]!r}")
        return int(text)

    def save(self, next_seq: int) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        with tmp.open("w") as fh:
            fh.write(f"{next_seq}\n")
            fh.flush()
            os.fsync(fh.fileno())
        tmp.replace(self.path)


class Ingest:
    """Fires triggers on a fixed period and publishes one FrameSet per trigger.

    Parameters
    ----------
    source : FrameSource
    publish : callable(bytes) -> None
        Sends the encoded FrameSet (a zenoh publisher's ``put``).
    period_s : float
        Trigger period (``trigger_period_s``).
    encoding : {"raw", "png"}
        Image encoding on the wire.
    on_trigger : callable(FrameSet) -> None, optional
        Called after each publish (benchmarks, tests, logs).
    seq_state : SeqState, optional
        Where the numbering goes on from after a restart.
    """

    def __init__(
        self,
        source: FrameSource,
        publish: Callable[[bytes], None],
        *,
        period_s: float,
        encoding: str = "raw",
        on_trigger: Callable[[FrameSet], None] | None = None,
        seq_state: SeqState | None = None,
    ) -> None:
        if period_s <= 0:
            raise ValueError("period_s must be positive")
        self.source = source
        self.publish = publish
        self.period_s = period_s
        self.encoding = encoding
        self.on_trigger = on_trigger
        self.seq_state = seq_state
        self.seq = seq_state.load() if seq_state is not None else 0
        if self.seq:
            log.info("ingest: going on from seq %d", self.seq)
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        self.last_triggered_ns: int | None = None
        """Trigger time of the last FrameSet published (None: none yet)."""

    def trigger(self) -> FrameSet:
        """Fire one trigger now: capture, publish, count."""
        if self.seq_state is not None:
            self.seq_state.save(self.seq + 1)
        t_ns = time.time_ns()
        fs = self.source.capture(self.seq, t_ns)
        self.publish(encode_frameset(fs, encoding=self.encoding))
        self.last_triggered_ns = t_ns
        self.seq += 1
        if self.on_trigger is not None:
            self.on_trigger(fs)
        return fs

    def run(self, count: int | None = None) -> None:
        """Trigger until :meth:`stop` (or ``count`` triggers).

        A failed capture is logged and still uses up its seq (the worker sees a gap).
        """
        t0 = time.monotonic()
        k = 0
        while not self.stop_event.is_set() and (count is None or k < count):
            delay = t0 + k * self.period_s - time.monotonic()
            if delay > 0 and self.stop_event.wait(delay):
                break
            if delay < -self.period_s:
                # Behind by more than a period: parts went by without being
                # captured. Skip ahead rather than fire a burst, and spend their
                # seq numbers so the worker records them as missed.
                skipped = int(-delay // self.period_s)
                log.warning("ingest fell %d triggers behind; those parts are missed", skipped)
                k += skipped
                self.seq += skipped
            try:
                self.trigger()
            except Exception:
                log.exception("trigger seq %d failed; the worker will see a gap", self.seq)
                self.seq += 1
            k += 1

    def start(self, count: int | None = None) -> None:
        self._thread = threading.Thread(target=self.run, args=(count,), name="ingest", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 30.0) -> None:
        self.stop_event.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
