"""A recording as Foxglove reads it, checked by a reader that is not ours.

The file is read with the mcap package's reader and every protobuf message is
decoded from the schema stored in the file itself (its FileDescriptorSet, through
google.protobuf's descriptor pool and message factory), never through our
recorder or the foxglove schema package. The fields are then checked as Foxglove's
3D and Image panels use them: the transform tree (rig to each camera, rig to the
part's CAD), the calibrations in the cameras' own frames, the cloud's pose, the CAD
as a scene entity, the markers and the log. A second check reads the same file with
the MCAP project's TypeScript reader where Node.js and that package are at hand.

The recorded triggers are real: frames of the flash rig measured by the line's stages,
recorded by the station's own recorder (configs/line.toml's storage settings).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from linekit import PART, ROOT, demo, pipeline, rig
from mcap.reader import make_reader

from inspection import Rig
from service.config import load_line_config
from service.line import Station
from service.models import InspectionResult

N = 3
LAYOUT = ROOT / "docs" / "foxglove-layout.json"
NODE_READER = Path(__file__).with_name("mcap_reader.mjs")


def message_classes(path: Path) -> dict[int, type]:
    """Schema id -> message class, built from the FileDescriptorSet each schema stores."""
    out = {}
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    for sid, schema in summary.schemas.items():
        if schema.encoding != "protobuf":
            continue
        fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
        pool = descriptor_pool.DescriptorPool()
        pending = list(fds.file)
        while pending:  # dependencies first, whatever order the set lists them in
            ready = [f for f in pending if all(_has_file(pool, d) for d in f.dependency)]
            assert ready, f"{schema.name}: the schema's files depend on files it lacks"
            for f in ready:
                pool.Add(f)
                pending.remove(f)
        out[sid] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    return out


def _has_file(pool: descriptor_pool.DescriptorPool, name: str) -> bool:
    try:
        pool.FindFileByName(name)
        return True
    except KeyError:
        return False


def read(path: Path) -> dict[str, list]:
    """Topic -> [(schema name, log_time, decoded message or JSON document)], in log time."""
    classes = message_classes(path)
    by_topic: dict[str, list] = {}
    with path.open("rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=True):
            assert schema is not None, channel.topic
            if channel.message_encoding == "protobuf":
                cls = classes[schema.id]
                assert cls.DESCRIPTOR.full_name == schema.name
                msg = cls.FromString(message.data)
            else:
                assert channel.message_encoding == "json"
                msg = json.loads(message.data)
            by_topic.setdefault(channel.topic, []).append((schema.name, message.log_time, msg))
    return by_topic


def quat_to_matrix(q) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix(tf) -> np.ndarray:
    """T_parent_child of a FrameTransform."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(tf.rotation)
    T[:3, 3] = tf.translation.x, tf.translation.y, tf.translation.z
    return T


@pytest.fixture(scope="module")
def recorded(trees, tmp_path_factory):
    """Three triggers (defects on every part) recorded by the station's own recorder; the
    second file of a recorder that rotates after every trigger too."""
    stages, part = demo(trees)
    r, p = rig(stages, part, defect_rate=1.0, seed=5), pipeline(trees)
    triggers = []
    for seq in range(N):
        fs = r.capture(seq, 1_800_000_000_000_000_000 + seq * 10**9)
        triggers.append((p.run(fs), fs))
    cfg = load_line_config(ROOT / "configs" / "line.toml")
    station = Station(cfg, stages, {PART: part})
    out = tmp_path_factory.mktemp("foxglove")
    rec = station.recorder(out / "one")
    for o, fs in triggers:
        rec.record(o, fs)
    rec.close()
    rotating = station.recorder(out / "rotating")
    rotating.rotate_bytes = 1
    for o, fs in triggers:
        rotating.record(o, fs)
    rotating.close()
    (path,) = rec.files
    return path, rotating.files[:-1], triggers


@pytest.fixture(scope="module")
def topics(recorded):
    return read(recorded[0])


def test_every_camera_has_a_static_transform_from_the_rig(recorded, topics):
    path, _, _ = recorded
    calibrated = Rig.default()
    assert len(calibrated.cameras) == 4
    for cam in calibrated.cameras:
        (sent,) = topics[f"/{cam.name}/transform"]  # once per file
        schema, _, tf = sent
        assert schema == "foxglove.FrameTransform"
        assert (tf.parent_frame_id, tf.child_frame_id) == ("rig", cam.name)
        T_rig_cam = matrix(tf)
        # OpenCV's extrinsics map rig points into the camera: x_cam = R x_rig + t.
        np.testing.assert_allclose(T_rig_cam[:3, :3], np.asarray(cam.R).T, atol=1e-9)
        np.testing.assert_allclose(
            T_rig_cam[:3, 3], -np.asarray(cam.R).T @ np.ravel(cam.t), atol=1e-6
        )


def test_calibrations_are_in_the_camera_frames(topics, recorded):
    _, _, triggers = recorded
    calibrated = Rig.default()
    rng = np.random.default_rng(0)
    in_volume = rng.uniform([-300, -200, 0], [300, 200, 150], size=(50, 3))
    for i, cam in enumerate(calibrated.cameras):
        (sent,) = topics[f"/{cam.name}/calibration"]
        schema, _, cal = sent
        assert schema == "foxglove.CameraCalibration"
        assert cal.frame_id == cam.name and cal.distortion_model == "plumb_bob"
        K = np.array(cal.K).reshape(3, 3)
        np.testing.assert_allclose(K, cam.K)
        np.testing.assert_allclose(cal.D, np.ravel(cam.dist))
        np.testing.assert_array_equal(np.array(cal.R).reshape(3, 3), np.eye(3))
        P = np.array(cal.P).reshape(3, 4)
        np.testing.assert_allclose(P, np.hstack([K, np.zeros((3, 1))]))
        h, w = triggers[0][1].images[i].shape
        assert (cal.width, cal.height) == (w, h)
        # What Foxglove draws: rig points through the recorded transform, then P, land
        # where the calibrated camera projects them (distortion aside).
        (tf,) = [m for _, _, m in topics[f"/{cam.name}/transform"]]
        T_cam_rig = np.linalg.inv(matrix(tf))
        x = P @ (T_cam_rig @ np.c_[in_volume, np.ones(len(in_volume))].T)
        uv = (x[:2] / x[2]).T
        rvec, _ = cv2.Rodrigues(np.asarray(cam.R))
        want, _ = cv2.projectPoints(in_volume, rvec, np.ravel(cam.t), K, np.zeros(5))
        np.testing.assert_allclose(uv, want.reshape(-1, 2), atol=1e-6)


def test_images_are_in_their_calibrations_frames(topics):
    transforms = {m.child_frame_id for t in topics if t.endswith("/transform")
                  for _, _, m in topics[t]}  # fmt: skip
    cameras = [t.split("/")[1] for t in topics if t.endswith("/image")]
    assert len(cameras) == 4
    for cam in cameras:
        images = topics[f"/{cam}/image"]
        assert len(images) == N
        ((_, _, cal),) = topics[f"/{cam}/calibration"]
        for schema, log_time, img in images:
            assert schema in ("foxglove.RawImage", "foxglove.CompressedImage")
            assert img.frame_id == cal.frame_id == cam
            # The per-file records come first in log time: the panel has them for every image.
            assert log_time >= topics[f"/{cam}/calibration"][0][1]
        assert cam in transforms


def test_the_cloud_has_a_pose_and_the_part_a_transform(topics, recorded):
    _, _, triggers = recorded
    clouds = topics["/cloud"]
    assert len(clouds) == N
    for (schema, _, cloud), (outcome, _) in zip(clouds, triggers, strict=True):
        assert schema == "foxglove.PointCloud" and cloud.frame_id == "rig"
        assert cloud.HasField("pose")
        p, q = cloud.pose.position, cloud.pose.orientation
        assert (p.x, p.y, p.z, q.x, q.y, q.z, q.w) == (0, 0, 0, 0, 0, 0, 1)
        fields = {f.name: (f.offset, f.type) for f in cloud.fields}
        float32 = 7  # foxglove.PackedElementField.NumericType.FLOAT32
        assert fields == {n: (4 * i, float32) for i, n in enumerate(["x", "y", "z", "deviation"])}
        assert cloud.point_stride == 16 and len(cloud.data) == 16 * len(outcome.points)
    poses = topics["/part/pose"]
    assert len(poses) == sum(o.transform is not None for o, _ in triggers) > 0
    for (_, log_time, tf), (outcome, fs) in zip(poses, triggers, strict=True):
        assert (tf.parent_frame_id, tf.child_frame_id) == ("rig", "part_cad")
        assert log_time == fs.triggered_ns
        np.testing.assert_allclose(matrix(tf), np.linalg.inv(outcome.transform), atol=1e-6)


def test_the_cad_is_a_scene_entity_in_the_part_frame(topics, recorded, trees):
    _, rotated, _ = recorded
    _, part = demo(trees)
    (sent,) = topics["/part/cad"]  # once per part type per file
    schema, _, update = sent
    assert schema == "foxglove.SceneUpdate"
    (entity,) = update.entities
    assert entity.frame_id == "part_cad" and entity.id == f"cad/{PART}" and entity.frame_locked
    (tri,) = entity.triangles
    V, F = part.cad.vertices, part.cad.faces
    assert len(tri.points) == len(V) and len(tri.indices) == 3 * len(F)
    np.testing.assert_array_equal(np.array(tri.indices).reshape(-1, 3), F)
    pts = np.array([[p.x, p.y, p.z] for p in tri.points])
    np.testing.assert_allclose(pts, V)
    assert 0 < tri.color.a < 1  # the cloud shows through
    # A new file holds its own copy, and its own cameras.
    assert len(rotated) == N
    for path in rotated:
        t = read(path)
        assert len(t["/part/cad"]) == 1 and len(t["/cam0/transform"]) == 1


def test_comparison_points_and_defects_are_labelled_coloured_markers(topics, recorded, trees):
    _, _, triggers = recorded
    _, part = demo(trees)
    where = {p.name: np.array(p.position) for p in part.model.comparison_points}
    updates = topics["/part/markers"]
    assert len(updates) == N
    defects = 0
    for (schema, _, update), (outcome, _) in zip(updates, triggers, strict=True):
        assert schema == "foxglove.SceneUpdate"
        result: InspectionResult = outcome.result
        (deletion,) = update.deletions
        assert deletion.type == 1  # ALL: the last part's markers go
        by_id = {e.id: e for e in update.entities}
        assert set(by_id) == {f"point/{c.name}" for c in result.comparison} | {
            f"defect/{i}" for i in range(len(result.defects))
        }
        for c in result.comparison:
            e = by_id[f"point/{c.name}"]
            assert e.frame_id == "part_cad" and e.frame_locked
            (sphere,) = e.spheres
            at = sphere.pose.position
            np.testing.assert_allclose([at.x, at.y, at.z], where[c.name])
            red, green = sphere.color.r > 0.5, sphere.color.g > 0.5
            assert (red, green) == {"pass": (False, True), "fail": (True, False)}.get(
                c.verdict.value, (True, True)
            )
            (label,) = e.texts
            assert label.text.startswith(c.name) and label.billboard
            if c.deviation_mm is not None:
                assert f"{c.deviation_mm:+.3f}" in label.text
        for i, d in enumerate(result.defects):
            e = by_id[f"defect/{i}"]
            (sphere,) = e.spheres
            at = sphere.pose.position
            np.testing.assert_allclose([at.x, at.y, at.z], d.center_mm)
            assert sphere.size.x > 0 and d.kind in e.texts[0].text
        defects += len(result.defects)
    assert defects > 0, "the dented parts should show defect markers"


def test_results_are_log_lines_beside_the_json(topics, recorded):
    _, _, triggers = recorded
    logs, results = topics["/log"], topics["/result"]
    assert len(logs) == len(results) == N
    levels = {"pass": 2, "fail": 3, "not_measurable": 3, "error": 4, "missed": 4}
    for (schema, t, log), (_, t2, doc), (outcome, _) in zip(logs, results, triggers, strict=True):
        r = outcome.result
        assert schema == "foxglove.Log" and t == t2 and doc["id"] == r.id
        assert log.level == levels[r.status.value]
        assert r.serial in log.message and r.status.value.upper() in log.message
        assert log.name == f"{r.line}/{r.station}"
        assert log.timestamp.seconds * 10**9 + log.timestamp.nanos == r.triggered_ns


def layout_topics(layout: dict) -> set[str]:
    """Every topic a Foxglove layout names: keys and values that start with a slash, a
    message path cut at its first field (``/result.status`` names ``/result``)."""
    found: set[str] = set()

    def walk(node: object) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                if isinstance(k, str) and k.startswith("/"):
                    found.add(k)
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)
        elif isinstance(node, str) and node.startswith("/"):
            found.add(re.split(r"[.{\[]", node, maxsplit=1)[0])

    walk(layout["configById"])
    return found


def test_the_layout_names_only_topics_the_recording_has(topics):
    layout = json.loads(LAYOUT.read_text())
    named = layout_topics(layout)
    assert {"/cloud", "/part/cad", "/part/markers", "/result", "/log", "/cam0/image"} <= named
    assert named <= set(topics), sorted(named - set(topics))
    # Every panel the layout places is configured, and every configured panel is placed.
    placed: set[str] = set()

    def leaves(node: object) -> None:
        if isinstance(node, str):
            placed.add(node)
        else:
            assert isinstance(node, dict)
            leaves(node["first"])
            leaves(node["second"])

    leaves(layout["layout"])
    assert placed == set(layout["configById"])
    cloud = layout["configById"]["3D!scene"]["topics"]["/cloud"]
    assert cloud["colorField"] == "deviation" and cloud["colorMode"] == "colormap"


def test_the_layout_check_fails_on_a_topic_the_recording_lacks(topics):
    layout = json.loads(LAYOUT.read_text())
    layout["configById"]["RawMessages!result"]["topicPath"] = "/results.status"
    assert "/results" in layout_topics(layout) - set(topics)


def _node_reader() -> list[str]:
    node = shutil.which("node")
    if node is None:
        pytest.skip("Node.js is not installed")
    probe = subprocess.run(
        [
            node,
            "-e",
            "for (const p of ['@mcap/core', 'fzstd', 'lz4js', 'protobufjs']) require.resolve(p)",
        ],
        cwd=NODE_READER.parent / "node",
        capture_output=True,
        text=True,
    )
    if probe.returncode != 0:
        pytest.skip(
            "the reader's packages are not installed: npm install --prefix tests/service/node"
        )
    return [node, str(NODE_READER)]


def test_the_typescript_reader_finds_the_same_topics(recorded, topics):
    cmd = _node_reader()
    path, _, _ = recorded
    done = subprocess.run([*cmd, str(path)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout)
    assert {t: (v["schema"], v["count"]) for t, v in seen.items()} == {
        t: (m[0][0], len(m)) for t, m in topics.items()
    }
    for cam in ("cam0", "cam1", "cam2", "cam3"):
        tf = seen[f"/{cam}/transform"]["first"]
        assert (tf["parent_frame_id"], tf["child_frame_id"]) == ("rig", cam)
        cal = seen[f"/{cam}/calibration"]["first"]
        assert cal["frame_id"] == cam == seen[f"/{cam}/image"]["first"]["frame_id"]
        assert cal["R"] == np.eye(3).ravel().tolist()
        ((_, _, ours),) = topics[f"/{cam}/calibration"]
        assert cal["P"] == list(ours.P) and cal["P"][3::4] == [0, 0, 0]
    assert seen["/cloud"]["first"]["pose"]["orientation"]["w"] == 1
    assert seen["/part/pose"]["first"]["child_frame_id"] == "part_cad"
    assert seen["/part/cad"]["first"]["entities"] == [[f"cad/{PART}", "part_cad", 1]]
    markers = seen["/part/markers"]["first"]["entities"]
    assert markers and all(frame == "part_cad" for _, frame, _ in markers)
