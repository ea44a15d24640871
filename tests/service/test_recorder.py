"""MCAP recording: Foxglove schemas read back, crash safety, rotation and retention.

The recorded triggers are real: frames of the flash rig measured by the line's stages.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import pickle
import sys

import numpy as np
import pytest
from linekit import LINE, PART, STATION, demo, pipeline, rig
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader, make_reader
from mcap_protobuf.decoder import DecoderFactory

from inspection.defects import Dent
from service.models import InspectionResult, Status
from service.pipeline import Outcome, missed_result
from service.recorder import RecordedPart, Recorder, Retention, read_recording, read_run, recover

N = 3


@pytest.fixture(scope="module")
def outcomes(trees):
    stages, part = demo(trees)
    r, p = rig(stages, part, defect_rate=0.5, seed=3), pipeline(trees)
    out = []
    for seq in range(N):
        fs = r.capture(seq, 1_800_000_000_000_000_000 + seq * 10**9)
        out.append((p.run(fs), fs))
    return out


def metadata():
    return {"config": {"hash": "abc", "json": "{}"}, "cad": {f"{PART}.cad_hash": "123"}}


CALS = [
    {
        "name": "cam0",
        "width": 400,
        "height": 250,
        "K": [1, 0, 200, 0, 1, 125, 0, 0, 1],
        "T_camera_rig": np.eye(4).ravel().tolist(),
    }
]


def test_round_trip_with_foxglove_schemas(tmp_path, outcomes):
    rec = Recorder(tmp_path, "run", metadata=metadata(), calibrations=CALS)
    for o, fs in outcomes:
        rec.record(o, fs)
    rec.close()
    (path,) = rec.files
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        schemas = {s.name for s in summary.schemas.values()}
        assert {
            "foxglove.RawImage",
            "foxglove.PointCloud",
            "foxglove.FrameTransform",
            "foxglove.CameraCalibration",
            "InspectionResult",
        } <= schemas
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["config"]["hash"] == "abc"
        by_topic: dict[str, list] = {}
        for _schema, channel, message, decoded in reader.iter_decoded_messages(
            topics=["/cam0/image", "/cloud", "/part/pose", "/cam0/calibration"]
        ):
            by_topic.setdefault(channel.topic, []).append((message, decoded))
    assert len(by_topic["/cam0/image"]) == N and len(by_topic["/cam0/calibration"]) == 1
    msg, img = by_topic["/cam0/image"][0]
    assert img.encoding == "mono8" and msg.log_time == outcomes[0][1].triggered_ns
    np.testing.assert_array_equal(
        np.frombuffer(img.data, np.uint8).reshape(img.height, img.width), outcomes[0][1].images[0]
    )
    _, cloud = by_topic["/cloud"][0]
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "deviation"]
    arr = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 4)
    np.testing.assert_allclose(arr[:, :3], outcomes[0][0].points, atol=1e-3)
    np.testing.assert_allclose(arr[:, 3], outcomes[0][0].distances, atol=1e-5)
    _, pose = by_topic["/part/pose"][0]
    T_rig_cad = np.linalg.inv(outcomes[0][0].transform)
    assert pose.parent_frame_id == "rig"
    np.testing.assert_allclose(
        [pose.translation.x, pose.translation.y, pose.translation.z], T_rig_cad[:3, 3], atol=1e-9
    )
    # Results: JSON validating against the pydantic model, schema recorded alongside.
    with path.open("rb") as fh:
        reader = make_reader(fh)
        results = [(s, m) for s, _, m in reader.iter_messages(topics=["/result"])]
    assert json.loads(results[0][0].data)["title"] == "InspectionResult"
    assert [InspectionResult.model_validate_json(m.data) for _, m in results] == [
        o.result for o, _ in outcomes
    ]


@pytest.mark.parametrize("compression", ["none", "lz4", "zstd"])
@pytest.mark.parametrize("images", ["raw", "png"])
def test_every_recording_choice_reads_back_bit_for_bit(tmp_path, outcomes, images, compression):
    rec = Recorder(tmp_path, "choice", image_encoding=images, compression=compression)
    rec.record(*outcomes[0])
    rec.close()
    (path,) = rec.files
    with path.open("rb") as fh:
        reader = make_reader(fh)
        chunks = {c.compression for c in reader.get_summary().chunk_indexes}
        schemas = {s.name for s in reader.get_summary().schemas.values()}
    assert chunks == {"" if compression == "none" else compression}
    assert ("foxglove.CompressedImage" if images == "png" else "foxglove.RawImage") in schemas
    _, trig = read_recording(rec.files)
    for a, b in zip(trig[0].frameset.images, outcomes[0][1].images, strict=True):
        np.testing.assert_array_equal(a, b)


def test_unknown_recording_choices_are_refused(tmp_path):
    with pytest.raises(ValueError, match="compression must be"):
        Recorder(tmp_path, "bad", compression="gzip")
    with pytest.raises(ValueError, match="image_encoding must be"):
        Recorder(tmp_path, "bad", image_encoding="jpeg")
    bad = [{**CALS[0], "T_camera_rig": [1, 0, 0]}]
    with pytest.raises(ValueError, match="T_camera_rig must hold 16"):
        Recorder(tmp_path, "bad", calibrations=bad)


class _TruthBeforeTheList:
    """A truth as recordings made before ``defects`` held it: one ``defect`` or null."""

    def __init__(self, T: np.ndarray, dent: dict | None) -> None:
        self.T, self.dent = T, dent

    def to_json(self) -> dict:
        return {"T_rig_part": self.T.tolist(), "defect": self.dent}


def test_the_truth_reads_back_from_new_and_older_recordings(tmp_path, outcomes):
    (o, fs), (o2, fs2) = outcomes[:2]
    dent = {"center_mm": [1.0, 2.0, 30.0], "normal": [0.0, 0.0, 1.0], "depth_mm": 1.5,
            "radius_mm": 15.0}  # fmt: skip
    old = dataclasses.replace(fs2, truth=_TruthBeforeTheList(fs2.truth.T_rig_part, dent))
    rec = Recorder(tmp_path, "truth")
    rec.record(o, fs)
    rec.record(o2, old)
    rec.close()
    _, (new_trig, old_trig) = read_recording(rec.files)
    assert new_trig.frameset.truth.defects == fs.truth.defects
    np.testing.assert_array_equal(new_trig.frameset.truth.T_rig_part, fs.truth.T_rig_part)
    assert old_trig.frameset.truth.defects == (Dent((1.0, 2.0, 30.0), (0.0, 0.0, 1.0), 1.5, 15.0),)


def _record_and_die(directory: str, triggers: str) -> None:
    sys.path.insert(0, os.path.dirname(__file__))
    with open(triggers, "rb") as fh:
        outcomes = pickle.load(fh)
    rec = Recorder(directory, "killed")
    for o, fs in outcomes:
        rec.record(o, fs)
    os.kill(os.getpid(), 9)  # no finish(), no close: like a power cut


def test_killed_recorder_leaves_a_readable_file_and_recover_repairs_it(tmp_path, outcomes):
    triggers = tmp_path / "triggers.pickle"
    triggers.write_bytes(pickle.dumps(outcomes))
    out = tmp_path / "mcap"
    ctx = multiprocessing.get_context("spawn")
    proc = ctx.Process(target=_record_and_die, args=(str(out), str(triggers)))
    proc.start()
    proc.join(120)
    assert proc.exitcode == -9
    (path,) = out.glob("*.mcap")
    with path.open("rb") as fh:
        with pytest.raises(Exception):  # noqa: B017 - no summary in a killed file
            make_reader(fh).get_summary().statistics  # noqa: B018
    got = []
    with path.open("rb") as fh:
        # The plain mcap reader, in file order, gets every result up to the torn end.
        with pytest.raises(EndOfFile):
            for _, c, m in NonSeekingReader(fh).iter_messages(log_time_order=False):
                got += [m] if c.topic == "/result" else []
    assert len(got) == N
    _, recorded = read_recording([path])
    assert [t.result.seq for t in recorded] == list(range(N)) and all(t.frameset for t in recorded)
    fixed = recover(path)
    with fixed.path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary.statistics.message_count == fixed.messages > 0
    fixed.path.unlink()
    # The next recorder in the directory finishes the torn file in place, while its own
    # open file stays out of reach of another recorder's recovery.
    nxt = Recorder(out, "next")
    try:
        assert [r.path for r in nxt.recovered] == [path]
        with path.open("rb") as fh:
            assert make_reader(fh).get_summary().statistics.message_count == fixed.messages
        assert Recorder(out, "third").recovered == []  # "next" is open and locked
    finally:
        nxt.close()


def test_a_part_created_over_the_api_is_kept_once_per_file_and_survives_a_recovery(
    tmp_path, outcomes
):
    """Its CAD file as an attachment (with its media type) and its spec as a metadata
    record, written with the first result measured with it, read back as they went in."""
    first = outcomes[0][0].result
    kept = RecordedPart(name=PART, revision=3, spec='{"name": "demo-panel"}', cad_file="cad.stl",
                        cad=b"solid x\nendsolid x\n", cad_hash=first.cad_hash,
                        tree_hash=first.tree_hash, spec_version=first.spec_version)  # fmt: skip
    rec = Recorder(tmp_path / "mcap", "run", metadata=metadata(), calibrations=CALS)
    rec.set_part(PART, None, kept)
    for o, fs in outcomes:
        rec.record(o, fs)
    (path,) = rec.files
    fixed = recover(path, tmp_path / "recovered.mcap")  # what a killed recorder leaves
    rec.close()
    for p in (path, fixed.path):
        with p.open("rb") as fh:
            [a] = list(make_reader(fh).iter_attachments())
        assert (a.name, a.media_type, a.data) == (kept.attachment, "model/stl", kept.cad)
        [got] = read_run([p]).parts()
        assert vars(got) == vars(kept)


def test_rotation_by_time(tmp_path, outcomes):
    """Files are finished after ``rotate_s`` too: every file but the open one is indexed."""
    rec = Recorder(tmp_path, "aged", rotate_s=0.0)
    try:
        for o, fs in outcomes:
            rec.record(o, fs)
        finished = rec.files[:-1]
        assert len(finished) == len(outcomes)
        for path in finished:
            with path.open("rb") as fh:
                assert make_reader(fh).get_summary().statistics.message_count > 0
    finally:
        rec.close()


def test_the_budget_holds_after_every_trigger_not_only_at_rotation(tmp_path, outcomes):
    one = Recorder(tmp_path / "one", "one")
    one.record(*outcomes[0])
    one.close()
    size = one.files[0].stat().st_size
    budget = int(2.5 * size)
    rec = Recorder(tmp_path / "kept", "budget", rotate_bytes=10**12,
                   retention=Retention(max_total_bytes=budget))  # fmt: skip
    try:
        for o, fs in outcomes * 3:
            rec.record(o, fs)
            used = sum(p.stat().st_size for p in (tmp_path / "kept").glob("*.mcap"))
            assert used <= budget
    finally:
        rec.close()


def test_rotation_by_size(tmp_path, outcomes):
    rec = Recorder(tmp_path, "rot", rotate_bytes=1)
    for o, fs in outcomes:
        rec.record(o, fs)
    rec.close()
    assert len(rec.files) == len(outcomes) + 1
    _, triggers = read_recording(rec.files)
    assert [t.result for t in triggers] == [o.result for o, _ in outcomes]


@pytest.mark.parametrize(
    "policy, kept",
    [("all", "all"), ("failures", "failed"), ("every_nth", "nth")],
)
def test_retention_policy_decides_whose_frames_are_kept(tmp_path, outcomes, policy, kept):
    rec = Recorder(tmp_path, policy, retention=Retention(record=policy, every_nth=2))
    flags = [rec.record(o, fs) for o, fs in outcomes]
    miss = missed_result(line=LINE, station=STATION, seq=9, triggered_ns=1, reason="x")
    assert rec.record(Outcome(miss), None) is False
    rec.close()
    failed = [o.result.status is not Status.passed for o, _ in outcomes]
    expect = {
        "all": [True] * N,
        "failures": failed,
        "every_nth": [f or i % 2 == 0 for i, f in enumerate(failed)],
    }[policy]
    assert flags == expect
    _, triggers = read_recording(rec.files)
    assert len(triggers) == N + 1  # results are always recorded


def test_size_budget_deletes_oldest_files(tmp_path, outcomes):
    # A budget just above what the last two triggers take (one file each).
    free = Recorder(tmp_path / "free", "budget", rotate_bytes=1)
    for o, fs in outcomes:
        free.record(o, fs)
    free.close()
    budget = sum(p.stat().st_size for p in free.files[-3:]) + 1000
    rec = Recorder(
        tmp_path / "kept", "budget", rotate_bytes=1, retention=Retention(max_total_bytes=budget)
    )
    for o, fs in outcomes:
        rec.record(o, fs)
    rec.close()
    left = sorted((tmp_path / "kept").glob("*.mcap"))
    assert sum(p.stat().st_size for p in left) <= budget
    assert left and left[-1] == rec.files[-1] and rec.files[0] not in left


def test_alarms_are_recorded_and_the_recording_locates_a_result(tmp_path, outcomes):
    from service.models import Alarm
    from service.recordings import locate

    rec = Recorder(tmp_path, "run", metadata=metadata())
    (outcome, fs) = outcomes[0]
    rec.record(outcome, fs)
    alarm = Alarm(kind="spc_rule", message="centre beyond 3 sigma", triggered_ns=fs.triggered_ns,
                  line=LINE, station=STATION, raised_ns=fs.triggered_ns + 5, feature="centre",
                  rule="nelson1")  # fmt: skip
    rec.record_alarm(alarm)
    r = outcome.result
    open_file = locate(tmp_path, r.id, r.triggered_ns)  # still being written: read from its start
    assert open_file is not None and not open_file.finished and "/result" in open_file.topics
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    with path.open("rb") as fh:
        got = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(fh).iter_messages(
            topics=["/alarm"])]  # fmt: skip
    assert [(t, ns) for t, ns, _ in got] == [("/alarm", alarm.raised_ns)]
    assert Alarm.model_validate_json(got[0][2]) == alarm
    found = locate(tmp_path, r.id, r.triggered_ns)  # finished: through its index
    assert found is not None and found.finished and found.file == path.name
    assert found.start_ns == found.end_ns == r.triggered_ns
    assert "/cam0/image" in found.topics or "/result" in found.topics
    assert locate(tmp_path, "no-such-id", r.triggered_ns) is None


def test_the_recording_being_written_is_searched_chunk_by_chunk(tmp_path, outcomes):
    from service.recordings import locate

    rec = Recorder(tmp_path, "run", metadata=metadata())
    for outcome, fs in outcomes:
        rec.record(outcome, fs)
    # Each trigger finishes its chunk: a search unpacks only the one that holds it, and
    # finds what the index of the finished file finds.
    live = [locate(tmp_path, o.result.id, o.result.triggered_ns) for o, _ in outcomes]
    rec.close()
    done = [locate(tmp_path, o.result.id, o.result.triggered_ns) for o, _ in outcomes]
    assert all(x is not None and not x.finished for x in live)
    assert all(x is not None and x.finished for x in done)
    assert [(x.file, x.start_ns, x.topics) for x in live] == [
        (x.file, x.start_ns, x.topics) for x in done
    ]
    assert len({x.start_ns for x in live}) == len(outcomes) > 1
