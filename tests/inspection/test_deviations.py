"""Deviations: a dent found at its comparison point after a robust fit, the
verdict rules, comparison point validation and robust averaging."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _fitcases import apply, measure, perturbation

from inspection.deviations import (
    ComparisonPoint,
    Deviations,
    FieldSummary,
    Verdict,
    deviations,
    load_comparison_points,
    robust_location,
)
from inspection.errors import InvalidInput
from inspection.grid import GridTree
from inspection.panel import PanelSpec, sheet_metal_panel
from inspection.registration import register


@pytest.fixture(scope="module")
def panel():
    cad = sheet_metal_panel(PanelSpec().scaled(300.0, 200.0))
    return cad, GridTree.build(cad)


def surface_point(cad, x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
    """The top surface point above (x, y) and its outward normal (a ray from above)."""
    mesh = cad.to_trimesh()
    loc, _, tri = mesh.ray.intersects_location([[x, y, 1000.0]], [[0.0, 0.0, -1.0]])
    assert len(loc), f"no surface at ({x}, {y})"
    top = int(np.argmax(loc[:, 2]))
    return loc[top], cad.face_normals[tri[top]]


# On the panel's top, clear of its holes, embossing and character line.
SPOTS = {"dent": (-20.0, 10.0), "a": (40.0, -40.0), "b": (-60.0, 60.0), "c": (100.0, 10.0)}


def comparison_points(cad, radius_mm=5.0) -> list[ComparisonPoint]:
    out = []
    for name, (x, y) in SPOTS.items():
        p, n = surface_point(cad, x, y)
        out.append(ComparisonPoint(name, tuple(p), tuple(n), -0.3, 0.3, radius_mm))
    return out


def test_dent_is_measured_after_a_robust_fit(panel):
    cad, tree = panel
    cps = comparison_points(cad)
    pts, normals = measure(cad, np.eye(4), 50_000, noise_mm=0.02, seed=21)
    # A 0.5 mm dent, flat across the support radius and fading out beyond it.
    centre = np.asarray(cps[0].position)
    rho = np.linalg.norm((pts - centre)[:, :2], axis=1)
    depth = 0.5 * np.clip((11.0 - rho) / 5.0, 0.0, 1.0)
    pts = pts - depth[:, None] * normals
    T_data_cad = perturbation(np.random.default_rng(21), 5.0, 10.0, pts.mean(axis=0))
    data = apply(T_data_cad, pts)

    reg = register(tree, data)
    devs = deviations(tree, apply(reg.transform, data), cps)

    assert isinstance(devs, Deviations)
    by_name = {c.name: c for c in devs.comparison}
    assert by_name["dent"].deviation_mm == pytest.approx(-0.5, abs=0.02)
    assert by_name["dent"].verdict is Verdict.FAIL
    for name in ("a", "b", "c"):
        assert by_name[name].deviation_mm == pytest.approx(0.0, abs=0.02), name
        assert by_name[name].verdict is Verdict.PASS
        assert by_name[name].support >= 20
    assert devs.verdict is Verdict.FAIL
    assert devs.distances.shape == (len(data),)
    # Most of the field is on the nominal surface.
    assert abs(devs.summary.median_mm) < 0.005
    assert devs.summary.min_mm == pytest.approx(-0.5, abs=0.1)


def exact_cloud(cad, n=20_000, seed=0):
    pts, _ = measure(cad, np.eye(4), n, noise_mm=0.0, seed=seed)
    return pts


def test_verdicts_and_their_precedence(panel):
    cad, tree = panel
    pts = exact_cloud(cad)
    cps = comparison_points(cad)
    ok = deviations(tree, pts, cps)
    assert ok.verdict is Verdict.PASS
    assert all(c.verdict is Verdict.PASS for c in ok.comparison)
    # A point off the part has no support: not measurable, and so is the part.
    lost = ComparisonPoint("lost", (0.0, 0.0, 500.0), (0.0, 0.0, 1.0), -0.1, 0.1, 5.0)
    nm = deviations(tree, pts, [*cps, lost])
    assert nm.comparison[-1].verdict is Verdict.NOT_MEASURABLE
    assert nm.comparison[-1].support == 0 and np.isnan(nm.comparison[-1].deviation_mm)
    assert nm.verdict is Verdict.NOT_MEASURABLE
    # A tolerance that excludes zero fails; a failure outranks not measurable.
    p = cps[1]
    tight = ComparisonPoint("tight", p.position, p.normal, 0.1, 0.2, 5.0)
    fail = deviations(tree, pts, [*cps, lost, tight])
    assert fail.comparison[-1].verdict is Verdict.FAIL
    assert fail.verdict is Verdict.FAIL
    # No comparison points: the field alone passes.
    assert deviations(tree, pts, []).verdict is Verdict.PASS


def test_min_support_per_point_and_global(panel):
    cad, tree = panel
    pts = exact_cloud(cad)
    p = comparison_points(cad)[1]
    n_support = deviations(tree, pts, [p]).comparison[0].support
    needy = ComparisonPoint(
        "needy", p.position, p.normal, -1.0, 1.0, 5.0, min_support=n_support + 1
    )
    assert deviations(tree, pts, [needy]).comparison[0].verdict is Verdict.NOT_MEASURABLE
    assert deviations(tree, pts, [p], min_support=n_support + 1).verdict is Verdict.NOT_MEASURABLE
    assert deviations(tree, pts, [p], min_support=n_support).verdict is Verdict.PASS


def test_sign_follows_the_comparison_normal(panel):
    cad, tree = panel
    p = comparison_points(cad)[2]
    pts = exact_cloud(cad) + 0.2 * np.asarray(p.normal)  # the whole part 0.2 mm outward there
    out = ComparisonPoint("out", p.position, p.normal, -1.0, 1.0, 5.0)
    inward = ComparisonPoint("in", p.position, tuple(-np.asarray(p.normal)), -1.0, 1.0, 5.0)
    devs = deviations(tree, pts, [out, inward])
    assert devs.comparison[0].deviation_mm == pytest.approx(0.2, abs=0.01)
    assert devs.comparison[1].deviation_mm == pytest.approx(-0.2, abs=0.01)


def test_features_are_left_to_the_images(panel):
    cad, tree = panel
    p = comparison_points(cad)[1]
    hole = ComparisonPoint(
        "hole", p.position, p.normal, -1.0, 1.0, 5.0, kind="hole", diameter_mm=8.0
    )
    devs = deviations(tree, exact_cloud(cad), [hole])
    assert devs.comparison[0].verdict is Verdict.NOT_MEASURABLE
    assert devs.comparison[0].kind == "hole"
    assert devs.comparison[0].reason == "a hole is measured from the images after the fit"


def test_robust_location_ignores_a_minority_of_outliers():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(0.1, 0.02, 700), rng.uniform(2.0, 5.0, 300)])
    loc, scale = robust_location(x)
    assert loc == pytest.approx(0.1, abs=0.02)
    assert np.mean(x) > 0.8  # what a plain mean would say
    same, zero = robust_location(np.full(10, 0.25))
    assert same == 0.25 and zero == 0.0


def test_field_summary_matches_numpy():
    d = np.random.default_rng(4).normal(0.01, 0.03, 5000)
    s = FieldSummary.of(d)
    assert s.n == 5000
    assert s.mean_mm == pytest.approx(d.mean())
    assert s.std_mm == pytest.approx(d.std())
    assert s.max_abs_mm == pytest.approx(np.abs(d).max())
    assert s.p95_mm == pytest.approx(np.percentile(d, 95))
    assert set(s.to_dict()) >= {"mean_mm", "std_mm", "p01_mm", "p99_mm", "max_abs_mm"}


# --------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "kwargs",
    [
        {"name": ""},
        {"normal": (0.0, 0.0, 0.0)},
        {"position": (0.0, np.nan, 0.0)},
        {"position": (0.0, 0.0)},
        {"lower_mm": 1.0, "upper_mm": -1.0},
        {"radius_mm": 0.0},
        {"radius_mm": float("inf")},
        {"kind": "blob"},
        {"min_support": 0},
    ],
)
def test_bad_comparison_points_raise(kwargs):
    base = dict(
        name="p", position=(0, 0, 0), normal=(0, 0, 2), lower_mm=-1, upper_mm=1, radius_mm=5
    )
    with pytest.raises(InvalidInput):
        ComparisonPoint(**{**base, **kwargs})


def test_comparison_point_normalises_and_is_frozen():
    p = ComparisonPoint("p", np.array([1.0, 2.0, 3.0]), (0.0, 0.0, 2.0), -1, 1, 5)
    assert p.normal == (0.0, 0.0, 1.0)
    assert p.position == (1.0, 2.0, 3.0)
    with pytest.raises(AttributeError):
        p.radius_mm = 3.0  # type: ignore[misc]
    assert ComparisonPoint.from_dict(p.to_dict()) == p


def test_load_comparison_points(tmp_path):
    items = [
        {
            "name": "a",
            "position": [0, 0, 1],
            "normal": [0, 0, 1],
            "lower_mm": -0.2,
            "upper_mm": 0.2,
            "radius_mm": 4,
        },
        {
            "name": "b",
            "position": [5, 0, 1],
            "normal": [0, 0, 1],
            "lower_mm": -0.2,
            "upper_mm": 0.2,
            "radius_mm": 4,
        },
    ]
    f = tmp_path / "points.json"
    f.write_text(json.dumps(items))
    assert [p.name for p in load_comparison_points(f)] == ["a", "b"]
    f.write_text(json.dumps({"points": items}))
    assert len(load_comparison_points(f)) == 2
    for bad in ([items[0], items[0]], [{**items[0], "colour": "red"}], [{"name": "x"}], {"x": 1}):
        f.write_text(json.dumps(bad))
        with pytest.raises(InvalidInput):
            load_comparison_points(f)
    f.write_text("{not json")
    with pytest.raises(InvalidInput):
        load_comparison_points(f)


def test_bad_points_raise(panel):
    with pytest.raises(InvalidInput):
        deviations(panel[1], np.full((10, 3), np.nan))
    with pytest.raises(InvalidInput):
        deviations(panel[1], np.zeros((10, 2)))
    p = ComparisonPoint("p", (0, 0, 0), (0, 0, 1), -1, 1, 5)
    with pytest.raises(InvalidInput):
        deviations(panel[1], np.zeros((10, 3)), [p, p])


def test_support_is_every_point_within_the_radius(panel):
    """The pooled points are exactly those a kd-tree finds in each ball (scipy as oracle)."""
    from scipy.spatial import cKDTree

    cad, tree = panel
    cps = comparison_points(cad, radius_mm=7.0)
    pts, _ = measure(cad, np.eye(4), 30_000, noise_mm=0.02, seed=5)
    devs = deviations(tree, pts, cps)
    kd = cKDTree(pts)
    normals = tree.query(pts).normals
    for cp, res in zip(cps, devs.comparison, strict=True):
        idx = np.asarray(kd.query_ball_point(cp.position, cp.radius_mm), dtype=np.int64)
        facing = np.abs(normals[idx] @ np.asarray(cp.normal)) >= 0.5
        assert res.support == int(facing.sum()) > 20
