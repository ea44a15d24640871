"""Replay: a recorded run re-measured gives the same results; differences fail the command.

One short run on the flash rig is recorded twice (as logged, and with one
result tampered with); the tests read those two recordings.
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
from linekit import LINE, PART, PARTS_DIR, ROOT, STATION, demo, free_port, peer, pipeline, rig

from service import bus
from service.cli import main as cli
from service.config import PartSpec, load_line_config
from service.line import Station, recording_listener
from service.models import Status
from service.parts import PartRegistry
from service.pipeline import Pipeline
from service.protocol import Keys, decode_frameset, encode_frameset
from service.recorder import Recorder, read_recording, read_run
from service.replay import ReplayError, recorded_stages, replay
from service.station_parts import StationParts
from service.store import ResultStore
from service.worker import Job, JobQueue, Worker


def shift(outcome):
    """The result as another software would have logged it: deviations 1 um off."""
    r = outcome.result
    c = [p.model_copy(update={"deviation_mm": (p.deviation_mm or 0) + 1e-3}) for p in r.comparison]
    return type(outcome)(
        r.model_copy(update={"comparison": c}),
        outcome.points,
        outcome.distances,
        outcome.transform,
    )


def record_run(directory, trees, *, n=3, gap=1):
    """Record a short run through the worker on the flash rig; seq ``gap`` never arrives
    (a missed part). Returns the files of the recording and of a copy whose measured
    results are tampered with."""
    cfg = load_line_config(ROOT / "configs" / "line.toml")
    stages, part = demo(trees)
    station = Station(cfg, stages, {PART: part})
    logged, tampered = (
        Recorder(
            directory / name, "run", metadata=station.metadata(), calibrations=stages.calibrations()
        )  # fmt: skip
        for name in ("logged", "tampered")
    )

    def sink(outcome, fs):
        logged.record(outcome, fs)
        tampered.record(shift(outcome) if outcome.result.comparison else outcome, fs)

    w = Worker(pipeline(trees), JobQueue(8), [sink], line=LINE, station=STATION, missed_part=PART)
    r = rig(stages, part, defect_rate=0.5, seed=11)
    for seq in range(n):
        if seq == gap:
            continue
        w.handle(Job(encode_frameset(r.capture(seq, 1_800_000_000_000_000_000 + seq * 10**9)), 0))
    logged.close()
    tampered.close()
    return logged.files, tampered.files


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, trees):
    return record_run(tmp_path_factory.mktemp("rec"), trees)


@pytest.fixture(scope="module")
def recording(recordings):
    return recordings[0]


def test_replay_reproduces_every_result(recording, trees):
    seen: list[tuple[int, int]] = []
    report = replay(
        recording, parts_dir=PARTS_DIR, trees_dir=trees, progress=lambda *a: seen.append(a)
    )
    assert report.ok, report.summary()
    # The progress the CLI's bar draws: the count once read, then after each trigger.
    assert seen == [(0, 3), (1, 3), (2, 3), (3, 3)]
    assert report.triggers == 3 and report.replayed == 2 and report.not_replayable == 1
    assert report.same == 2
    assert report.max_transform_diff <= 1e-9 and report.max_deviation_diff_mm <= 1e-6


def test_cli_compare_fails_on_a_difference(tmp_path, recordings, trees, capsys):
    where = ["--parts-dir", str(PARTS_DIR), "--trees-dir", str(trees)]
    assert cli(["replay", str(recordings[1][0]), "--compare", *where]) == 1
    assert "DIFFERENT" in capsys.readouterr().out
    assert cli(["replay", str(tmp_path / "nope.mcap")]) == 2


def test_replay_refuses_a_changed_cad(tmp_path, recording):
    from mcap.writer import Writer

    # Rewrite the metadata with another CAD hash.
    files = recording
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
        replay([fake], parts_dir=PARTS_DIR, trees_dir=tmp_path)


def test_replay_matches_as_the_recording_did(recording):
    meta, _ = read_recording(recording)
    assert meta["rig"]["guided"] == "true"  # the line's default
    assert recorded_stages(meta).guided
    one_pass = {"rig": {**meta["rig"], "guided": "false"}}
    assert not recorded_stages(one_pass).guided
    # A recording from before the guided pass existed was measured in one pass.
    older = {"rig": {k: v for k, v in meta["rig"].items() if k != "guided"}}
    assert not recorded_stages(older).guided


def test_publish_replays_frames_onto_zenoh(recording):
    port = free_port()
    keys = Keys(LINE)
    got = []
    done = threading.Event()

    def on_frames(sample):
        got.append(decode_frameset(sample.payload.to_bytes()))
        if len(got) == 2:
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


def binary_ply(cad) -> bytes:
    """The CAD as a PLY file of doubles: read back, it hashes as ``cad`` does."""
    v, f = cad.vertices, cad.faces
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
        "property double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    faces = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, f
    return header.encode() + v.astype("<f8").tobytes() + faces.tobytes()


def test_a_part_created_over_the_api_is_replayed_from_the_recording_alone(tmp_path, trees):
    """The station takes a part from the store while it runs: the recording keeps its spec
    and CAD file with the first result measured with it, and replay measures with them,
    with no file of that part anywhere but in the recording (DESIGN 1.5)."""
    cfg = load_line_config(ROOT / "configs" / "line.toml")
    stages, part = demo(trees)
    # The demo panel's geometry under another name, as an upload (its tree is cached).
    own = part.spec.model_dump(exclude={"name", "cad", "panel"})
    spec = PartSpec(**own, name="bracket", cad="cad.ply")
    store = ResultStore(tmp_path / "results.sqlite")
    store.add_part("bracket", spec.model_dump_json(), binary_ply(part.cad))
    parts = {PART: part}
    registry = PartRegistry(trees, tmp_path / "station")
    recorder = Recorder(tmp_path / "rec", "run", metadata=Station(cfg, stages, parts).metadata(),
                        calibrations=stages.calibrations())  # fmt: skip
    station = StationParts(parts, store, registry, station=STATION, poll_s=3600,
                           listeners=[recording_listener(recorder)], close_store=True)  # fmt: skip
    w = Worker(Pipeline(stages, parts, line=LINE, station=STATION), JobQueue(4),
               [recorder.record], line=LINE, station=STATION, parts=station)  # fmt: skip
    r = rig(stages, part, defect_rate=0.5, seed=11)
    try:
        fs = r.capture(0, 1_800_000_000_000_000_000)
        w.handle(Job(encode_frameset(dataclasses.replace(fs, part="bracket")), 0))
        assert w.drain(300)
    finally:
        station.close()
        registry.close()
        recorder.close()
    run = read_run(recorder.files)
    [measured] = [t.result for t in run.triggers]
    assert measured.part == "bracket" and measured.status is not Status.error, measured.reason
    [kept] = run.parts()
    assert (kept.name, kept.revision, kept.cad) == ("bracket", 1, binary_ply(part.cad))
    assert "bracket.spec" not in run.metadata["cad"]  # not a part of the configuration
    report = replay(recorder.files, parts_dir=PARTS_DIR, trees_dir=trees)
    assert report.ok, report.summary()
    assert report.replayed == 1 and report.same == 1
