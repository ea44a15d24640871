"""A holographic station: ``inspection run`` on configs/line-holography.toml, seen from outside.

One line runs for the module (small holograms, a short trigger period): its
FrameSets and results are read on zenoh, its results over REST, its
recording with the mcap reader, and the recording is replayed.
"""

from __future__ import annotations

import json
import math
import os
import pickle
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
import zenoh
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from linekit import ROOT, client, free_port
from mcap.reader import make_reader

from service import bus
from service.config import ConfigError, load_line_config, load_part_spec
from service.ingest import FixtureSettings, SimPart, SimulatedHead
from service.parts import load_part, load_part_cad
from service.pipeline import HoloRig, Pipeline, error_result, holography_stages
from service.protocol import FrameSet, decode_frameset, frameset_version
from service.recorder import Recorder, read_recording
from service.replay import Tolerances, recorded_stages, replay
from service.results import Outcome
from service.worker import result_from_json

PIXELS = 128
LINE, STATION, PART = "line1", "holo1", "holo-plate"
WANTED = 4  # results whose FrameSet the test saw


def line_file(tmp_path: Path, trees: Path) -> Path:
    """configs/line-holography.toml with small holograms, a short period, the repo's parts
    and the session's tree cache."""
    text = (ROOT / "configs" / "line-holography.toml").read_text()
    for old, new in [
        ("pixels = 256 ", f"pixels = {PIXELS} "),
        ("trigger_period_s = 1.0", "trigger_period_s = 0.4"),
        ('parts_dir = "parts"', f'parts_dir = "{ROOT / "configs" / "parts"}"'),
        ("metrics_port = 9465", "metrics_port = 0"),
        ('data_dir = "runs/holography"', f'data_dir = "runs/holography"\ntrees_dir = "{trees}"'),
    ]:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / "line-holography.toml"
    path.write_text(text)
    return path


def get_json(url: str) -> tuple[int, Any]:
    with urllib.request.urlopen(url, timeout=10) as resp:
        return resp.status, json.loads(resp.read())


@pytest.fixture(scope="module")
def line(tmp_path_factory, trees) -> dict[str, Any]:
    """Run the line until WANTED results of FrameSets seen on zenoh came in, read its REST
    API, stop it with SIGINT; what was seen, and where its data went."""
    tmp = tmp_path_factory.mktemp("holo-line")
    port, http_port = free_port(), free_port()
    data = tmp / "data"
    config = line_file(tmp, trees)
    run = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "run", "--config", str(config),
         "--data-dir", str(data), "--http-port", str(http_port),
         "--zenoh-listen", f"tcp/127.0.0.1:{port}"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    frames: dict[str, bytes] = {}
    results: dict[str, Any] = {}
    rest: dict[str, Any] = {}
    try:
        assert run.stdout is not None
        for text in run.stdout:
            if text.strip().startswith("data:"):
                break  # parts loaded, head calibrated, API up, ingest triggering
        else:
            pytest.fail(f"the line did not start: {run.stderr.read()[-3000:]}")  # type: ignore[union-attr]
        prefix = f"insp/v1/{LINE}/{STATION}"
        with bus.open_session(client(port)) as session:
            fsub = session.declare_subscriber(f"{prefix}/frames", zenoh.handlers.FifoChannel(64))
            rsub = session.declare_subscriber(f"{prefix}/result/**", zenoh.handlers.FifoChannel(64))
            # A result comes after its FrameSet: wait on the results, then take the frames
            # that came before (the line triggers until it is stopped).
            while len(set(frames) & set(results)) < WANTED and len(results) < 4 * WANTED:
                doc = result_from_json(rsub.handler.recv().payload.to_bytes())
                results[doc.serial] = doc
                s = fsub.handler.try_recv()
                while s is not None:
                    raw = s.payload.to_bytes()
                    frames[decode_frameset(raw).serial] = raw
                    s = fsub.handler.try_recv()
            fsub.undeclare()
            rsub.undeclare()
        base = f"http://127.0.0.1:{http_port}"
        for serial in set(frames) & set(results):
            code, doc = get_json(f"{base}/v1/inspections/{results[serial].id}")
            assert code == 200
            rest[serial] = doc
        # The colour map of a measured part, from the deviations the line kept.
        any_id = next(iter(results.values())).id
        with urllib.request.urlopen(f"{base}/v1/inspections/{any_id}/colormap.png") as resp:
            rest["colormap"] = (resp.status, resp.headers["content-type"], resp.read()[:8])
    finally:
        if run.poll() is None:
            run.send_signal(signal.SIGINT)
        try:
            code = run.wait(60)
        except subprocess.TimeoutExpired:
            run.kill()
            raise
    assert code == 0, run.stderr.read()[-3000:]  # type: ignore[union-attr]
    seen = sorted(set(frames) & set(results))
    assert len(seen) >= WANTED, (sorted(frames), sorted(results))
    return dict(
        frames={s: frames[s] for s in seen},
        results={s: results[s] for s in seen},
        rest=rest,
        mcap=sorted((data / "mcap").glob("*.mcap")),
        trees=trees,
    )


def test_frames_on_zenoh_are_single_mono16_holograms(line):
    for serial, raw in line["frames"].items():
        fs = decode_frameset(raw)
        assert frameset_version(raw) == 2 and fs.sensor == "holography"
        assert len(fs.images) == 1 and fs.images[0].dtype == np.uint16
        assert fs.images[0].shape == (PIXELS, PIXELS) and fs.images[0].max() > 255
        assert fs.part == PART and fs.serial == serial
        # The part in its fixture, within the fixture's play (50 um, 2 mrad).
        T = fs.truth.T_rig_part
        assert abs(T[2, 3]) <= 0.05 and np.allclose(T[:2, 3], 0.0)
        assert np.abs(T[:3, :3] - np.eye(3)).max() <= 2.1e-3


def test_results_on_zenoh_and_rest_agree_and_are_measured(line):
    assert line["rest"]["colormap"] == (200, "image/png", b"\x89PNG\r\n\x1a\n")
    ids = set()
    for serial, r in line["results"].items():
        assert r.status.value in ("pass", "fail"), (r.status, r.reason)
        assert r.part == PART and r.calibration_id and r.cad_hash and r.tree_hash
        assert {c.name for c in r.comparison} == {"pad", "plate"}
        assert r.rms_mm is not None and r.rms_mm < 0.02
        assert set(r.timings_ms) >= {"hologram", "align", "deviations"}
        # The fit's transform is T_cad_head: near the fixture's pose (identity).
        T = np.asarray(r.transform)
        fs = decode_frameset(line["frames"][serial])
        # The fit finds where the part truly lay (its truth), to micrometres in height.
        T_true_cad_head = np.linalg.inv(fs.truth.T_rig_part)
        assert abs(T[2, 3] - T_true_cad_head[2, 3]) < 0.005
        doc = line["rest"][serial]
        assert doc["id"] == r.id and doc["status"] == r.status.value
        assert doc["transform"] == r.transform and doc["calibration_id"] == r.calibration_id
        ids.add(r.id)
    assert len(ids) == len(line["results"])


def _messages(paths: list[Path]) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = {}
    for path in paths:
        with path.open("rb") as fh:
            for _, channel, message in make_reader(fh).iter_messages():
                out.setdefault(channel.topic, []).append(message)
    return out


def _raw(message: Any) -> RawImage:
    img = RawImage()
    img.ParseFromString(message.data)
    return img


def test_recording_holds_the_hologram_its_phase_and_deviation_maps(line):
    msgs = _messages(line["mcap"])
    by_time = {json.loads(m.data)["id"]: m.log_time for m in msgs["/result"]}
    images = {m.log_time: _raw(m) for m in msgs["/holo/image"]}
    phases = {m.log_time: _raw(m) for m in msgs["/maps/phase"]}
    deviations = {m.log_time: _raw(m) for m in msgs["/maps/deviation"]}
    headers = {m.log_time: json.loads(m.data) for m in msgs["/frameset"]}
    for serial, r in line["results"].items():
        t = by_time[r.id]
        assert headers[t]["sensor"] == "holography" and headers[t]["serial"] == serial
        img = images[t]
        assert (img.encoding, img.width, img.height, img.step) == ("mono16", PIXELS, PIXELS, 256)
        sent = decode_frameset(line["frames"][serial]).images[0]
        assert np.array_equal(np.frombuffer(img.data, "<u2").reshape(PIXELS, PIXELS), sent)
        phase = np.frombuffer(phases[t].data, "<f4").reshape(PIXELS, PIXELS)
        dev = np.frombuffer(deviations[t].data, "<f4").reshape(PIXELS, PIXELS)
        assert phases[t].encoding == deviations[t].encoding == "32FC1"
        # The phase is wrapped; the deviations are the result's, pixel for pixel.
        assert np.nanmax(np.abs(phase)) <= np.pi + 1e-6
        measured = np.isfinite(dev)
        assert measured.sum() == r.field.points - r.field.far > PIXELS**2 / 2
        assert np.isfinite(phase[measured]).all()
        # Around each comparison point the map holds what the point pooled.
        x, y = np.meshgrid(*(np.arange(PIXELS) - (PIXELS - 1) / 2,) * 2)
        x, y = x * 18.0 / PIXELS, y * 18.0 / PIXELS
        for c, (cx, cy) in zip(r.comparison, [(5.0, -4.0), (-5.0, 4.0)], strict=True):
            near = measured & (np.hypot(x - cx, y - cy) < 1.5)
            assert np.median(dev[near]) == pytest.approx(c.deviation_mm, abs=0.003), c.name


def test_the_recording_says_the_pose_started_from_the_gradient_field(line):
    # The demo line's default: replay must measure the same way.
    metadata, _ = read_recording(line["mcap"])
    assert metadata["rig"]["coarse_pose"] == "true"
    assert recorded_stages(metadata).remake.coarse_pose is True


def test_replay_reproduces_the_results_bit_for_bit(line):
    report = replay(
        line["mcap"],
        parts_dir=ROOT / "configs" / "parts",
        trees_dir=line["trees"],
        tolerances=Tolerances(transform=0.0, deviation_mm=0.0),
    )
    assert report.replayed >= len(line["results"]) and report.not_replayable == 0
    assert report.differences == [] and report.same == report.replayed
    assert report.max_transform_diff == 0.0 and report.max_deviation_diff_mm == 0.0


# --------------------------------------------------------------------------- without the line


@pytest.fixture(scope="module")
def stages():
    from inspection.holography import HoloHead

    rig = HoloRig.simulated(HoloHead.small_field(PIXELS))
    return holography_stages(rig.calibrate(), T_head_cad=np.eye(4), truth=rig)


@pytest.fixture(scope="module")
def plate(trees):
    spec = load_part_spec(ROOT / "configs" / "parts" / f"{PART}.toml")
    return load_part(spec, ROOT / "configs" / "parts", trees)


def _head(stages, defect_rate: float) -> SimulatedHead:
    cad = load_part_cad(load_part_spec(ROOT / "configs" / "parts" / f"{PART}.toml"), ROOT)
    return SimulatedHead(
        stages,
        [SimPart.from_cad(PART, cad)],
        line=LINE,
        station=STATION,
        settings=FixtureSettings(T_head_cad=np.eye(4), defect_rate=defect_rate, seed=3),
    )


def test_the_simulated_head_is_seeded_and_its_dents_are_measured_where_its_truth_says(
    stages, plate
):
    head = _head(stages, defect_rate=1.0)
    a, b = head.capture(7, 10), head.capture(7, 10)
    assert np.array_equal(a.images[0], b.images[0]) and a.serial == b.serial
    assert not np.array_equal(a.images[0], head.capture(3, 10).images[0])
    (dent,) = a.truth.defects
    # Seed 3, seq 7: a dent on the plate, clear of the CAD's edges (whose band is not measured).
    assert dent.center_mm[0] < -1.5 and dent.center_mm[1] > 1.5
    m = stages.measure(plate, a.images)
    dev = m.maps["deviation"]
    x, y = stages.rig.head.grid()
    centre = np.linalg.inv(m.transform) @ np.array([*dent.center_mm, 1.0])
    r = np.hypot(x - centre[0], y - centre[1])
    # The deepest measured pixels lie at the dent's centre, as deep as its truth.
    core = np.isfinite(dev) & (r < 0.2 * dent.radius_mm)
    clear = np.isfinite(dev) & (r > 1.5 * dent.radius_mm)
    assert core.any() and clear.sum() > 1000
    assert np.median(dev[core]) == pytest.approx(-dent.depth_mm, abs=0.25 * dent.depth_mm + 0.01)
    assert abs(np.median(dev[clear])) < 0.005


def test_the_holographic_stages_measure_the_same_in_another_process(stages, plate):
    fs = _head(stages, defect_rate=0.0).capture(0, 10)
    remade = pickle.loads(pickle.dumps(stages.remake))(1)
    assert remade.name == "holography" and remade.calibration_id == stages.calibration_id
    here, there = stages.measure(plate, fs.images), remade.measure(plate, fs.images)
    assert np.array_equal(here.transform, there.transform)
    assert np.array_equal(here.maps["deviation"], there.maps["deviation"], equal_nan=True)


def test_a_part_tilted_a_few_degrees_is_measured_only_with_the_coarse_pose(stages, plate):
    from inspection.holography import HoloCalibration
    from inspection.holography.shape import _pose_update

    # 3 degrees about y and 1.8 about x, 20 um high: beyond what the phase pose alone finds.
    T_head_part = _pose_update(np.array([0.02, math.tan(math.radians(3.0)), 0.0314]))
    mesh = trimesh.Trimesh(plate.cad.vertices, plate.cad.faces, process=False)
    fs = FrameSet(
        line=LINE, station=STATION, part=PART, serial="tilted", seq=0, triggered_ns=1,
        calibration_id=stages.calibration_id, cameras=["holo"], sensor="holography",
        images=[stages.rig.record(mesh, T_head_part, None, 1)],
    )  # fmt: skip
    calib = HoloCalibration.from_toml(stages.calibration_toml)
    phase_only = holography_stages(calib, T_head_cad=np.eye(4), coarse_pose=False)
    assert stages.remake.coarse_pose and not phase_only.remake.coarse_pose
    found = Pipeline(stages, {PART: plate}).run(fs).result
    assert found.status.value == "pass", found.reason
    # T_cad_head T_head_part is the identity in height and tilts (the plate's in-plane
    # turn is the fit's weak direction, whatever the start).
    E = np.asarray(found.transform) @ T_head_part
    assert abs(E[2, 3]) < 0.005 and np.abs(E[2, :2]).max() < 1e-3
    lost = Pipeline(phase_only, {PART: plate}).run(fs).result
    assert lost.status.value != "pass"


def test_config_maps_the_coarse_pose_onto_the_stages_and_replay_onto_old_recordings(
    tmp_path, stages
):
    from service.line import holo_stages_for

    (tmp_path / "holo.toml").write_text(stages.calibration_toml)
    path = tmp_path / "line.toml"
    section = '[station]\nsensor = "holography"\n\n[holography]\ncalibration = "holo.toml"\n'
    for text, want in [("", True), ("coarse_pose = false\n", False)]:
        path.write_text(section + f"pixels = {PIXELS}\n" + text)
        cfg = load_line_config(path)
        assert cfg.head().coarse_pose is want
        assert holo_stages_for(cfg).remake.coarse_pose is want
    path.write_text(section + f"pixels = {PIXELS}\ncoarse_pose = 2\n")
    with pytest.raises(ConfigError, match="coarse_pose"):
        load_line_config(path)
    # A recording from before the key was measured without the coarse pose.
    rig = {"stages": "holography", "calibration_toml": stages.calibration_toml,
           "T_head_cad": json.dumps(np.eye(4).tolist())}  # fmt: skip
    for meta, want in [({}, False), ({"coarse_pose": "true"}, True)]:
        again = recorded_stages({"rig": rig | meta})
        assert again.remake.coarse_pose is want


def test_a_hologram_of_another_size_is_an_error_result(stages, plate):
    fs = _head(stages, defect_rate=0.0).capture(0, 10)
    small = FrameSet(
        line=LINE, station=STATION, part=PART, serial="s2", seq=1, triggered_ns=2,
        calibration_id=stages.calibration_id, images=[fs.images[0][:64, :64].copy()],
        sensor="holography",
    )  # fmt: skip
    r = Pipeline(stages, {PART: plate}).run(small).result
    assert r.status.value == "error" and "128x128 mono16" in r.reason


def test_a_flash_frameset_is_refused_by_a_holographic_station(stages):
    fs = FrameSet(
        line=LINE, station=STATION, part=PART, serial="s1", seq=0, triggered_ns=1,
        calibration_id="", images=[np.zeros((8, 8), np.uint8)] * 4,
    )  # fmt: skip
    r = Pipeline(stages, {}).run(fs).result
    assert r.status.value == "error"
    assert "flash sensor" in r.reason and "holography" in r.reason


def test_config_refuses_a_holography_section_on_a_flash_station(tmp_path):
    path = tmp_path / "line.toml"
    path.write_text('[station]\nsensor = "flash"\n\n[holography]\npixels = 128\n')
    with pytest.raises(ConfigError, match="holography"):
        load_line_config(path)
    path.write_text('[station]\nsensor = "holography"\n\n[holography]\npixels = 127\n')
    with pytest.raises(ConfigError, match="even"):
        load_line_config(path)
    path.write_text('[station]\nsensor = "laser"\n')
    with pytest.raises(ConfigError, match="sensor"):
        load_line_config(path)


@pytest.mark.parametrize("encoding", ["raw", "png"])
def test_a_mono16_frameset_and_its_maps_are_recorded_and_read_back(tmp_path, encoding):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 4096, (32, 48)).astype(np.uint16)
    fs = FrameSet(
        line=LINE, station=STATION, part=PART, serial="s3", seq=0, triggered_ns=5,
        calibration_id="c", images=[image], cameras=["holo"], sensor="holography",
    )  # fmt: skip
    maps = {"phase": np.where(image > 2000, 1.5, np.nan), "deviation": np.full((32, 48), -0.01)}
    result = error_result(line=LINE, station=STATION, seq=0, triggered_ns=5, reason="r",
                          part=PART, serial="s3")  # fmt: skip
    rec = Recorder(tmp_path, "run", image_encoding=encoding)
    rec.record(Outcome(result, maps=maps), fs)
    rec.close()
    files = sorted(tmp_path.glob("*.mcap"))
    _, (trigger,) = read_recording(files)
    back = trigger.frameset
    assert back is not None and back.sensor == "holography" and back.cameras == ["holo"]
    assert back.images[0].dtype == np.uint16 and np.array_equal(back.images[0], image)
    msgs = _messages(files)
    phase = _raw(msgs["/maps/phase"][0])
    values = np.frombuffer(phase.data, "<f4").reshape(32, 48)
    assert np.array_equal(np.isnan(values), np.isnan(maps["phase"]))
    assert np.all(values[~np.isnan(values)] == 1.5)


def test_config_reads_the_heads_calibration_file_at_load(tmp_path, stages):
    cal = tmp_path / "holo.toml"
    cal.write_text(stages.calibration_toml)
    path = tmp_path / "line.toml"
    section = '[station]\nsensor = "holography"\n\n[holography]\ncalibration = "holo.toml"\n'
    path.write_text(section + f"pixels = {PIXELS}\n")
    assert load_line_config(path).holo_calibration_path() == cal
    path.write_text(section + "pixels = 256\n")
    with pytest.raises(ConfigError, match="is for 128 px"):
        load_line_config(path)
    cal.write_text(stages.calibration_toml.replace("[residual]", "[residual]\nextra = 1"))
    path.write_text(section + f"pixels = {PIXELS}\n")
    with pytest.raises(ConfigError, match="unknown keys"):
        load_line_config(path)
    cal.unlink()
    with pytest.raises(ConfigError, match="no such file"):
        load_line_config(path)
