"""The cloud-to-result step's own rules: cloud validation, subsampling, status."""

from __future__ import annotations

import numpy as np
import pytest

from inspection.errors import InvalidInput
from service.inspect import MIN_POINTS, _reason, part_status, subsample, validate_cloud
from service.models import PointResult, Status


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
def test_bad_clouds_are_refused(cloud, match):
    with pytest.raises(InvalidInput, match=match):
        validate_cloud(cloud)


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


def pr(name, verdict, dev=0.0):
    return PointResult(
        name=name, deviation_mm=None if verdict == "not_measurable" else dev,
        lower_mm=-1, upper_mm=1, support=0 if verdict == "not_measurable" else 20, verdict=verdict,
    )  # fmt: skip


@pytest.mark.parametrize(
    "verdicts, status",
    [
        ([], Status.passed),
        (["pass", "pass"], Status.passed),
        (["pass", "not_measurable"], Status.not_measurable),
        (["fail", "not_measurable"], Status.fail),
        (["pass", "fail"], Status.fail),
    ],
)
def test_part_status(verdicts, status):
    points = [pr(f"p{i}", v) for i, v in enumerate(verdicts)]
    assert part_status(points) == status


def test_reason_names_the_points_and_the_note():
    pts = [pr("a", "fail", 2.0), pr("b", "pass"), pr("c", "fail", -2.0)]
    assert _reason(Status.fail, pts, None) == "out of tolerance at a, c"
    assert _reason(Status.passed, pts[1:2], "pose ambiguous") == "pose ambiguous"
    assert _reason(Status.passed, pts[1:2], None) is None


@pytest.fixture(scope="module")
def thin_sheet(tmp_path_factory):
    """A 1 mm sheet modelled as a solid, as a part of the line."""
    from service.config import PartSpec
    from service.parts import load_part

    spec = PartSpec(
        name="sheet",
        cad="generated:panel",
        panel={"length_mm": 300.0, "width_mm": 200.0, "thickness_mm": 1.0, "holes": []},
    )
    tmp = tmp_path_factory.mktemp("sheet")
    return load_part(spec, tmp, tmp / "trees")


@pytest.mark.parametrize("seen_from_above", [None, False])
def test_the_line_fits_a_thin_solid_to_its_top(thin_sheet, seen_from_above):
    """A cloud in the rig frame of the sheet lying flat (where the rig measures:
    faces within 60 deg of up). By default (tukey) the fit knows the cameras
    look down and keeps the points off the underside, 1 mm below; turned
    off, this cloud ends on it."""
    from dataclasses import replace

    from inspection.alignment import sample_facing
    from service.inspect import Trigger, inspect_cloud

    part = thin_sheet
    settings = part.spec.registration.model_copy(update={"seen_from_above": seen_from_above})
    part = replace(part, spec=part.spec.model_copy(update={"registration": settings}))
    cad = part.cad
    T_rig_cad = np.eye(4)
    T_rig_cad[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    T_rig_cad[:3, 3] = (-74.0, 55.0, 0.0)
    pts, _ = sample_facing(
        cad.vertices, cad.faces, cad.face_normals, T_rig_cad, 50_000, seed=0, min_cos=0.5
    )
    cloud = pts + np.random.default_rng(0).normal(scale=0.02, size=pts.shape)
    trigger = Trigger("r1", "line", "station", "s1", 1, 0)
    res = inspect_cloud(part, cloud, trigger).result
    T = np.asarray(res.transform) @ T_rig_cad  # identity when exact
    corners = cad.bounds[[0, 1]]
    off = np.abs(corners @ T[:3, :3].T + T[:3, 3] - corners).max()
    if seen_from_above is None:
        assert off < 0.01, off
    else:
        assert off > 0.5, off
