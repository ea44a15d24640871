"""The rig simulator: determinism, exact geometry, faults and input checks."""

from __future__ import annotations

import dataclasses
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from inspection.board import CharucoSpec, board_lying_flat
from inspection.calibration import detect_board
from inspection.errors import InvalidInput
from inspection.panel import Hole, PanelSpec, sheet_metal_panel, surface_point
from inspection.rig import Rig, belt_pose
from inspection.simulate import RenderOptions, simulate, simulate_board
from inspection.transforms import apply


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.nominal()


@pytest.fixture(scope="module")
def panel() -> trimesh.Trimesh:
    """A 400 x 260 x 2 mm plate with a 40 mm wall along one edge."""
    plate = trimesh.creation.box((400.0, 260.0, 2.0))
    plate.apply_translation((0.0, 0.0, 1.0))
    wall = trimesh.creation.box((400.0, 3.0, 40.0))
    wall.apply_translation((0.0, 128.5, 20.0))
    mesh = trimesh.util.concatenate([plate, wall])
    assert isinstance(mesh, trimesh.Trimesh)
    return mesh


@pytest.fixture(scope="module")
def rendered(rig, panel):
    return simulate(rig, panel, belt_pose(40.0, -25.0, 25.0), seed=3, return_truth=True)


def test_four_uint8_frames_of_the_camera_size(rig, rendered) -> None:
    images, truths = rendered
    assert len(images) == 4 and len(truths) == 4
    for cam, img in zip(rig, images, strict=True):
        assert img.dtype == np.uint8 and img.shape == (cam.height, cam.width)


def test_same_seed_same_images_other_seed_other_noise(rig, panel, rendered) -> None:
    images, _ = rendered
    again = simulate(rig, panel, belt_pose(40.0, -25.0, 25.0), seed=3)
    for a, b in zip(images, again, strict=True):
        assert np.array_equal(a, b)
    other = simulate(rig, panel, belt_pose(40.0, -25.0, 25.0), seed=4)
    assert not np.array_equal(images[0], other[0])


def test_truth_points_lie_on_the_pixel_rays(rig, rendered) -> None:
    _, truths = rendered
    rng = np.random.default_rng(0)
    for cam, truth in zip(rig, truths, strict=True):
        v = rng.integers(0, cam.height, 400)
        u = rng.integers(0, cam.width, 400)
        back = cam.project(truth.points[v, u].astype(np.float64))
        # float32 points at ~1.4 m: ~1e-4 mm, i.e. ~1e-4 px
        assert np.abs(back - np.stack([u, v], axis=1)).max() < 2e-3


def test_truth_points_lie_on_the_part_or_the_belt(rig, panel, rendered) -> None:
    _, truths = rendered
    T = belt_pose(40.0, -25.0, 25.0)
    for truth in truths:
        belt = truth.points[~truth.part]
        assert np.abs(belt[:, 2]).max() < 1e-4
        pts = truth.points[truth.part].astype(np.float64)
        local = (pts - T[:3, 3]) @ T[:3, :3]  # rig -> part frame
        lo, hi = panel.bounds
        excess = np.maximum(lo - local, local - hi).max(axis=1)
        # Exact inside faces; a ray grazing a crease next to a face thinner
        # than a pixel may land on the neighbour's plane, within a pixel.
        assert excess.max() < 1.0
        assert np.mean(excess > 1e-3) < 2e-3
        # the top of the plate (most part pixels) is exactly at z = 2
        assert np.median(pts[:, 2]) == pytest.approx(2.0, abs=1e-3)
        assert truth.part.mean() > 0.05


def test_pattern_on_the_part_and_shadow_behind_the_wall(rig, rendered) -> None:
    """The speckle lies on the lit part, and the shadow is dark: inside it, that is, not
    on its outline, where a pixel also collects the lit side's light (and the blur's)."""
    images, truths = rendered
    shadows = 0
    for img, truth in zip(images, truths, strict=True):
        lit = truth.part & truth.lit & ~truth.saturated
        assert lit.sum() > 10000
        assert img[lit].std() > 25  # the speckle is there
        dark = truth.part & ~truth.lit
        inside = ndimage.binary_erosion(dark, np.ones((5, 5), bool))
        if inside.sum() > 100:
            shadows += 1
            assert img[inside].mean() < 0.2 * img[lit].mean()
    assert shadows >= 1


def test_faults_saturate_and_clean_options_do_not(rig, panel, rendered) -> None:
    _, truths = rendered
    assert sum(int(t.saturated.sum()) for t in truths) > 500  # mirror highlights
    images, clean = simulate(
        rig,
        panel,
        belt_pose(40.0, -25.0, 25.0),
        seed=3,
        options=RenderOptions.clean(),
        return_truth=True,
    )
    assert sum(int(t.saturated.sum()) for t in clean) == 0


def test_part_lying_outside_the_view_only_shows_belt(rig, panel) -> None:
    _, truths = simulate(rig, panel, belt_pose(3000.0, 0.0, 0.0), seed=0, return_truth=True)
    assert not any(t.part.any() for t in truths)


def test_board_corners_render_where_the_camera_model_puts_them(rig) -> None:
    spec = CharucoSpec()
    T = board_lying_flat(spec, (30.0, -20.0), 12.0, height_mm=40.0)
    images = simulate_board(rig, T, spec, seed=1, supersample=2)
    corners = spec.corners_mm()
    for cam, img in zip(rig, images, strict=True):
        det = detect_board(img, spec)
        assert det is not None and len(det.ids) > 60
        truth = cam.project(apply(T, corners[det.ids]))
        err = np.linalg.norm(truth - det.image_points, axis=1)
        assert np.sqrt(np.mean(err**2)) < 0.15, cam.name


@pytest.mark.parametrize(
    "mesh_kind, T, message",
    [
        ("empty", np.eye(4), "faces"),
        ("nan", np.eye(4), "finite"),
        ("ok", np.eye(3), "shape"),
        ("ok", np.diag([1.0, 1.0, -1.0, 1.0]), "rigid"),
        ("ok", np.full((4, 4), np.nan), "finite"),
        ("object", np.eye(4), "vertices and faces"),
    ],
)
def test_bad_inputs_are_refused(rig, mesh_kind, T, message) -> None:
    box = trimesh.creation.box((10.0, 10.0, 10.0))
    mesh = {
        "ok": box,
        "empty": trimesh.Trimesh(
            vertices=np.zeros((3, 3)), faces=np.zeros((0, 3), int), process=False
        ),
        "nan": trimesh.Trimesh(
            vertices=np.where(box.vertices > 0, np.nan, box.vertices),
            faces=box.faces,
            process=False,
        ),
        "object": object(),
    }[mesh_kind]
    with pytest.raises(InvalidInput, match=message):
        simulate(rig, mesh, T)


def test_bad_seed_and_options_are_refused(rig) -> None:
    box = trimesh.creation.box((10.0, 10.0, 10.0))
    with pytest.raises(InvalidInput, match="seed"):
        simulate(rig, box, np.eye(4), seed=-1)
    with pytest.raises(InvalidInput, match="blur_px"):
        RenderOptions(blur_px=-1.0)
    with pytest.raises(InvalidInput, match="Rig"):
        simulate("rig", box, np.eye(4))  # type: ignore[call-overload]


def test_a_pixel_integrates_the_pattern_over_its_area() -> None:
    """A pixel is the mean of the light over its area, as a sensor's is: at
    3 x 3 samples it matches a render at three times the resolution averaged
    over 3 x 3 blocks (the same sample positions); the pixel centre alone
    (``pixel_samples=1``) aliases the speckle and is far from it."""
    plate = trimesh.creation.box((300.0, 200.0, 30.0))
    plate.apply_translation((0.0, 0.0, 15.0))
    sharp = replace(RenderOptions.clean(), blur_px=0.0)
    w, h = 480, 384
    fine = simulate(
        Rig.nominal(3 * w, 3 * h), plate, np.eye(4), options=replace(sharp, pixel_samples=1)
    )
    centre = (slice(h // 2 - 48, h // 2 + 48), slice(w // 2 - 64, w // 2 + 64))
    for n, bound in ((3, 1.5), (1, None)):
        images = simulate(
            Rig.nominal(w, h), plate, np.eye(4), options=replace(sharp, pixel_samples=n)
        )
        for image, reference in zip(images, fine, strict=True):
            box = reference.astype(np.float64).reshape(h, 3, w, 3).mean(axis=(1, 3))
            diff = float(np.abs(image[centre] - box[centre]).mean())
            if bound is not None:
                assert diff < bound
            else:
                assert diff > 4.0, "the centre sample alone should alias the speckle"
    with pytest.raises(InvalidInput, match="pixel_samples"):
        RenderOptions(pixel_samples=0)


def test_an_outline_pixel_collects_the_light_over_its_area() -> None:
    """A pixel straddling the part's outline is the mean over its area of the part's
    light and the belt's, as a sensor's is: at 3 x 3 rays it matches a render at three
    times the resolution averaged over 3 x 3 blocks; decided at its centre
    (``edge_samples=1``) it is all one or the other, far from it."""
    plate = trimesh.creation.box((300.0, 200.0, 30.0))
    plate.apply_translation((0.0, 0.0, 15.0))
    sharp = replace(RenderOptions.clean(), blur_px=0.0)
    w, h = 480, 384
    fine = simulate(
        Rig.nominal(3 * w, 3 * h), plate, np.eye(4),
        options=replace(sharp, pixel_samples=1, edge_samples=1),
    )  # fmt: skip
    coarse, truths = simulate(
        Rig.nominal(w, h), plate, np.eye(4), options=replace(sharp, edge_samples=3),
        return_truth=True,
    )  # fmt: skip
    centred = simulate(Rig.nominal(w, h), plate, np.eye(4), options=replace(sharp, edge_samples=1))
    for image, one, reference, truth in zip(coarse, centred, fine, truths, strict=True):
        box = reference.astype(np.float64).reshape(h, 3, w, 3).mean(axis=(1, 3))
        outline = ndimage.binary_dilation(truth.part) & ~ndimage.binary_erosion(truth.part)
        assert outline.sum() > 500
        area = float(np.abs(image[outline] - box[outline]).mean())
        centre = float(np.abs(one[outline] - box[outline]).mean())
        assert area < 1.0 and centre > 5 * area, (area, centre)
    with pytest.raises(InvalidInput, match="edge_samples"):
        RenderOptions(edge_samples=9)


def test_a_hole_rim_drawn_by_slivers_renders_where_the_mesh_puts_it() -> None:
    """The panel's holes are drawn by the grid's faces cut at the rim: slivers, and faces
    smaller than a pixel, that hold no pixel centre of the z-buffer. A ray that meets
    one finds it (it is not the belt): every pixel whose ray meets the sheet more than
    0.1 mm from the rim shows the part, and none inside the hole does."""
    spec = dataclasses.replace(
        PanelSpec(holes=(Hole(170.0, 110.0, 16.0), Hole(-200.0, 120.0, 10.5)),
                  hole_spacing_mm=0.7).scaled(400.0, 260.0)
    )  # fmt: skip
    rig = Rig.nominal()
    T = belt_pose(0.0, 0.0, 0.0)
    _, truths = simulate(rig, sheet_metal_panel(spec), T, options=RenderOptions.clean(),
                         return_truth=True)  # fmt: skip
    T_part_rig = np.linalg.inv(T)
    for h in spec.holes:
        (cx, cy, cz), n = surface_point(spec, h.x_mm, h.y_mm)
        centre, n = np.array([cx, cy, cz]), np.asarray(n)
        for cam, truth in zip(rig, truths, strict=True):
            u, v = (int(c) for c in cam.project(apply(T, centre[None]))[0])
            rows, cols = np.mgrid[v - 20 : v + 20, u - 20 : u + 20]
            o, d = cam.rays(np.column_stack([cols.ravel(), rows.ravel()]).astype(np.float64))
            o, d = apply(T_part_rig, o), d @ T_part_rig[:3, :3].T
            hit = o + (((centre - o) @ n) / (d @ n))[:, None] * d
            r = np.linalg.norm(hit[:, :2] - centre[:2], axis=1) - h.radius_mm
            part = truth.part[rows.ravel(), cols.ravel()]
            assert part[r > 0.1].all(), (cam.name, h, int((~part[r > 0.1]).sum()))
            assert not part[r < -0.1].any(), (cam.name, h)


_HASH_SCRIPT = """
import hashlib, numpy as np, trimesh
from inspection.rig import Rig
from inspection.simulate import simulate
box = trimesh.creation.box((300.0, 200.0, 30.0))
box.apply_translation((0.0, 0.0, 15.0))
images = simulate(Rig.nominal(320, 256), box, np.eye(4), seed=7)
print(hashlib.sha256(b"".join(i.tobytes() for i in images)).hexdigest())
"""


def test_images_do_not_depend_on_the_thread_count() -> None:
    import os
    import subprocess
    import sys

    digests = set()
    for threads in ("1", "2"):
        env = dict(os.environ, NUMBA_NUM_THREADS=threads)
        out = subprocess.run(
            [sys.executable, "-c", _HASH_SCRIPT],
            env=env,
            capture_output=True,
            text=True,
            check=True,
            timeout=300,
        )
        digests.add(out.stdout.strip())
    assert len(digests) == 1


def test_concurrent_calls_from_threads(rig, panel) -> None:
    """The line renders in its ingest thread while other threads compute: no
    crash whatever numba's threading layer, and the same images."""
    from concurrent.futures import ThreadPoolExecutor

    T = belt_pose(0.0, 0.0, 0.0)
    alone = simulate(rig, panel, T, seed=11)
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(lambda _: simulate(rig, panel, T, seed=11), range(2)))
    for images in results:
        assert all(np.array_equal(a, b) for a, b in zip(alone, images, strict=True))


def _even_rig(width: int, height: int) -> Rig:
    """The nominal rig with an even flash (no speckle) and a plain belt: edges alone."""
    rig = Rig.nominal(width, height)
    even = replace(rig.projector, pattern=replace(rig.projector.pattern, low=0.95, high=1.0))
    return replace(rig, projector=even, conveyor=replace(rig.conveyor, texture_contrast=0.0))


def _steepest(img: np.ndarray, rows: slice, cols: slice, axis: int) -> float:
    """The steepest step along ``axis`` in the window, averaged over the window's lines."""
    band = img[rows, cols].astype(np.float64)
    return float(np.abs(np.diff(band, axis=axis)).max(axis=axis).mean())


def test_a_long_flash_smears_the_frames_along_the_belt_only() -> None:
    """2 ms at 1 m/s: the plate travels 2 mm during the flash (1.5 px here). Its
    edges across the belt's motion soften; those along it stay as sharp; the
    truth is the pose at the middle of the flash."""
    rig = _even_rig(640, 512)
    plate = trimesh.creation.box((300.0, 200.0, 20.0))
    plate.apply_translation((0.0, 0.0, 10.0))
    clean = RenderOptions.clean()
    short, truth = simulate(rig, plate, np.eye(4), options=clean, return_truth=True)
    long, truth_long = simulate(
        rig, plate, np.eye(4), options=replace(clean, flash_us=2000.0), return_truth=True
    )
    top = np.array([[x, y, 20.0] for x in (-150.0, 150.0) for y in (-100.0, 100.0)])
    for cam, a, b in zip(rig, short, long, strict=True):
        lo = np.floor(cam.project(top).min(axis=0)).astype(int) - 6
        hi = np.ceil(cam.project(top).max(axis=0)).astype(int) + 6
        u0, v0 = (int(c) for c in cam.project(np.array([[0.0, 0.0, 20.0]]))[0])
        rows, cols = slice(v0 - 3, v0 + 4), slice(lo[0], hi[0])  # across the x-edges
        # The outline's pixels are area-sampled: the short flash's step already spans two
        # pixels, and the smear softens it by less than a step decided at pixel centres.
        assert _steepest(b, rows, cols, 1) < 0.95 * _steepest(a, rows, cols, 1), cam.name
        rows, cols = slice(lo[1], hi[1]), slice(u0 - 3, u0 + 4)  # across the y-edges
        assert _steepest(b, rows, cols, 0) == pytest.approx(_steepest(a, rows, cols, 0), rel=0.01)
    for t, t_long in zip(truth, truth_long, strict=True):
        np.testing.assert_array_equal(t.points, t_long.points)


def test_a_still_belt_or_a_short_flash_leave_the_frames_as_they_are() -> None:
    rig = Rig.nominal(320, 256)
    box = trimesh.creation.box((300.0, 200.0, 30.0))
    box.apply_translation((0.0, 0.0, 15.0))
    still = replace(rig, conveyor=replace(rig.conveyor, speed_mm_s=0.0))
    reference = simulate(rig, box, np.eye(4), seed=2, options=RenderOptions(flash_us=0.0))
    for r, flash_us in ((rig, 50.0), (still, 50.0), (still, 5000.0)):
        images = simulate(r, box, np.eye(4), seed=2, options=RenderOptions(flash_us=flash_us))
        assert all(np.array_equal(a, b) for a, b in zip(reference, images, strict=True))
    with pytest.raises(InvalidInput, match="flash_us"):
        RenderOptions(flash_us=-1.0)


def test_the_pattern_seed_picks_the_projected_speckle() -> None:
    rig = Rig.nominal(320, 256)
    box = trimesh.creation.box((300.0, 200.0, 30.0))
    box.apply_translation((0.0, 0.0, 15.0))
    other = replace(
        rig, projector=replace(rig.projector, pattern=replace(rig.projector.pattern, seed=8))
    )
    assert other.id != rig.id
    a = simulate(rig, box, np.eye(4), options=RenderOptions.clean())
    b = simulate(other, box, np.eye(4), options=RenderOptions.clean())
    again = simulate(rig, box, np.eye(4), options=RenderOptions.clean())
    centre = (slice(100, 156), slice(130, 190))  # the box's top, in every camera
    for x, y, z in zip(a, b, again, strict=True):
        assert np.array_equal(x, z)
        assert np.abs(x[centre].astype(np.float64) - y[centre]).mean() > 10.0
