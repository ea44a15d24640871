"""Replay recorded runs: re-measure every recorded FrameSet, compare, or publish it again.

The recording carries what replay needs: the FrameSets (header and images),
the results, and in its metadata the part specs, CAD hashes and the stages
the line measured with. :func:`replay` rebuilds the pipeline from these (the
CAD of a configured part is regenerated or read from the part's file, that of
a part created over the API from the recording itself, and each must hash the
same), runs each FrameSet through :meth:`Pipeline.run`, the worker's own code
path, with the revision of its part its result names, and compares with the
logged result:

- the same status and the same verdict at every comparison point;
- ``transform`` (T_cad_rig) within :attr:`Tolerances.transform` per element;
- every deviation within :attr:`Tolerances.deviation_mm`.
"""

from __future__ import annotations

import json
import logging
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inspection.measure import MeasurePath

from .config import PartSpec
from .models import InspectionResult
from .parts import LoadedPart, load_part, load_part_cad
from .pipeline import Pipeline, Stages, flash_stages, holography_stages
from .protocol import FrameSet, encode_frameset
from .recorder import RecordedPart, RecordedTrigger, read_recording, read_run

log = logging.getLogger(__name__)


class ReplayError(RuntimeError):
    """A recording that cannot be replayed (no specs, a CAD that changed, other stages)."""


@dataclass(frozen=True)
class Tolerances:
    transform: float = 1e-9
    deviation_mm: float = 1e-6


@dataclass
class Difference:
    id: str
    what: str


@dataclass
class ReplayReport:
    triggers: int = 0
    replayed: int = 0
    not_replayable: int = 0
    same: int = 0
    differences: list[Difference] = field(default_factory=list)
    max_transform_diff: float = 0.0
    max_deviation_diff_mm: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.differences

    def summary(self) -> str:
        lines = [
            f"{self.triggers} triggers, {self.replayed} replayed "
            f"({self.not_replayable} without frames: missed or not kept), {self.same} identical",
            f"max |transform difference| {self.max_transform_diff:.3g}, "
            f"max |deviation difference| {self.max_deviation_diff_mm:.3g} mm",
        ]
        for d in self.differences[:50]:
            lines.append(f"  DIFFERENT {d.id}: {d.what}")
        if len(self.differences) > 50:
            lines.append(f"  ... and {len(self.differences) - 50} more")
        return "\n".join(lines)


def parts_from_metadata(
    metadata: dict[str, dict[str, str]], stages: Stages, parts_dir: Path, trees_dir: Path
) -> dict[str, LoadedPart]:
    """Load the recorded parts of the station's configuration (trees from the cache in
    ``trees_dir``, else built); the CAD and the tree must hash as recorded.

    Raises
    ------
    ReplayError
    """
    cad_meta = metadata.get("cad", {})
    specs = {k[: -len(".spec")]: v for k, v in cad_meta.items() if k.endswith(".spec")}
    if not specs:
        raise ReplayError("the recording has no part specs in its metadata")
    rig = metadata.get("rig", {})
    if rig.get("stages") and rig["stages"] != stages.name:
        raise ReplayError(
            f"recorded with the {rig['stages']!r} stages, replaying with {stages.name!r}"
        )
    parts = {}
    for name, spec_json in specs.items():
        spec = PartSpec.model_validate_json(spec_json)
        cad = load_part_cad(spec, parts_dir)
        want = cad_meta.get(f"{name}.cad_hash")
        if want and cad.hash != want:
            raise ReplayError(
                f"part {name}: the CAD changed since the recording ({cad.hash[:12]} vs {want[:12]})"
            )
        parts[name] = load_part(spec, parts_dir, trees_dir)
        want_tree = cad_meta.get(f"{name}.tree_hash")
        if want_tree and parts[name].tree_hash != want_tree:
            raise ReplayError(f"part {name}: the tree differs from the recorded one")
    return parts


def load_recorded_part(part: RecordedPart, trees_dir: Path) -> LoadedPart:
    """A part created over the API, rebuilt from what the recording holds of it (its spec
    and CAD file; the tree from the cache in ``trees_dir``, else built); the CAD and the
    tree must hash as its results say.

    Raises
    ------
    ReplayError
    """
    which = f"part {part.name} (revision {part.revision})"
    try:
        spec = PartSpec.model_validate_json(part.spec)
    except ValueError as exc:
        raise ReplayError(f"{which}: the recorded spec is not a part spec: {exc}") from exc
    with tempfile.TemporaryDirectory(prefix="replay-part-") as folder:
        (Path(folder) / part.cad_file).write_bytes(part.cad)
        loaded = load_part(spec, Path(folder), trees_dir)
    if loaded.cad.hash != part.cad_hash:
        raise ReplayError(f"{which}: the recorded CAD loads as {loaded.cad.hash[:12]}, "
                          f"measured as {part.cad_hash[:12]}")  # fmt: skip
    if loaded.tree_hash != part.tree_hash:
        raise ReplayError(f"{which}: the tree differs from the recorded one")
    return loaded


def recorded_stages(metadata: dict[str, dict[str, str]]) -> Stages:
    """The flash stages with the calibrated rig the recording was measured with.

    Raises
    ------
    ReplayError
        The recording names other stages, or its calibration does not load.
    """
    rig = metadata.get("rig", {})
    if rig.get("stages") == "holography":
        return _holography_stages(rig)
    if rig.get("stages", "flash") != "flash":
        raise ReplayError(f"recorded with the {rig['stages']!r} stages, which no longer exist")
    # Recordings from before the guided pass existed say nothing: they were one pass.
    guided = rig.get("guided", "false") == "true"
    # ... and from before the comparison-point path existed, on the cloud.
    paths: dict[str, MeasurePath] = {"cloud": "cloud", "comparison_points": "comparison_points"}
    path = paths.get(rig.get("path", "cloud"))
    if path is None:
        raise ReplayError(f"recorded on path {rig['path']!r}, which does not exist")
    toml = rig.get("calibration_toml")
    if not toml:
        return flash_stages(None, guided=guided, path=path)
    with tempfile.TemporaryDirectory() as tmp:
        file = Path(tmp) / "rig.toml"
        file.write_text(toml)
        try:
            stages = flash_stages(file, guided=guided, path=path)
        except Exception as exc:
            raise ReplayError(f"the recorded rig calibration does not load: {exc}") from exc
    want = rig.get("calibration_id")
    if want and stages.calibration_id != want:
        raise ReplayError(
            f"the recorded calibration loads as {stages.calibration_id!r}, recorded {want!r}"
        )
    return stages


def _holography_stages(rig: dict[str, str]) -> Stages:
    """The holographic stages with the calibrated head and the fixture of the recording."""
    from inspection.errors import InspectionError
    from inspection.holography import HoloCalibration

    try:
        calib = HoloCalibration.from_toml(rig["calibration_toml"], where="recorded calibration")
        T = np.asarray(json.loads(rig["T_head_cad"]), dtype=np.float64)
        # Recordings from before the coarse pose was a setting were measured without it.
        coarse = rig.get("coarse_pose", "false") == "true"
        stages = holography_stages(calib, T_head_cad=T, coarse_pose=coarse)
    except KeyError as exc:
        raise ReplayError(f"the recording lacks the holographic head's {exc.args[0]}") from exc
    except (InspectionError, ValueError) as exc:
        raise ReplayError(f"the recorded holographic head does not load: {exc}") from exc
    want = rig.get("calibration_id")
    if want and stages.calibration_id != want:
        raise ReplayError(
            f"the recorded calibration loads as {stages.calibration_id!r}, recorded {want!r}"
        )
    return stages


def compare(
    new: InspectionResult, old: InspectionResult, tol: Tolerances
) -> tuple[list[str], float, float]:
    """Differences beyond tolerance between a replayed and a logged result."""
    diffs = []
    t_diff = dev_diff = 0.0
    if new.status != old.status:
        diffs.append(f"status {new.status.value} vs logged {old.status.value}")
    if new.path != old.path:
        diffs.append(f"measured on path {new.path} vs logged {old.path}")
    if (new.transform is None) != (old.transform is None):
        diffs.append("transform present in only one of them")
    elif new.transform is not None and old.transform is not None:
        t_diff = float(np.max(np.abs(np.asarray(new.transform) - np.asarray(old.transform))))
        if t_diff > tol.transform:
            diffs.append(f"transform differs by {t_diff:.3g}")
    old_points = {c.name: c for c in old.comparison}
    if {c.name for c in new.comparison} != set(old_points):
        diffs.append("different comparison points")
    for c in new.comparison:
        o = old_points.get(c.name)
        if o is None:
            continue
        if c.verdict != o.verdict:
            diffs.append(f"{c.name}: verdict {c.verdict.value} vs logged {o.verdict.value}")
        if (c.deviation_mm is None) != (o.deviation_mm is None):
            diffs.append(f"{c.name}: deviation measured in only one of them")
        elif c.deviation_mm is not None and o.deviation_mm is not None:
            d = abs(c.deviation_mm - o.deviation_mm)
            dev_diff = max(dev_diff, d)
            if d > tol.deviation_mm:
                diffs.append(f"{c.name}: deviation differs by {d:.3g} mm")
    for name in ("mean_mm", "rms_mm", "min_mm", "max_mm") if new.field and old.field else ():
        a, b = getattr(new.field, name), getattr(old.field, name)
        if a is not None and b is not None:
            dev_diff = max(dev_diff, abs(a - b))
            if abs(a - b) > tol.deviation_mm:
                diffs.append(f"field {name} differs by {abs(a - b):.3g} mm")
    return diffs, t_diff, dev_diff


def replay(
    paths: Sequence[str | Path],
    *,
    stages: Stages | None = None,
    parts_dir: str | Path = "configs/parts",
    trees_dir: str | Path = "runs/trees",
    tolerances: Tolerances | None = None,
    on_result: Callable[[InspectionResult, InspectionResult], None] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ReplayReport:
    """Re-run every recorded FrameSet and compare with the logged results.

    ``progress(done, total)`` is called once the recording is read (``done``
    0) and after each recorded trigger.
    """
    tol = tolerances or Tolerances()
    run = read_run(paths)
    metadata, triggers = run.metadata, run.triggers
    if stages is None:
        stages = recorded_stages(metadata)
    parts = parts_from_metadata(metadata, stages, Path(parts_dir), Path(trees_dir))
    pipeline = Pipeline(stages, parts)
    try:
        recorded = run.parts()
    except ValueError as exc:
        raise ReplayError(str(exc)) from exc
    created = [(p, load_recorded_part(p, Path(trees_dir))) for p in recorded]
    report = ReplayReport(triggers=len(triggers))
    if progress is not None:
        progress(0, len(triggers))
    for k, t in enumerate(triggers, 1):
        if progress is not None and k > 1:
            progress(k - 1, len(triggers))
        if t.frameset is None:
            report.not_replayable += 1
            continue
        # A part created over the API: the revision its result was measured with.
        revision = next((loaded for p, loaded in created if p.measured(t.result)), None)
        run_with = (
            pipeline if revision is None else Pipeline(stages, {**parts, t.result.part: revision})
        )
        new = run_with.run(t.frameset).result
        report.replayed += 1
        diffs, t_diff, d_diff = compare(new, t.result, tol)
        report.max_transform_diff = max(report.max_transform_diff, t_diff)
        report.max_deviation_diff_mm = max(report.max_deviation_diff_mm, d_diff)
        if diffs:
            report.differences.append(Difference(t.result.id, "; ".join(diffs)))
        else:
            report.same += 1
        if on_result is not None:
            on_result(new, t.result)
    if progress is not None:
        progress(len(triggers), len(triggers))
    return report


def framesets(triggers: Iterable[RecordedTrigger]) -> list[FrameSet]:
    return [t.frameset for t in triggers if t.frameset is not None]


def publish(
    paths: Sequence[str | Path],
    put: Callable[[bytes], None],
    *,
    speed: float = 1.0,
    stop: threading.Event | None = None,
    encoding: str = "raw",
) -> int:
    """Publish the recorded FrameSets again, spaced as recorded (divided by ``speed``).

    ``speed`` 0 or below: as fast as the subscriber takes them (BLOCK congestion
    control paces the publisher). Returns the number published.
    """
    _, triggers = read_recording(paths)
    sets = framesets(triggers)
    stop = stop or threading.Event()
    t0_wall = time.monotonic()
    t0_rec = sets[0].triggered_ns if sets else 0
    n = 0
    for fs in sets:
        if speed > 0:
            due = t0_wall + (fs.triggered_ns - t0_rec) / 1e9 / speed
            delay = due - time.monotonic()
            if delay > 0 and stop.wait(delay):
                break
        if stop.is_set():
            break
        put(encode_frameset(fs, encoding=encoding))
        n += 1
    return n


def recording_files(path: str | Path) -> list[Path]:
    """A file, or every ``.mcap`` of a directory in name order (rotated files of a run)."""
    p = Path(path)
    if p.is_dir():
        return sorted(p.glob("*.mcap"))
    return [p]
