"""The measuring sequence's own rules: its inputs, its fit diagnostics, its verdict.

The clouds here are sampled from small synthetic parts, so that what the
fit can and cannot determine is known exactly: a flat plate (three free
directions, none of which moves a point on its face) and a step whose
only wall is seen by a handful of points (the direction across the wall
is all but free, and it moves a point on the wall along its normal).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh

from inspection.alignment import sample_facing
from inspection.cad import CadModel
from inspection.deviations import ComparisonPoint, ComparisonResult, Verdict, part_verdict
from inspection.errors import InvalidInput, TreeMismatch
from inspection.measure import (
    MIN_POINTS,
    MeasureParams,
    PartModel,
    RegisterParams,
    measure_cloud,
    measure_frames,
    pose_sigma_mm,
    subsample,
    validate_cloud,
)
from inspection.transforms import apply


def cad_of(mesh: trimesh.Trimesh, name: str) -> CadModel:
    return CadModel.from_arrays(np.asarray(mesh.vertices), np.asarray(mesh.faces), name=name)


def grid(xs: tuple[float, float], ys: tuple[float, float], z: float, step: float) -> np.ndarray:
    x, y = np.meshgrid(np.arange(*xs, step), np.arange(*ys, step))
    return np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])


def surface_point(name: str, x: float, y: float, z: float, normal=(0.0, 0.0, 1.0), **kw):
    kw = {"lower_mm": -0.05, "upper_mm": 0.05, "radius_mm": 5.0} | kw
    return ComparisonPoint(name, (x, y, z), normal, **kw)


@pytest.fixture(scope="module")
def plate() -> PartModel:
    box = trimesh.creation.box(extents=(200.0, 150.0, 2.0))  # top face at z = 1
    points = [surface_point("a", -50.0, 20.0, 1.0), surface_point("b", 60.0, -30.0, 1.0)]
    return PartModel.build(cad_of(box, "plate"), points, spacing_mm=2.0, alignment=False)


@pytest.fixture(scope="module")
def step() -> PartModel:
    """Two blocks side by side, tops at z = 2 (x < 0) and z = 6 (x > 0), a wall between at x = 0."""
    low = trimesh.creation.box(extents=(100.0, 150.0, 2.0))
    low.apply_translation((-50.0, 0.0, 1.0))
    high = trimesh.creation.box(extents=(100.0, 150.0, 6.0))
    high.apply_translation((50.0, 0.0, 3.0))
    mesh = trimesh.util.concatenate([low, high])
    points = [
        surface_point("low", -50.0, 10.0, 2.0),
        surface_point("high", 50.0, -10.0, 6.0),
        surface_point("wall", 0.0, 0.0, 4.0, normal=(-1.0, 0.0, 0.0), min_support=5),
    ]
    return PartModel.build(cad_of(mesh, "step"), points, spacing_mm=1.0, alignment=False)


def noisy(points: np.ndarray, sigma: float = 0.005, seed: int = 0) -> np.ndarray:
    return points + np.random.default_rng(seed).normal(scale=sigma, size=points.shape)


# ----------------------------------------------------------------------------- inputs


@pytest.mark.parametrize(
    "cloud, match",
    [
        (np.zeros((100, 2)), "shape"),
        (np.zeros((3, 100)), "shape"),
        (np.zeros(300), "shape"),
        (np.zeros((MIN_POINTS - 1, 3)), "at least"),
        (np.array([[np.nan, 0, 0]] + [[0, 0, 0]] * 20), "1 of 21 points"),
        (np.array([[np.inf, 0, 0]] * 20), "non-finite"),
        (np.array([["a", "b", "c"]] * 20), "numbers"),
    ],
)
def test_bad_clouds_are_refused(plate, cloud, match):
    with pytest.raises(InvalidInput, match=match):
        validate_cloud(cloud)
    with pytest.raises(InvalidInput, match=match):
        measure_cloud(plate, cloud, frame="cad")


def test_valid_clouds_become_float64_without_mutation():
    a = np.arange(60, dtype=np.float32).reshape(20, 3)
    before = a.copy()
    out = validate_cloud(a)
    assert out.dtype == np.float64 and out.flags.c_contiguous
    np.testing.assert_array_equal(out, before)
    np.testing.assert_array_equal(a, before)


def test_subsample_is_deterministic_and_keeps_order():
    p = np.arange(3000, dtype=np.float64).reshape(1000, 3)
    s = subsample(p, 100)
    assert len(s) == 100 and np.all(np.diff(s[:, 0]) > 0)
    np.testing.assert_array_equal(s, subsample(p, 100))
    assert subsample(p, 5000) is p


def test_an_unknown_path_is_refused():
    with pytest.raises(InvalidInput, match="path"):
        MeasureParams(path="holography")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"max_points": 10}, "max_points"),
        ({"min_inlier_fraction": 1.5}, "min_inlier_fraction"),
        ({"uncertainty_fraction": 0.0}, "uncertainty_fraction"),
        ({"register": RegisterParams(loss="l2", view_direction=None), "min_support": 0}, "support"),
    ],
)
def test_bad_parameters_fail_fast(kw, match):
    with pytest.raises(InvalidInput, match=match):
        MeasureParams(**kw)


def test_a_view_direction_needs_a_loss_with_a_plateau():
    with pytest.raises(InvalidInput, match="plateau"):
        dataclasses.replace(MeasureParams().register, loss="l2")
    with pytest.raises(InvalidInput, match="plateau"):
        RegisterParams(loss="l2", view_direction=(0.0, 0.0, 1.0))


def test_the_line_fits_seen_from_above_in_the_rig_frame_only():
    """The line's fit is register's with fewer iterations and a tighter gate;
    its view direction applies to clouds in the rig frame only."""
    p = MeasureParams()
    assert p.register == RegisterParams(
        max_iterations=50, max_distance_mm=10.0, view_direction=(0.0, 0.0, 1.0)
    )
    assert p.fit_params("rig") is p.register
    for frame in ("data", "cad"):
        assert p.fit_params(frame) == dataclasses.replace(p.register, view_direction=None)


def test_a_cloud_anywhere_needs_the_alignment_model(plate):
    cloud = grid((-90, 90), (-60, 60), 1.0, 5.0)
    with pytest.raises(InvalidInput, match="alignment model"):
        measure_cloud(plate, cloud, frame="rig")
    with pytest.raises(InvalidInput, match="frame"):
        measure_cloud(plate, cloud, frame="world")  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- verdict


def _result(name: str, verdict: Verdict) -> ComparisonResult:
    return ComparisonResult(name, 0.0, 20, verdict, -1.0, 1.0, 0.0)


@pytest.mark.parametrize(
    "verdicts, part",
    [
        ([], Verdict.PASS),
        (["pass", "pass"], Verdict.PASS),
        (["pass", "not_measurable"], Verdict.NOT_MEASURABLE),
        (["fail", "not_measurable"], Verdict.FAIL),
        (["pass", "fail"], Verdict.FAIL),
    ],
)
def test_the_part_verdict(verdicts, part):
    assert part_verdict([_result(f"p{i}", Verdict(v)) for i, v in enumerate(verdicts)]) is part


# ----------------------------------------------------------------------------- fit diagnostics


def test_a_flat_plate_passes_and_names_its_three_free_directions(plate):
    cloud = noisy(grid((-95, 95), (-70, 70), 1.0, 1.0))
    m = measure_cloud(plate, cloud, frame="cad")
    assert m.verdict is Verdict.PASS, m.reason
    q = m.quality
    assert q is not None and q.converged
    assert sorted(q.weak_directions) == [
        "rotation about z", "translation along x", "translation along y",
    ]  # fmt: skip
    assert q.observability < 1e-3 and q.ambiguous is None
    assert [c.verdict for c in m.deviations.comparison] == [Verdict.PASS, Verdict.PASS]
    assert all(abs(c.deviation_mm) < 0.005 for c in m.deviations.comparison)
    # Every stage's CPU time beside its wall time, the total covering the stages.
    assert set(m.cpu_ms) == set(m.timings_ms) == {"align", "deviations", "total"}
    assert 0 < m.cpu_ms["align"] + m.cpu_ms["deviations"] <= m.cpu_ms["total"] + 1.0


def step_cloud(wall_points: int, sigma: float = 0.005) -> np.ndarray:
    low = grid((-95, -5), (-70, 70), 2.0, 1.0)
    high = grid((5, 95), (-70, 70), 6.0, 1.0)
    rng = np.random.default_rng(1)
    wall = np.column_stack(
        [np.zeros(wall_points), rng.uniform(-3, 3, wall_points), rng.uniform(3, 5, wall_points)]
    )
    return noisy(np.concatenate([low, high, wall]), sigma)


def test_a_weak_direction_that_moves_a_point_makes_it_not_measurable(step):
    """A handful of noisy points on the wall: across it the pose is all but free."""
    m = measure_cloud(step, step_cloud(5, sigma=0.05), frame="cad")
    by_name = {c.name: c for c in m.deviations.comparison}
    assert by_name["low"].verdict is Verdict.PASS and by_name["high"].verdict is Verdict.PASS
    wall = by_name["wall"]
    assert wall.support >= 5  # seen: only the pose leaves it undetermined
    assert wall.verdict is Verdict.NOT_MEASURABLE and math.isnan(wall.deviation_mm)
    assert "translation along x" in wall.reason and "weakly constrained" in wall.reason
    assert "translation along x" in " ".join(m.quality.weak_directions)
    assert m.verdict is Verdict.NOT_MEASURABLE
    assert "wall" in m.reason and "translation along x" in m.reason


def test_a_free_direction_leaves_a_point_it_moves_undetermined(plate):
    """The plate does not resolve its in-plane slide at all: a normal with a
    component along x is moved by it without bound; one along z is not."""
    m = measure_cloud(plate, noisy(grid((-95, 95), (-70, 70), 1.0, 1.0)), frame="cad")
    tilted = np.array([0.6, 0.0, 0.8])
    sigma, free = pose_sigma_mm(m.registration, (10.0, 5.0, 1.0), tilted)
    assert math.isinf(sigma) and "translation along x" in free
    sigma, free = pose_sigma_mm(m.registration, (10.0, 5.0, 1.0), (0.0, 0.0, 1.0))
    assert free == () and 0 < sigma < 1e-3


def test_the_same_wall_seen_well_is_measured(step):
    m = measure_cloud(step, step_cloud(3000), frame="cad")
    assert m.verdict is Verdict.PASS, m.reason
    assert not any("translation along x" in d for d in m.quality.weak_directions)


def test_a_tight_tolerance_meets_the_pose_uncertainty(step):
    """Not free, only weak: the uncertainty along the wall's normal, not a free
    direction, is what a tight band cannot afford."""
    tight = dataclasses.replace(step.comparison_points[2], lower_mm=-0.0005, upper_mm=0.0005)
    part = dataclasses.replace(step, comparison_points=(*step.comparison_points[:2], tight))
    m = measure_cloud(part, step_cloud(200), frame="cad")
    wall = {c.name: c for c in m.deviations.comparison}["wall"]
    assert wall.verdict is Verdict.NOT_MEASURABLE, (wall, m.quality)
    assert "uncertain" in wall.reason


def test_a_thin_solid_is_fitted_to_its_top_when_seen_from_above():
    """A 1 mm sheet modelled as a solid, lying turned and shifted on the belt
    (where the rig measures: faces within 60 deg of up). With the view
    direction the fit keeps the points off the underside, 1 mm below;
    without it, this cloud ends on it."""
    from inspection.panel import PanelSpec, sheet_metal_panel

    spec = PanelSpec(length_mm=300.0, width_mm=200.0, thickness_mm=1.0, holes=())
    part = PartModel.build(sheet_metal_panel(spec, name="sheet"), spacing_mm=2.0)
    T_rig_cad = np.eye(4)
    T_rig_cad[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    T_rig_cad[:3, 3] = (-74.0, 55.0, 0.0)
    cad = part.cad
    pts, _ = sample_facing(
        cad.vertices, cad.faces, cad.face_normals, T_rig_cad, 50_000, seed=0, min_cos=0.5
    )
    cloud = noisy(pts, 0.02)
    corners = cad.bounds[[0, 1]]
    for view, on_top in (((0.0, 0.0, 1.0), True), (None, False)):
        params = MeasureParams(
            register=dataclasses.replace(MeasureParams().register, view_direction=view)
        )
        m = measure_cloud(part, cloud, params, frame="rig")
        T = m.transform @ T_rig_cad  # identity when exact
        off = np.abs(apply(T, corners) - corners).max()
        assert (off < 0.01) if on_top else (off > 0.5), (view, off)


# ----------------------------------------------------------------------------- the part


def test_a_part_model_round_trips_and_refuses_another_cad(plate, tmp_path):
    plate.save(tmp_path / "plate")
    again = PartModel.load(tmp_path / "plate", cad=plate.cad)
    assert again.tree.hash == plate.tree.hash and again.alignment is None
    assert again.comparison_points == plate.comparison_points
    other = cad_of(trimesh.creation.box(extents=(200.0, 150.0, 3.0)), "other")
    with pytest.raises(TreeMismatch):
        PartModel.load(tmp_path / "plate", cad=other)


def test_duplicate_comparison_points_are_refused(plate):
    with pytest.raises(InvalidInput, match="duplicate"):
        dataclasses.replace(plate, comparison_points=plate.comparison_points[:1] * 2)


def test_black_frames_are_measured_as_no_surface(plate):
    from inspection.rig import Rig

    rig = Rig.nominal().with_image_size(320, 256)
    frames = [np.zeros((256, 320), np.uint8) for _ in rig.cameras]
    part = dataclasses.replace(plate, alignment=_model(plate))
    m = measure_frames(part, rig, frames)
    assert m.verdict is None and "empty cloud" in m.reason
    assert m.transform is None and m.timings_ms["reconstruct"] >= 0.0


def _model(part: PartModel):
    from inspection.alignment import alignment_model

    return alignment_model(part.cad)
