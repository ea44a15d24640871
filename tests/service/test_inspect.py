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
