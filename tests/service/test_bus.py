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
    """A reader stuck on one sample while more arrive then gets only the newest
    ``capacity``: zenoh's ring drops the oldest instead of growing, and the last
    sample published is delivered."""
    port, capacity, n = free_port(), 3, 50
    holding, release, fenced, last_read = (threading.Event() for _ in range(4))
    got = []

    def slow(sample):
        seq = int.from_bytes(sample.payload.to_bytes(), "little")
        holding.set()
        release.wait(10)  # the reader is stuck: zenoh's ring must drop, not grow
        got.append(seq)
        if seq == n - 1:
            last_read.set()

    with bus.open_session(peer(port)) as a, bus.open_session(client(port)) as b:
        sub = bus.RingSubscriber(a, "t/x", slow, capacity=capacity)
        # b's puts reach a over one link and a dispatches them in order, so once the
        # fence (a key `sub` does not match) is seen, every sample is in `sub`'s ring.
        fence_sub = bus.RingSubscriber(a, "t/fence", lambda s: fenced.set(), capacity=1)
        pub = bus.frame_publisher(b, "t/x")  # BLOCK: any loss is the ring's, not the link's
        fence = bus.frame_publisher(b, "t/fence")
        try:
            assert bus.wait_for_subscribers(pub, 10) and bus.wait_for_subscribers(fence, 10)
            pub.put((0).to_bytes(4, "little"))
            assert holding.wait(10)  # the reader holds sample 0; the ring is empty
            for i in range(1, n):
                pub.put(i.to_bytes(4, "little"))
            fence.put(b"")
            assert fenced.wait(10)
        finally:
            release.set()
        # close() would discard what still waits in the ring: read it all first.
        assert last_read.wait(10)
        fence_sub.close()
        sub.close()
        fence.undeclare()
        pub.undeclare()
    assert got == [0, *range(n - capacity, n)]


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
