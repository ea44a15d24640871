"""The FrameSet wire format: round trips, validation, and a reader built from the doc alone."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from inspection.defects import Dent
from service.protocol import (
    FrameSet,
    Keys,
    ProtocolError,
    Truth,
    decode_frameset,
    encode_frameset,
    parse_result_key,
    peek_identity,
    read_header,
    validate_name,
)


def make_frameset(seed: int = 0, *, truth: bool = True, shape=(48, 64)) -> FrameSet:
    rng = np.random.default_rng(seed)
    images = [rng.integers(0, 256, size=shape, dtype=np.uint8) for _ in range(4)]
    T = np.eye(4)
    T[:3, 3] = rng.normal(size=3)
    return FrameSet(
        line="demo",
        station="s1",
        part="panel",
        serial=f"P-{seed:06d}",
        seq=seed,
        triggered_ns=1_795_340_000_123_456_789 + seed,
        calibration_id="rig-abc",
        images=images,
        truth=Truth(T, (Dent((1.0, 2.0, 3.0), (0.0, 0.0, 1.0), 0.8, 12.0, 4.0),))
        if truth
        else None,
    )


def doc_reader(data: bytes) -> tuple[dict, list[bytes]]:
    """A reader written from docs/protocol.md alone (struct + json)."""
    magic, version, _flags, hlen = struct.unpack_from("<4sHHI", data, 0)
    assert magic == b"INSF" and version == 1
    header = json.loads(data[12 : 12 + hlen].decode("utf-8"))
    offset = 12 + hlen
    payloads = []
    for meta in header["images"]:
        payloads.append(data[offset : offset + meta["length"]])
        offset += meta["length"]
    assert offset == len(data)
    return header, payloads


@pytest.mark.parametrize("encoding", ["raw", "png"])
@pytest.mark.parametrize("truth", [True, False])
def test_round_trip_is_lossless(encoding, truth):
    fs = make_frameset(3, truth=truth)
    back = decode_frameset(encode_frameset(fs, encoding=encoding))
    for name in (
        "line",
        "station",
        "part",
        "serial",
        "seq",
        "triggered_ns",
        "calibration_id",
        "cameras",
    ):
        assert getattr(back, name) == getattr(fs, name)
    assert all(np.array_equal(a, b) for a, b in zip(fs.images, back.images, strict=True))
    if truth:
        np.testing.assert_array_equal(back.truth.T_rig_part, fs.truth.T_rig_part)
        assert back.truth.defects == fs.truth.defects  # Dent records compare by value
    else:
        assert back.truth is None


def test_the_truth_lists_every_injected_defect_and_reads_older_recordings():
    """The truth is a list that later kinds extend: kinds this reader does not know
    are skipped. A truth written before the list (one ``defect``, or null) still reads."""
    dents = (
        Dent((1.0, 2.0, 3.0), (0.0, 0.0, 1.0), 0.8, 12.0),
        Dent((-5.0, 0.0, 3.0), (0.0, 0.6, 0.8), -0.3, 9.0, 2.0),
    )
    truth = Truth(np.eye(4), dents)
    as_json = json.loads(json.dumps(truth.to_json()))
    assert [d["kind"] for d in as_json["defects"]] == ["dent", "dent"]
    assert Truth.from_json(as_json).defects == dents
    newer = dict(as_json, defects=[{"kind": "hole_shift", "dx_mm": 0.2}, *as_json["defects"]])
    assert Truth.from_json(newer).defects == dents
    old = {"T_rig_part": np.eye(4).tolist(), "defect": {"center_mm": [1, 2, 3],
           "normal": [0, 0, 1], "depth_mm": 0.8, "radius_mm": 12.0}}  # fmt: skip
    assert Truth.from_json(old).defects == (dents[0],)
    assert Truth.from_json(dict(old, defect=None)).defects == ()
    fs = make_frameset(5)
    header, _ = read_header(encode_frameset(fs))
    assert header["truth"]["defects"][0]["flat_mm"] == 4.0


def test_doc_reader_parses_raw_frames():
    fs = make_frameset(1)
    header, payloads = doc_reader(encode_frameset(fs))
    assert header["triggered_ns"] == fs.triggered_ns and header["seq"] == 1
    for meta, payload, img in zip(header["images"], payloads, fs.images, strict=True):
        assert (meta["pixel_format"], meta["encoding"]) == ("mono8", "raw")
        arr = np.frombuffer(payload, np.uint8).reshape(meta["height"], meta["width"])
        assert np.array_equal(arr, img)


def test_preamble_is_little_endian():
    data = encode_frameset(make_frameset(0))
    assert data[:4] == b"INSF" and data[4:6] == b"\x01\x00"
    hlen = int.from_bytes(data[8:12], "little")
    assert data[12 + hlen - 1 : 12 + hlen] == b"}"


def corruptions():
    good = encode_frameset(make_frameset(2))
    hlen = int.from_bytes(good[8:12], "little")
    header = json.loads(good[12 : 12 + hlen])

    def with_header(**changes):
        h = dict(header, **changes)
        body = json.dumps(h).encode()
        return struct.pack("<4sHHI", b"INSF", 1, 0, len(body)) + body + good[12 + hlen :]

    bad_img = [dict(m) for m in header["images"]]
    bad_img[0]["width"] += 1

    png = encode_frameset(make_frameset(2), encoding="png")
    plen = int.from_bytes(png[8:12], "little")
    png_header = json.loads(png[12 : 12 + plen])
    first = png_header["images"][0]["length"]

    def with_png(images, payload):
        body = json.dumps(dict(png_header, images=images)).encode()
        return struct.pack("<4sHHI", b"INSF", 1, 0, len(body)) + body + payload

    empty_png = [dict(png_header["images"][0], length=0), *png_header["images"][1:]]
    wider = [dict(m, width=m["width"] + 1) for m in png_header["images"]]
    return {
        "header_nested_deeply": struct.pack("<4sHHI", b"INSF", 1, 0, 200_000)
        + b"[" * 100_000
        + b"]" * 100_000,
        "png_of_length_0": with_png(empty_png, png[12 + plen + first :]),
        "png_not_a_png": with_png(png_header["images"], b"\0" * first + png[12 + plen + first :]),
        "png_of_another_size": with_png(wider, png[12 + plen :]),
        "empty": b"",
        "short": good[:7],
        "magic": b"XXXX" + good[4:],
        "version": good[:4] + b"\x03\x00" + good[6:],
        "header_too_long": good[:8] + (10**6).to_bytes(4, "little") + good[12:],
        "header_not_json": good[:12] + b"{" * hlen + good[12 + hlen :],
        "header_is_list": struct.pack("<4sHHI", b"INSF", 1, 0, 2) + b"[]",
        "truncated_payload": good[:-1],
        "trailing": good + b"\0",
        "bad_serial": with_header(serial="a/b"),
        "wildcard_station": with_header(station="*"),
        "missing_seq": with_header(seq=None),
        "negative_seq": with_header(seq=-1),
        "size_mismatch": with_header(images=bad_img),
        "no_images": with_header(images=[]),
        "bad_truth": with_header(truth={"T_rig_part": [[1, 2], [3, 4]]}),
        "bad_defect": with_header(
            truth={"T_rig_part": np.eye(4).tolist(), "defects": [{"kind": "dent", "depth_mm": 1}]}
        ),
        "defect_without_kind": with_header(
            truth={"T_rig_part": np.eye(4).tolist(), "defects": [{"depth_mm": 1}]}
        ),
        "defects_not_a_list": with_header(truth={"T_rig_part": np.eye(4).tolist(), "defects": {}}),
        "unknown_encoding": with_header(
            images=[dict(m, encoding="jpeg") for m in header["images"]]
        ),
    }


@pytest.mark.parametrize("name", sorted(corruptions()))
def test_malformed_framesets_raise_protocol_error(name):
    with pytest.raises(ProtocolError):
        decode_frameset(corruptions()[name])


def test_peek_identity_of_bad_bytes_keeps_valid_fields():
    good = encode_frameset(make_frameset(5))
    ident = peek_identity(good[:-10])
    assert ident["serial"] == "P-000005" and ident["seq"] == 5
    assert peek_identity(b"garbage") == {}


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "a b", "é", "x" * 65, None, 3])
def test_names_are_restricted(bad):
    with pytest.raises(ProtocolError):
        validate_name(bad)


def test_keys():
    k = Keys("demo")
    assert k.frames("s1") == "insp/v1/demo/s1/frames"
    assert k.result("s1", "panel", "P-1") == "insp/v1/demo/s1/result/panel/P-1"
    assert k.results() == "insp/v1/demo/*/result/**"
    assert k.status("s1") == "insp/v1/demo/s1/status"
    assert k.worker_token("s1", "w-1") == "@insp/v1/demo/s1/worker/w-1"
    assert parse_result_key(k.result("s1", "panel", "P-1")) == ("demo", "s1", "panel", "P-1")
    assert Keys("demo", prefix="plant7/insp/v1").frames("s2") == "plant7/insp/v1/demo/s2/frames"
    with pytest.raises(ProtocolError):
        Keys("demo", prefix="/insp")
    with pytest.raises(ProtocolError):
        k.result("s1", "panel", "P/1")
    with pytest.raises(ProtocolError):
        parse_result_key("insp/v1/demo/s1/frames")


def test_frameset_rejects_bad_images():
    with pytest.raises(ProtocolError):
        FrameSet("l", "s", "p", "x", 0, 0, "", [np.zeros((4, 4), np.float32)])
    with pytest.raises(ProtocolError):
        FrameSet("l", "s", "p", "x", 0, 0, "", [])
