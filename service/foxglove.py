"""Foxglove's well-known messages (protobuf) for what the line records.

Frames, as Foxglove's 3D and Image panels resolve them:

- ``rig``: the rig frame (mm); the fixed frame of a recording.
- ``<camera>``: each camera's optical frame (OpenCV's: x right, y down, z
  forward), placed by a :func:`camera_transform` from ``rig``.
- ``part_cad``: the part's CAD frame, placed by :func:`part_pose` from ``rig``
  for each measured part; the CAD (:func:`cad_scene`) and the markers
  (:func:`markers`) live in it.

Lengths are millimetres, as everywhere in the project (Foxglove has no unit;
a layout's grid and marker sizes are chosen for mm).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.timestamp_pb2 import Timestamp

from inspection.deviations import ComparisonPoint

from .models import InspectionResult, Status

RIG_FRAME = "rig"
PART_FRAME = "part_cad"

# Verdict colours (r, g, b, a): what an operator reads at a glance. Half transparent, so
# the cloud's own deviation colours show through the support region.
PASS_COLOUR = (0.15, 0.75, 0.25, 0.5)
FAIL_COLOUR = (0.9, 0.1, 0.1, 0.6)
UNMEASURED_COLOUR = (0.6, 0.6, 0.6, 0.5)
DENT_COLOUR = (0.85, 0.0, 0.85, 0.5)
BUMP_COLOUR = (1.0, 0.55, 0.0, 0.5)
CAD_COLOUR = (0.7, 0.75, 0.8, 0.35)
LABEL_COLOUR = (1.0, 1.0, 1.0, 1.0)
LABEL_OFFSET_MM = 12.0
"""Labels stand this far off the surface along the point's normal, clear of the cloud."""


def timestamp(ns: int) -> Timestamp:
    """``ns`` since the Unix epoch as a protobuf Timestamp."""
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method, stable for every angle)."""
    m = R
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
        return float(q[0]), float(q[1]), float(q[2]), float(q[3])
    i = int(np.argmax([m[0, 0], m[1, 1], m[2, 2]]))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
    out = [0.0, 0.0, 0.0, 0.0]
    out[i] = s / 4
    out[j] = (m[j, i] + m[i, j]) / s
    out[k] = (m[k, i] + m[i, k]) / s
    out[3] = (m[k, j] - m[j, k]) / s
    return out[0], out[1], out[2], out[3]


def _colour(rgba: tuple[float, float, float, float]) -> Color:
    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def _transform(parent: str, child: str, T_parent_child: np.ndarray, t: int) -> FrameTransform:
    x, y, z, w = quaternion(T_parent_child[:3, :3])
    msg = FrameTransform(timestamp=timestamp(t), parent_frame_id=parent, child_frame_id=child)
    msg.translation.x, msg.translation.y, msg.translation.z = (
        float(v) for v in T_parent_child[:3, 3]
    )
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = x, y, z, w
    return msg


def _pose_at(position: Sequence[float] | np.ndarray) -> Pose:
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in position)
    pose.orientation.w = 1.0
    return pose


# --------------------------------------------------------------------------- the rig


def camera_transform(cal: Mapping[str, Any], t: int) -> FrameTransform:
    """The static transform placing camera ``cal["name"]`` in the rig frame.

    ``cal["T_camera_rig"]`` (16 numbers, rows first) maps rig points into the
    camera frame (OpenCV's ``[R | t]``); a FrameTransform gives the child's
    pose in its parent, T_rig_camera, its inverse.
    """
    T_camera_rig = np.asarray(cal["T_camera_rig"], dtype=np.float64).reshape(4, 4)
    return _transform(RIG_FRAME, str(cal["name"]), np.linalg.inv(T_camera_rig), t)


def camera_calibration(cal: Mapping[str, Any], t: int) -> CameraCalibration:
    """The camera's intrinsics in its own frame, as Foxglove defines them.

    The images are recorded unrectified: ``R`` is the identity and
    ``P = K [I | 0]``; where the camera sits is the :func:`camera_transform`.
    ``D`` is OpenCV's (k1, k2, p1, p2, k3): the plumb-bob model.
    """
    K = np.asarray(cal["K"], dtype=np.float64).reshape(3, 3)
    P = np.hstack([K, np.zeros((3, 1))])
    return CameraCalibration(
        timestamp=timestamp(t),
        frame_id=str(cal["name"]),
        width=int(cal["width"]),
        height=int(cal["height"]),
        distortion_model=str(cal.get("distortion_model", "plumb_bob")),
        D=[float(x) for x in cal.get("D", [0.0] * 5)],
        K=K.ravel().tolist(),
        R=np.eye(3).ravel().tolist(),
        P=P.ravel().tolist(),
    )


# --------------------------------------------------------------------------- one part


def cloud(points: np.ndarray, distances: np.ndarray | None, t: int) -> PointCloud:
    """The measured cloud in the rig frame (pose: the identity), with its ``deviation`` field.

    Parameters
    ----------
    points : (N, 3) float64, mm, rig frame
    distances : (N,) float64 or None
        Signed deviation from the CAD, mm (NaN where not an inlier).
    """
    n = len(points)
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("deviation", "<f4")])
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    rec["deviation"] = distances if distances is not None and len(distances) == n else np.nan
    f32 = PackedElementField.FLOAT32
    return PointCloud(
        timestamp=timestamp(t),
        frame_id=RIG_FRAME,
        pose=_pose_at((0.0, 0.0, 0.0)),
        point_stride=16,
        fields=[
            PackedElementField(name=name, offset=4 * i, type=f32)
            for i, name in enumerate(("x", "y", "z", "deviation"))
        ],
        data=rec.tobytes(),
    )


def part_pose(T_rig_cad: np.ndarray, t: int) -> FrameTransform:
    """The transform placing the part's CAD frame in the rig frame (the fit's inverse)."""
    return _transform(RIG_FRAME, PART_FRAME, T_rig_cad, t)


def cad_scene(name: str, vertices: np.ndarray, faces: np.ndarray, t: int) -> SceneUpdate:
    """The part's CAD as one scene entity (an indexed triangle list) in the ``part_cad`` frame.

    Parameters
    ----------
    name : str
        The part's name: the entity's id is ``cad/<name>``.
    vertices : (V, 3) float64, mm, CAD frame
    faces : (F, 3) int
    """
    entity = SceneEntity(
        timestamp=timestamp(t), frame_id=PART_FRAME, id=f"cad/{name}", frame_locked=True
    )
    entity.metadata.add(key="part", value=name)
    tri = entity.triangles.add()
    tri.pose.CopyFrom(_pose_at((0.0, 0.0, 0.0)))
    tri.color.CopyFrom(_colour(CAD_COLOUR))
    v = np.asarray(vertices, dtype=np.float64)
    for x, y, z in v.tolist():
        tri.points.add(x=x, y=y, z=z)
    tri.indices.extend(np.asarray(faces, dtype=np.int64).ravel().tolist())
    return SceneUpdate(entities=[entity])


def _verdict_colour(verdict: str) -> tuple[float, float, float, float]:
    return {"pass": PASS_COLOUR, "fail": FAIL_COLOUR}.get(verdict, UNMEASURED_COLOUR)


def markers(result: InspectionResult, points: Sequence[ComparisonPoint], t: int) -> SceneUpdate:
    """Labelled, coloured markers of one part, in the ``part_cad`` frame.

    Every earlier marker on the topic is deleted first, so a part's markers
    never mix with the previous part's. Each comparison point of the result
    is a sphere of its support radius coloured by its verdict, labelled
    with its name and deviation; each surface defect is a sphere of its
    area's equivalent diameter, coloured by kind, labelled with its peak.

    Parameters
    ----------
    result : InspectionResult
    points : sequence of ComparisonPoint
        The part's comparison points (where each lies, CAD frame); results
        name them.
    """
    update = SceneUpdate()
    update.deletions.add(timestamp=timestamp(t), type=SceneEntityDeletion.ALL)
    where = {p.name: p for p in points}
    for c in result.comparison:
        p = where.get(c.name)
        if p is None:
            continue
        verdict = str(c.verdict.value)
        dev = "not measurable" if c.deviation_mm is None else f"{c.deviation_mm:+.3f} mm"
        label = f"{c.name} {dev}"
        entity = _entity(f"point/{c.name}", t, {"verdict": verdict, "support": str(c.support)})
        _sphere(entity, p.position, 2 * p.radius_mm, _verdict_colour(verdict))
        _label(entity, np.add(p.position, LABEL_OFFSET_MM * np.asarray(p.normal)), label)
        update.entities.append(entity)
    for i, d in enumerate(result.defects or ()):
        entity = _entity(f"defect/{i}", t, {"kind": d.kind, "area_mm2": f"{d.area_mm2:.1f}"})
        size = 2 * float(np.sqrt(d.area_mm2 / np.pi))
        _sphere(entity, d.center_mm, size, DENT_COLOUR if d.kind == "dent" else BUMP_COLOUR)
        _label(
            entity,
            np.add(d.center_mm, (0.0, 0.0, LABEL_OFFSET_MM)),
            f"{d.kind} {d.peak_mm:+.2f} mm",
        )
        update.entities.append(entity)
    return update


def _entity(id_: str, t: int, metadata: Mapping[str, str]) -> SceneEntity:
    entity = SceneEntity(timestamp=timestamp(t), frame_id=PART_FRAME, id=id_, frame_locked=True)
    for k, v in metadata.items():
        entity.metadata.add(key=k, value=v)
    return entity


def _sphere(
    entity: SceneEntity, at: Sequence[float], diameter_mm: float, rgba: tuple[float, ...]
) -> None:
    s = entity.spheres.add()
    s.pose.CopyFrom(_pose_at(at))
    s.size.x = s.size.y = s.size.z = float(diameter_mm)
    s.color.CopyFrom(_colour(rgba))  # type: ignore[arg-type]


def _label(entity: SceneEntity, at: Sequence[float] | np.ndarray, text: str) -> None:
    label = entity.texts.add(text=text, billboard=True, font_size=14.0, scale_invariant=True)
    label.pose.CopyFrom(_pose_at(at))
    label.color.CopyFrom(_colour(LABEL_COLOUR))


_LEVEL = {
    Status.passed: Log.INFO,
    Status.fail: Log.WARNING,
    Status.not_measurable: Log.WARNING,
    Status.error: Log.ERROR,
    Status.missed: Log.ERROR,
}


def result_log(result: InspectionResult, t: int) -> Log:
    """One log line of a result: its status as the level, what failed in the message."""
    parts = [f"{result.part} {result.serial} seq {result.seq}: {result.status.value.upper()}"]
    if result.reason:
        parts.append(result.reason)
    bad = [c for c in result.comparison if c.verdict.value != "pass"]
    for c in bad:
        dev = "not measurable" if c.deviation_mm is None else f"{c.deviation_mm:+.3f} mm"
        parts.append(f"{c.name} {dev} [{c.lower_mm:+g}, {c.upper_mm:+g}]")
    for d in result.defects or ():
        parts.append(f"{d.kind} {d.peak_mm:+.2f} mm over {d.area_mm2:.0f} mm2")
    if result.rms_mm is not None:
        parts.append(f"fit RMS {result.rms_mm:.3f} mm")
    return Log(
        timestamp=timestamp(t),
        level=_LEVEL[result.status],
        message="; ".join(parts),
        name=f"{result.line}/{result.station}",
    )
