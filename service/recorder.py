"""MCAP recording of the line: frames, clouds, poses, calibrations and results.

One recorder per run writes ``<dir>/<run_id>-<index>.mcap``, starting a new
file when the current one passes ``rotate_bytes``. Channels (Foxglove's
well-known schemas, as protobuf; results as JSON with their JSON Schema):

=========================  ==============================  ================================
topic                      schema                          what
=========================  ==============================  ================================
``/<camera>/image``        foxglove.RawImage (mono8,       one per camera and trigger
                           mono16) or                      (frame ``<camera>``)
                           foxglove.CompressedImage (png)
``/<camera>/calibration``  foxglove.CameraCalibration      once per file: intrinsics in the
                                                           camera's frame (R = I, P = K[I|0])
``/<camera>/transform``    foxglove.FrameTransform         once per file: ``rig`` to
                                                           ``<camera>`` (static)
``/frameset``              JSON (FrameSet header)          line, station, part, serial,
                                                           seq, triggered_ns, truth, sensor
``/maps/<name>``           foxglove.RawImage (32FC1)       a sensor's maps with its frames:
                                                           the holographic head's ``phase``
                                                           (rad) and ``deviation`` (mm),
                                                           NaN where not measured
``/cloud``                 foxglove.PointCloud             x, y, z (rig frame, mm) and
                                                           ``deviation`` (mm, float32)
``/part/pose``             foxglove.FrameTransform         T_rig_cad (``rig`` to ``part_cad``)
``/part/cad``              foxglove.SceneUpdate            the CAD in ``part_cad``, once per
                                                           part type per file
``/part/markers``          foxglove.SceneUpdate            comparison points and defects,
                                                           labelled, coloured by verdict
``/result``                JSON (InspectionResult)         every result, always
``/log``                   foxglove.Log                    every result as one line
``/alarm``                 JSON (Alarm)                    every alarm, when raised
=========================  ==============================  ================================

A part created over the API while the line runs (taken from the store,
:mod:`service.station_parts`) is written into a file with the first result
measured with it there, so that replay rebuilds it from the file alone: its
CAD file's bytes as an MCAP attachment ``parts/<name>/<revision>/<file>``
(Foxglove lists attachments with their media type, and saves them) and a
metadata record ``part/<name>/<revision>`` with its spec and the hashes its
results carry (:class:`RecordedPart`).

The frames and messages are those of :mod:`service.foxglove`; docs/foxglove.md
describes the layout that opens a recording. The per-file records (the
cameras' transforms and calibrations, a part type's CAD) are written with
the first trigger that needs them, at its time, so they precede everything
that refers to them in log time.

Disk cost: chunk compression (``none``, ``lz4``, ``zstd``) and the image
encoding (``raw``, or lossless ``png``) are configured
(``storage.mcap_compression``, ``storage.mcap_image_encoding``); what each
costs on the line's frames is measured by ``make bench BENCH=line``.

All timestamps are ns since the Unix epoch; every message of one trigger has
the trigger's time as ``log_time``. Config, rig calibration and CAD hashes go
into the file's metadata records.

Crash safety: the writer finishes its chunk and flushes after every trigger,
so a killed process leaves a file readable up to the last completed trigger;
:func:`recover` rewrites such a file into a complete, indexed one, and a
recorder that starts does so for every unfinished file in its directory that
no live recorder holds (each holds an exclusive lock on its open file). A
file is finished after ``rotate_s`` as well as at ``rotate_bytes``, so every
file but the open one can be read with the indexed reader.

Retention: the policy decides whose frames and cloud are written (every part,
failures only, or every n-th part plus all failures; results are always
written, they are small), and the oldest files are deleted when the directory
passes its size budget or a file its age limit, checked after every trigger.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import threading
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set

from inspection.deviations import ComparisonPoint

from . import foxglove
from .config import RetentionSection
from .models import Alarm, InspectionResult, Status
from .pipeline import Outcome
from .protocol import FrameSet

log = logging.getLogger(__name__)

PROFILE = "inspection"
COMPRESSIONS = {
    "none": CompressionType.NONE,
    "lz4": CompressionType.LZ4,
    "zstd": CompressionType.ZSTD,
}
IMAGE_ENCODINGS = ("raw", "png")
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY,
              cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]  # fmt: skip
"""Camera noise defeats deflate's string matching: PNG's row filters with Huffman coding
alone give a smaller file than the default strategy, and sooner (the line bench sweeps
OpenCV's PNG settings)."""


RAW_DTYPES: dict[str, np.dtype[Any]] = {"mono8": np.dtype(np.uint8), "mono16": np.dtype("<u2")}
"""The camera images' RawImage encodings, as read back."""


@dataclass(frozen=True, eq=False)
class RecordedPart:
    """A part created over the API as a recording keeps it, for replay: its spec, the CAD
    file it was loaded from, and what the results measured with it carry.

    Attributes
    ----------
    name : str
    revision : int
        Its revision in the result store.
    spec : str
        The part spec as JSON (``service.config.PartSpec``).
    cad_file : str
        The CAD file's name, as the spec's ``cad`` names it (its suffix says the format).
    cad : bytes
        The CAD file.
    cad_hash, tree_hash, spec_version : str
        As each result measured with this revision has them.
    """

    name: str
    revision: int
    spec: str
    cad_file: str
    cad: bytes
    cad_hash: str
    tree_hash: str
    spec_version: str

    @property
    def attachment(self) -> str:
        """The name of the CAD file's attachment."""
        return f"parts/{self.name}/{self.revision}/{self.cad_file}"

    @property
    def record(self) -> str:
        """The name of its metadata record."""
        return f"part/{self.name}/{self.revision}"

    def measured(self, result: InspectionResult) -> bool:
        """Whether ``result`` was measured with this revision."""
        return (result.part, result.cad_hash, result.tree_hash, result.spec_version) == (
            self.name, self.cad_hash, self.tree_hash, self.spec_version,
        )  # fmt: skip

    def metadata(self) -> dict[str, str]:
        return {
            "name": self.name, "revision": str(self.revision), "spec": self.spec,
            "attachment": self.attachment, "cad_hash": self.cad_hash,
            "tree_hash": self.tree_hash, "spec_version": self.spec_version,
        }  # fmt: skip


CAD_MEDIA_TYPES = {".stl": "model/stl", ".obj": "model/obj", ".step": "model/step",
                   ".stp": "model/step"}  # fmt: skip
"""Media types of the CAD attachments (IANA's); any other file is application/octet-stream."""


def recorded_parts(
    metadata: Mapping[str, Mapping[str, str]], attachments: Mapping[str, bytes]
) -> list[RecordedPart]:
    """The parts created over the API that a recording holds (see :class:`RecordedPart`).

    Raises
    ------
    ValueError
        A part record without its CAD attachment, or incomplete.
    """
    parts = []
    for name, meta in metadata.items():
        if not name.startswith("part/"):
            continue
        try:
            attachment = meta["attachment"]
            part = RecordedPart(
                name=meta["name"], revision=int(meta["revision"]), spec=meta["spec"],
                cad_file=attachment.rsplit("/", 1)[-1], cad=attachments[attachment],
                cad_hash=meta["cad_hash"], tree_hash=meta["tree_hash"],
                spec_version=meta["spec_version"],
            )  # fmt: skip
        except (KeyError, ValueError) as exc:
            raise ValueError(f"the recording's part {name!r} is incomplete: {exc!r}") from exc
        parts.append(part)
    return parts


@dataclass(frozen=True)
class PartScene:
    """What the recording shows of a part type: its CAD and its comparison points.

    Attributes
    ----------
    vertices : (V, 3) float64, mm, CAD frame
    faces : (F, 3) int64
    points : tuple of ComparisonPoint
    """

    vertices: np.ndarray
    faces: np.ndarray
    points: tuple[ComparisonPoint, ...] = ()


@dataclass(frozen=True)
class Retention:
    """What to record and how much disk to use.

    Attributes
    ----------
    record : {"all", "failures", "every_nth"}
    every_nth : int
    max_total_bytes : int or None
    max_age_s : float or None
    """

    record: str = "all"
    every_nth: int = 10
    max_total_bytes: int | None = None
    max_age_s: float | None = None

    def __post_init__(self) -> None:
        if self.record not in ("all", "failures", "every_nth"):
            raise ValueError(f"record must be all, failures or every_nth, got {self.record!r}")
        if self.every_nth < 1:
            raise ValueError("every_nth must be at least 1")

    @classmethod
    def from_config(cls, section: RetentionSection) -> Retention:
        """From the line config's ``[retention]`` section."""
        return cls(
            record=section.record.value,
            every_nth=section.every_nth,
            max_total_bytes=None
            if section.max_total_mb is None
            else int(section.max_total_mb * 1e6),
            max_age_s=None if section.max_age_h is None else section.max_age_h * 3600.0,
        )

    def keeps_frames(self, result: InspectionResult) -> bool:
        """Whether the frames and cloud of this result are recorded."""
        if result.status is Status.missed:
            return False  # nothing to record but the result
        failed = result.status is not Status.passed
        if self.record == "all" or failed:
            return True
        if self.record == "failures":
            return False
        return result.seq % self.every_nth == 0


def result_json_schema() -> str:
    """The JSON Schema of :class:`InspectionResult`, as recorded with the ``/result`` channel."""
    return json.dumps(InspectionResult.model_json_schema())


FRAMESET_SCHEMA = {
    "title": "FrameSetHeader",
    "type": "object",
    "description": "The FrameSet wire header (docs/protocol.md) without the image list.",
    "properties": {
        k: {"type": t}
        for k, t in [
            ("line", "string"),
            ("station", "string"),
            ("part", "string"),
            ("serial", "string"),
            ("seq", "integer"),
            ("triggered_ns", "integer"),
            ("calibration_id", "string"),
            ("cameras", "array"),
            ("truth", ["object", "null"]),
            ("sensor", "string"),
        ]
    },
}


class _File:
    """One open MCAP file with its registered schemas and channels."""

    def __init__(
        self,
        path: Path,
        metadata: Mapping[str, Mapping[str, str]],
        compression: CompressionType = CompressionType.NONE,
    ) -> None:
        self.path = path
        self.stream: IO[bytes] = path.open("wb")
        # Held while the file is open: a recorder starting meanwhile (another
        # worker, the same worker restarted) leaves this file alone.
        fcntl.flock(self.stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        self.opened = time.monotonic()
        self.writer = McapWriter(
            self.stream,
            chunk_size=4 * 1024 * 1024,
            compression=compression,
        )
        self.writer.start(profile=PROFILE, library="inspection-recorder")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.has_rig = False
        self.cads: set[str] = set()
        """Part types whose CAD this file holds."""
        self.parts: set[str] = set()
        """The parts created over the API it holds (:attr:`RecordedPart.record`)."""
        for name, data in metadata.items():
            self.writer.add_metadata(name, dict(data))
        self.writer.flush()

    def _proto_channel(self, topic: str, cls: Any) -> int:
        if topic not in self._channels:
            name = cls.DESCRIPTOR.full_name
            if name not in self._schemas:
                self._schemas[name] = self.writer.register_schema(
                    name=name,
                    encoding="protobuf",
                    data=build_file_descriptor_set(cls).SerializeToString(),
                )
            self._channels[topic] = self.writer.register_channel(
                topic=topic, message_encoding="protobuf", schema_id=self._schemas[name]
            )
        return self._channels[topic]

    def _json_channel(self, topic: str, schema_name: str, schema: str) -> int:
        if topic not in self._channels:
            if schema_name not in self._schemas:
                self._schemas[schema_name] = self.writer.register_schema(
                    name=schema_name, encoding="jsonschema", data=schema.encode()
                )
            self._channels[topic] = self.writer.register_channel(
                topic=topic, message_encoding="json", schema_id=self._schemas[schema_name]
            )
        return self._channels[topic]

    def proto(self, topic: str, msg: Any, log_ns: int) -> None:
        ch = self._proto_channel(topic, type(msg))
        self.writer.add_message(ch, log_ns, msg.SerializeToString(), time.time_ns())

    def json(self, topic: str, schema_name: str, schema: str, doc: bytes, log_ns: int) -> None:
        ch = self._json_channel(topic, schema_name, schema)
        self.writer.add_message(ch, log_ns, doc, time.time_ns())

    def part(self, part: RecordedPart, log_ns: int) -> None:
        """Write a part created over the API: its CAD as an attachment, its spec and hashes
        as a metadata record."""
        media = CAD_MEDIA_TYPES.get(Path(part.cad_file).suffix.lower(), "application/octet-stream")
        self.writer.add_attachment(log_ns, log_ns, part.attachment, media, part.cad)
        self.writer.add_metadata(part.record, part.metadata())
        self.parts.add(part.record)

    def size(self) -> int:
        return self.stream.tell()

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.finish()
        self.stream.close()


class Recorder:
    """Records every outcome of a run into rotated MCAP files.

    Parameters
    ----------
    directory : Path
    run_id : str
        File name stem; use something unique per run (start time, line).
    metadata : mapping of name to {key: value}
        Written into every file (config and its hash, rig calibration, CAD hashes).
    calibrations : list of dict, optional
        One per camera: ``name``, ``width``, ``height``, ``K`` (9, rows first),
        ``D`` (OpenCV's k1 k2 p1 p2 k3), ``T_camera_rig`` (16, rows first: rig
        points into the camera frame), optionally ``distortion_model``
        (default ``plumb_bob``). Each camera's transform and calibration are
        written once per file.
    parts : mapping of part name to PartScene, optional
        The CAD and comparison points of each part type: the CAD is written
        once per part type per file, the markers with every measured part.
    rotate_bytes : int
        A file is finished when it passes this size (at most half the
        retention's budget, so the budget holds with the open file in it).
    rotate_s : float, optional
        ... or when it has been open this long.
    retention : Retention
    image_encoding : {"raw", "png"}
        ``raw`` writes foxglove.RawImage, ``png`` a lossless CompressedImage.
    compression : {"none", "lz4", "zstd"}
        Chunk compression of the files (and of the files :func:`recover` repairs).
    """

    def __init__(
        self,
        directory: str | Path,
        run_id: str,
        *,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        calibrations: list[dict[str, Any]] | None = None,
        parts: Mapping[str, PartScene] | None = None,
        rotate_bytes: int = 512 * 1024 * 1024,
        rotate_s: float | None = None,
        retention: Retention | None = None,
        image_encoding: str = "raw",
        compression: str = "zstd",
    ) -> None:
        if image_encoding not in IMAGE_ENCODINGS:
            raise ValueError(f"image_encoding must be raw or png, got {image_encoding!r}")
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be none, lz4 or zstd, got {compression!r}")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.run_id = run_id
        self.metadata = {k: dict(v) for k, v in (metadata or {}).items()}
        self.calibrations = calibrations or []
        for cal in self.calibrations:
            if np.asarray(cal["T_camera_rig"], dtype=np.float64).shape != (16,):
                raise ValueError(f"{cal['name']}: T_camera_rig must hold 16 numbers")
        self.parts = dict(parts or {})
        self.kept: list[RecordedPart] = []
        """Parts created over the API that results may name (:meth:`set_part`)."""
        self.compression = compression
        self.retention = retention or Retention()
        budget = self.retention.max_total_bytes
        self.rotate_bytes = rotate_bytes if budget is None else min(rotate_bytes, budget // 2)
        self.rotate_s = rotate_s
        self.image_encoding = image_encoding
        self._lock = threading.Lock()
        self._index = 0
        self._file: _File | None = None
        self._schema = result_json_schema()
        self._alarm_schema = json.dumps(Alarm.model_json_schema())
        self.files: list[Path] = []
        self.recorded = 0
        self.frames_recorded = 0
        self.recovered = recover_unfinished(self.directory, compression)
        self._open_next()

    # ------------------------------------------------------------------ files

    def _open_next(self) -> None:
        path = self.directory / f"{self.run_id}-{self._index:04d}.mcap"
        self._index += 1
        self._file = _File(path, self.metadata, COMPRESSIONS[self.compression])
        self.files.append(path)
        self.enforce_budget()
        log.info("recording to %s", path)

    def enforce_budget(self) -> list[Path]:
        """Delete the oldest finished files beyond the size or age budget; returns them.

        Files another recorder is still writing are not finished, and not touched.
        """
        current = self._file.path if self._file else None
        files = sorted(
            (p for p in self.directory.glob("*.mcap") if p != current and is_finished(p)),
            key=lambda p: p.stat().st_mtime,
        )
        removed = []
        now = time.time()
        if self.retention.max_age_s is not None:
            for p in list(files):
                if now - p.stat().st_mtime > self.retention.max_age_s:
                    files.remove(p)
                    removed.append(p)
        if self.retention.max_total_bytes is not None:
            total = sum(p.stat().st_size for p in files) + (self._file.size() if self._file else 0)
            while files and total > self.retention.max_total_bytes:
                p = files.pop(0)
                total -= p.stat().st_size
                removed.append(p)
        for p in removed:
            log.info("retention: deleting %s", p)
            p.unlink(missing_ok=True)
        return removed

    def set_part(
        self, name: str, scene: PartScene | None, kept: RecordedPart | None = None
    ) -> None:
        """Show part ``name`` as ``scene`` from now on (None: no more): a part the station
        took from the store while it runs, or a new revision of one (its CAD is written
        again). ``kept``: that revision's files, written into each file with the first
        result measured with it, so that replay rebuilds it."""
        with self._lock:
            if scene is None:
                self.parts.pop(name, None)
            else:
                self.parts[name] = scene
            if kept is not None:
                # Every revision stays: results of an older one may come after a newer one.
                self.kept.append(kept)
            if self._file is not None:
                self._file.cads.discard(name)

    # ------------------------------------------------------------------ records

    def record(self, outcome: Outcome, fs: FrameSet | None) -> bool:
        """Write one trigger; returns whether its frames were kept. Flushes before returning."""
        result = outcome.result
        with self._lock:
            assert self._file is not None, "recorder is closed"
            f = self._file
            t = result.triggered_ns
            if not f.has_rig:
                self._write_rig(f, t)
            kept = next((k for k in reversed(self.kept) if k.measured(result)), None)
            if kept is not None and kept.record not in f.parts:
                f.part(kept, t)
            keep = fs is not None and self.retention.keeps_frames(result)
            if keep:
                assert fs is not None
                header = {
                    "line": fs.line,
                    "station": fs.station,
                    "part": fs.part,
                    "serial": fs.serial,
                    "seq": fs.seq,
                    "triggered_ns": fs.triggered_ns,
                    "calibration_id": fs.calibration_id,
                    "cameras": list(fs.cameras),
                    "truth": None if fs.truth is None else fs.truth.to_json(),
                    "sensor": fs.sensor,
                }
                f.json(
                    "/frameset",
                    "FrameSetHeader",
                    json.dumps(FRAMESET_SCHEMA),
                    json.dumps(header).encode(),
                    t,
                )
                for cam, img in zip(fs.cameras, fs.images, strict=True):
                    f.proto(f"/{cam}/image", self._image(cam, img, t), t)
                for name, values in outcome.maps.items():
                    f.proto(f"/maps/{name}", _float_image(fs.cameras[0], values, t), t)
                if outcome.points is not None and len(outcome.points):
                    f.proto("/cloud", foxglove.cloud(outcome.points, outcome.distances, t), t)
                self.frames_recorded += 1
            placed = outcome.transform is not None and np.isfinite(outcome.transform).all()
            if placed:
                assert outcome.transform is not None
                f.proto("/part/pose", foxglove.part_pose(np.linalg.inv(outcome.transform), t), t)
            scene = self.parts.get(result.part)
            if scene is not None:
                if result.part not in f.cads:
                    cad = foxglove.cad_scene(result.part, scene.vertices, scene.faces, t)
                    f.proto("/part/cad", cad, t)
                    f.cads.add(result.part)
                # Unplaced (an error): the update only deletes the last part's markers.
                shown = (
                    result
                    if placed
                    else result.model_copy(update={"comparison": [], "defects": []})
                )
                f.proto("/part/markers", foxglove.markers(shown, scene.points, t), t)
            f.json(
                "/result", "InspectionResult", self._schema, result.model_dump_json().encode(), t
            )
            f.proto("/log", foxglove.result_log(result, t), t)
            # Finish the chunk now: a killed process loses at most the trigger
            # being written, never the ones before it.
            f.flush()
            self.recorded += 1
            aged = self.rotate_s is not None and time.monotonic() - f.opened > self.rotate_s
            if f.size() > self.rotate_bytes or aged:
                f.close()
                self._open_next()
            else:
                self.enforce_budget()
            return keep

    __call__ = record

    def _write_rig(self, f: _File, t: int) -> None:
        """Each camera's static transform from the rig and its calibration, at ``t``."""
        for cal in self.calibrations:
            f.proto(f"/{cal['name']}/transform", foxglove.camera_transform(cal, t), t)
            f.proto(f"/{cal['name']}/calibration", foxglove.camera_calibration(cal, t), t)
        f.has_rig = True

    def record_alarm(self, alarm: Alarm) -> None:
        """Write one alarm, at the time it was raised; flushes before returning."""
        with self._lock:
            if self._file is None:
                return  # closed: the alarm is in the store and on zenoh
            doc = alarm.model_dump_json().encode()
            self._file.json("/alarm", "Alarm", self._alarm_schema, doc, alarm.raised_ns)
            self._file.flush()

    def _image(self, cam: str, img: np.ndarray, t: int) -> Any:
        if self.image_encoding == "png":
            ok, buf = cv2.imencode(".png", img, PNG_PARAMS)
            if not ok:
                raise ValueError(f"{cam}: the image cannot be encoded as PNG")
            return CompressedImage(
                timestamp=foxglove.timestamp(t), frame_id=cam, format="png", data=buf.tobytes()
            )
        h, w = img.shape
        wide = img.dtype == np.uint16
        return RawImage(
            timestamp=foxglove.timestamp(t),
            frame_id=cam,
            width=w,
            height=h,
            encoding="mono16" if wide else "mono8",
            step=2 * w if wide else w,
            data=np.ascontiguousarray(img, dtype="<u2" if wide else np.uint8).tobytes(),
        )

    def close(self) -> None:
        """Finish the current file (summary and index written)."""
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None
        self.enforce_budget()


def _float_image(frame_id: str, values: np.ndarray, t: int) -> RawImage:
    """A map as foxglove.RawImage ``32FC1`` (little-endian float32, NaN where not measured)."""
    h, w = values.shape
    return RawImage(
        timestamp=foxglove.timestamp(t),
        frame_id=frame_id,
        width=w,
        height=h,
        encoding="32FC1",
        step=4 * w,
        data=np.ascontiguousarray(values, dtype="<f4").tobytes(),
    )


# --------------------------------------------------------------------------- reading


def iter_records(path: str | Path) -> Iterator[Any]:
    """Every record of a possibly unfinished MCAP file, stopping quietly at a torn end."""
    with Path(path).open("rb") as fh:
        reader = StreamReader(fh, skip_magic=False)
        try:
            yield from reader.records
        except Exception as exc:  # a torn record at the end of a killed file
            log.info("%s: stopped at a damaged record (%s)", path, exc)


@dataclass(frozen=True)
class Recovered:
    """What :func:`recover` saved."""

    path: Path
    messages: int
    channels: int
    metadata: int


def recover(
    path: str | Path, out: str | Path | None = None, compression: str = "zstd"
) -> Recovered:
    """Rewrite an unfinished MCAP file (a killed recorder) into a complete one.

    Every message of every completed chunk is kept; the torn tail is dropped.
    ``out`` defaults to ``<path stem>.recovered.mcap``; the original is left alone.
    ``compression`` (none, lz4, zstd) is that of the rewritten file's chunks.
    """
    src = Path(path)
    dst = Path(out) if out is not None else src.with_suffix(".recovered.mcap")
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    n_msgs = n_meta = 0
    with dst.open("wb") as fh:
        w = McapWriter(fh, compression=COMPRESSIONS[compression])
        w.start(profile=PROFILE, library="inspection-recover")
        schema_map: dict[int, int] = {}
        channel_map: dict[int, int] = {}
        for rec in iter_records(src):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Metadata):
                w.add_metadata(rec.name, dict(rec.metadata))
                n_meta += 1
            elif isinstance(rec, Attachment):
                w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            elif isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is None:
                    continue
                if ch.id not in channel_map:
                    sid = 0
                    if ch.schema_id:
                        if ch.schema_id not in schema_map:
                            s = schemas[ch.schema_id]
                            schema_map[ch.schema_id] = w.register_schema(s.name, s.encoding, s.data)
                        sid = schema_map[ch.schema_id]
                    channel_map[ch.id] = w.register_channel(
                        ch.topic, ch.message_encoding, sid, dict(ch.metadata)
                    )
                w.add_message(
                    channel_map[ch.id], rec.log_time, rec.data, rec.publish_time, rec.sequence
                )
                n_msgs += 1
        w.finish()
    log.info("recovered %d messages from %s into %s", n_msgs, src, dst)
    return Recovered(dst, n_msgs, len(channel_map), n_meta)


MCAP_MAGIC = b"\x89MCAP0\r\n"


def is_finished(path: str | Path) -> bool:
    """Whether an MCAP file ends with its footer's magic (a finished, indexed file)."""
    try:
        with Path(path).open("rb") as fh:
            fh.seek(0, os.SEEK_END)
            if fh.tell() < 2 * len(MCAP_MAGIC):
                return False
            fh.seek(-len(MCAP_MAGIC), os.SEEK_END)
            return fh.read() == MCAP_MAGIC
    except OSError:
        return False


def recover_unfinished(directory: str | Path, compression: str = "zstd") -> list[Recovered]:
    """Rewrite, in place, every unfinished MCAP file in ``directory`` that no live recorder
    holds: what a killed recorder left becomes a complete, indexed file of the same name
    (its chunks compressed with ``compression``)."""
    out = []
    for path in sorted(Path(directory).glob("*.mcap")):
        if is_finished(path):
            continue
        try:
            with path.open("rb") as fh:
                try:
                    fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    continue  # being written by a live recorder
                tmp = path.with_suffix(".recovering")
                r = recover(path, tmp, compression)
                tmp.replace(path)
        except OSError as exc:
            log.error("%s: not recovered: %s", path, exc)
            continue
        log.warning("%s was left unfinished (a killed recorder): %d messages recovered",
                    path.name, r.messages)  # fmt: skip
        out.append(Recovered(path, r.messages, r.channels, r.metadata))
    return out


@dataclass(frozen=True, eq=False)
class RecordedTrigger:
    """One trigger read back: the FrameSet (when its frames were kept) and the logged result."""

    frameset: FrameSet | None
    result: InspectionResult


@dataclass(frozen=True, eq=False)
class Recording:
    """A recording read back (:func:`read_run`)."""

    metadata: dict[str, dict[str, str]]
    triggers: list[RecordedTrigger]
    """Ordered by (triggered_ns, seq)."""
    attachments: dict[str, bytes]
    """By name."""

    def parts(self) -> list[RecordedPart]:
        """The parts created over the API it holds (:func:`recorded_parts`)."""
        return recorded_parts(self.metadata, self.attachments)


def read_recording(
    paths: Iterable[str | Path],
) -> tuple[dict[str, dict[str, str]], list[RecordedTrigger]]:
    """The metadata and the triggers of :func:`read_run`."""
    run = read_run(paths)
    return run.metadata, run.triggers


def read_run(paths: Iterable[str | Path]) -> Recording:
    """Read recorded files back into FrameSets and results, in trigger order.

    Works on finished and unfinished files alike (messages are read in file
    order, not through the index).

    Returns
    -------
    Recording
        Its metadata (name to {key: value}), triggers and attachments.
    """
    metadata: dict[str, dict[str, str]] = {}
    attachments: dict[str, bytes] = {}
    headers: dict[int, dict[str, Any]] = {}
    images: dict[tuple[int, str], np.ndarray] = {}
    results: list[InspectionResult] = []
    for path in paths:
        channels: dict[int, Channel] = {}
        schema_names: dict[int, str] = {}
        for rec in iter_records(path):
            if isinstance(rec, Schema):
                schema_names[rec.id] = rec.name
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Metadata):
                metadata[rec.name] = dict(rec.metadata)
            elif isinstance(rec, Attachment):
                attachments[rec.name] = rec.data
            elif isinstance(rec, Message) and rec.channel_id in channels:
                topic = channels[rec.channel_id].topic
                if topic == "/result":
                    results.append(InspectionResult.model_validate_json(rec.data))
                elif topic == "/frameset":
                    h = json.loads(rec.data)
                    headers[h["triggered_ns"]] = h
                elif topic.endswith("/image"):
                    cam = topic[1 : -len("/image")]
                    schema = schema_names.get(channels[rec.channel_id].schema_id, "")
                    images[(rec.log_time, cam)] = _decode_image(topic, schema, rec.data)
    from .protocol import Truth

    triggers = []
    for r in sorted(results, key=lambda r: (r.triggered_ns, r.seq)):
        h = headers.get(r.triggered_ns)
        fs = None
        if h is not None and h["seq"] == r.seq:
            cams = h["cameras"]
            if all((r.triggered_ns, c) in images for c in cams):
                fs = FrameSet(
                    line=h["line"],
                    station=h["station"],
                    part=h["part"],
                    serial=h["serial"],
                    seq=h["seq"],
                    triggered_ns=h["triggered_ns"],
                    calibration_id=h["calibration_id"],
                    images=[images[(r.triggered_ns, c)] for c in cams],
                    cameras=cams,
                    truth=None if h["truth"] is None else Truth.from_json(h["truth"]),
                    # Recordings from before the holographic head are of the flash rig.
                    sensor=h.get("sensor", "flash"),
                )
        triggers.append(RecordedTrigger(fs, r))
    return Recording(metadata, triggers, attachments)


def _decode_image(topic: str, schema: str, data: bytes) -> np.ndarray:
    if schema == "foxglove.RawImage":
        raw = RawImage()
        raw.ParseFromString(data)
        dtype = RAW_DTYPES.get(raw.encoding)
        if dtype is None or len(raw.data) != raw.height * raw.step or raw.step % dtype.itemsize:
            raise ValueError(
                f"{topic}: not a mono8 or mono16 image of {raw.height} rows of {raw.step}"
            )
        arr = np.frombuffer(raw.data, dtype).reshape(raw.height, raw.step // dtype.itemsize)
        return arr[:, : raw.width].astype(dtype.newbyteorder("="))
    comp = CompressedImage()
    comp.ParseFromString(data)
    img = cv2.imdecode(np.frombuffer(comp.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{topic}: image cannot be decoded")
    return img
