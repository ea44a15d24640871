"""A line subscriber written from docs/protocol.md alone: zenoh, json and struct, nothing of ours.

Usage: python doc_subscriber.py ENDPOINT LINE N
Prints one JSON line per InspectionResult and per FrameSet received (a summary
of what it parsed) and exits after N results of parts whose frames it received
(one that joins the line between a part's frames and its result counts the next).
"""

import json
import struct
import sys

import zenoh


def parse_frameset(data: bytes) -> dict:
    magic, version, _flags, hlen = struct.unpack_from("<4sHHI", data, 0)
    if magic != b"INSF" or version != 1:
        raise ValueError("not a version-1 FrameSet")
    header = json.loads(data[12 : 12 + hlen].decode("utf-8"))
    offset = 12 + hlen
    sizes = []
    for meta in header["images"]:
        payload = data[offset : offset + meta["length"]]
        offset += meta["length"]
        if meta["encoding"] == "raw":
            assert meta["pixel_format"] == "mono8"
            assert len(payload) == meta["width"] * meta["height"]
        else:
            assert payload[:8] == b"\x89PNG\r\n\x1a\n"
        sizes.append([meta["height"], meta["width"]])
    if offset != len(data):
        raise ValueError("trailing bytes")
    return {"kind": "frameset", "seq": header["seq"], "serial": header["serial"], "sizes": sizes}


def main() -> int:
    endpoint, line, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    results = 0
    framed = set()  # serials whose FrameSet arrived
    with zenoh.open(cfg) as session:
        sub = session.declare_subscriber(f"insp/v1/{line}/**", zenoh.handlers.FifoChannel(256))
        print(json.dumps({"kind": "ready"}), flush=True)
        while results < n:
            sample = sub.handler.recv()
            key = str(sample.key_expr).split("/")
            data = sample.payload.to_bytes()
            if key[-1] == "frames":
                frameset = parse_frameset(data)
                framed.add(frameset["serial"])
                print(json.dumps(frameset), flush=True)
            elif len(key) == 7 and key[4] == "result":
                r = json.loads(data)
                assert (r["part"], r["serial"]) == (key[5], key[6])
                assert r["status"] in ("pass", "fail", "not_measurable", "error", "missed")
                fields = (
                    "id",
                    "line",
                    "station",
                    "part",
                    "serial",
                    "seq",
                    "triggered_ns",
                    "status",
                    "transform",
                    "comparison",
                    "timings_ms",
                    "spec_version",
                    "cad_hash",
                    "tree_hash",
                    "calibration_id",
                    "software_version",
                    "schema_version",
                )
                print(json.dumps({"kind": "result", **{f: r[f] for f in fields}}), flush=True)
                results += r["serial"] in framed
        sub.undeclare()
    ours = sorted(m for m in sys.modules if m.split(".")[0] in ("service", "inspection"))
    print(json.dumps({"kind": "done", "our_modules": ours}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
