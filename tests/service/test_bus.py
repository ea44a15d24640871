"""Zenoh helpers on loopback: settings, BLOCK publishing, bounded subscribers, tokens, heartbeat."""

from __future__ import annotations

import json
import threading

import pytest
import zenoh
from linekit import client, free_port, peer

from service import bus


def test_settings_are_validated_and_scouting_is_off():
    cfg = json.loads(bus.make_config(peer(7447)).get_json("scouting/multicast/enabled"))
    assert cfg is False
    listen = json.loads(bus.make_config(peer(7447)).get_json("listen/endpoints"))
    assert listen == ["tcp/127.0.0.1:7447"]
    with pytest.raises(ValueError):
        bus.BusSettings(mode="client")  # a client needs somewhere to connect
    with pytest.raises(ValueError):
        bus.BusSettings(mode="mesh")
    with pytest.raises(ValueError):
        bus.BusSettings(listen=("localhost",))


def test_client_fails_fast_without_a_listener():
    with pytest.raises(RuntimeError, match="cannot open a zenoh client"):
        bus.open_session(client(free_port()))


def test_frames_arrive_in_order_with_block_and_ring_subscriber():
    port = free_port()
    got, done = [], threading.Event()

    def on_sample(sample):
        got.append(sample.payload.to_bytes())
        if len(got) == 20:
            done.set()

    with bus.open_session(peer(port)) as a, bus.open_session(client(port)) as b:
        sub = bus.RingSubscriber(a, "t/frames", on_sample, capacity=32)
        pub = bus.frame_publisher(b, "t/frames")
        assert pub.congestion_control == zenoh.CongestionControl.BLOCK
        assert bus.wait_for_subscribers(pub, 10)
        for i in range(20):
            pub.put(i.to_bytes(4, "little") * 1000)
        assert done.wait(10)
        sub.close()
        sub.close()  # idempotent
        pub.undeclare()
    assert [int.from_bytes(g[:4], "little") for g in got] == list(range(20))


def test_ring_subscriber_stays_bounded_when_the_reader_is_slow():
    port = free_port()
    release = threading.Event()
    got = []

    def slow(sample):
        release.wait(10)  # the reader is stuck: zenoh's ring must drop, not grow
        got.append(int.from_bytes(sample.payload.to_bytes(), "little"))

    with bus.open_session(peer(port)) as a, bus.open_session(client(port)) as b:
        sub = bus.RingSubscriber(a, "t/x", slow, capacity=3)
        pub = b.declare_publisher("t/x")
        assert bus.wait_for_subscribers(pub, 10)
        for i in range(50):
            pub.put(i.to_bytes(4, "little"))
        # Wait until the last one is in the ring (the reader holds at most one more).
        flushed = threading.Event()
        marker = bus.RingSubscriber(
            a,
            "t/x",
            lambda s: flushed.set() if s.payload.to_bytes() == (49).to_bytes(4, "little") else None,
            capacity=64,
        )
        pub.put((49).to_bytes(4, "little"))
        assert flushed.wait(10)
        release.set()
        marker.close()
        sub.close()
        pub.undeclare()
    assert len(got) <= 1 + 3 + 1 and got[-1] == 49


def test_liveliness_token_and_heartbeat():
    port = free_port()
    with bus.open_session(peer(port)) as a, bus.open_session(client(port)) as b:
        beats = b.declare_subscriber("t/status", zenoh.handlers.FifoChannel(16))
        live = b.liveliness().declare_subscriber(
            "@t/worker/*", zenoh.handlers.FifoChannel(16), history=True
        )
        token = a.liveliness().declare_token("@t/worker/w1")
        assert str(live.handler.recv().key_expr) == "@t/worker/w1"
        hb = bus.Heartbeat(a, "t/status", lambda: {"state": "ready"}, period_s=0.05)
        doc = json.loads(beats.handler.recv().payload.to_bytes())
        assert doc["state"] == "ready" and doc["time_ns"] > 0
        hb.close()
        token.undeclare()
        gone = live.handler.recv()
        assert gone.kind == zenoh.SampleKind.DELETE
        live.undeclare()
        beats.undeclare()
        assert bus.is_connected(b)
    assert not bus.is_connected(a)
