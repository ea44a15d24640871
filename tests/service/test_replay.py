"""Replay: a recorded run re-measured gives the same results; differences fail the command."""

from __future__ import annotations

import threading

import pytest
from linekit import LINE, PART, ROOT, STATION, demo, free_port, peer, pipeline, rig

from service import bus
from service.cli import main as cli
from service.config import load_line_config
from service.line import Station
from service.models import Status
from service.protocol import Keys, decode_frameset, encode_frameset
from service.recorder import Recorder, read_recording
from service.replay import ReplayError, replay
from service.worker import Job, JobQueue, Worker


def record_run(directory, *, n=5, tamper=None, gap=True):
    """Record a short run through the worker: one seq skipped (a missed part)."""
    cfg = load_line_config(ROOT / "configs" / "line.toml")
    stages, part = demo()
    station = Station(cfg, stages, {PART: part})
    rec = Recorder(
        directory, "run", metadata=station.metadata(), calibrations=stages.calibrations()
    )

    def sink(outcome, fs):
        if tamper is not None and outcome.result.seq == 1:
            outcome = tamper(outcome)
        rec.record(outcome, fs)

    w = Worker(pipeline(), JobQueue(8), [sink], line=LINE, station=STATION, missed_part=PART)
    r = rig(defect_rate=0.5, seed=11)
    for seq in range(n):
        if gap and seq == 2:
            continue
        w.handle(Job(encode_frameset(r.capture(seq, 1_800_000_000_000_000_000 + seq * 10**9)), 0))
    rec.close()
    return rec.files


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return record_run(tmp_path_factory.mktemp("rec"))


def test_replay_reproduces_every_result(recording):
    report = replay(recording, parts_dir=ROOT / "configs" / "parts")
    assert report.ok, report.summary()
    assert report.triggers == 5 and report.replayed == 4 and report.not_replayable == 1
    assert report.same == 4
    assert report.max_transform_diff <= 1e-9 and report.max_deviation_diff_mm <= 1e-6


def test_cli_compare_exit_codes(tmp_path, recording, capsys):
    assert cli(["replay", str(recording[0]), "--compare"]) == 0

    def shift(outcome):
        r = outcome.result
        c = [
            p.model_copy(update={"deviation_mm": (p.deviation_mm or 0) + 1e-3})
            for p in r.comparison
        ]
        return type(outcome)(
            r.model_copy(update={"comparison": c}),
            outcome.points_rig,
            outcome.distances,
            outcome.T_cad_rig,
        )

    tampered = record_run(tmp_path, n=3, tamper=shift, gap=False)
    assert cli(["replay", str(tampered[0]), "--compare"]) == 1
    assert "DIFFERENT" in capsys.readouterr().out
    assert cli(["replay", str(tmp_path / "nope.mcap")]) == 2


def test_replay_refuses_a_changed_cad(tmp_path):
    files = record_run(tmp_path, n=1, gap=False)
    from mcap.writer import Writer

    # Rewrite the metadata with another CAD hash.
    meta, _ = read_recording(files)
    meta["cad"][f"{PART}.cad_hash"] = "0" * 64
    fake = tmp_path / "fake.mcap"
    with fake.open("wb") as fh:
        w = Writer(fh)
        w.start()
        for name, data in meta.items():
            w.add_metadata(name, data)
        w.finish()
    with pytest.raises(ReplayError, match="CAD changed"):
        replay([fake], parts_dir=ROOT / "configs" / "parts")


def test_publish_replays_frames_onto_zenoh(recording):
    port = free_port()
    keys = Keys(LINE)
    got = []
    done = threading.Event()

    def on_frames(sample):
        got.append(decode_frameset(sample.payload.to_bytes()))
        if len(got) == 4:
            done.set()

    with bus.open_session(peer(port)) as session:
        sub = bus.RingSubscriber(session, keys.frames(STATION), on_frames, capacity=16)
        try:
            code = cli(
                [
                    "replay",
                    str(recording[0]),
                    "--publish",
                    "--speed",
                    "0",
                    "--zenoh-connect",
                    f"tcp/127.0.0.1:{port}",
                ]
            )
            assert code == 0 and done.wait(30)
        finally:
            sub.close()
    _, triggers = read_recording(recording)
    sent = [t.frameset for t in triggers if t.frameset is not None]
    assert [g.serial for g in got] == [s.serial for s in sent]
    assert all(t.result.status is not Status.missed for t in triggers if t.frameset)
