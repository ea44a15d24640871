"""The wire format of the line: FrameSet bytes and zenoh key expressions.

A FrameSet is one trigger's worth of camera images plus the metadata that
makes it traceable. It travels on ``<prefix>/<line>/<station>/frames`` as::

    offset  size  field
    0       4     magic b"INSF"
    4       2     version (uint16, little-endian): 1, or 2 for what version 1
                  cannot say (16-bit pixels, a sensor other than the flash rig)
    6       2     flags (uint16, little-endian), 0; readers ignore unknown bits
    8       4     header length H in bytes (uint32, little-endian)
    12      H     header: UTF-8 JSON object (see docs/protocol.md)
    12+H    ...   image payloads, concatenated in header order

The header lists every image with its size, pixel format and encoding (raw
``mono8`` or little-endian ``mono16`` rows, or a PNG file), and the byte
``length`` of its payload; version 2 also names the ``sensor``. A FrameSet
that version 1 can carry is written as version 1, so that readers of version
1 keep reading the flash rig's frames, and refuse (by its version) what they
could not read right. The
format is specified in ``docs/protocol.md`` precisely enough for a reader in
any language; this module is the reference implementation.

Names (line, station, part, serial) follow :mod:`service.names` (1 to 64
characters from ``[A-Za-z0-9._-]``, not dots alone) and are rejected at the
edge otherwise, so that a name can never add a level to a key expression,
match as a wildcard, or name a parent folder.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from inspection.defects import Defect, Dent
from inspection.panel import HoleShift

from .names import NAME_MAX_LEN, NAME_RULE, is_valid_name

MAGIC = b"INSF"
VERSION = 2
"""The newest version this module writes and reads; it reads every one of VERSIONS."""
VERSIONS = (1, 2)
PREAMBLE = struct.Struct("<4sHHI")
"""Magic, version, flags, header length: 12 bytes, little-endian."""

DEFAULT_PREFIX = "insp/v1"
ENCODINGS = ("raw", "png")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PIXEL_FORMATS = ("mono8", "mono16")
"""mono16 (version 2): two bytes per pixel, little-endian, as holographic cameras give."""
SENSORS = ("flash", "holography")
"""What took the images: the four-camera flash rig, or a holographic head (version 2)."""
_DTYPES: dict[str, np.dtype[Any]] = {"mono8": np.dtype(np.uint8), "mono16": np.dtype("<u2")}

# Generous upper bounds: a hostile or corrupt header must not make us allocate
# gigabytes before we notice.
MAX_HEADER_BYTES = 1 << 20
MAX_IMAGES = 16
MAX_SIDE_PX = 16384


class ProtocolError(ValueError):
    """Bytes or names that do not follow the wire format."""


# --------------------------------------------------------------------------- names and keys


def validate_name(value: object, what: str = "name") -> str:
    """Return ``value`` if it is a valid line, station, part or serial name.

    Raises
    ------
    ProtocolError
        Not a string, or not a name by :data:`service.names.NAME_RULE`.
    """
    if not isinstance(value, str):
        raise ProtocolError(f"{what} must be a string, got {type(value).__name__}")
    if not is_valid_name(value):
        shown = value if len(value) <= NAME_MAX_LEN else value[:NAME_MAX_LEN] + "..."
        raise ProtocolError(f"{what} {shown!r} is not a name: {NAME_RULE}")
    return value


def validate_prefix(prefix: str) -> str:
    """Return ``prefix`` if it is one or more valid names joined by ``/``."""
    if not isinstance(prefix, str) or not prefix:
        raise ProtocolError("key prefix must be a non-empty string")
    for chunk in prefix.split("/"):
        validate_name(chunk, "key prefix chunk")
    return prefix


@dataclass(frozen=True)
class Keys:
    """The key expressions of one line (DESIGN.md section 5).

    Parameters
    ----------
    line : str
    prefix : str
        Default ``insp/v1``.
    """

    line: str
    prefix: str = DEFAULT_PREFIX

    def __post_init__(self) -> None:
        validate_name(self.line, "line")
        validate_prefix(self.prefix)

    def frames(self, station: str) -> str:
        """``<prefix>/<line>/<station>/frames``: FrameSet bytes."""
        return f"{self.prefix}/{self.line}/{validate_name(station, 'station')}/frames"

    def result(self, station: str, part: str, serial: str) -> str:
        """``<prefix>/<line>/<station>/result/<part>/<serial>``: InspectionResult JSON."""
        return (
            f"{self.prefix}/{self.line}/{validate_name(station, 'station')}/result/"
            f"{validate_name(part, 'part')}/{validate_name(serial, 'serial')}"
        )

    def results(self, station: str = "*") -> str:
        """Selector for every result of a station (``*``: of every station)."""
        if station != "*":
            validate_name(station, "station")
        return f"{self.prefix}/{self.line}/{station}/result/**"

    def history(self, station: str) -> str:
        """``<prefix>/<line>/<station>/results``: queryable over the station's stored results."""
        return f"{self.prefix}/{self.line}/{validate_name(station, 'station')}/results"

    def alarm(self, station: str) -> str:
        """``<prefix>/<line>/<station>/alarm``: Alarm JSON."""
        return f"{self.prefix}/{self.line}/{validate_name(station, 'station')}/alarm"

    def alarms(self, station: str = "*") -> str:
        """Selector for the alarms of a station (``*``: of every station)."""
        if station != "*":
            validate_name(station, "station")
        return f"{self.prefix}/{self.line}/{station}/alarm"

    def status(self, station: str) -> str:
        """``<prefix>/<line>/<station>/status``: worker status and heartbeat (JSON)."""
        return f"{self.prefix}/{self.line}/{validate_name(station, 'station')}/status"

    def fired(self, station: str) -> str:
        """``<prefix>/<line>/<station>/fired``: the trigger source's count (JSON), so that a
        trigger whose FrameSet never came is answered even when no later one shows the gap."""
        return f"{self.prefix}/{self.line}/{validate_name(station, 'station')}/fired"

    def worker_token(self, station: str, worker_id: str) -> str:
        """``@<prefix>/<line>/<station>/worker/<id>``: liveliness token of one worker."""
        return (
            f"@{self.prefix}/{self.line}/{validate_name(station, 'station')}/worker/"
            f"{validate_name(worker_id, 'worker id')}"
        )

    def workers(self, station: str = "*") -> str:
        """Selector for the liveliness tokens of a station's workers."""
        if station != "*":
            validate_name(station, "station")
        return f"@{self.prefix}/{self.line}/{station}/worker/*"


def parse_result_key(key: str, prefix: str = DEFAULT_PREFIX) -> tuple[str, str, str, str]:
    """Split a result key into ``(line, station, part, serial)``."""
    head = prefix + "/"
    if not key.startswith(head):
        raise ProtocolError(f"key {key!r} does not start with {head!r}")
    parts = key[len(head) :].split("/")
    if len(parts) != 5 or parts[2] != "result":
        raise ProtocolError(f"{key!r} is not a result key")
    line, station, _, part, serial = parts
    for value, what in ((line, "line"), (station, "station"), (part, "part"), (serial, "serial")):
        validate_name(value, what)
    return line, station, part, serial


# --------------------------------------------------------------------------- FrameSet


def _vec3(obj: Any, what: str) -> tuple[float, float, float]:
    v = [float(c) for c in obj]
    if len(v) != 3:
        raise ProtocolError(f"{what} needs three numbers")
    return v[0], v[1], v[2]


def _dent_from_json(obj: dict[str, Any]) -> Dent:
    return Dent(
        _vec3(obj["center_mm"], "dent center_mm"),
        _vec3(obj["normal"], "dent normal"),
        float(obj["depth_mm"]),
        float(obj["radius_mm"]),
        float(obj.get("flat_mm", 0.0)),
    )


def _defect_to_json(defect: Defect) -> dict[str, Any]:
    return {
        "kind": defect.kind,
        "center_mm": list(defect.center_mm),
        "normal": list(defect.normal),
        "depth_mm": defect.depth_mm,
        "radius_mm": defect.radius_mm,
        "flat_mm": defect.flat_mm,
    }


_DEFECT_READERS: dict[str, Callable[[dict[str, Any]], Defect]] = {"dent": _dent_from_json}
"""Defect kind -> its reader; kinds not listed are skipped (written by a newer line)."""


@dataclass(frozen=True, eq=False)
class Truth:
    """What the simulator knows about a simulated part (absent for real parts).

    Attributes
    ----------
    T_rig_part : (4, 4) float64
        Pose of the part in the nominal rig's frame (maps part points to rig points).
    defects : tuple of inspection.defects.Defect
        Every defect injected into the part (part frame), in the order pressed;
        empty for a good part. Later kinds extend this list.
    holes : tuple of inspection.panel.HoleShift
        How far each of a generated panel's holes was made off its drawn one, in
        the design's order (empty: as drawn, or not a generated panel).
    """

    T_rig_part: np.ndarray
    defects: tuple[Defect, ...] = ()
    holes: tuple[HoleShift, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "T_rig_part": np.asarray(self.T_rig_part, dtype=np.float64).tolist(),
            "defects": [_defect_to_json(d) for d in self.defects],
            "holes": [{"dx_mm": h.dx_mm, "dy_mm": h.dy_mm, "dr_mm": h.dr_mm} for h in self.holes],
        }

    @classmethod
    def from_json(cls, obj: Any) -> Truth:
        """Read a truth record; one written before ``defects`` existed has a single
        ``defect`` (an object or null), read as a dent without a flat bottom."""
        if not isinstance(obj, dict):
            raise ProtocolError("truth must be a JSON object")
        try:
            T = np.asarray(obj["T_rig_part"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise ProtocolError(f"bad truth.T_rig_part: {exc}") from exc
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ProtocolError("truth.T_rig_part must be a finite 4x4 matrix")
        if "defects" in obj:
            records = obj["defects"]
        else:
            legacy = obj.get("defect")
            records = [] if legacy is None else [{"kind": "dent", **legacy}]
        if not isinstance(records, list):
            raise ProtocolError("truth.defects must be a list")
        defects = []
        for i, rec in enumerate(records):
            if not isinstance(rec, dict) or not isinstance(rec.get("kind"), str):
                raise ProtocolError(f"truth.defects[{i}] must be an object with a kind")
            reader = _DEFECT_READERS.get(rec["kind"])
            if reader is None:
                continue
            try:
                defects.append(reader(rec))
            except (KeyError, TypeError, ValueError) as exc:
                raise ProtocolError(f"bad truth.defects[{i}]: {exc}") from exc
        holes = obj.get("holes", [])
        if not isinstance(holes, list):
            raise ProtocolError("truth.holes must be a list")
        try:
            shifts = tuple(
                HoleShift(float(h["dx_mm"]), float(h["dy_mm"]), float(h["dr_mm"])) for h in holes
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ProtocolError(f"bad truth.holes: {exc}") from exc
        if not all(math.isfinite(v) for h in shifts for v in (h.dx_mm, h.dy_mm, h.dr_mm)):
            raise ProtocolError("truth.holes must hold finite numbers")
        return cls(T, tuple(defects), shifts)


@dataclass(frozen=True, eq=False)
class FrameSet:
    """One trigger: the rig's images and their metadata.

    Attributes
    ----------
    line, station, part, serial : str
        Names matching ``[A-Za-z0-9._-]+``. ``part`` is the part spec's name.
    seq : int
        Per-station sequence number, counting up by one per trigger from 0.
    triggered_ns : int
        Trigger time, ns since the Unix epoch, from the ingest host's clock.
    calibration_id : str
        Identifies the rig calibration the frames are meant to be measured with.
    images : list of (H, W) uint8 or uint16
        One image per camera, in the rig's camera order (uint16: mono16).
    cameras : list of str
        Camera names, one per image.
    truth : Truth or None
        Pose and injected defects of a simulated part.
    sensor : str
        One of :data:`SENSORS`.
    """

    line: str
    station: str
    part: str
    serial: str
    seq: int
    triggered_ns: int
    calibration_id: str
    images: list[np.ndarray]
    cameras: list[str] = field(default_factory=list)
    truth: Truth | None = None
    sensor: str = "flash"

    def __post_init__(self) -> None:
        validate_name(self.line, "line")
        validate_name(self.station, "station")
        validate_name(self.part, "part")
        validate_name(self.serial, "serial")
        for value, what in ((self.seq, "seq"), (self.triggered_ns, "triggered_ns")):
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 2**63:
                raise ProtocolError(f"{what} must be an integer in [0, 2**63), got {value!r}")
        if not isinstance(self.calibration_id, str) or len(self.calibration_id) > 256:
            raise ProtocolError("calibration_id must be a string of at most 256 characters")
        if not 1 <= len(self.images) <= MAX_IMAGES:
            raise ProtocolError(
                f"a FrameSet carries 1..{MAX_IMAGES} images, got {len(self.images)}"
            )
        if self.sensor not in SENSORS:
            raise ProtocolError(f"sensor must be one of {SENSORS}, got {self.sensor!r}")
        for i, img in enumerate(self.images):
            if (
                not isinstance(img, np.ndarray)
                or img.dtype not in (np.uint8, np.uint16)
                or img.ndim != 2
            ):
                raise ProtocolError(f"image {i} must be a (H, W) uint8 or uint16 array")
            if not (0 < img.shape[0] <= MAX_SIDE_PX and 0 < img.shape[1] <= MAX_SIDE_PX):
                raise ProtocolError(f"image {i} has an unsupported size {img.shape}")
        if not self.cameras:
            object.__setattr__(self, "cameras", [f"cam{i}" for i in range(len(self.images))])
        if len(self.cameras) != len(self.images):
            raise ProtocolError("one camera name per image")
        for name in self.cameras:
            validate_name(name, "camera")


def _pixel_format(img: np.ndarray) -> str:
    return "mono16" if img.dtype == np.uint16 else "mono8"


def wire_version(fs: FrameSet) -> int:
    """The oldest version that carries ``fs``: 1 for the flash rig's mono8 frames."""
    plain = fs.sensor == "flash" and all(img.dtype == np.uint8 for img in fs.images)
    return 1 if plain else 2


def _encode_image(img: np.ndarray, encoding: str) -> bytes:
    if encoding == "raw":
        return np.ascontiguousarray(img, dtype=_DTYPES[_pixel_format(img)]).tobytes()
    # Level 1: the images are noisy, higher levels cost time and save little.
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover - OpenCV fails only on unsupported arrays
        raise ProtocolError("PNG encoding failed")
    return buf.tobytes()


def encode_frameset(fs: FrameSet, *, encoding: str = "raw") -> bytes:
    """Serialise a FrameSet to its wire bytes.

    Parameters
    ----------
    fs : FrameSet
    encoding : {"raw", "png"}
        Both are lossless: ``raw`` is fastest, ``png`` is smaller.

    Returns
    -------
    bytes
    """
    if encoding not in ENCODINGS:
        raise ProtocolError(f"encoding must be one of {ENCODINGS}, got {encoding!r}")
    payloads = [_encode_image(img, encoding) for img in fs.images]
    header: dict[str, Any] = {
        "line": fs.line,
        "station": fs.station,
        "part": fs.part,
        "serial": fs.serial,
        "seq": fs.seq,
        "triggered_ns": fs.triggered_ns,
        "calibration_id": fs.calibration_id,
        "images": [
            {
                "camera": cam,
                "width": int(img.shape[1]),
                "height": int(img.shape[0]),
                "pixel_format": _pixel_format(img),
                "encoding": encoding,
                "length": len(p),
            }
            for cam, img, p in zip(fs.cameras, fs.images, payloads, strict=True)
        ],
        "truth": None if fs.truth is None else fs.truth.to_json(),
    }
    version = wire_version(fs)
    if version >= 2:
        header["sensor"] = fs.sensor
    head = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    return b"".join([PREAMBLE.pack(MAGIC, version, 0, len(head)), head, *payloads])


def read_header(data: bytes | bytearray | memoryview) -> tuple[dict[str, Any], int]:
    """Parse the preamble and JSON header.

    Returns
    -------
    header : dict
    payload_offset : int
        Where the first image's bytes start.

    Raises
    ------
    ProtocolError
    """
    buf = memoryview(data)
    if len(buf) < PREAMBLE.size:
        raise ProtocolError(f"truncated FrameSet: {len(buf)} bytes, the preamble alone is 12")
    magic, version, _flags, hlen = PREAMBLE.unpack_from(buf, 0)
    if magic != MAGIC:
        raise ProtocolError(f"not a FrameSet: magic {bytes(magic)!r}, expected {MAGIC!r}")
    if version not in VERSIONS:
        raise ProtocolError(
            f"unsupported FrameSet version {version} (this reader knows "
            f"{', '.join(map(str, VERSIONS))})"
        )
    if hlen > MAX_HEADER_BYTES or PREAMBLE.size + hlen > len(buf):
        raise ProtocolError(f"truncated FrameSet: header of {hlen} bytes does not fit")
    try:
        header = json.loads(bytes(buf[PREAMBLE.size : PREAMBLE.size + hlen]).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ProtocolError(f"FrameSet header is not UTF-8 JSON: {exc}") from exc
    except RecursionError as exc:
        raise ProtocolError("FrameSet header is JSON nested too deeply") from exc
    if not isinstance(header, dict):
        raise ProtocolError("FrameSet header must be a JSON object")
    return header, PREAMBLE.size + hlen


def frameset_version(data: bytes | bytearray | memoryview) -> int:
    """The version in a FrameSet's preamble (checked by :func:`read_header`)."""
    buf = memoryview(data)
    if len(buf) < PREAMBLE.size:
        raise ProtocolError(f"truncated FrameSet: {len(buf)} bytes, the preamble alone is 12")
    return int(PREAMBLE.unpack_from(buf, 0)[1])


def _decode_image(payload: memoryview, meta: dict[str, Any], i: int, version: int) -> np.ndarray:
    w, h = meta["width"], meta["height"]
    fmt = meta["pixel_format"]
    if fmt not in PIXEL_FORMATS or (fmt == "mono16" and version < 2):
        raise ProtocolError(f"image {i}: unsupported pixel_format {fmt!r} in version {version}")
    dtype = _DTYPES[fmt]
    if meta["encoding"] == "raw":
        if len(payload) != w * h * dtype.itemsize:
            raise ProtocolError(f"image {i}: {len(payload)} bytes for a {w}x{h} {fmt} image")
        return np.frombuffer(payload, dtype=dtype).reshape(h, w).astype(dtype.newbyteorder("="))
    if meta["encoding"] == "png":
        # The PNG's own size comes first, before anything is decoded: a small
        # payload can expand to gigabytes.
        if len(payload) < 24 or bytes(payload[:8]) != PNG_SIGNATURE:
            raise ProtocolError(f"image {i}: {len(payload)} bytes are not a PNG file")
        pw, ph = struct.unpack(">II", payload[16:24])
        if (pw, ph) != (w, h):
            raise ProtocolError(f"image {i}: the PNG is {pw}x{ph}, the header says {w}x{h}")
        img = cv2.imdecode(np.frombuffer(payload, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ProtocolError(f"image {i}: PNG payload cannot be decoded")
        if img.dtype != dtype or img.ndim != 2 or img.shape != (h, w):
            raise ProtocolError(
                f"image {i}: PNG is {img.dtype} {img.shape}, header says {h}x{w} {fmt}"
            )
        return img
    raise ProtocolError(f"image {i}: unknown encoding {meta['encoding']!r}")


def decode_frameset(
    data: bytes | bytearray | memoryview,
    *,
    cameras: Sequence[tuple[str, int, int]] | None = None,
) -> FrameSet:
    """Parse wire bytes into a FrameSet, validating everything.

    Parameters
    ----------
    data : bytes
    cameras : list of (name, width, height), optional
        The station's cameras: the header must announce one image of each
        one's size, checked before any image is decoded (a small PNG can
        decode to a gigabyte).

    Raises
    ------
    ProtocolError
        Wrong magic or version, truncated data, a header that does not match
        the payload or the cameras, invalid names, undecodable images, a
        version 1 FrameSet with mono16 images, a version 2 one without its
        ``sensor``.
    """
    header, offset = read_header(data)
    version = frameset_version(data)
    buf = memoryview(data)
    try:
        metas = header["images"]
        if not isinstance(metas, list) or not 1 <= len(metas) <= MAX_IMAGES:
            raise ProtocolError(f"header.images must list 1..{MAX_IMAGES} images")
        if cameras is not None:
            _check_cameras(metas, cameras)
        images = []
        names = []
        for i, meta in enumerate(metas):
            if not isinstance(meta, dict):
                raise ProtocolError(f"image {i}: metadata must be an object")
            for key in ("width", "height", "length"):
                v = meta[key]
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise ProtocolError(f"image {i}: {key} must be a non-negative integer")
            if not (0 < meta["width"] <= MAX_SIDE_PX and 0 < meta["height"] <= MAX_SIDE_PX):
                raise ProtocolError(f"image {i}: unsupported size {meta['width']}x{meta['height']}")
            end = offset + meta["length"]
            if end > len(buf):
                raise ProtocolError(f"truncated FrameSet: image {i} ends past the data")
            images.append(_decode_image(buf[offset:end], meta, i, version))
            names.append(meta.get("camera", f"cam{i}"))
            offset = end
        if offset != len(buf):
            raise ProtocolError(f"{len(buf) - offset} trailing bytes after the last image")
        truth = header.get("truth")
        sensor = header["sensor"] if version >= 2 else "flash"
        return FrameSet(
            line=header["line"],
            station=header["station"],
            part=header["part"],
            serial=header["serial"],
            seq=header["seq"],
            triggered_ns=header["triggered_ns"],
            calibration_id=header.get("calibration_id", ""),
            images=images,
            cameras=names,
            truth=None if truth is None else Truth.from_json(truth),
            sensor=sensor,
        )
    except KeyError as exc:
        raise ProtocolError(f"FrameSet header lacks the field {exc.args[0]!r}") from exc


def _check_cameras(metas: list[Any], cameras: Sequence[tuple[str, int, int]]) -> None:
    if len(metas) != len(cameras):
        raise ProtocolError(f"the FrameSet carries {len(metas)} images; the rig has {len(cameras)}")
    for i, (meta, (name, w, h)) in enumerate(zip(metas, cameras, strict=True)):
        size = (meta.get("width"), meta.get("height")) if isinstance(meta, dict) else None
        if size != (w, h):
            shown = f"{size[0]} x {size[1]} px" if size else "not described"
            raise ProtocolError(f"image {i} is {shown}; camera {name} takes {w} x {h} px")


def peek_identity(data: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Best-effort ``line, station, part, serial, seq, triggered_ns`` of bad bytes.

    A worker that cannot decode a FrameSet still wants to say which trigger the
    error belongs to. Fields that cannot be read, or are not valid, are left out.
    """
    try:
        header, _ = read_header(data)
    except ProtocolError:
        return {}
    out: dict[str, Any] = {}
    for key in ("line", "station", "part", "serial"):
        try:
            out[key] = validate_name(header.get(key), key)
        except ProtocolError:
            pass
    for key in ("seq", "triggered_ns"):
        v = header.get(key)
        if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2**63:
            out[key] = v
    if isinstance(header.get("calibration_id"), str):
        out["calibration_id"] = header["calibration_id"]
    return out
