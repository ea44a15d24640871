"""The whole surface: dents and bumps found as objects where they are, edge artefacts and
outliers counted apart, occlusion edges from the cameras' view, and the surface band's checks."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from _fitcases import measure
from scipy.spatial import cKDTree

from inspection.cad import CadModel
from inspection.defects import Dent, press, random_dent
from inspection.deviations import ComparisonPoint, Verdict, deviations
from inspection.errors import InvalidInput
from inspection.grid import GridTree
from inspection.measure import MeasureParams, PartModel, measure_cloud
from inspection.panel import PanelSpec, sheet_metal_panel
from inspection.surface import EDGE_MM, SurfaceModel, SurfaceParams

SPEC = PanelSpec().scaled(300.0, 200.0)
NOISE_MM = 0.03
POINTS = 120_000  # about 2 per mm^2 of the 300 x 200 mm panel


@pytest.fixture(scope="module")
def panel():
    cad = sheet_metal_panel(SPEC)
    return cad, GridTree.build(cad), SurfaceModel.build(cad.vertices, cad.faces, cad.face_normals)


def top(cad, x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
    """The top surface point above (x, y) and its normal."""
    mesh = cad.to_trimesh()
    loc, _, tri = mesh.ray.intersects_location([[x, y, 1000.0]], [[0.0, 0.0, -1.0]])
    k = int(np.argmax(loc[:, 2]))
    return loc[k], cad.face_normals[tri[k]]


def dent_at(cad, x: float, y: float, depth_mm: float, radius_mm: float = 14.0) -> Dent:
    p, n = top(cad, x, y)
    return Dent(tuple(p), tuple(n), depth_mm, radius_mm, 7.0)


def cloud(cad, dents=(), *, seed=0, n=POINTS) -> np.ndarray:
    """Noisy points over the side of ``cad`` (dents pressed in) that faces +z."""
    shape = cad if not dents else CadModel.from_mesh(press(cad, dents), name="dented")
    pts, _ = measure(shape, np.eye(4), n, noise_mm=NOISE_MM, seed=seed)
    return pts


DEFAULT = SurfaceParams()


def judge(panel, points, cps=(), params=DEFAULT, **kw):
    cad, tree, surface = panel
    return deviations(
        tree, points, cps, surface=surface, surface_params=params, max_distance_mm=10.0,
        outlier_mm=4.685 * NOISE_MM, view_directions=np.array([[0.0, 0.0, 1.0]]), **kw,
    )  # fmt: skip


def test_dents_and_bumps_are_found_where_they_are(panel):
    cad = panel[0]
    dent = dent_at(cad, -20.0, 10.0, 0.5)
    bump = dent_at(cad, 100.0, -20.0, -0.3)
    p, n = top(cad, 95.0, -25.0)
    cps = [ComparisonPoint("near-bump", tuple(p), tuple(n), -0.5, 0.5, 5.0)]
    devs = judge(panel, cloud(cad, [dent, bump]), cps)

    assert [f.kind for f in sorted(devs.defects, key=lambda f: f.peak_mm)] == ["dent", "bump"]
    for truth in (dent, bump):
        f = min(devs.defects, key=lambda f: np.linalg.norm(f.center_mm - truth.center_mm))
        assert np.linalg.norm(f.center_mm - truth.center_mm) < 2.0
        assert f.peak_mm == pytest.approx(-truth.depth_mm, abs=0.03)
        assert abs(f.mean_mm) < abs(f.peak_mm) and np.sign(f.mean_mm) == np.sign(f.peak_mm)
        assert np.pi * 7.0**2 < f.area_mm2 < np.pi * truth.radius_mm**2
        assert f.points > 100
        assert f.nearest_point == "near-bump"
    assert devs.verdict is Verdict.FAIL, "a defect fails the part by default"

    lenient = judge(panel, cloud(cad, [dent, bump]), cps, SurfaceParams(fails_part=False))
    assert len(lenient.defects) == 2 and lenient.verdict is Verdict.PASS
    wide = judge(panel, cloud(cad, [dent, bump]), cps, SurfaceParams(-0.6, 0.6))
    assert wide.defects == () and wide.verdict is Verdict.PASS


def test_an_undented_surface_has_no_defect_and_a_field_within_its_noise(panel):
    cad = panel[0]
    pts = cloud(cad, seed=3)
    rng = np.random.default_rng(3)
    # Stray reflections: 0.3 % of the points 2 mm off the surface.
    stray = rng.choice(len(pts), len(pts) // 300, replace=False)
    pts[stray, 2] += 2.0
    # The reconstruction carries the surface 1.5 mm on across a hole (points over it).
    hole = SPEC.holes[0]
    a = rng.uniform(0, 2 * np.pi, 300)
    rho = hole.radius_mm - rng.uniform(0.2, 1.5, 300)
    z = top(cad, hole.x_mm + hole.radius_mm + 1.0, hole.y_mm)[0][2]
    over = np.c_[hole.x_mm + rho * np.cos(a), hole.y_mm + rho * np.sin(a), np.full(300, z)]
    devs = judge(panel, np.concatenate([pts, over]))

    assert devs.defects == () and devs.verdict is Verdict.PASS
    s = devs.summary
    assert s.n == len(pts) + 300
    assert (devs.classes.outlier | devs.classes.edge)[stray].all()
    assert s.outliers >= len(stray) // 2, "most reflections land away from the edges"
    assert s.edge >= 300, "the points over the hole are edge points"
    assert s.inliers + s.edge + s.outliers + s.far == s.n
    assert max(abs(s.p001_mm), abs(s.p999_mm)) < 4 * NOISE_MM
    assert s.max_mm < 4.685 * NOISE_MM + 1e-9, "no stray reflection in the field's max"
    assert devs.classes is not None and devs.classes.edge[-300:].all()


def test_a_hole_rim_is_not_a_defect_but_a_dent_by_the_hole_is(panel):
    cad, tree, surface = panel
    hole = SPEC.holes[1]
    pts = cloud(cad, seed=5)
    # The reconstruction's edge artefact: a ring 2 mm wide round the hole sunk by 0.5 mm.
    gap = np.hypot(pts[:, 0] - hole.x_mm, pts[:, 1] - hole.y_mm) - hole.radius_mm
    ring = (gap >= 0) & (gap < 2.0) & (pts[:, 2] > 20.0)
    assert ring.sum() > 100
    sunk = pts.copy()
    sunk[ring, 2] -= 0.5
    assert judge(panel, sunk).defects == ()

    # A dent whose rim runs into the hole: centre 4 mm from the hole's edge.
    dent = dent_at(cad, hole.x_mm - hole.radius_mm - 4.0, hole.y_mm, 0.4)
    devs = judge(panel, cloud(cad, [dent], seed=5))
    assert len(devs.defects) == 1
    f = devs.defects[0]
    assert f.kind == "dent" and np.linalg.norm(f.center_mm - dent.center_mm) < 5.0
    assert f.peak_mm == pytest.approx(-0.4, abs=0.05)

    # The sunk ring beside a dent, every region counted however small: edge nodes that
    # no piece of the dent's core joins are still no defect of their own.
    dent = dent_at(cad, hole.x_mm - hole.radius_mm - 6.0, hole.y_mm, 0.4, radius_mm=12.0)
    pts = cloud(cad, [dent], seed=5)
    gap = np.hypot(pts[:, 0] - hole.x_mm, pts[:, 1] - hole.y_mm) - hole.radius_mm
    pts[(gap >= 0) & (gap < 2.0) & (pts[:, 2] > 20.0), 2] -= 0.5
    devs = judge(panel, pts, params=SurfaceParams(min_area_mm2=0.0))
    assert [f.kind for f in devs.defects] == ["dent"]
    assert np.linalg.norm(devs.defects[0].center_mm - dent.center_mm) < 5.0


@pytest.mark.parametrize("depth_mm", [1.5, -1.5])
def test_a_dent_across_the_embossing_edge_is_one_defect_where_it_is(panel, depth_mm):
    """The band of edge nodes along a rounded bend is wider than the support: a dent
    centred on it would leave a piece of core on either side."""
    cad = panel[0]
    cx, cy = SPEC.emboss_center_mm
    dent = dent_at(cad, cx + 0.5 * SPEC.emboss_size_mm[0], cy, depth_mm, radius_mm=16.0)
    assert_one_defect_where_it_is(panel, dent, seed=7, depth_tol_mm=0.1)


def assert_one_defect_where_it_is(panel, dent: Dent, *, seed: int, depth_tol_mm: float) -> None:
    devs = judge(panel, cloud(panel[0], [dent], seed=seed))
    assert len(devs.defects) == 1, [f.describe() for f in devs.defects]
    f = devs.defects[0]
    assert f.kind == ("dent" if dent.depth_mm > 0 else "bump")
    assert np.linalg.norm(f.center_mm - dent.center_mm) < 3.0
    assert f.peak_mm == pytest.approx(-dent.depth_mm, abs=depth_tol_mm)


@pytest.mark.parametrize("depth_mm", [0.4, -0.4])
def test_a_dent_on_the_character_line_is_found(panel, depth_mm):
    """The character line's two bends, with the edge distance on both sides, leave no node
    of a small dent on it away from the edges; away from the outline and the silhouettes
    such a bend is judged past its allowance."""
    cad = panel[0]
    dent = dent_at(cad, -20.0, SPEC.character_line_y_mm, depth_mm, radius_mm=12.0)
    assert_one_defect_where_it_is(panel, dent, seed=11, depth_tol_mm=0.05)


@pytest.mark.parametrize("shift_mm", [0.25, -0.25])
def test_the_rounding_of_the_character_line_is_not_a_defect(panel, shift_mm):
    """The reconstruction rounds a bend: the field along one stretch of the line, lifted or
    sunk by as much as the undented rig's reaches there, stays within the allowance."""
    cad = panel[0]
    pts = cloud(cad, seed=12)
    y = SPEC.character_line_y_mm
    band = (np.abs(pts[:, 1] - y) < EDGE_MM) & (np.abs(pts[:, 0] + 20.0) < 20.0)
    pts[band & (pts[:, 2] > 20.0), 2] += shift_mm
    assert judge(panel, pts).defects == ()


def test_the_smoothed_field_is_the_one_the_search_reads_its_peak_on(panel):
    cad, tree, surface = panel
    dent = dent_at(cad, -20.0, 10.0, 0.5)
    pts = cloud(cad, [dent], seed=2)
    devs = judge(panel, pts)
    (f,) = devs.defects
    cl = tree.query(pts)
    nodes = surface.nodes_of(cl.points, cl.normals)
    field, count = surface.smoothed(cl.distances, nodes, ~devs.classes.edge)
    near = np.linalg.norm(surface.centres - dent.center_mm, axis=1) < dent.radius_mm
    assert np.nanmin(field[near]) == pytest.approx(f.peak_mm, abs=1e-12)
    assert np.isnan(field[count == 0]).all() and (count[near] > 100).all()


def test_occlusion_edges_are_the_silhouettes_the_cameras_see():
    box = trimesh.creation.box((100.0, 100.0, 100.0))
    surface = SurfaceModel.build(box.vertices, box.faces, box.face_normals)
    # Seen from far along (1, 0, 1): faces +x and +z turn towards the sensor.
    samples = surface.occlusion_edges(directions=np.array([[1.0, 0.0, 1.0]]) / np.sqrt(2))
    assert len(samples) > 0
    on_two_faces = (np.isclose(np.abs(samples), 50.0).sum(axis=1)) >= 2
    assert on_two_faces.all(), "only the cube's edges, not its faces' diagonals"
    corner = np.isclose(np.abs(samples), 50.0).all(axis=1)
    seen = (np.isclose(samples[:, 0], 50.0) | np.isclose(samples[:, 2], 50.0)) & ~(
        np.isclose(samples[:, 0], 50.0) & np.isclose(samples[:, 2], 50.0)
    )
    assert (seen | corner).all(), "between a face turned to the sensor and one turned away"
    assert not corner.all()
    # From a camera centre right above the middle, only +z faces it: its four edges.
    above = surface.occlusion_edges(viewpoints=np.array([[0.0, 0.0, 500.0]]))
    assert np.isclose(above[:, 2], 50.0).all() and len(above) > 0
    assert len(surface.occlusion_edges()) == 0


def test_edge_points_lie_within_the_stated_distance(panel):
    cad, tree, surface = panel
    pts = cloud(cad, seed=7)
    devs = judge(panel, pts)
    cl = tree.query(pts)
    gap, _ = cKDTree(surface.boundary).query(np.asarray(cl.points))
    edge = devs.classes.edge
    # Near the boundary or a bend every point is an edge point; far from them, no point
    # on the top is (the view from above adds occlusion edges on the flanges' walls only).
    assert edge[gap <= EDGE_MM - 0.01].all()
    on_top = np.asarray(cl.normals)[:, 2] > 0.5
    assert not edge[(gap > EDGE_MM + 0.01) & on_top].any()
    assert 0 < edge.mean() < 0.5


def test_measure_cloud_reports_and_names_the_defect():
    cad = sheet_metal_panel(SPEC)
    part = PartModel.build(cad, alignment=False)
    assert part.surface is not None
    dent = dent_at(cad, 40.0, -40.0, 0.6)
    m = measure_cloud(part, cloud(cad, [dent], seed=9), frame="cad")
    assert m.verdict is Verdict.FAIL
    assert m.deviations is not None and len(m.deviations.defects) == 1
    assert "1 surface defect: dent 0.6" in m.reason
    off = measure_cloud(
        part, cloud(cad, [dent], seed=9), frame="cad",
        params=MeasureParams(surface=SurfaceParams(fails_part=False)),
    )  # fmt: skip
    assert off.verdict is Verdict.PASS and len(off.deviations.defects) == 1


@pytest.mark.parametrize(
    "kwargs",
    [
        {"lower_mm": 0.1},
        {"upper_mm": -0.1},
        {"upper_mm": float("nan")},
        {"min_area_mm2": -1.0},
        {"fails_part": "yes"},
        {"lower_mm": True},
    ],
)
def test_bad_surface_bands_raise(kwargs):
    with pytest.raises(InvalidInput):
        SurfaceParams(**kwargs)


def test_measure_params_take_surface_params_only():
    with pytest.raises(InvalidInput, match="SurfaceParams"):
        MeasureParams(surface={"lower_mm": -0.1})  # type: ignore[arg-type]
    assert MeasureParams().surface == SurfaceParams()


def test_random_dents_land_on_the_surface_the_cameras_see(panel):
    mesh = panel[0].to_trimesh()
    rng = np.random.default_rng(1)
    dents = [
        random_dent(mesh, rng, depth_mm=(0.2, 2.0), radius_mm=(12.0, 20.0)) for _ in range(200)
    ]
    depths = np.array([d.depth_mm for d in dents])
    assert 0.2 <= np.abs(depths).min() and np.abs(depths).max() <= 2.0
    assert 60 < (depths < 0).sum() < 140, "about half of them bumps"
    assert all(np.asarray(d.normal)[2] > 0.7 and 12.0 <= d.radius_mm <= 20.0 for d in dents)
    _, dist, _ = trimesh.proximity.closest_point(mesh, np.array([d.center_mm for d in dents]))
    assert dist.max() < 1e-6
    with pytest.raises(InvalidInput):
        random_dent(mesh, rng, radius_mm=(5.0, 6.0), flat_mm=7.0)


def test_the_one_pass_kernel_agrees_with_the_array_steps(panel):
    """Each point's node and whether its offset runs across the surface, from the compiled
    pass, are what the cell keys and the lateral offset give step by step."""
    from inspection.surface import _keys, _point_nodes

    cad, tree, surface = panel
    pts = cloud(cad, n=20_000, seed=3)
    pts[:500, 0] = cad.vertices[:, 0].max() + 3.0  # beyond the outline: offsets run across
    q = tree.query(pts)
    normals = q.normals
    key = _keys(surface.origin, surface.dims, surface.node_mm, q.points, normals)
    pos = np.minimum(np.searchsorted(surface.keys, key), len(surface.keys) - 1)
    expected = np.where(surface.keys[pos] == key, pos, -1)
    nodes, off = _point_nodes(
        surface.origin, surface.dims, surface.node_mm, surface.keys, pts, q.points, normals,
        q.distances, 0.05, 0.1,
    )  # fmt: skip
    np.testing.assert_array_equal(nodes, expected)
    np.testing.assert_array_equal(off, surface.off_edge(pts, q.points, normals, q.distances))
    assert off[:500].sum() > 100 and off[500:].mean() < 0.05  # both kinds are in the test


@pytest.mark.parametrize("reach", [0.2, 4.0, 8.0, 60.0])
def test_the_nearest_edge_sample_within_reach_is_the_kd_trees(panel, reach):
    """The binned search gives each point the distance to its nearest sample below the
    reach, and inf beyond it, as a k-d tree does: on the panel's outline samples, from
    points on, beside and far off the part, and from a point with no sample near."""
    from inspection.surface import _nearest_within

    cad, tree, surface = panel
    rng = np.random.default_rng(11)
    pts = np.concatenate(
        [
            cloud(cad, n=5000, seed=5),
            surface.boundary[:2000] + rng.normal(0.0, reach / 2, (2000, 3)),
            rng.uniform(-2000.0, 2000.0, (500, 3)),
        ]
    )
    samples = surface.boundary
    expected, _ = cKDTree(samples).query(pts, distance_upper_bound=reach)
    got = _nearest_within(pts, samples, reach)
    np.testing.assert_array_equal(got, expected)
    assert np.isfinite(got).sum() > 1000 and np.isinf(got).sum() > 400  # both kinds
    assert np.isinf(_nearest_within(pts, np.empty((0, 3)), reach)).all()


def test_node_medians_are_the_medians_of_each_nodes_points():
    """Per node, the median and count of the points ``first`` selects and of those
    ``second`` selects, as numpy gives them: on nodes of a few points (sorted in place)
    and on crowded ones (sorted by argsort), with ties, and on nodes with none."""
    from inspection.surface import _INSERTION_MAX, _node_medians

    rng = np.random.default_rng(3)
    m = 400
    sizes = np.concatenate([rng.integers(0, 12, m - 3), [0, 3 * _INSERTION_MAX, 500]])
    nodes = np.repeat(np.arange(m), sizes)
    rng.shuffle(nodes)
    n = len(nodes)
    d = np.round(rng.normal(0.0, 0.1, n), 2)  # rounded: ties
    first = rng.random(n) < 0.9
    second = first & (rng.random(n) < 0.7)
    med_second, n_second, med_first, n_first = _node_medians(d, nodes, first, second, m)
    for j in range(m):
        for sel, med, count in ((first, med_first, n_first), (second, med_second, n_second)):
            v = d[sel & (nodes == j)]
            assert count[j] == len(v)
            assert med[j] == (np.median(v) if len(v) else 0.0)
    assert n_first[-1] > 400 and n_first[-2] > _INSERTION_MAX and n_first[-3] == 0
