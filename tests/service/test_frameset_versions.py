"""FrameSet version 2: 16-bit images and the sensor, written only where version 1 cannot."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from service.protocol import (
    FrameSet,
    ProtocolError,
    decode_frameset,
    encode_frameset,
    frameset_version,
)


def frameset(images: list[np.ndarray], sensor: str = "flash") -> FrameSet:
    return FrameSet(
        line="demo",
        station="holo1",
        part="plate",
        serial="P-000001",
        seq=1,
        triggered_ns=1_795_340_000_000_000_000,
        calibration_id="b6968f5d5bbddf11",
        images=images,
        sensor=sensor,
    )


@pytest.fixture(scope="module")
def hologram() -> np.ndarray:
    # 12-bit values: most of them above what one byte holds.
    return np.random.default_rng(0).integers(0, 4096, size=(40, 48), dtype=np.uint16)


def test_the_flash_rigs_frames_stay_version_1():
    rng = np.random.default_rng(1)
    fs = frameset([rng.integers(0, 256, size=(16, 24), dtype=np.uint8) for _ in range(4)])
    data = encode_frameset(fs)
    assert frameset_version(data) == 1
    header = json.loads(data[12 : 12 + struct.unpack_from("<I", data, 8)[0]])
    assert "sensor" not in header
    back = decode_frameset(data)
    assert back.sensor == "flash"
    assert all(np.array_equal(a, b) for a, b in zip(back.images, fs.images, strict=True))


@pytest.mark.parametrize("encoding", ["raw", "png"])
def test_a_holographic_mono16_frameset_round_trips_as_version_2(hologram, encoding):
    fs = frameset([hologram], sensor="holography")
    data = encode_frameset(fs, encoding=encoding)
    assert frameset_version(data) == 2
    header = json.loads(data[12 : 12 + struct.unpack_from("<I", data, 8)[0]])
    assert header["sensor"] == "holography"
    assert header["images"][0]["pixel_format"] == "mono16"
    if encoding == "raw":  # little-endian, two bytes per pixel, rows first
        payload = data[len(data) - header["images"][0]["length"] :]
        assert payload == hologram.astype("<u2").tobytes()
    back = decode_frameset(data)
    assert back.sensor == "holography"
    assert back.images[0].dtype == np.uint16
    assert np.array_equal(back.images[0], hologram)


def test_a_reader_of_version_1_refuses_version_2_by_its_version(hologram):
    """The rule every reader follows (docs/protocol.md): a version it does not know is
    refused. A reader of version 1 sees 2 as this reader sees 3."""
    data = encode_frameset(frameset([hologram], sensor="holography"))
    _, version, _, _ = struct.unpack_from("<4sHHI", data, 0)
    assert version == 2
    newer = data[:4] + struct.pack("<H", 3) + data[6:]
    with pytest.raises(ProtocolError, match="unsupported FrameSet version 3"):
        decode_frameset(newer)


def _rewrite(data: bytes, version: int, **changes: object) -> bytes:
    hlen = struct.unpack_from("<I", data, 8)[0]
    header = json.loads(data[12 : 12 + hlen])
    for key, value in changes.items():
        if value is None:
            header.pop(key, None)
        else:
            header[key] = value
    head = json.dumps(header).encode()
    return struct.pack("<4sHHI", b"INSF", version, 0, len(head)) + head + data[12 + hlen :]


def test_what_version_2_adds_is_refused_where_it_does_not_belong(hologram):
    data = encode_frameset(frameset([hologram], sensor="holography"))
    with pytest.raises(ProtocolError, match="mono16"):
        decode_frameset(_rewrite(data, 1, sensor=None))  # version 1 has no mono16
    with pytest.raises(ProtocolError, match="sensor"):
        decode_frameset(_rewrite(data, 2, sensor=None))
    with pytest.raises(ProtocolError, match="sensor"):
        decode_frameset(_rewrite(data, 2, sensor="lidar"))
    hlen = struct.unpack_from("<I", data, 8)[0]
    meta = json.loads(data[12 : 12 + hlen])["images"][0]
    short = _rewrite(data[:-1], 2, images=[dict(meta, length=meta["length"] - 1)])
    with pytest.raises(ProtocolError, match="bytes for a 48x40 mono16"):
        decode_frameset(short)  # half a pixel short
    with pytest.raises(ProtocolError, match="sensor"):
        frameset([hologram], sensor="lidar")
    with pytest.raises(ProtocolError, match="uint8 or uint16"):
        frameset([hologram.astype(np.float32)])
