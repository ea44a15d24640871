"""Local photogrammetry at the comparison points: deviations of a dented panel, and the reasons
a point cannot be measured."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from inspection.cadpoints import LocalModel, LocalParams, measure_points
from inspection.cadpoints.imagepose import ImagePoseModel, image_pose, outline_pose
from inspection.defects import Dent, press
from inspection.deviations import ComparisonPoint, Verdict
from inspection.errors import InvalidInput
from inspection.measure import MeasureParams, PartModel, measure_cloud, measure_frames
from inspection.panel import PanelSpec, sheet_metal_panel
from inspection.reconstruct import Reconstructor
from inspection.rig import Rig, belt_pose
from inspection.simulate import simulate
from inspection.surface import SurfaceParams

DENT_MM = 0.5
POSE = (30.0, -20.0, 20.0)


@pytest.fixture(scope="module")
def scene():  # type: ignore[no-untyped-def]
    cad = sheet_metal_panel(PanelSpec().scaled(240.0, 160.0))
    mesh = cad.to_trimesh()

    def top(x: float, y: float, name: str, radius: float = 10.0) -> ComparisonPoint:
        loc, _, tri = mesh.ray.intersects_location([[x, y, 500.0]], [[0.0, 0.0, -1.0]])
        k = int(np.argmax(loc[:, 2]))
        return ComparisonPoint(name, tuple(loc[k]), tuple(mesh.face_normals[tri[k]]), -0.2, 0.2,
                               radius)  # fmt: skip

    dent = top(0.0, 5.0, "dent")
    flat = top(40.0, -25.0, "flat")
    small = top(40.0, -25.0, "flat_4mm", 4.0)
    # Beneath the panel, facing the belt: no camera sees it.
    under = ComparisonPoint("under", (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), -0.2, 0.2, 10.0)
    dented = press(mesh, [Dent(dent.position, (0.0, 0.0, 1.0), DENT_MM, 30.0, 16.0)])
    T_rig_part = belt_pose(*POSE)
    frames = simulate(Rig.nominal(), dented, T_rig_part, seed=3)
    model = LocalModel.build(cad, [dent, flat, small, under], Rig.default())
    return model, frames, np.linalg.inv(T_rig_part), cad


@pytest.fixture(scope="module")
def measured(scene):  # type: ignore[no-untyped-def]
    model, frames, T_cad_rig, _ = scene
    return {m.name: m for m in measure_points(model, frames, T_cad_rig)}


def test_a_dent_and_the_flat_surface_are_measured(measured) -> None:  # type: ignore[no-untyped-def]
    dent, flat = measured["dent"], measured["flat"]
    assert dent.measurable and flat.measurable
    assert dent.deviation_mm == pytest.approx(-DENT_MM, abs=0.04)
    assert flat.deviation_mm == pytest.approx(0.0, abs=0.04)
    for m in (dent, flat):
        assert 0.0 < m.sigma_mm < 0.1
        assert m.support >= 100
        assert sum(k.reason is None for k in m.pairs) >= 2  # at least two pairs agree
        assert len(m.points) == m.support == len(m.deviations)


def test_a_smaller_support_pools_fewer_windows(measured) -> None:  # type: ignore[no-untyped-def]
    small, flat = measured["flat_4mm"], measured["flat"]
    assert small.measurable
    assert small.support < flat.support / 3
    assert small.deviation_mm == pytest.approx(0.0, abs=0.08)
    assert small.sigma_mm > flat.sigma_mm


def test_a_point_no_camera_sees_is_not_measurable_with_the_reason(measured) -> None:  # type: ignore[no-untyped-def]
    under = measured["under"]
    assert not under.measurable
    assert math.isnan(under.deviation_mm) and under.support == 0
    assert under.reason is not None and "no camera pair sees it well" in under.reason
    assert all(k.reason is not None for k in under.pairs)


def test_the_deviation_is_measured_from_the_pose(scene) -> None:  # type: ignore[no-untyped-def]
    # The CAD placed 0.4 mm lower than the part: the surface is 0.4 mm above it.
    model, frames, T_cad_rig, _ = scene
    lower = np.eye(4)
    lower[2, 3] = 0.4
    m = measure_points(model, frames, lower @ T_cad_rig)[1]
    assert m.measurable
    assert m.deviation_mm == pytest.approx(0.4, abs=0.06)


def test_a_part_outside_the_views_is_not_measurable(scene) -> None:  # type: ignore[no-untyped-def]
    model, frames, _, _ = scene
    far = np.linalg.inv(belt_pose(2000.0, 0.0, 0.0))
    m = measure_points(model, frames, far)[0]
    assert not m.measurable
    assert m.reason is not None


def test_bad_input_is_refused(scene) -> None:  # type: ignore[no-untyped-def]
    model, frames, T, _ = scene
    with pytest.raises(InvalidInput):
        measure_points(model, [f.astype(np.float32) for f in frames], T)
    with pytest.raises(InvalidInput, match="one per camera"):
        measure_points(model, frames[:2], T)
    with pytest.raises(InvalidInput, match="frame 0"):
        measure_points(model, [f[::2, ::2].copy() for f in frames], T)
    with pytest.raises(InvalidInput):
        measure_points(model, frames, np.zeros((4, 4)))
    with pytest.raises(InvalidInput):
        LocalParams(window=8)
    with pytest.raises(InvalidInput):
        LocalParams(max_view_deg=95.0)


# --------------------------------------------------------------------------- the path


@pytest.fixture(scope="module")
def part(scene):  # type: ignore[no-untyped-def]
    model, _, _, cad = scene
    # The dent out of a +-0.2 mm tolerance, the flat surface within it.
    return PartModel.build(cad, model.points[:2])


@pytest.fixture(scope="module")
def on_points(scene, part):  # type: ignore[no-untyped-def]
    _, frames, _, _ = scene
    params = MeasureParams(path="comparison_points", surface=SurfaceParams(fails_part=False))
    with Reconstructor.build(Rig.default()) as rec:
        return measure_frames(part, rec, frames, params)


def test_the_comparison_point_path_measures_through_the_sequence(on_points) -> None:  # type: ignore[no-untyped-def]
    m = on_points
    assert m.path == "comparison_points"
    assert m.verdict is Verdict.FAIL and m.reason is not None and "dent" in m.reason
    dent, flat = m.deviations.comparison
    assert dent.verdict is Verdict.FAIL and flat.verdict is Verdict.PASS
    assert dent.deviation_mm == pytest.approx(-DENT_MM, abs=0.05)
    assert flat.deviation_mm == pytest.approx(0.0, abs=0.05)
    assert m.deviations.defects is None  # the surface between the points was not checked
    assert [p.name for p in m.local] == ["dent", "flat"]
    assert {"reconstruct", "align", "points", "total"} <= set(m.timings_ms)
    assert m.transform is not None and m.registration is not None


def test_the_comparison_point_path_places_the_part_on_a_subsample(scene, part) -> None:  # type: ignore[no-untyped-def]
    _, frames, _, _ = scene
    params = MeasureParams(
        path="comparison_points", surface=SurfaceParams(fails_part=False), pose_points=3000
    )
    with Reconstructor.build(Rig.default()) as rec:
        m = measure_frames(part, rec, frames, params)
    assert m.registration is not None and 0 < m.registration.subset_sizes[-1] <= 3000
    assert len(m.points) > 3 * 3000
    dent, flat = m.deviations.comparison
    assert dent.deviation_mm == pytest.approx(-DENT_MM, abs=0.05)
    assert flat.deviation_mm == pytest.approx(0.0, abs=0.05)


def test_the_path_is_refused_where_it_cannot_judge() -> None:
    with pytest.raises(InvalidInput, match="surface"):
        MeasureParams(path="comparison_points")  # defects fail parts by default
    p = MeasureParams(path="comparison_points", surface=SurfaceParams(fails_part=False))
    with pytest.raises(InvalidInput, match="pose_points"):
        dataclasses.replace(p, pose_points=50)
    with pytest.raises(InvalidInput, match="frames"):
        measure_cloud(None, np.zeros((20, 3)), p)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- the image pose


def pose_error(T_fit: np.ndarray, T_cad_rig: np.ndarray) -> tuple[float, float]:
    dT = T_fit @ np.linalg.inv(T_cad_rig)
    cos = (np.trace(dT[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))), float(np.linalg.norm(dT[:3, 3]))


def test_the_images_alone_place_the_part_near_its_pose(scene, part) -> None:  # type: ignore[no-untyped-def]
    _, frames, T_cad_rig, _ = scene
    model = ImagePoseModel.build(part, Rig.default())
    outline = outline_pose(model, frames)
    fit, _ = image_pose(model, frames)
    # A near-symmetric outline leaves the turn open between its candidates, one of
    # which is close; the sites tell them apart.
    errors = [pose_error(T, T_cad_rig) for T in outline.candidates]
    deg, mm = min(errors)
    assert deg < 1.0 and mm < 8.0
    deg_fit, mm_fit = pose_error(fit.transform, T_cad_rig)
    assert fit.converged and fit.rms_mm < 0.2
    assert deg_fit < 0.5 and mm_fit < 3.0
    assert np.isfinite(fit.pose_covariance).all()


def test_frames_without_a_part_are_refused(part) -> None:  # type: ignore[no-untyped-def]
    model = ImagePoseModel.build(part, Rig.default())
    dark = [np.zeros((1024, 1280), np.uint8)] * 4
    with pytest.raises(InvalidInput):
        outline_pose(model, dark)


# --------------------------------------------------------------------------- windows on a bend


def test_windows_on_the_character_line_fit_its_sheen() -> None:
    # Across the line the normal turns and each camera sees the flash's sheen change by
    # another amount; windows that fit only a gain and an offset read the point low.
    spec = PanelSpec().scaled(400.0, 260.0)
    cad = sheet_metal_panel(spec)
    mesh = cad.to_trimesh()
    loc, _, tri = mesh.ray.intersects_location(
        [[0.0, spec.character_line_y_mm, 500.0]], [[0.0, 0.0, -1.0]]
    )
    k = int(np.argmax(loc[:, 2]))
    line = ComparisonPoint("line", tuple(loc[k]), tuple(mesh.face_normals[tri[k]]), -0.2, 0.2, 10.0)
    model = LocalModel.build(cad, [line], Rig.default())
    shaded, plain = [], []
    for pose, seed in (((40.0, -30.0, 25.0), 1), ((0.0, 0.0, 0.0), 1), ((0.0, 0.0, 0.0), 3)):
        T_rig_part = belt_pose(*pose)
        frames = simulate(Rig.nominal(), mesh, T_rig_part, seed=seed)
        T_cad_rig = np.linalg.inv(T_rig_part)
        (on,) = measure_points(model, frames, T_cad_rig)
        (off,) = measure_points(model, frames, T_cad_rig, LocalParams(shading_bend=math.inf))
        shaded.append(on.deviation_mm)
        plain.append(off.deviation_mm)
    # The CAD is the part: the truth is 0.
    assert abs(np.mean(shaded)) < 0.02
    assert abs(np.mean(shaded)) < 0.5 * abs(np.mean(plain))


def test_a_bad_shading_bend_is_refused() -> None:
    for bad in (0.0, -0.01, math.nan, "0.01", True):
        with pytest.raises(InvalidInput, match="shading_bend"):
            LocalParams(shading_bend=bad)  # type: ignore[arg-type]
