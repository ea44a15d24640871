"""The rig model: projection, rays, TOML round trips and input checks."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from inspection.errors import InvalidInput
from inspection.rig import Camera, Rig, belt_pose, rigid_align

VOLUME_CORNERS = np.array(
    [[sx * 400.0, sy * 250.0, z] for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, 200.0)]
)


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.nominal()


def test_every_camera_sees_the_whole_volume(rig: Rig) -> None:
    for cam in rig:
        px = cam.project(VOLUME_CORNERS)
        assert np.all(px[:, 0] > 10) and np.all(px[:, 0] < cam.width - 10), cam.name
        assert np.all(px[:, 1] > 10) and np.all(px[:, 1] < cam.height - 10), cam.name


def test_rays_invert_projection(rig: Rig) -> None:
    rng = np.random.default_rng(0)
    for cam in rig:
        px = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(500, 2))
        origins, dirs = cam.rays(px)
        assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
        assert np.allclose(origins, cam.centre)
        back = cam.project(origins + 1234.5 * dirs)
        assert np.abs(back - px).max() < 1e-8


def test_projection_matches_opencv(rig: Rig) -> None:
    import cv2

    rng = np.random.default_rng(1)
    pts = rng.uniform([-400, -250, 0], [400, 250, 200], size=(200, 3))
    for cam in rig:
        rvec, _ = cv2.Rodrigues(cam.R)
        ref, _ = cv2.projectPoints(pts, rvec, cam.t, cam.K, cam.dist)
        assert np.abs(ref.reshape(-1, 2) - cam.project(pts)).max() < 1e-6


def test_centre_and_transforms(rig: Rig) -> None:
    for cam in rig:
        assert np.allclose(cam.T_rig_cam @ cam.T_cam_rig, np.eye(4))
        assert np.allclose(cam.to_camera(cam.centre[None])[0], 0.0, atol=1e-9)
        assert 1250 < cam.centre[2] < 1350


def test_toml_round_trip_is_exact(rig: Rig, tmp_path) -> None:
    path = rig.save(tmp_path / "rig.toml")
    back = Rig.load(path)
    assert back.id == rig.id
    for a, b in zip(rig, back, strict=True):
        assert a.name == b.name
        for attr in ("K", "dist", "R", "t"):
            assert np.array_equal(getattr(a, attr), getattr(b, attr))


def test_edited_file_is_refused_unless_id_removed(rig: Rig, tmp_path) -> None:
    path = rig.save(tmp_path / "rig.toml")
    text = path.read_text().replace("width = 1280", "width = 1281", 1)
    path.write_text(text)
    with pytest.raises(InvalidInput, match="does not match"):
        Rig.load(path)
    path.write_text("\n".join(line for line in text.splitlines() if not line.startswith("id =")))
    assert Rig.load(path).cameras[0].width == 1281


def test_default_reads_env_override(rig: Rig, tmp_path, monkeypatch) -> None:
    path = rig.save(tmp_path / "other.toml")
    monkeypatch.setenv("INSPECTION_RIG", str(path))
    assert Rig.default().id == rig.id
    monkeypatch.setenv("INSPECTION_RIG", str(tmp_path / "missing.toml"))
    with pytest.raises(FileNotFoundError, match="inspection calibrate"):
        Rig.default()


def test_with_image_size_keeps_the_field_of_view(rig: Rig) -> None:
    small = rig.with_image_size(640, 512)
    for a, b in zip(rig, small, strict=True):
        pa = a.project(VOLUME_CORNERS)
        pb = b.project(VOLUME_CORNERS)
        assert np.allclose((pb + 0.5) * 2.0 - 0.5, pa, atol=1e-9)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"K": np.eye(2)}, "shape"),
        ({"R": np.diag([1.0, 1.0, -1.0])}, "rotation"),
        ({"dist": [0.0, 0.0, np.nan, 0.0, 0.0]}, "finite"),
        ({"width": 0}, "width"),
        ({"K": [[-5.0, 0, 1], [0, 5, 1], [0, 0, 1]]}, "fx"),
    ],
)
def test_bad_camera_is_refused(rig: Rig, kwargs, message) -> None:
    cam = rig.cameras[0]
    args: dict[str, Any] = {
        "name": cam.name,
        "width": cam.width,
        "height": cam.height,
        "K": cam.K,
        "dist": cam.dist,
        "R": cam.R,
        "t": cam.t,
    }
    args.update(kwargs)
    with pytest.raises(InvalidInput, match=message):
        Camera(**args)


def test_bad_rig_and_files_are_refused(rig: Rig, tmp_path) -> None:
    with pytest.raises(InvalidInput, match="four"):
        Rig(rig.cameras[:3], rig.projector)
    bad = tmp_path / "bad.toml"
    bad.write_text("format = 'inspection-rig/1'\nsurprise = 1\n")
    with pytest.raises(InvalidInput, match="unknown keys"):
        Rig.load(bad)
    bad.write_text("this is not toml ===")
    with pytest.raises(InvalidInput, match="TOML"):
        Rig.load(bad)
    with pytest.raises(InvalidInput, match=r"\(N, 3\)"):
        rig.cameras[0].project(np.zeros((4, 2)))


def test_rigid_align_recovers_a_transform() -> None:
    rng = np.random.default_rng(2)
    a = rng.normal(size=(10, 3)) * 100
    from inspection.rig.poses import rotvec_matrix

    R = rotvec_matrix(np.array([0.3, -0.2, 0.9]))
    b = a @ R.T + [10.0, -5.0, 3.0]
    T = rigid_align(a, b)
    assert np.allclose(T[:3, :3], R) and np.allclose(T[:3, 3], [10.0, -5.0, 3.0])


def test_belt_pose_turns_then_moves_and_refuses_nonsense() -> None:
    T = belt_pose(100.0, -50.0, 90.0, z_mm=5.0)
    # The part's +x turns to the rig's +y, and its origin lands at (100, -50, 5).
    np.testing.assert_allclose(T[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T @ [10.0, 0.0, 0.0, 1.0], [100.0, -40.0, 5.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    with pytest.raises(InvalidInput, match="finite"):
        belt_pose(float("nan"), 0.0, 0.0)


def test_pictures_of_the_rig(rig: Rig, tmp_path) -> None:
    import cv2

    from inspection.pictures import draw_frames, draw_rig_layout, write_png

    layout = draw_rig_layout(rig)
    assert layout.ndim == 3 and layout.shape[2] == 3 and layout.dtype == np.uint8
    path = write_png(tmp_path / "sub" / "layout.png", layout)
    read = cv2.imread(str(path))
    assert read is not None
    back = cv2.cvtColor(read, cv2.COLOR_BGR2RGB)
    assert np.array_equal(back, layout)
    grey = np.zeros((rig.cameras[0].height, rig.cameras[0].width), np.uint8)
    tiled = draw_frames(rig, [grey] * 4, width=640)
    assert tiled.shape[1] == 640
    with pytest.raises(InvalidInput, match="uint8"):
        write_png(tmp_path / "x.png", np.zeros((4, 4), np.float32))
    with pytest.raises(InvalidInput, match="4 images"):
        draw_frames(rig, [grey] * 3)
