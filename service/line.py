"""The simulated line: ingest, worker, store, recorder and API, together or apart.

:func:`run_line` runs everything in one process on one zenoh session in peer
mode, listening only where the config says (subscribers connect to it as
clients). The same pieces run as separate processes with :func:`run_router`
(a zenoh router), :func:`run_ingest`, :func:`run_worker` and :func:`run_api`,
each a client of the router.

Every ``run_*`` returns when ``stop`` is set (SIGINT in the CLI) and closes
what it opened in reverse order: zenoh sessions with live subscribers would
otherwise keep the process from exiting.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from inspection.cad import CadModel
from inspection.rig import Rig
from inspection.simulate import RenderOptions
from inspection.transforms import apply

from . import bus, startup
from .api import ResultHub, create_app
from .config import GENERATED_PANEL, ConfigError, LineConfig, PartSpec, Sensor, load_part_spec
from .executor import Executor, InProcessExecutor
from .ingest import (
    Drift,
    FixtureSettings,
    FrameSource,
    Ingest,
    SeqState,
    SimPart,
    SimulatedHead,
    SimulatedRig,
    SimulationSettings,
    line_rig,
)
from .journal import Journal
from .metrics import Metrics
from .models import Alarm, software_version
from .parts import LoadedPart, PartRegistry, load_part_cad, panel_spec, stored_cad
from .pipeline import HoloRig, Outcome, Pipeline, Stages, flash_stages, holography_stages
from .protocol import FrameSet, Keys
from .recorder import PartScene, RecordedPart, Recorder, Retention
from .retention import Janitor
from .spc import SpcMonitor, SpcSettings
from .station_parts import PartListener, StationParts
from .store import DeviationArchive, ResultStore, StoredPart
from .worker import ZenohWorker, result_from_json, zenoh_alarm_sink

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- set-up


@dataclass
class Station:
    """A station's measuring set-up: the stages and its loaded parts.

    ``parts`` are the objects of ``registry`` (when there is one): the worker
    measures with the very tree, alignment model and spec the REST API serves.
    They start as the station's configured parts; a running worker adds those
    created over the API as it takes them from the store
    (:mod:`service.station_parts`).
    """

    cfg: LineConfig
    stages: Stages
    parts: dict[str, LoadedPart]
    registry: PartRegistry | None = None
    cads: dict[str, tuple[PartSpec, CadModel]] = field(default_factory=dict)
    """What the simulator renders: every part's spec and CAD (those of ``parts`` by default)."""
    keys: Keys = field(init=False)

    def __post_init__(self) -> None:
        self.keys = Keys(self.cfg.line.name, self.cfg.zenoh.prefix)
        if not self.cads:
            self.cads = {name: (p.spec, p.cad) for name, p in self.parts.items()}

    @classmethod
    def load(
        cls,
        cfg: LineConfig,
        stages: Stages | None = None,
        *,
        build_trees: bool = True,
        warm_up: bool = True,
        talk: Callable[[str], None] | None = None,
        store: ResultStore | None = None,
        simulate: bool = True,
    ) -> Station:
        """Load every part of the station (tree, alignment model, spec) and warm the kernels up.

        Returns only once the station can measure at full speed. ``build_trees=False``
        loads the CAD only (enough for the ingest's simulator: the parts of
        ``[simulator] parts``, those created over the API read from the store).
        ``simulate=False``: this process runs no simulated ingest (a worker of its own),
        so ``[simulator] parts`` is not read, and a part it names that nobody created
        yet does not stop it.
        ``talk`` is told each phase as it starts, with its progress and whether
        it is a first start (:mod:`service.startup`); without it the phases are
        logged. ``store``: the station's registry serves an API of this process
        too, and holds the parts created over it (:meth:`PartRegistry.sync_store`);
        without it, the registry keeps the parts the worker takes from the
        store in the station's own folder.

        Raises
        ------
        service.parts.PartError
            A part of the station could not be loaded.
        ConfigError
            A part of ``[simulator] parts`` is not to be had (with ``simulate``).
        """
        say = talk if talk is not None else (lambda line: log.info("start-up: %s", line))
        say(startup.kernels_line())
        with startup.kernel_compiles(say):
            return cls._load(
                cfg, stages, say, build_trees=build_trees, warm_up=warm_up, store=store,
                simulate=simulate,
            )  # fmt: skip

    @classmethod
    def _load(
        cls,
        cfg: LineConfig,
        stages: Stages | None,
        say: Callable[[str], None],
        *,
        build_trees: bool,
        warm_up: bool,
        store: ResultStore | None,
        simulate: bool,
    ) -> Station:
        if stages is None:
            t0 = time.perf_counter()
            say("rig: loading its calibration and preparing the measuring stages")
            stages = stages_for(cfg)
            say(f"rig: ready in {time.perf_counter() - t0:.1f} s")
        if not build_trees:
            station = cls(cfg, stages, {}, cads=simulated_cads(cfg, {}, say))
            if warm_up:
                station.warm_up(measure=False, talk=say)
            return station
        line, name = cfg.line.name, cfg.station.name
        registry = (
            PartRegistry.from_config(cfg, store=store)
            if store is not None
            else PartRegistry.from_config(
                cfg, uploads=False, uploads_dir=cfg.storage.station_parts_path(line, name)
            )
        )
        try:
            t0 = time.perf_counter()
            say(f"station {cfg.station.name}: loading its parts (tree cache {registry.trees_dir})")
            built = startup.preload(registry, say)
            parts = registry.loaded(list(cfg.station.parts))
            loaded_s = time.perf_counter() - t0
            new = sorted(n for n, b in built.items() if b)
            say(
                f"station {cfg.station.name}: parts ready in {loaded_s:.1f} s; "
                + (f"trees built for {', '.join(new)} (first start)" if new
                   else "every tree loaded from the cache")
            )  # fmt: skip
            cads = simulated_cads(cfg, parts, say) if simulate and cfg.simulator.parts else {}
            station = cls(cfg, stages, parts, registry, cads=cads)
            if warm_up:
                station.warm_up(talk=say)
        except BaseException:
            registry.close()
            raise
        return station

    def warm_up(self, *, measure: bool = True, talk: Callable[[str], None] | None = None) -> None:
        """Render one FrameSet (and measure it): the simulator's and the reconstruction's
        kernels compile here, not on the first part of the shift."""
        say = talk if talk is not None else (lambda line: log.info("start-up: %s", line))
        say("warm-up: rendering one frame set (the simulator's kernels load or compile)")
        t0 = time.perf_counter()
        fs = self.warm_up_frames()
        t1 = time.perf_counter()
        if not measure:
            say(f"warm-up: rendered in {t1 - t0:.1f} s")
            return
        say(
            f"warm-up: rendered in {t1 - t0:.1f} s; measuring it "
            "(the reconstruction's kernels load or compile)"
        )
        r = self.pipeline().run(fs).result
        say(f"warm-up: measured in {time.perf_counter() - t1:.1f} s ({r.status.value})")
        log.info("warm-up timings: %s", r.timings_ms)
        if r.status.value == "error":
            log.warning("warm-up measurement gave an error: %s", r.reason)

    def close(self) -> None:
        if self.registry is not None:
            self.registry.close()

    @property
    def name(self) -> str:
        return self.cfg.station.name

    def pipeline(self) -> Pipeline:
        return Pipeline(self.stages, self.parts, line=self.cfg.line.name, station=self.name)

    def missed_part(self) -> str:
        return next(iter(self.parts)) if len(self.parts) == 1 else "unknown"

    def warm_up_frames(self) -> FrameSet:
        """One simulated FrameSet of a part the station holds (the kernels' warm-up)."""
        own = [n for n in self.cads if n in self.parts]
        return self.simulated_rig(own or None).capture(0, time.time_ns())

    def simulated_rig(self, names: list[str] | None = None) -> FrameSource:
        """The station's simulated sensor: the flash rig, or the holographic head, sending
        the parts ``names`` (default: all of :attr:`cads`)."""
        sim = self.cfg.simulator
        # The generated panel's own design, so that the simulator can move its holes.
        parts = [
            SimPart.from_cad(
                n,
                cad,
                flat=spec.is_generated,
                panel=panel_spec(spec.panel) if spec.cad == GENERATED_PANEL else None,
            )  # fmt: skip
            for n, (spec, cad) in self.cads.items()
            if names is None or n in names
        ]
        if self.cfg.station.sensor is Sensor.holography:
            head = self.cfg.head()
            return SimulatedHead(
                self.stages,
                parts,
                line=self.cfg.line.name,
                station=self.name,
                settings=FixtureSettings(
                    T_head_cad=fixture_pose(self.cfg),
                    height_range_mm=head.height_range_mm,
                    tilt_range_mrad=head.tilt_range_mrad,
                    defect_rate=sim.defect_rate,
                    dent_depth_mm=head.dent_depth_mm,
                    dent_radius_mm=head.dent_radius_mm,
                    seed=sim.seed,
                ),
            )
        return SimulatedRig(
            self.stages,
            parts,
            line=self.cfg.line.name,
            station=self.name,
            settings=SimulationSettings(
                defect_rate=sim.defect_rate,
                dent_depth_mm=sim.dent_depth_mm,
                dent_radius_mm=sim.dent_radius_mm,
                dent_flat_mm=sim.dent_flat_mm,
                dent_bump_fraction=sim.dent_bump_fraction,
                position_range_mm=(sim.position_range_x_mm, sim.position_range_y_mm),
                yaw_range_deg=sim.yaw_range_deg,
                flip=sim.flip,
                hole_shift_mm=sim.hole_shift_mm,
                hole_radius_mm=sim.hole_radius_mm,
                seed=sim.seed,
                drift=self._drift(),
            ),
        )

    def _drift(self) -> Drift | None:
        sim = self.cfg.simulator
        if sim.drift_point is None:
            return None
        spec, _ = next(iter(self.cads.values()))
        point = next((p for p in spec.points if p.name == sim.drift_point), None)
        if point is None:
            raise ConfigError(f"[simulator] drift_point {sim.drift_point!r} is not a comparison "
                              f"point of {spec.name!r}")  # fmt: skip
        return Drift(
            tuple(point.position_mm), tuple(point.normal),  # type: ignore[arg-type]
            after_seq=sim.drift_after_seq, mm_per_part=sim.drift_mm_per_part,
        )  # fmt: skip

    def metadata(self) -> dict[str, dict[str, str]]:
        """MCAP metadata: effective config and hash, rig calibration, CAD and tree hashes."""
        return {
            "config": {"hash": self.cfg.hash(), "json": json.dumps(self.cfg.effective())},
            "rig": self.rig_metadata(),
            "cad": {
                **{f"{n}.cad_hash": p.cad.hash for n, p in self.parts.items()},
                **{f"{n}.tree_hash": p.tree_hash for n, p in self.parts.items()},
                **{f"{n}.spec_version": p.spec.version for n, p in self.parts.items()},
                **{f"{n}.spec": p.spec.model_dump_json() for n, p in self.parts.items()},
            },
            "software": {"version": software_version()},
        }

    def rig_metadata(self) -> dict[str, str]:
        """The stages (whether they match a second time, guided by the CAD, and which path
        they measure), the calibration id and the calibrated rig itself (TOML)."""
        meta = {
            "stages": self.stages.name,
            "guided": "true" if self.stages.guided else "false",
            "path": self.stages.path,
            "calibration_id": self.stages.calibration_id,
        }
        if self.stages.calibration_toml is not None:
            meta["calibration_toml"] = self.stages.calibration_toml
        if self.cfg.station.sensor is Sensor.holography:
            meta["T_head_cad"] = json.dumps(fixture_pose(self.cfg).tolist())
            meta["coarse_pose"] = "true" if self.cfg.head().coarse_pose else "false"
        return meta

    def recorder(self, data_dir: Path | None = None) -> Recorder:
        st = self.cfg.storage
        mcap_dir = (data_dir / st.mcap_dir) if data_dir else st.mcap_path()
        run_id = f"{self.cfg.line.name}-{self.name}-{time.strftime('%Y%m%dT%H%M%S')}"
        return Recorder(
            mcap_dir,
            run_id,
            metadata=self.metadata(),
            calibrations=self.stages.calibrations(),
            parts={
                n: PartScene(p.cad.vertices, p.cad.faces, p.model.comparison_points)
                for n, p in self.parts.items()
            },
            rotate_bytes=int(st.mcap_rotate_mb * 1e6),
            rotate_s=st.mcap_rotate_min * 60.0,
            retention=Retention.from_config(self.cfg.retention),
            image_encoding=st.mcap_image_encoding,
            compression=st.mcap_compression,
        )


def simulated_cads(
    cfg: LineConfig, loaded: Mapping[str, LoadedPart], say: Callable[[str], None]
) -> dict[str, tuple[PartSpec, CadModel]]:
    """The spec and CAD of each part the simulated ingest sends (``[simulator] parts``, else
    the station's): from ``loaded``, the station's spec files, or, for a part created over
    the API, the result store.

    Raises
    ------
    ConfigError
        A part neither of the station nor of the store.
    """
    own = {p.stem: p for p in cfg.part_spec_paths()}
    cads: dict[str, tuple[PartSpec, CadModel]] = {}
    store: ResultStore | None = None
    try:
        for name in cfg.simulator.parts or cfg.station.parts:
            if name in loaded:
                cads[name] = (loaded[name].spec, loaded[name].cad)
            elif name in own:
                spec = load_part_spec(own[name])
                say(f"part {name}: loading CAD")
                cads[name] = (spec, load_part_cad(spec, own[name].parent))
            else:
                store = store or ResultStore(cfg.storage.store_target())
                stored = store.part(name)
                if stored is None:
                    raise ConfigError(
                        f"[simulator] parts: {name!r} is neither a part of station "
                        f"{cfg.station.name} nor one created over the API (none in {store.where})"
                    )
                say(f"part {name}: loading CAD (revision {stored.revision}, from the store)")
                cads[name] = stored_cad(stored)
    finally:
        if store is not None:
            store.close()
    return cads


def fixture_pose(cfg: LineConfig) -> np.ndarray:
    """T_head_cad of a holographic station: the part's frame at the fixture's height."""
    T = np.eye(4)
    T[2, 3] = cfg.head().fixture_height_mm
    return T


def holo_stages_for(cfg: LineConfig) -> Stages:
    """A holographic station's stages: the head of ``[holography]``, calibrated from its
    file (or, without one, from a simulated flat plate under the simulated head)."""
    from inspection.errors import InspectionError
    from inspection.holography import HoloCalibration, HoloHead

    h = cfg.head()
    head = HoloHead.small_field(h.pixels, field_mm=h.field_mm)
    head = dataclasses.replace(head, synthetic_mm=h.synthetic_mm)
    truth = HoloRig.simulated(head)
    path = cfg.holo_calibration_path()
    try:
        calib = HoloCalibration.load(path) if path is not None else truth.calibrate()
    except (OSError, InspectionError) as exc:
        raise ConfigError(f"[holography] calibration: {exc}") from exc
    if calib.head != head:
        raise ConfigError(
            f"[holography] calibration {path} is for another head "
            f"({calib.head.pixels} px over {calib.head.field_mm:g} mm, synthetic "
            f"{calib.head.synthetic_mm:g} mm) than the section's"
        )
    log.info("holographic head calibrated: %s (%s)", calib.id, calib.source)
    return holography_stages(
        calib, T_head_cad=fixture_pose(cfg), truth=truth, coarse_pose=h.coarse_pose
    )


def stages_for(cfg: LineConfig) -> Stages:
    """The line's stages: the four-camera flash rig, calibrated as configured, whose
    simulator renders the line as configured (belt speed, flash duration, slide) at the
    calibrated cameras' image size; or, for ``sensor = "holography"``, the head's
    (:func:`holo_stages_for`)."""
    if cfg.station.sensor is Sensor.holography:
        return holo_stages_for(cfg)
    path = cfg.rig_calibration_path()
    cam = (Rig.load(path) if path else Rig.default()).cameras[0]
    truth = line_rig(
        Rig.nominal(cam.width, cam.height),
        conveyor_speed_mm_s=cfg.line.conveyor_speed_mm_s,
        pattern_seed=cfg.projector.pattern_seed,
    )
    return flash_stages(
        cfg.rig_calibration_path(),
        guided=cfg.station.guided_matching,
        path=cfg.station.path,
        truth=truth,
        render_options=RenderOptions(flash_us=cfg.projector.flash_us),
    )


def bus_settings(cfg: LineConfig, mode: str | None = None) -> bus.BusSettings:
    """The line's zenoh settings: endpoints, TLS files resolved against the line file, and
    access control over the line's keys."""
    z = cfg.zenoh
    ca = cfg.zenoh_tls_path("tls_ca_certificate")
    tls = (
        None
        if ca is None
        else bus.TlsSettings(
            ca_certificate=ca,
            certificate=cfg.zenoh_tls_path("tls_certificate"),
            private_key=cfg.zenoh_tls_path("tls_private_key"),
            mutual=z.tls_mutual,
            verify_name=z.tls_verify_name,
        )
    )
    acl = z.access_control
    access = (
        None
        if acl is None
        else bus.AccessControl(
            line_prefix=f"{z.prefix}/{cfg.line.name}",
            ingest=tuple(acl.ingest),
            worker=tuple(acl.worker),
            subscriber=tuple(acl.subscriber),
        )
    )
    return bus.BusSettings(
        mode=mode or str(z.mode.value),
        listen=tuple(z.listen),
        connect=tuple(z.connect),
        multicast_scouting=z.multicast_scouting,
        tls=tls,
        access=access,
    )


def archive_sink(archive: DeviationArchive) -> Callable[[Outcome, FrameSet | None], None]:
    """Keep the per-point deviations of every measured result (the colour map's data).

    Goes before the store's sink: a client that sees the row finds the arrays.
    """

    def sink(outcome: Outcome, fs: FrameSet | None) -> None:
        T, points, d = outcome.transform, outcome.points, outcome.distances
        if T is None or points is None or d is None:
            return
        try:
            archive.save(outcome.result.id, apply(T, points), d)
        except OSError as exc:  # a full disk must not lose the result itself
            log.error("deviations of %s not kept: %s", outcome.result.id, exc)

    return sink


def worker_state(cfg: LineConfig, store: ResultStore) -> dict[str, Any]:
    """What a station's worker keeps across a restart: the store it goes on from,
    its journal, and the bound on a seq's jump; and how long a FrameSet waits for its part."""
    line, station = cfg.line.name, cfg.station.name
    return dict(
        store=store,
        journal=Journal(cfg.storage.journal_path(line, station)),
        max_seq_jump=cfg.station.max_seq_jump,
        part_wait_s=cfg.station.part_wait_s,
    )


def make_executor(cfg: LineConfig, station: Station) -> Executor:
    """Where the station's measurements run, as ``[station] executor`` says.

    In-process: the worker's own pipeline. Dask: connected to the cluster
    (or a local one started), the station loaded and warmed up on every
    worker there, with a FrameSet rendered here.

    Raises
    ------
    service.executor.ExecutorError
        The cluster cannot be reached or cannot load the station.
    """
    address = cfg.station.dask_address()
    pipeline = station.pipeline()
    if address is None:
        return InProcessExecutor(pipeline)
    from .dask_executor import DaskExecutor

    warm_up = station.warm_up_frames() if station.cads else None
    return DaskExecutor.connect(
        address, pipeline, warm_up=warm_up, trees_dir=cfg.storage.trees_path()
    )


def make_ingest(cfg: LineConfig, station: Station, publish: Callable[[bytes], None]) -> Ingest:
    """The station's simulated ingest, numbering on from where it stopped last."""
    return Ingest(
        station.simulated_rig(),
        publish,
        period_s=cfg.line.trigger_period_s,
        seq_state=SeqState(cfg.storage.ingest_seq_path(cfg.line.name, station.name)),
    )


FIRED_EVERY_S = 1.0
"""Period of the ingest's count on the ``fired`` key (also sent after each trigger)."""


class FiredCount:
    """The ingest's count of fired triggers on ``<prefix>/<line>/<station>/fired``.

    Sent after each trigger, every :data:`FIRED_EVERY_S` (a worker started
    later, or one that missed a sample, hears it) and once more at the stop.
    The station's worker answers ``missed`` the triggers it counts whose
    FrameSet never came, when no later FrameSet shows the gap: the last ones
    before a stop, those fired while the worker was down.
    """

    def __init__(
        self, session: zenoh.Session, key: str, ingest: Ingest, *, period_s: float = FIRED_EVERY_S
    ) -> None:
        self._ingest = ingest
        self._beat = bus.Heartbeat(session, key, self._count, period_s=period_s)
        chained = ingest.on_trigger

        def after(fs: FrameSet) -> None:
            if chained is not None:
                chained(fs)
            self._beat.publish()

        ingest.on_trigger = after

    def _count(self) -> dict[str, int] | None:
        t_ns = self._ingest.last_triggered_ns
        if t_ns is None:
            return None  # nothing fired yet
        return {"next_seq": self._ingest.seq, "triggered_ns": t_ns}

    def publish(self) -> None:
        """Send the count now (nothing before the first trigger)."""
        self._beat.publish()

    def close(self) -> None:
        """Stop the periodic count, after sending it once more (stop the ingest first)."""
        self._beat.close()
        self._beat.publish()


def store_sink(store: ResultStore) -> Callable[[Outcome, FrameSet | None], None]:
    def sink(outcome: Outcome, fs: FrameSet | None) -> None:
        store.put(outcome.result)

    return sink


class ResultCounter:
    """A sink that counts results and sets ``done`` after ``limit`` of them."""

    def __init__(self, limit: int | None) -> None:
        self.limit = limit
        self.count = 0
        self.done = threading.Event()
        self._lock = threading.Lock()
        self.last_seq = -1
        self._seen = threading.Condition(self._lock)

    def __call__(self, outcome: Outcome, fs: FrameSet | None) -> None:
        with self._lock:
            self.count += 1
            self.last_seq = max(self.last_seq, outcome.result.seq)
            self._seen.notify_all()
            if self.limit is not None and self.count >= self.limit:
                self.done.set()

    def wait_seq(self, seq: int, timeout_s: float) -> bool:
        """Wait until a result with seq >= ``seq`` has been seen."""
        with self._lock:
            return self._seen.wait_for(lambda: self.last_seq >= seq, timeout_s)


# --------------------------------------------------------------------------- API


class ApiServer:
    """The FastAPI app on uvicorn, in a thread of this process."""

    def __init__(self, api: Api, host: str, port: int) -> None:
        import uvicorn

        self.server = uvicorn.Server(
            uvicorn.Config(api.app, host=host, port=port, log_level="warning", lifespan="on")
        )
        self.thread = threading.Thread(target=self.server.run, name="api", daemon=True)
        self.thread.start()

    def wait_started(self, timeout_s: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout_s
        stop = threading.Event()
        while not self.server.started and time.monotonic() < deadline:
            if not self.thread.is_alive():
                return False
            stop.wait(0.05)
        return bool(self.server.started)

    @property
    def port(self) -> int:
        for server in getattr(self.server, "servers", []):
            for sock in server.sockets:
                return int(sock.getsockname()[1])
        return int(self.server.config.port)

    def close(self) -> None:
        self.server.should_exit = True
        self.thread.join(15.0)


class Api:
    """The REST API's app with the part registry it serves.

    ``owns_registry``: the registry was made for the API alone and closes with
    it; a station's registry closes with the station.
    """

    def __init__(self, app: Any, registry: Any, *, owns_registry: bool = True) -> None:
        self.app = app
        self.registry = registry
        self.owns_registry = owns_registry

    def close(self) -> None:
        if self.registry is not None and self.owns_registry:
            self.registry.close()


def make_app(
    cfg: LineConfig,
    *,
    store: ResultStore,
    hub: ResultHub,
    checks: dict[str, Callable[[], bool]],
    registry: PartRegistry | None = None,
    metrics: Metrics | None = None,
) -> Api | None:
    """The app of :func:`service.api.create_app`, or None when it could not be built.

    ``registry``: the station's (already loaded) part registry, shared with the
    worker. Without one (the API as its own process) a registry is made with
    the parts of ``store`` and its trees are built in the background;
    readiness waits for them.
    """
    own = registry is None
    try:
        reg = PartRegistry.from_config(cfg, store=store) if registry is None else registry
    except Exception:
        log.exception("the REST API's parts could not be read; running without it")
        return None
    try:
        if own:
            reg.start()
        app = create_app(cfg, store=store, parts=reg, bus=hub, checks=checks, metrics=metrics)
    except Exception:
        # The line measures without the API; say so loudly rather than stop it.
        log.exception("the REST API could not be built; running without it")
        if own:
            reg.close()
        return None
    return Api(app, reg, owns_registry=own)


def spc_monitor(
    cfg: LineConfig, station: Station, store: ResultStore, alarms: list[Callable[[Alarm], object]]
) -> SpcMonitor:
    """Charts each measured part of the station; run rules that fire go to ``alarms``."""
    return SpcMonitor(
        store, SpcSettings.from_config(cfg.spc), subgroups=Subgroups(station.parts), alarms=alarms
    )


class Subgroups(Mapping[str, int]):
    """Each part's subgroup size, read from the station's parts as they are now."""

    def __init__(self, parts: Mapping[str, LoadedPart]) -> None:
        self.parts = parts

    def __getitem__(self, name: str) -> int:
        return int(self.parts[name].spec.subgroup_size)

    def __iter__(self) -> Iterator[str]:
        return iter(list(self.parts))

    def __len__(self) -> int:
        return len(self.parts)


def follow_store_parts(cfg: LineConfig, station: Station, recorder: Recorder) -> StationParts:
    """The station's worker takes the parts created over the API from the store (through a
    connection of their own: a CAD read must not hold the one the results are written
    through), and its recordings show them and keep them for replay."""
    assert station.registry is not None, "a station that measures has a part registry"
    store = ResultStore(cfg.storage.store_target())
    return StationParts(
        station.parts, store, station.registry, station=station.name,
        wait_s=cfg.station.part_wait_s, listeners=[recording_listener(recorder)],
        close_store=True,
    )  # fmt: skip


def recording_listener(recorder: Recorder) -> PartListener:
    """Tells ``recorder`` each part the station takes from the store: what its scenes show,
    and the revision's spec and CAD file, which go into the recording with the first result
    measured with it (:class:`~service.recorder.RecordedPart`)."""

    def show(name: str, part: LoadedPart | None, stored: StoredPart | None) -> None:
        if part is None or stored is None:
            recorder.set_part(name, None)
            return
        scene = PartScene(part.cad.vertices, part.cad.faces, part.model.comparison_points)
        kept = RecordedPart(
            name=name, revision=stored.revision, spec=stored.spec, cad_file=part.spec.cad,
            cad=stored.cad, cad_hash=part.cad.hash, tree_hash=part.tree_hash,
            spec_version=part.spec.version,
        )  # fmt: skip
        recorder.set_part(name, scene, kept)

    return show


def hub_sink(hub: ResultHub) -> Callable[[Outcome, FrameSet | None], None]:
    def sink(outcome: Outcome, fs: FrameSet | None) -> None:
        hub.publish(outcome.result)

    return sink


# --------------------------------------------------------------------------- runs


@dataclass
class LineHandles:
    """What :func:`start_line` started, for tests and for :func:`run_line`."""

    session: zenoh.Session
    station: Station
    store: ResultStore
    recorder: Recorder
    worker: ZenohWorker
    ingest: Ingest
    counter: ResultCounter
    api: ApiServer | None
    hub: ResultHub
    app: Api | None = None
    janitor: Janitor | None = None
    executor: Executor | None = None
    fired: FiredCount | None = None
    parts: StationParts | None = None

    def close(self) -> None:
        """Stop triggering, let the worker finish what was triggered, close everything."""
        self.ingest.stop()
        if self.fired is not None:
            self.fired.close()
        last = self.ingest.seq - 1
        if last >= 0 and not self.counter.wait_seq(last, 60.0):
            log.warning("stopping before the result of seq %d arrived", last)
        self.worker.close()
        if self.parts is not None:
            self.parts.close()
        if self.executor is not None:
            self.executor.close()
        self.recorder.close()
        if self.janitor is not None:
            self.janitor.close()
        if self.api is not None:
            self.api.close()
        if self.app is not None:
            self.app.close()
        self.store.close()
        self.hub.close()
        self.station.close()
        bus.close_all([self.session])


def start_line(
    cfg: LineConfig,
    *,
    parts_limit: int | None = None,
    stages: Stages | None = None,
    http: bool = True,
    extra_sinks: tuple[Callable[[Outcome, FrameSet | None], None], ...] = (),
    talk: Callable[[str], None] | None = None,
) -> LineHandles:
    """Start the whole line in this process; see :func:`run_line`."""
    log.info("line config %s: %s", cfg.hash()[:12], json.dumps(cfg.effective()))
    store = ResultStore(cfg.storage.store_target())
    try:
        # Measuring here warms the kernels up; a station measured on Dask warms its workers.
        # With the API, the station's registry is the API's too: the parts of the store.
        station = Station.load(
            cfg, stages, warm_up=cfg.station.dask_address() is None, talk=talk,
            store=store if http else None,
        )  # fmt: skip
    except BaseException:
        store.close()
        raise
    try:
        executor = make_executor(cfg, station)
    except BaseException:
        station.close()
        store.close()
        raise
    try:
        session = bus.open_session(bus_settings(cfg, "peer"))
    except BaseException:
        executor.close()
        station.close()
        store.close()
        raise
    opened: list[Any] = [station, executor, session, store]
    try:
        recorder = station.recorder()
        opened.append(recorder)
        counter = ResultCounter(parts_limit)
        hub = ResultHub()
        metrics = Metrics()
        archive = DeviationArchive(
            cfg.storage.deviations_path(), max_bytes=cfg.deviations_max_bytes()
        )
        janitor = Janitor(store, archive, cfg.retention)
        opened.append(janitor)
        sinks = [archive_sink(archive), store_sink(store), *extra_sinks, hub_sink(hub)]
        alarms = [store.put_alarm, hub.publish, recorder.record_alarm]
        # Stored before published: whoever sees an alarm on zenoh can then find
        # it (and acknowledge it) over REST.
        published = [*alarms, zenoh_alarm_sink(session, station.keys)]
        monitor = spc_monitor(cfg, station, store, published)
        parts = follow_store_parts(cfg, station, recorder)
        opened.append(parts)
        worker = ZenohWorker(
            session,
            station.keys,
            station.name,
            station.pipeline(),
            queue_size=cfg.station.queue_size,
            sinks=sinks,
            # Counted once recorded and charted: stopping after N results stops with N
            # recorded, and their alarms raised.
            after_publish=[recorder.record, monitor, counter],
            missed_part=station.missed_part(),
            metrics=metrics,
            executor=executor,
            alarms=alarms,
            parts=parts,
            **worker_state(cfg, store),
        )
        opened.append(worker)
        api = None
        made = None
        if http:
            made = make_app(
                cfg,
                store=store,
                hub=hub,
                checks={
                    "zenoh": lambda: not session.is_closed(),
                    "executor": lambda: worker.worker.executor_status()["workers"] > 0,
                },
                registry=station.registry,
                metrics=metrics,
            )
            if made is not None:
                opened.append(made)
                api = ApiServer(made, cfg.http.host, cfg.http.port)
                opened.append(api)
                if not api.wait_started():
                    raise RuntimeError(f"the API did not start on {cfg.http.host}:{cfg.http.port}")
        publisher = bus.frame_publisher(session, station.keys.frames(station.name))
        ingest = make_ingest(cfg, station, publisher.put)
        fired = FiredCount(session, station.keys.fired(station.name), ingest)
        opened.append(fired)
        ingest.start()
    except BaseException:
        bus.close_all(reversed(opened))
        raise
    return LineHandles(
        session, station, store, recorder, worker, ingest, counter, api, hub, made, janitor,
        executor, fired, parts,
    )  # fmt: skip


def run_line(
    cfg: LineConfig,
    stop: threading.Event,
    *,
    parts_limit: int | None = None,
    out: Callable[[str], None] = print,
) -> int:
    """Run the whole simulated line until ``stop`` is set or ``parts_limit`` results arrived."""
    h = start_line(cfg, parts_limit=parts_limit, talk=out)
    try:
        where = [f"zenoh: listening on {', '.join(cfg.zenoh.listen) or 'nothing'}"]
        if h.api is not None:
            where.insert(0, f"API docs: http://{cfg.http.host}:{h.api.port}/docs")
        where.append(f"data: {cfg.storage.data_path().resolve()}")
        if cfg.storage.url is not None:
            where.append(f"results: {h.store.where}")
        where.append(f"results on zenoh: {h.station.keys.results()}")
        out("the line is running (Ctrl-C stops it)\n  " + "\n  ".join(where))
        while not stop.is_set() and not h.counter.done.is_set():
            stop.wait(0.2) if parts_limit is None else h.counter.done.wait(0.2)
    finally:
        h.close()
    files = ", ".join(map(str, h.recorder.files))
    out(f"stopped after {h.counter.count} results; recordings: {files}")
    return 0


def run_router(
    settings: bus.BusSettings, stop: threading.Event, *, out: Callable[[str], None] = print
) -> int:
    """A zenoh router (a Python session in router mode) until ``stop``."""
    with contextlib.closing(bus.open_session(settings)):
        out(f"zenoh router listening on {', '.join(settings.listen)}")
        stop.wait()
    return 0


def run_ingest(
    cfg: LineConfig,
    stop: threading.Event,
    *,
    count: int | None = None,
    talk: Callable[[str], None] | None = None,
) -> int:
    """The ingest adapter alone, publishing to the bus until ``stop`` (or ``count`` triggers)."""
    station = Station.load(cfg, build_trees=False, talk=talk)
    with contextlib.closing(bus.open_session(bus_settings(cfg))) as session:
        publisher = bus.frame_publisher(session, station.keys.frames(station.name))
        ingest = make_ingest(cfg, station, publisher.put)
        fired = FiredCount(session, station.keys.fired(station.name), ingest)
        ingest.start(count)
        while not stop.is_set() and ingest._thread is not None and ingest._thread.is_alive():
            stop.wait(0.2)
        ingest.stop()
        fired.close()
        publisher.undeclare()
    return 0


def run_worker(
    cfg: LineConfig, stop: threading.Event, *, talk: Callable[[str], None] | None = None
) -> int:
    """A worker alone: measures (or has its executor measure), publishes, stores and
    records until ``stop``."""
    station = Station.load(
        cfg, warm_up=cfg.station.dask_address() is None, talk=talk, simulate=False
    )
    with (
        contextlib.closing(station),
        contextlib.closing(make_executor(cfg, station)) as executor,
        contextlib.closing(bus.open_session(bus_settings(cfg))) as session,
    ):
        store = ResultStore(cfg.storage.store_target())
        archive = DeviationArchive(
            cfg.storage.deviations_path(), max_bytes=cfg.deviations_max_bytes()
        )
        janitor = Janitor(store, archive, cfg.retention)
        recorder = station.recorder()
        parts = follow_store_parts(cfg, station, recorder)
        metrics = Metrics()
        served = None
        if cfg.station.metrics_port is not None:
            served = metrics.serve(cfg.http.host, cfg.station.metrics_port)
        worker = ZenohWorker(
            session,
            station.keys,
            station.name,
            station.pipeline(),
            queue_size=cfg.station.queue_size,
            sinks=[archive_sink(archive), store_sink(store)],
            after_publish=[
                recorder.record,
                spc_monitor(
                    cfg,
                    station,
                    store,
                    [
                        store.put_alarm,
                        zenoh_alarm_sink(session, station.keys),
                        recorder.record_alarm,
                    ],
                ),
            ],  # fmt: skip
            missed_part=station.missed_part(),
            metrics=metrics,
            executor=executor,
            alarms=[store.put_alarm, recorder.record_alarm],
            parts=parts,
            **worker_state(cfg, store),
        )
        try:
            stop.wait()
        finally:
            worker.close()
            parts.close()
            recorder.close()
            janitor.close()
            store.close()
            if served is not None:
                served.shutdown()
    return 0


def run_api(cfg: LineConfig, stop: threading.Event) -> int:
    """The REST API alone: serves the store, streams results it receives on the bus."""
    with contextlib.closing(bus.open_session(bus_settings(cfg))) as session:
        store = ResultStore(cfg.storage.store_target())
        hub = ResultHub()
        keys = Keys(cfg.line.name, cfg.zenoh.prefix)

        def on_result(sample: zenoh.Sample) -> None:
            hub.publish(result_from_json(sample.payload.to_bytes()))

        def on_alarm(sample: zenoh.Sample) -> None:
            hub.publish(Alarm.model_validate_json(sample.payload.to_bytes()))

        sub = bus.RingSubscriber(
            session, keys.results(), on_result, capacity=256, name="results-rx"
        )
        alarm_sub = bus.RingSubscriber(
            session, keys.alarms(), on_alarm, capacity=256, name="alarms-rx"
        )
        made = make_app(
            cfg, store=store, hub=hub, checks={"zenoh": lambda: bus.is_connected(session)}
        )
        api = ApiServer(made, cfg.http.host, cfg.http.port) if made is not None else None
        try:
            if api is not None and not api.wait_started():
                raise RuntimeError(f"the API did not start on {cfg.http.host}:{cfg.http.port}")
            stop.wait()
        finally:
            if api is not None:
                api.close()
            if made is not None:
                made.close()
            sub.close()
            alarm_sub.close()
            store.close()
    return 0
