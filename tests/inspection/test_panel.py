import numpy as np
import pytest
import trimesh

from inspection import InvalidInput
from inspection.panel import Hole, PanelSpec, panel_height, sheet_metal_panel, vary_holes


@pytest.fixture(scope="module")
def panel():
    return sheet_metal_panel()


def test_footprint_and_height(panel):
    spec = PanelSpec()
    extents = panel.extents
    # The flange bends outwards by its bend radius all round.
    np.testing.assert_allclose(
        extents[:2],
        [spec.length_mm + 2 * spec.bend_radius_mm, spec.width_mm + 2 * spec.bend_radius_mm],
        atol=1e-6,
    )
    assert panel.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    top = panel_height(spec, np.array([0.0]), np.array([0.0]))[0]
    assert panel.bounds[1, 2] >= top


def test_single_manifold_sheet_with_one_boundary_per_hole(panel):
    mesh = panel.to_trimesh()
    assert mesh.is_winding_consistent
    assert len(mesh.split(only_watertight=False)) == 1
    edges = mesh.edges_sorted
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() == 2  # manifold: no edge shared by three faces
    boundary = unique[counts == 1]
    # Boundary loops: one per hole plus the flange's lower edge.
    import networkx as nx

    graph = nx.Graph()
    graph.add_edges_from(boundary)
    assert nx.number_connected_components(graph) == len(PanelSpec().holes) + 1


def test_normals_face_the_visible_side(panel):
    centres = panel.vertices[panel.faces].mean(axis=1)
    spec = PanelSpec()
    top = (np.abs(centres[:, 0]) < spec.length_mm / 2 - 1) & (
        np.abs(centres[:, 1]) < spec.width_mm / 2 - 1
    )
    assert (panel.face_normals[top, 2] > 0.5).all()
    wall = centres[:, 2] < spec.flange_mm - 2 * spec.bend_radius_mm
    outward = np.einsum("ij,ij->i", panel.face_normals[wall, :2], centres[wall, :2])
    assert (outward > 0).all()


def test_holes_are_open(panel):
    for hole in PanelSpec().holes:
        origin = np.array([[hole.x_mm, hole.y_mm, 200.0]])
        hits = trimesh.ray.ray_triangle.RayMeshIntersector(panel.to_trimesh()).intersects_any(
            origin, np.array([[0.0, 0.0, -1.0]])
        )
        assert not hits[0]


def test_surface_matches_the_height_function(panel):
    spec = PanelSpec()
    rng = np.random.default_rng(3)
    xy = rng.uniform([-250, -170], [250, 170], size=(200, 2))
    far_from_holes = np.all(
        [np.hypot(xy[:, 0] - h.x_mm, xy[:, 1] - h.y_mm) > h.radius_mm + 10 for h in spec.holes],
        axis=0,
    )
    xy = xy[far_from_holes]
    mesh = panel.to_trimesh()
    locations, index_ray, _ = mesh.ray.intersects_location(
        np.column_stack([xy, np.full(len(xy), 200.0)]), np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    )
    z = np.full(len(xy), np.nan)
    z[index_ray] = locations[:, 2]
    # Piecewise-linear mesh vs the smooth height function: within a small chord error.
    np.testing.assert_allclose(z, panel_height(spec, xy[:, 0], xy[:, 1]), atol=0.05)


def test_scaled_panel_fits_the_rig_volume():
    small = sheet_metal_panel(PanelSpec().scaled(400.0, 260.0))
    assert small.extents[0] <= 420 and small.extents[1] <= 280


def test_a_hole_drawn_as_small_as_its_rim_allows_is_made_no_smaller():
    # The second hole is drawn at 1.5 x the 4 mm spacing its rim is drawn by.
    spec = PanelSpec(holes=(Hole(100.0, 50.0, 9.0), Hole(-100.0, 0.0, 6.0)))
    rng = np.random.default_rng(3)
    grew = shrank = 0
    for _ in range(12):
        made, shifts = vary_holes(spec, rng, shift_mm=0.1, radius_mm=0.05)
        sheet_metal_panel(made)  # refused if a rim could not be drawn
        for drawn, h, s in zip(spec.holes, made.holes, shifts, strict=True):
            assert h.radius_mm == pytest.approx(drawn.radius_mm + s.dr_mm, abs=1e-12)
            assert abs(s.dr_mm) <= 0.05 and abs(s.dx_mm) <= 0.1 and abs(s.dy_mm) <= 0.1
        assert made.holes[1].radius_mm >= 6.0 and shifts[1].dr_mm >= 0.0
        grew += shifts[1].dr_mm > 0
        shrank += shifts[0].dr_mm < 0
    assert grew and shrank


@pytest.mark.parametrize(
    "spec",
    [
        PanelSpec(length_mm=-1.0),
        PanelSpec(bend_radius_mm=30.0),
        PanelSpec(holes=(Hole(295.0, 0.0, 10.0),)),
        PanelSpec(holes=(Hole(0.0, 0.0, 2.0),)),
        PanelSpec(feature_spacing_mm=10.0),
        PanelSpec(thickness_mm=-1.0),
        PanelSpec(thickness_mm=float("nan")),
        PanelSpec(thickness_mm=5.0),  # the bend radius
        PanelSpec(thickness_mm=3.0),  # folds over at the embossing's corners
    ],
)
def test_bad_specs_are_refused(spec):
    with pytest.raises(InvalidInput):
        sheet_metal_panel(spec)


@pytest.mark.parametrize("size", [(400.0, 260.0), (300.0, 200.0)])
def test_thickness_makes_a_closed_solid_sheet(size):
    """The same outer skin, an inner one 1 mm below along the normals, closed
    along the outline and the holes: a watertight solid of volume area x 1 mm."""
    skin = sheet_metal_panel(PanelSpec().scaled(*size))
    solid = sheet_metal_panel(PanelSpec(thickness_mm=1.0).scaled(*size))
    s = solid.to_trimesh()
    assert s.is_watertight and s.is_winding_consistent
    assert s.volume == pytest.approx(skin.to_trimesh().area * 1.0, rel=0.02)
    # The outer skin is unchanged, and the solid rests on the same plane.
    assert np.array_equal(solid.vertices[: len(skin.vertices)], skin.vertices)
    np.testing.assert_allclose(solid.bounds, skin.bounds, atol=1e-9)
    # The inner skin lies 1 mm inside the outer one (a little less at the
    # embossing's corners, creases where the offset follows smoothed normals).
    inner = solid.vertices[len(skin.vertices) :]
    _, dist, _ = trimesh.proximity.closest_point(skin.to_trimesh(), inner[::25])
    assert np.median(np.abs(dist - 1.0)) < 1e-3
    assert np.all(np.abs(dist - 1.0) < 0.15)
