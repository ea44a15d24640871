"""Reconstruction from simulated flash frames: heights, dents, bad frames, fusion, PLY."""

from __future__ import annotations

import dataclasses
import os
import signal

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from inspection.errors import InspectionError, InvalidInput
from inspection.grid import GridTree
from inspection.panel import PanelSpec, sheet_metal_panel
from inspection.reconstruct import (
    FLAG_EMPTY,
    FLAG_SATURATED,
    FLAG_TOO_DARK,
    Cloud,
    Guide,
    Matching,
    Prior,
    Reconstructor,
    ReconstructParams,
    kernels,
    reconstruct,
)
from inspection.reconstruct import kernels as reconstruct_kernels
from inspection.reconstruct.matching import fill_gaps, grid_pixels, local_normalise, spline_rows
from inspection.reconstruct.warping import bends, shading
from inspection.registration import register
from inspection.rig import Rig, belt_pose
from inspection.simulate import simulate

PLATE_TOP_MM = 40.0
DENT_DEPTH_MM = 1.0
DENT_SIGMA_MM = 8.0
DENT_AT = np.array([30.0, -20.0])


def plate_mesh(
    top_mm: float, dent_depth_mm: float = 0.0, size=(300.0, 200.0), spacing=2.0
) -> trimesh.Trimesh:
    """A flat plate (top as a height field, on a box) with an optional Gaussian dent."""
    nx = int(size[0] / spacing) + 1
    ny = int(size[1] / spacing) + 1
    x, y = np.meshgrid(
        np.linspace(-size[0] / 2, size[0] / 2, nx), np.linspace(-size[1] / 2, size[1] / 2, ny)
    )
    r2 = (x - DENT_AT[0]) ** 2 + (y - DENT_AT[1]) ** 2
    z = top_mm - dent_depth_mm * np.exp(-r2 / (2 * DENT_SIGMA_MM**2))
    top = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    plate = trimesh.Trimesh(top, faces, process=False)
    # The body under the plate stays below the dent's bottom, or it would show through.
    body = top_mm - 5.0
    walls = trimesh.creation.box(extents=(size[0], size[1], body))
    walls.apply_translation((0, 0, body / 2))
    return trimesh.util.concatenate([plate, walls])


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.nominal()


@pytest.fixture(scope="module")
def reconstructor(rig: Rig) -> Reconstructor:
    return Reconstructor.build(rig)


@pytest.fixture(scope="module")
def plate_frames(rig: Rig) -> list[np.ndarray]:
    T = np.eye(4)
    T[:3, 3] = (-40.0, 25.0, 0.0)
    return simulate(rig, plate_mesh(PLATE_TOP_MM), T, seed=3)


@pytest.fixture(scope="module")
def plate_cloud(reconstructor: Reconstructor, plate_frames) -> Cloud:
    return reconstructor(plate_frames)


def test_plane_at_known_height(plate_cloud: Cloud) -> None:
    top = plate_cloud.points[np.abs(plate_cloud.points[:, 2] - PLATE_TOP_MM) < 1.0]
    # 300 x 200 mm at ~0.8 mm per pixel, every second column, two pairs: ~90k points.
    assert len(top) > 50_000
    assert abs(np.median(top[:, 2]) - PLATE_TOP_MM) < 0.03
    assert np.sqrt(np.mean((top[:, 2] - PLATE_TOP_MM) ** 2)) < 0.15
    # Nothing of the belt survives: no point lower than the background threshold.
    assert plate_cloud.points[:, 2].min() >= ReconstructParams().z_min_mm
    # Points lie on the plate's footprint (moved by -40, +25).
    inner = top[(np.abs(top[:, 0] + 40) < 151) & (np.abs(top[:, 1] - 25) < 101)]
    assert len(inner) > 0.99 * len(top)


def test_cloud_fields_and_report(plate_cloud: Cloud, rig: Rig) -> None:
    n = len(plate_cloud)
    assert plate_cloud.points.shape == (n, 3) and plate_cloud.points.dtype == np.float64
    assert plate_cloud.weights.shape == (n,)
    assert np.all((plate_cloud.weights >= 0) & (plate_cloud.weights <= 1))
    assert set(np.unique(plate_cloud.pair)) == {0, 1}
    rep = plate_cloud.report
    assert rep.flags == ()
    assert rep.points == n
    assert len(rep.pairs) == 2
    for pr in rep.pairs:
        assert pr.coarse >= pr.foreground >= pr.refined >= pr.in_volume > 0
        assert pr.confirmed > 0.5 * pr.in_volume
    assert plate_cloud.rig_id == rig.id
    assert "total" in rep.timings_ms
    assert rep.as_dict()["points"] == n


def test_deterministic(reconstructor: Reconstructor, plate_frames, plate_cloud: Cloud) -> None:
    again = reconstructor(plate_frames)
    np.testing.assert_array_equal(again.points, plate_cloud.points)
    np.testing.assert_array_equal(again.weights, plate_cloud.weights)


def test_one_thread_gives_the_same_cloud(
    reconstructor: Reconstructor, plate_frames, plate_cloud: Cloud
) -> None:
    single = Reconstructor.build(reconstructor.rig, ReconstructParams(threads=1))
    assert single.executor is None
    one = single(plate_frames)
    np.testing.assert_array_equal(one.points, plate_cloud.points)
    np.testing.assert_array_equal(one.weights, plate_cloud.weights)


def test_the_pool_lives_as_long_as_its_reconstructor(rig: Rig, plate_frames) -> None:
    with Reconstructor.build(rig) as rec:
        assert rec.executor is not None
        assert len(rec(plate_frames)) > 0
    with pytest.raises(RuntimeError, match="shutdown"):
        rec(plate_frames)


def test_a_reconstructor_refuses_to_run_after_a_fork(
    reconstructor: Reconstructor, plate_frames
) -> None:
    # A forked child has the pool but not its threads: it would wait forever.
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        signal.alarm(30)
        try:
            reconstructor(plate_frames)
            os.write(write, b"ran")
        except InspectionError as exc:
            os.write(write, str(exc).encode())
        finally:
            os._exit(0)
    os.close(write)
    os.waitpid(pid, 0)
    with os.fdopen(read) as fh:
        assert "another process" in fh.read()


def test_warped_windows_keep_the_plane(
    reconstructor: Reconstructor, plate_frames, plate_cloud: Cloud
) -> None:
    square = Reconstructor.build(reconstructor.rig, ReconstructParams(warp_passes=0))(plate_frames)
    for cloud in (square, plate_cloud):
        top = cloud.points[np.abs(cloud.points[:, 2] - PLATE_TOP_MM) < 1.0]
        assert abs(np.median(top[:, 2]) - PLATE_TOP_MM) < 0.03
    # Warping only refits windows whose field bends or slopes: the plate's
    # outline, not its flat top; the count hardly changes.
    assert abs(len(plate_cloud) - len(square)) < 0.02 * len(square)


def test_frames_not_mutated(reconstructor: Reconstructor, plate_frames) -> None:
    copies = [f.copy() for f in plate_frames]
    reconstructor(plate_frames)
    for a, b in zip(copies, plate_frames, strict=True):
        np.testing.assert_array_equal(a, b)


def test_dent_is_visible(rig: Rig, reconstructor: Reconstructor) -> None:
    frames = simulate(rig, plate_mesh(PLATE_TOP_MM, DENT_DEPTH_MM), np.eye(4), seed=5)
    pts = reconstructor(frames).points
    r = np.hypot(pts[:, 0] - DENT_AT[0], pts[:, 1] - DENT_AT[1])
    centre = pts[r < 2.0, 2]
    ring = pts[(r > 40.0) & (r < 60.0), 2]
    assert len(centre) > 10 and len(ring) > 1000
    depth = np.median(ring) - np.median(centre)
    assert depth == pytest.approx(DENT_DEPTH_MM, abs=0.15)


def test_cyclopean_windows_give_the_same_plane(
    reconstructor: Reconstructor, plate_frames, plate_cloud: Cloud
) -> None:
    sym = Reconstructor.build(reconstructor.rig, ReconstructParams(symmetric=True))(plate_frames)
    top = sym.points[np.abs(sym.points[:, 2] - PLATE_TOP_MM) < 1.0]
    assert len(top) > 0.8 * len(plate_cloud)
    assert abs(np.median(top[:, 2]) - PLATE_TOP_MM) < 0.03
    # Both find the plate's edges (x -190..110, y -75..125 mm) to a few pixels: the
    # windows straddling the outline put the top surface past it (up to ~5 mm
    # on the edges facing a pair), a known limit of window matching.
    top0 = plate_cloud.points[np.abs(plate_cloud.points[:, 2] - PLATE_TOP_MM) < 1.0]
    for pts in (top, top0):
        lo = np.percentile(pts[:, :2], 0.05, axis=0)
        hi = np.percentile(pts[:, :2], 99.95, axis=0)
        np.testing.assert_allclose(lo, [-190.0, -75.0], atol=5.0)
        np.testing.assert_allclose(hi, [110.0, 125.0], atol=5.0)


def test_ring_pairs_add_points(
    reconstructor: Reconstructor, plate_frames, plate_cloud: Cloud
) -> None:
    rec = Reconstructor.build(reconstructor.rig, ReconstructParams(ring_pairs=True))
    assert [(p.left, p.right) for p in rec.pairs] == [(0, 1), (2, 3), (0, 2), (1, 3)]
    cloud = rec(plate_frames)
    assert set(np.unique(cloud.pair)) == {0, 1, 2, 3}
    top = cloud.points[np.abs(cloud.points[:, 2] - PLATE_TOP_MM) < 1.0]
    assert len(top) > 1.7 * len(
        plate_cloud.points[np.abs(plate_cloud.points[:, 2] - PLATE_TOP_MM) < 1.0]
    )
    assert abs(np.median(top[:, 2]) - PLATE_TOP_MM) < 0.03


def test_prior_narrows_the_search(
    reconstructor: Reconstructor, plate_frames, plate_cloud: Cloud
) -> None:
    prior = Prior(z_max_mm=60.0)
    cloud = reconstructor(plate_frames, prior=prior)
    for with_prior, without in zip(cloud.report.pairs, plate_cloud.report.pairs, strict=True):
        lo, hi = with_prior.disparity_range
        lo0, hi0 = without.disparity_range
        assert hi - lo < 0.5 * (hi0 - lo0)
    top = cloud.points[np.abs(cloud.points[:, 2] - PLATE_TOP_MM) < 1.0]
    assert len(top) > 0.95 * len(
        plate_cloud.points[np.abs(plate_cloud.points[:, 2] - PLATE_TOP_MM) < 1.0]
    )


def test_mesh_as_prior(rig: Rig, reconstructor: Reconstructor, plate_frames) -> None:
    cloud = reconstruct(
        rig, plate_frames, prior=plate_mesh(PLATE_TOP_MM), reconstructor=reconstructor
    )
    top = cloud.points[np.abs(cloud.points[:, 2] - PLATE_TOP_MM) < 1.0]
    assert len(top) > 50_000
    # The plate is 40 mm thick: the search stops ~10 mm above it.
    assert cloud.points[:, 2].max() < PLATE_TOP_MM + 12.0


def test_prior_from_cad() -> None:
    cad = sheet_metal_panel(PanelSpec().scaled(400, 260))
    prior = Prior.from_cad(cad)
    height = float(np.ptp(cad.vertices[:, 2]))
    assert height < prior.z_max_mm < height + 20.0
    with pytest.raises(InvalidInput):
        Prior.from_cad(np.zeros((2, 3)))
    with pytest.raises(InvalidInput):
        Prior(z_max_mm=-1.0)


# -- CAD-guided matching ------------------------------------------------------


@pytest.fixture(scope="module")
def panel_scene(rig: Rig, reconstructor: Reconstructor):  # type: ignore[no-untyped-def]
    """The demo panel across the belt: its CAD, tree, pose, frames and unguided cloud."""
    cad = sheet_metal_panel(PanelSpec().scaled(400.0, 260.0))
    T = belt_pose(-50.0, -150.0, 160.0)
    frames = simulate(rig, cad, T, seed=4)
    return cad, GridTree.build(cad), T, frames, reconstructor(frames)


@pytest.fixture(scope="module")
def panel_matching(reconstructor: Reconstructor, panel_scene) -> Matching:
    """What the matching of the panel scene's unguided pass found, for the guided passes."""
    return reconstructor.match(panel_scene[3])[1]


def _surface_errors(tree: GridTree, T: np.ndarray, cloud: Cloud) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances of the points within 1 mm of the posed CAD, and which lie on bends
    (normal over 15 degrees from the panel's up: emboss, character line, edge radii)."""
    P = (cloud.points - T[:3, 3]) @ T[:3, :3]
    q = tree.query(P)
    r = np.einsum("ij,ij->i", P - q.points, q.normals)
    near = np.abs(r) < 1.0
    bends = q.normals[:, 2] < np.cos(np.radians(15.0))
    return r[near], bends[near]


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r**2)))


def test_guide_follows_the_bends(reconstructor: Reconstructor, panel_scene) -> None:
    cad, tree, T, frames, plain = panel_scene
    guided = reconstructor(frames, guide=Guide.from_cad(cad, T))
    r0, b0 = _surface_errors(tree, T, plain)
    r1, b1 = _surface_errors(tree, T, guided)
    assert b0.sum() > 3000 and b1.sum() > 3000
    # Windows warped by the measured (smoothed) field leave the bends ~0.3 mm
    # off; warped by the CAD's field, about half that.
    assert _rms(r1[b1]) < 0.7 * _rms(r0[b0])
    assert _rms(r1[~b1]) <= _rms(r0[~b0])
    assert abs(np.median(r1[~b1])) < 0.01
    assert len(guided) > 0.98 * len(plain)
    assert {"guide0", "guide1"} <= set(guided.report.timings_ms)


def test_guided_from_a_matching_is_the_same_cloud(
    rig: Rig, reconstructor: Reconstructor, panel_scene
) -> None:
    cad, _, T, frames, plain = panel_scene
    guide = Guide.from_cad(cad, T)
    first, matching = reconstructor.match(frames)
    assert isinstance(matching, Matching) and matching.reconstructor is reconstructor
    np.testing.assert_array_equal(first.points, plain.points)
    np.testing.assert_array_equal(first.weights, plain.weights)
    again, guided = reconstructor.guided(matching, guide)
    once = reconstructor(frames, guide=guide)
    np.testing.assert_array_equal(again.points, once.points)
    np.testing.assert_array_equal(again.weights, once.weights)
    assert again.report.pairs == once.report.pairs
    assert isinstance(guided, Matching) and guided is not matching
    # A pass does not change the matching it starts from: it can start another.
    twice, _ = reconstructor.guided(matching, guide)
    np.testing.assert_array_equal(twice.points, again.points)
    # The stereo pairs ran only their warped passes again; the ring pairs are
    # matched in this pass alone, from the guide (no coarse search).
    ran = set(again.report.timings_ms)
    n = len(reconstructor.pairs)
    assert not any(k.startswith(("sgbm", "rectify")) for k in ran)
    assert not {f"refine{k}" for k in range(n)} & ran
    assert {f"refine{k}" for k in range(n, n + len(reconstructor.guide_pairs))} <= ran
    with pytest.raises(InvalidInput, match="Matching"):
        reconstructor.guided(plain, guide)  # type: ignore[arg-type]
    with pytest.raises(InvalidInput, match="another reconstructor"):
        Reconstructor.build(rig).guided(matching, guide)
    with pytest.raises(InvalidInput, match="Guide"):
        reconstructor.guided(matching, None)  # type: ignore[arg-type]


def _in_plane_errors(T_cad_rig: np.ndarray, T_rig_part: np.ndarray) -> tuple[float, float]:
    """The fitted pose's turn about the belt's normal (deg) and shift (mm), absolute."""
    dT = T_cad_rig @ T_rig_part
    turn = np.degrees(np.arctan2(dT[1, 0], dT[0, 0]))
    return abs(float(turn)), float(np.linalg.norm(dT[:3, 3]))


def _assert_on_the_rows_over_the_whole_part(
    reconstructor: Reconstructor, cloud: Cloud, plain: Cloud
) -> None:
    """Each pair's points lie on every sparse_rows-th rectified row, over the extent of
    its points in the full pass ``plain``."""
    rows = reconstructor.params.sparse_rows
    for k, pair in enumerate(reconstructor.pairs):
        mine = cloud.points[cloud.pair == k]
        _, y, _ = pair.project(mine)
        # Fused points move along the other pair's ray: off their row by a fraction.
        assert np.median(np.abs(y - rows * np.round(y / rows))) < 0.1
        full = plain.points[plain.pair == k]
        np.testing.assert_allclose(
            np.ptp(mine[:, :2], axis=0), np.ptp(full[:, :2], axis=0), atol=3.0
        )


def test_a_sparse_first_pass_places_the_guide_and_matches_the_same(
    reconstructor: Reconstructor, panel_scene
) -> None:
    cad, tree, T, frames, plain = panel_scene
    sparse, matching = reconstructor.match(frames, sparse=True)
    # Points from every sparse_rows-th rectified row only: of the rows refined (every
    # row_stride-th), the share row_stride / sparse_rows, on the whole part (each pair,
    # the same extent).
    rows = reconstructor.params.sparse_rows
    share = reconstructor.params.row_stride / rows
    assert 0.6 * share * len(plain) < len(sparse) < 1.4 * share * len(plain)
    _assert_on_the_rows_over_the_whole_part(reconstructor, sparse, plain)
    # As good a surface as the full pass's, point for point: the same windows, fewer.
    r, _ = _surface_errors(tree, T, sparse)
    r_full, _ = _surface_errors(tree, T, plain)
    assert len(r) > 0.95 * len(sparse) and _rms(r) < 1.1 * _rms(r_full)
    # What the guided pass starts from is every square window, as without sparse.
    guide = Guide.from_cad(cad, T)
    from_sparse, _ = reconstructor.guided(matching, guide)
    from_full, _ = reconstructor.guided(reconstructor.match(frames)[1], guide)
    np.testing.assert_array_equal(from_sparse.points, from_full.points)
    np.testing.assert_array_equal(from_sparse.weights, from_full.weights)
    with pytest.raises(InvalidInput, match="sparse"):
        reconstructor.match(frames, guide=guide, sparse=True)


def test_a_sparse_cloud_matches_its_rows_alone_and_places_the_part_as_well(
    reconstructor: Reconstructor, panel_scene
) -> None:
    cad, tree, T, frames, plain = panel_scene
    cloud = reconstructor.sparse_cloud(frames)
    sparse, _ = reconstructor.match(frames, sparse=True)
    assert 0.8 * len(sparse) < len(cloud) < 1.2 * len(sparse)
    _assert_on_the_rows_over_the_whole_part(reconstructor, cloud, plain)
    # The windows follow the sparse rows' field filled across the rows between: the
    # surface as good as the full pass's, on the bends too.
    r, bent = _surface_errors(tree, T, cloud)
    r_full, bent_full = _surface_errors(tree, T, plain)
    assert len(r) > 0.95 * len(cloud) and _rms(r) < 1.1 * _rms(r_full)
    assert _rms(r[bent]) < 1.1 * _rms(r_full[bent_full])


def test_a_sparse_cloud_warps_its_windows_as_its_own_params_say(
    reconstructor: Reconstructor, panel_scene
) -> None:
    frames = panel_scene[3]
    p = reconstructor.params

    def with_params(**changes: object) -> Reconstructor:
        return dataclasses.replace(reconstructor, params=dataclasses.replace(p, **changes))

    cloud = reconstructor.sparse_cloud(frames)
    # The first pass's warping does not reach it ...
    other_first = with_params(warp_slope=p.warp_slope + 0.5, warp_passes=p.warp_passes + 1)
    np.testing.assert_array_equal(other_first.sparse_cloud(frames).points, cloud.points)
    # ... its own does: the windows on the slopes between its threshold and the first
    # pass's are warped.
    assert p.sparse_cloud_warp_slope < p.warp_slope
    steeper = with_params(sparse_cloud_warp_slope=p.warp_slope).sparse_cloud(frames)
    assert len(steeper) != len(cloud) or not np.array_equal(steeper.points, cloud.points)


def test_field_slopes_against_numpy() -> None:
    rng = np.random.default_rng(3)
    field_ = rng.normal(size=(40, 50)).astype(np.float32)
    field_[rng.random(field_.shape) < 0.3] = np.nan
    field_[:, 20] = np.nan  # a column off the field: one-sided slopes beside it
    on = np.isfinite(field_)
    f = np.where(on, field_, 0.0).astype(np.float32)
    out = [np.empty_like(f), np.empty_like(f)]
    kernels.field_slopes(field_, *out)
    for axis, got in ((1, out[0]), (0, out[1])):
        fa, oa = np.moveaxis(f, axis, -1), np.moveaxis(on, axis, -1)
        both = oa[..., 1:] & oa[..., :-1]
        diff = np.where(both, fa[..., 1:] - fa[..., :-1], 0.0)
        total = np.zeros_like(fa)
        count = np.zeros(fa.shape)
        total[..., 1:] += diff
        total[..., :-1] += diff
        count[..., 1:] += both
        count[..., :-1] += both
        want = np.moveaxis(total / np.maximum(count, 1), -1, axis)
        np.testing.assert_allclose(got, want, atol=1e-6)
        assert (got[~on] == 0).all()


def _fill_once_along(a: np.ndarray, axis: int) -> np.ndarray:
    """One pass of the gap fill along ``axis``, in numpy: a NaN takes the mean of its
    measured neighbours (of the values before the pass)."""
    m = np.moveaxis(a, axis, -1)
    on = np.isfinite(m)
    v = np.where(on, m, 0.0)
    total = np.zeros_like(m)
    count = np.zeros(m.shape)
    total[..., 1:] += v[..., :-1]
    count[..., 1:] += on[..., :-1]
    total[..., :-1] += v[..., 1:]
    count[..., :-1] += on[..., 1:]
    out = np.where(~on & (count > 0), total / np.maximum(count, 1), m)
    return np.moveaxis(out, -1, axis)


def _field_with_holes(seed: int) -> np.ndarray:
    """A disparity field (px) with a ramp, a bend along each axis and holes, NaN off it."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:48, 0:64].astype(np.float32)
    f = 40.0 + 0.05 * x + 0.3 * np.maximum(x - 30.0, 0.0) + 0.2 * np.maximum(y - 24.0, 0.0)
    f = f.astype(np.float32)
    f += rng.normal(0.0, 0.001, f.shape).astype(np.float32)
    f[:, 40:][rng.random((48, 24)) < 0.05] = np.nan
    f[10:18, 5:15] = np.nan
    return f


def test_the_windows_on_bends_are_those_numpy_finds_to_the_bit() -> None:
    p = ReconstructParams()
    field_ = _field_with_holes(3)
    known = np.isfinite(field_)
    mask = known.astype(np.float32)
    smooth = np.where(known, field_, 0.0).astype(np.float32)
    py, px = np.nonzero(np.ones(field_.shape, bool))
    # The rule as numpy states it, in float32 throughout.
    kw = (p.window, p.window)
    num = cv2.boxFilter(smooth, cv2.CV_32F, kw, normalize=False, borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(mask, cv2.CV_32F, kw, normalize=False, borderType=cv2.BORDER_CONSTANT)
    cnt = den[py, px]
    off = np.abs(num[py, px] / np.maximum(cnt, 1.0) - smooth[py, px])
    right = smooth[py, np.minimum(px + 1, smooth.shape[1] - 1)]
    slope = np.abs(right - smooth[py, np.maximum(px - 1, 0)]) * 0.5
    want = (off > p.warp_curvature_px) | (slope > p.warp_slope) | (cnt < p.window**2 - 0.5)
    got = bends(smooth, mask, px, py, p)
    assert 0 < got.sum() < len(got)
    np.testing.assert_array_equal(got, want)


def test_the_windows_spanning_a_bend_and_the_light_coordinates_are_numpy_s() -> None:
    field_ = _field_with_holes(4).astype(np.float64)
    _, bent = shading(field_, 9, 0.01)
    on_part = np.isfinite(field_)
    a = np.empty(field_.shape, np.float32)
    b = np.empty(field_.shape, np.float32)
    reconstruct_kernels.field_slopes(field_.astype(np.float32), a, b)
    k = np.ones((9, 9), np.uint8)
    want = np.zeros(field_.shape, bool)
    for g in (a, b):
        hi = cv2.dilate(np.where(on_part, g, np.float32(-1e30)), k)
        lo = cv2.erode(np.where(on_part, g, np.float32(1e30)), k)
        want |= hi - lo > 0.01
    assert 0 < bent.sum() < bent.size
    np.testing.assert_array_equal(bent, want)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("view", ["whole", "crop"])
def test_local_normalisation_is_numpy_s_formula_to_the_bit(dtype: type, view: str) -> None:
    rng = np.random.default_rng(11)
    img = (rng.random((90, 120)) * 255.0).astype(dtype)
    # Nearly flat and bright: the box variance, a small difference of large sums,
    # rounds below 0 there.
    img[20:50, 30:80] = (200.0 + 0.01 * rng.random((30, 50))).astype(dtype)
    if view == "crop":
        img = img[5:83, 9:111]  # a strided view, as the crops are
    k = (15, 15)
    mean = cv2.boxFilter(img, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    sq = cv2.boxFilter(img * img, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    want = ((img - mean) / np.sqrt(np.maximum(sq - mean * mean, 0.0) + 4.0)).astype(np.float32)
    got = local_normalise(img, 15)
    assert got.dtype == np.float32 and got.shape == img.shape
    assert got.tobytes() == want.tobytes()


@pytest.mark.parametrize(("x0", "y0"), [(0, 0), (7, 3), (12, 9)])
@pytest.mark.parametrize(("stride", "row_stride"), [(1, 1), (2, 1), (2, 4), (3, 2)])
def test_the_pixels_refined_are_those_on_the_image_grid_in_row_major_order(
    x0: int, y0: int, stride: int, row_stride: int
) -> None:
    mask = np.random.default_rng(x0 + 10 * y0).random((37, 53)) < 0.6
    py, px = np.nonzero(mask)
    on_grid = ((px + x0) % stride == 0) & ((py + y0) % row_stride == 0)
    got_y, got_x = grid_pixels(mask, x0, y0, stride, row_stride)
    np.testing.assert_array_equal(got_y, py[on_grid])
    np.testing.assert_array_equal(got_x, px[on_grid])


@pytest.mark.parametrize("row_stride", [2, 4])
def test_the_gaps_between_refined_rows_and_columns_close_as_numpy_closes_them(
    row_stride: int,
) -> None:
    rng = np.random.default_rng(5)
    measured = rng.normal(100.0, 5.0, size=(60, 70)).astype(np.float32)
    measured[np.arange(60) % row_stride != 1, :] = np.nan  # the rows not refined
    measured[:, 1::2] = np.nan  # the columns not refined
    measured[20:30, 30:40] = np.nan  # a hole in the part
    p = ReconstructParams(stride=2, row_stride=row_stride)
    want = _fill_once_along(_fill_once_along(measured, 1), 1)
    for _ in range(row_stride // 2):
        want = _fill_once_along(want, 0)
    got = measured.copy()
    fill_gaps(got, p)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    # Every row and column gap is closed; the hole only shrinks by the passes' reach.
    assert np.isfinite(got[2:20]).all() and np.isfinite(got[40:58]).all()
    assert np.isnan(got[23:28, 33:37]).all()


@pytest.mark.parametrize(("deg", "shift"), [(0.05, (0.2, 0.0, 0.0)), (-0.05, (0.0, 0.2, 0.0))])
def test_rematching_the_bends_undoes_the_pull_of_a_misplaced_guide(
    reconstructor: Reconstructor,
    panel_scene,
    panel_matching: Matching,
    deg: float,
    shift: tuple[float, ...],
) -> None:
    # A guide turned 0.05 deg and shifted 0.2 mm in the belt's plane pulls the
    # windows on bends towards it: the fitted pose follows the guide by a
    # quarter of its turn. Matching those windows again with the guide in
    # place puts the fit back within what the noise and the outline's pixels
    # (each part material, part belt) leave.
    cad, tree, T, *_ = panel_scene
    D = np.eye(4)
    D[:3, :3] = Rotation.from_euler("z", deg, degrees=True).as_matrix()
    D[:3, 3] = T[:3, 3] - D[:3, :3] @ T[:3, 3] + np.asarray(shift)
    pulled, guided = reconstructor.guided(panel_matching, Guide.from_cad(cad, D @ T))

    def fit(cloud: Cloud) -> tuple[float, float]:
        reg = register(tree, cloud.points, init=np.linalg.inv(T), weights=cloud.weights)
        return _in_plane_errors(reg.transform, T)

    turn, moved = fit(pulled)
    assert turn > 0.008 and moved > 0.03
    again, rematched = reconstructor.rematch_bends(guided, Guide.from_cad(cad, T))
    turn, moved = fit(again)
    assert turn < 0.004 and moved < 0.03
    # Only the windows on bends and at the outline were matched again: most
    # points are those of the guided cloud, bit for bit.
    rows = np.dtype((np.void, 3 * 8))
    kept = np.isin(again.points.view(rows).ravel(), pulled.points.view(rows).ravel())
    assert 0.6 < kept.mean() < 0.95
    ran = set(again.report.timings_ms)
    pairs = len(reconstructor.pairs) + len(reconstructor.guide_pairs)
    assert {f"rematch{k}" for k in range(pairs)} <= ran
    assert not any(k.startswith(("sgbm", "refine", "warp")) for k in ran)
    # It can follow itself, with a guide still closer.
    assert len(reconstructor.rematch_bends(rematched, Guide.from_cad(cad, T))[0]) > 0


def test_rematch_bends_needs_a_guided_matching(
    rig: Rig, reconstructor: Reconstructor, panel_scene, panel_matching: Matching
) -> None:
    cad, _, T, _, plain = panel_scene
    guide = Guide.from_cad(cad, T)
    with pytest.raises(InvalidInput, match="Matching"):
        reconstructor.rematch_bends(plain, guide)  # type: ignore[arg-type]
    with pytest.raises(InvalidInput, match="guided"):
        reconstructor.rematch_bends(panel_matching, guide)
    _, guided = reconstructor.guided(panel_matching, guide)
    with pytest.raises(InvalidInput, match="another reconstructor"):
        Reconstructor.build(rig).rematch_bends(guided, guide)
    with pytest.raises(InvalidInput, match="Guide"):
        reconstructor.rematch_bends(guided, None)  # type: ignore[arg-type]


def test_ring_pairs_join_the_guided_pass(
    rig: Rig, reconstructor: Reconstructor, panel_scene
) -> None:
    # The ring pairs (baselines along y) are matched only with a guide, started
    # from its disparities: their points are as close to the surface as the
    # stereo pairs', and with twice the pairs more of them are confirmed.
    cad, tree, T, frames, plain = panel_scene
    assert len(reconstructor.guide_pairs) == len(rig.ring_pairs) == 2
    assert set(np.unique(plain.pair)) == {0, 1} and len(plain.report.pairs) == 2
    guided = reconstructor(frames, guide=Guide.from_cad(cad, T))
    assert set(np.unique(guided.pair)) == {0, 1, 2, 3}
    assert [r.pair for r in guided.report.pairs[2:]] == [p.name for p in reconstructor.guide_pairs]
    alone = Reconstructor.build(rig, ReconstructParams(guided_ring_pairs=False))
    two = alone(frames, guide=Guide.from_cad(cad, T))
    assert set(np.unique(two.pair)) == {0, 1}
    r2, _ = _surface_errors(tree, T, two)
    for k in (2, 3):
        sel = guided.pair == k
        ring = Cloud(guided.points[sel], guided.weights[sel], guided.pair[sel], guided.report)
        r, _ = _surface_errors(tree, T, ring)
        assert len(r) > 0.4 * len(r2)  # about as many as each stereo pair
        assert _rms(r) < 1.1 * _rms(r2)
    confirmed = sum(p.confirmed for p in guided.report.pairs[:2])
    assert confirmed > sum(p.confirmed for p in two.report.pairs)


def test_a_ring_pair_with_an_unusable_frame_is_skipped(
    reconstructor: Reconstructor, panel_scene
) -> None:
    cad, _, T, frames, _ = panel_scene
    dark = [f.copy() for f in frames]
    dark[2][:] = 0
    cloud = reconstructor(dark, guide=Guide.from_cad(cad, T))
    pairs = reconstructor.pairs + reconstructor.guide_pairs
    assert len(cloud.report.pairs) == 4
    for k, (pair, rep) in enumerate(zip(pairs, cloud.report.pairs, strict=True)):
        uses_dark = 2 in (pair.left, pair.right)
        assert bool(rep.skipped) == uses_dark
        assert (cloud.pair == k).any() != uses_dark
    assert "pair_skipped" in cloud.report.flags


def test_guide_off_the_part_does_no_harm(reconstructor: Reconstructor, panel_scene) -> None:
    cad, tree, T, frames, plain = panel_scene
    off = T.copy()
    off[2, 3] += 10.0  # 5 px of disparity: beyond guide_tolerance_px nearly everywhere
    cloud = reconstructor(frames, guide=Guide.from_cad(cad, off))
    r0, b0 = _surface_errors(tree, T, plain)
    r1, b1 = _surface_errors(tree, T, cloud)
    assert _rms(r1[b1]) < 1.05 * _rms(r0[b0])
    assert _rms(r1[~b1]) < 1.05 * _rms(r0[~b0])
    assert abs(len(cloud) - len(plain)) < 0.02 * len(plain)


def _shifted_speckle(shift: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random speckle blurred by a Gaussian of 0.8 px (band-limited, so that a shift by
    a fraction of a pixel is exact in Fourier space), and the same moved left by
    ``shift``: L(x) = R(x - shift). Both locally normalised."""
    rng = np.random.default_rng(seed)
    h, w = 48, 256
    f = np.fft.fftfreq(w)
    spectrum = np.fft.fft(rng.random((h, w)) ** 4, axis=1) * np.exp(-2.0 * (np.pi * 0.8 * f) ** 2)
    left = np.real(np.fft.ifft(spectrum, axis=1))
    right = np.real(np.fft.ifft(spectrum * np.exp(2j * np.pi * f * shift), axis=1))
    return (
        local_normalise(left.astype(np.float32), 15),
        local_normalise(right.astype(np.float32), 15),
    )


def test_sub_pixel_disparities_are_not_pulled_to_half_pixels() -> None:
    # Pixel locking: the interpolation of the right image smooths it by an amount
    # that depends on the disparity's fraction, and pulls the fit towards the
    # fractions it favours. Catmull-Rom's convolution pulls this speckle by up
    # to 0.029 px; the cubic B-spline through the pixels by 0.008 px.
    ys, xs = np.mgrid[8:40:2, 20:236:2]
    px, py = xs.ravel().astype(np.int64), ys.ravel().astype(np.int64)
    bias = []
    for shift in np.linspace(0.1, 0.9, 9):
        errors = []
        for seed in range(3):
            left, right = _shifted_speckle(shift, seed)
            ones = np.ones_like(left)
            out = [np.empty(len(px), np.float32) for _ in range(3)]
            start = np.full(len(px), shift + 0.3, np.float32)
            kernels.refine_pixels(left, spline_rows(right), ones, ones, px, py, start, 4, 10, *out)
            assert np.isfinite(out[0]).all()
            errors.append(out[0] - shift)
        bias.append(float(np.mean(errors)))
    assert max(abs(b) for b in bias) < 0.012


def _bend_pair(sheen_left: float, sheen_right: float, seed: int):  # type: ignore[no-untyped-def]
    """A rectified pair of one surface that bends (the disparity's slope turns from 0
    to 0.25 within a few pixels), covered in speckle of unit contrast, plus a sheen
    that grows with the slope, as strong as given in each view; locally normalised,
    with the field, the slope (x10) and the pixels across the bend."""
    rng = np.random.default_rng(seed)
    h, w, up, width = 41, 240, 4, 2.0
    x = np.arange(w, dtype=np.float64)

    def field(u):  # type: ignore[no-untyped-def]
        return 30.0 + 0.25 * width * np.logaddexp(0.0, (u - 120.0) / width)

    def slope(u):  # type: ignore[no-untyped-def]
        return 0.25 / (1.0 + np.exp(-(u - 120.0) / width))

    speckle = cv2.GaussianBlur(rng.standard_normal((h, up * w)).astype(np.float32), (0, 0), up)
    speckle /= speckle.std()

    def image(u, sheen):  # type: ignore[no-untyped-def]
        rows = [np.interp(u, np.arange(up * w) / up, speckle[r]) for r in range(h)]
        return local_normalise(
            (np.array(rows) + sheen * (slope(u) / 0.25) ** 2).astype(np.float32), 15
        )

    fine = np.linspace(0.0, w - 1.0, 20 * w)
    left = image(x, sheen_left)
    right = image(np.interp(x, fine - field(fine), fine), sheen_right)
    px = np.arange(100, 150, dtype=np.int64)
    shape = np.tile(field(x), (h, 1)).astype(np.float32)
    su = np.tile(10.0 * slope(x), (h, 1)).astype(np.float32)
    return left, right, shape, su, px, np.full(len(px), h // 2, np.int64), field(px)


def _bend_errors(sheen_left: float, sheen_right: float, seed: int) -> tuple[float, float]:
    """RMS disparity error across the bend of :func:`_bend_pair`, px: windows warped by
    the true field, fitted with a gain and offset, and with the light as well."""
    left, right, shape, su, px, py, truth = _bend_pair(sheen_left, sheen_right, seed)
    right = spline_rows(right)
    ones = np.ones_like(shape)
    start = (truth + 0.3).astype(np.float32)
    errors = []
    for shaded in (False, True):
        out = [np.empty(len(px), np.float32) for _ in range(3)]
        if shaded:
            kernels.refine_warped_shaded(
                left,
                right,
                ones,
                ones,
                shape,
                ones,
                su,
                np.zeros_like(su),
                1e-3,
                px,
                py,
                start,
                4,
                5,
                *out,
            )
        else:
            kernels.refine_warped(left, right, ones, ones, shape, ones, px, py, start, 4, 5, *out)
        errors.append(float(np.sqrt(np.mean((out[0] - truth) ** 2))))
    return errors[0], errors[1]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_light_that_follows_the_slope_does_not_shift_a_bend(seed: int) -> None:
    # Sheen six and one times the speckle's contrast: a gain and an offset leave
    # the bend 0.1-0.2 px off; fitting the light as a function of the slope
    # takes out most of it.
    plain, shaded = _bend_errors(6.0, 1.0, seed)
    assert plain > 0.09
    assert shaded < 0.5 * plain
    # Without sheen the extra terms cost next to nothing.
    plain, shaded = _bend_errors(0.0, 0.0, seed)
    assert shaded < 1.2 * plain


def test_guided_shading_on_the_panel(rig: Rig, panel_scene) -> None:
    # The simulator's flash has a broad sheen, which each camera sees at another
    # place: on the panel's bends, fitting it with the disparity brings the
    # error down by a fifth or more; off them, where the windows are fitted as
    # before, nothing gets worse.
    cad, tree, T, frames, _ = panel_scene
    guide = Guide.from_cad(cad, T)
    off = Reconstructor.build(rig, ReconstructParams(shading=False))(frames, guide=guide)
    on = Reconstructor.build(rig)(frames, guide=guide)
    r0, b0 = _surface_errors(tree, T, off)
    r1, b1 = _surface_errors(tree, T, on)
    assert _rms(r1[b1]) < 0.8 * _rms(r0[b0])
    assert _rms(r1[~b1]) <= _rms(r0[~b0])
    assert len(on) > 0.99 * len(off)


def test_guide_keeps_a_dent(rig: Rig, reconstructor: Reconstructor) -> None:
    # The guide is the undented plate: only the windows' shape comes from it,
    # the dent's depth is still measured.
    frames = simulate(rig, plate_mesh(PLATE_TOP_MM, DENT_DEPTH_MM), np.eye(4), seed=5)
    pts = reconstructor(frames, guide=Guide.from_cad(plate_mesh(PLATE_TOP_MM), np.eye(4))).points
    r = np.hypot(pts[:, 0] - DENT_AT[0], pts[:, 1] - DENT_AT[1])
    depth = np.median(pts[(r > 40.0) & (r < 60.0), 2]) - np.median(pts[r < 2.0, 2])
    assert depth == pytest.approx(DENT_DEPTH_MM, abs=0.15)


def test_bad_guides(rig: Rig, reconstructor: Reconstructor, plate_frames) -> None:
    plate = plate_mesh(PLATE_TOP_MM)
    skew = np.eye(4)
    skew[0, 1] = 0.1
    flipped = np.diag([1.0, 1.0, -1.0, 1.0])
    for cad, T, message in (
        (object(), np.eye(4), "vertices and faces"),
        (trimesh.Trimesh(plate.vertices[:2], np.zeros((0, 3), int)), np.eye(4), "vertices"),
        (trimesh.Trimesh(plate.vertices, plate.faces + len(plate.vertices), process=False),
         np.eye(4), "faces"),
        (plate, np.eye(3), "4, 4"),
        (plate, np.full((4, 4), np.nan), "non-finite"),
        (plate, skew, "rigid"),
        (plate, flipped, "rigid"),
    ):  # fmt: skip
        with pytest.raises(InvalidInput, match=message):
            Guide.from_cad(cad, T)
    with pytest.raises(InvalidInput, match="Guide"):
        reconstructor(plate_frames, guide=plate)
    symmetric = Reconstructor.build(rig, ReconstructParams(symmetric=True))
    with pytest.raises(InvalidInput, match="symmetric"):
        symmetric(plate_frames, guide=Guide.from_cad(plate, np.eye(4)))


# -- bad frames ---------------------------------------------------------------


def _frames(rig: Rig, value: int = 80) -> list[np.ndarray]:
    return [np.full(cam.shape, value, np.uint8) for cam in rig.cameras]


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda fr: fr[:3], "need 4 frames"),
        (lambda fr: fr + fr[:1], "need 4 frames"),
        (lambda fr: [fr[0][:-1]] + fr[1:], "shape"),
        (lambda fr: [fr[0].astype(np.uint16)] + fr[1:], "uint8"),
        (lambda fr: [fr[0].astype(np.float32)] + fr[1:], "uint8"),
        (lambda fr: [np.stack([fr[0]] * 3, axis=-1)] + fr[1:], "2-D"),
        (lambda fr: [fr[0].tolist()] + fr[1:], "numpy array"),
        (lambda fr: None, "sequence"),
    ],
)
def test_malformed_frames_raise(rig: Rig, reconstructor: Reconstructor, make, message: str) -> None:
    with pytest.raises(InvalidInput, match=message):
        reconstruct(rig, make(_frames(rig)), reconstructor=reconstructor)


@pytest.mark.parametrize("value, flag", [(0, FLAG_TOO_DARK), (255, FLAG_SATURATED)])
def test_black_or_saturated_frames_give_empty_flagged_cloud(
    rig: Rig, reconstructor: Reconstructor, value: int, flag: str
) -> None:
    cloud = reconstruct(rig, _frames(rig, value), reconstructor=reconstructor)
    assert cloud.empty and len(cloud.weights) == 0 and cloud.points.shape == (0, 3)
    assert flag in cloud.report.flags and FLAG_EMPTY in cloud.report.flags
    assert all(flag in f for f in cloud.report.frame_flags)
    assert all(p.skipped for p in cloud.report.pairs)


def test_one_dark_frame_loses_one_pair(
    rig: Rig, reconstructor: Reconstructor, plate_frames
) -> None:
    frames = list(plate_frames)
    frames[2] = np.zeros_like(frames[2])
    cloud = reconstructor(frames)
    assert FLAG_TOO_DARK in cloud.report.flags and not cloud.empty
    assert set(np.unique(cloud.pair)) == {0}
    assert cloud.report.pairs[1].skipped


def test_featureless_frames_give_empty_cloud(rig: Rig, reconstructor: Reconstructor) -> None:
    cloud = reconstruct(rig, _frames(rig, 120), reconstructor=reconstructor)
    assert cloud.empty and FLAG_EMPTY in cloud.report.flags


def test_empty_belt_gives_empty_cloud(rig: Rig, reconstructor: Reconstructor) -> None:
    far = np.eye(4)
    far[:3, 3] = (5000.0, 0.0, 0.0)  # the part is out of view: only the belt is seen
    frames = simulate(rig, plate_mesh(PLATE_TOP_MM, size=(20.0, 20.0)), far, seed=1)
    cloud = reconstructor(frames)
    assert FLAG_EMPTY in cloud.report.flags
    assert len(cloud) == 0


def test_reconstructor_of_another_rig_is_refused(reconstructor: Reconstructor) -> None:
    other = Rig.nominal(640, 512)
    with pytest.raises(InvalidInput, match="built for rig"):
        reconstruct(other, _frames(other), reconstructor=reconstructor)


def test_bad_params() -> None:
    with pytest.raises(InvalidInput):
        ReconstructParams(window=4)
    with pytest.raises(InvalidInput):
        ReconstructParams(z_min_mm=10.0, z_max_mm=5.0)
    with pytest.raises(InvalidInput):
        ReconstructParams(stride=0)
    for bad in (
        {"warp_passes": -1},
        {"sparse_cloud_warp_passes": -1},
        {"sparse_cloud_warp_slope": -0.1},
        {"warp_iterations": 0},
        {"warp_smooth": 4},
        {"threads": 0},
        {"warp_slope": float("nan")},
        {"score_full": 0.5},
        {"guide_tolerance_px": -1.0},
        {"guide_passes": 0},
        {"shading_bend": -0.01},
        {"row_stride": 0},
        {"row_stride": 3},  # sparse_rows (4) is not a multiple of it
    ):
        with pytest.raises(InvalidInput):
            ReconstructParams(**bad)


def test_other_image_size() -> None:
    small = Rig.nominal(640, 512)
    frames = simulate(small, plate_mesh(PLATE_TOP_MM), np.eye(4), seed=2)
    cloud = reconstruct(small, frames)
    top = cloud.points[np.abs(cloud.points[:, 2] - PLATE_TOP_MM) < 2.0]
    assert len(top) > 10_000
    assert abs(np.median(top[:, 2]) - PLATE_TOP_MM) < 0.1
