"""Injected defects: a dent pressed into any mesh is the truth it claims to be."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from inspection import InvalidInput
from inspection.defects import Dent, press
from inspection.panel import PanelSpec, sheet_metal_panel
from inspection.transforms import apply


@pytest.fixture(scope="module")
def panel():
    return sheet_metal_panel(PanelSpec().scaled(400.0, 260.0))


def test_pressed_dents_have_their_depth_and_leave_the_rest(panel):
    """A dent is ``depth`` deep across its flat bottom (measured against the
    undented surface), blends back to it by ``radius_mm``, and nothing else moves."""
    dents = [
        Dent((-60.0, 30.0, 0.0), (0.0, 0.0, 1.0), 0.3, 30.0, flat_mm=16.0),
        Dent((60.0, -70.0, 0.0), (0.0, 0.0, 1.0), 1.0, 30.0, flat_mm=16.0),
    ]
    out = press(panel, dents)
    v = out.vertices
    top = v[:, 2] > 5.0
    r = np.min([np.hypot(v[:, 0] - d.center_mm[0], v[:, 1] - d.center_mm[1]) for d in dents], 0)
    near = top & (r < 40)
    gap = np.zeros(len(v))  # how far below the undented surface (exact closest points)
    _, dist, _ = trimesh.proximity.closest_point(panel.to_trimesh(), v[near])
    gap[near] = dist
    for d in dents:
        r_d = d.axis_distance(v)
        bottom = top & (r_d < 15.0)
        assert bottom.sum() > 50
        # Pressed along the normal: nearly vertical on this gently curved top.
        np.testing.assert_allclose(gap[bottom], d.depth_mm, rtol=0.01)
        edge = top & (r_d > 30.5) & (r_d < 40.0)
        np.testing.assert_allclose(gap[edge], 0.0, atol=1e-9)
    # Vertices away from the dents stay where they were (the refinement only adds some).
    kept = {tuple(p) for p in np.round(panel.vertices, 9)}
    assert all(tuple(p) in kept for p in np.round(v[(r > 31.0) & ~near], 9))
    assert len(out.faces) > len(panel.faces)  # refined around the dents


def test_a_dent_goes_into_any_mesh_along_its_normal_and_a_bump_comes_out():
    """A sphere, dented where its surface faces a tilted direction: the dent's
    bottom lies ``depth`` inside the undented surface, beyond the rim nothing
    moves; a negative depth bulges out."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=100.0)
    n = np.array([1.0, 2.0, 2.0]) / 3.0
    for depth in (0.8, -0.5):
        out = press(sphere, [Dent(tuple(100.0 * n), tuple(n), depth, 25.0, flat_mm=8.0)])
        v = out.vertices
        foot, gap, _ = trimesh.proximity.closest_point(sphere, v)
        inward = np.einsum("ij,ij->i", foot - v, foot) > 0
        r_axis = np.linalg.norm(v - np.outer(v @ n, n), axis=1)
        bottom = (v @ n > 0) & (r_axis < 7.0)
        assert bottom.sum() > 5
        np.testing.assert_allclose(gap[bottom], abs(depth), rtol=0.01)
        assert np.all(inward[bottom] == (depth > 0))
        np.testing.assert_allclose(gap[(r_axis > 25.0) | (v @ n < 0)], 0.0, atol=1e-9)


def test_only_the_outer_surface_facing_the_dent_moves(panel):
    """In a solid sheet the inner skin under the dent (facing down) keeps its place,
    and moving the part and the dent together moves the result with them."""
    solid = sheet_metal_panel(PanelSpec(thickness_mm=1.0).scaled(400.0, 260.0))
    dent = Dent((10.0, 10.0, 0.0), (0.0, 0.0, 1.0), 0.5, 20.0, flat_mm=8.0)
    out = press(solid, [dent])
    moved = np.linalg.norm(out.vertices[: len(solid.vertices)] - solid.vertices, axis=1) > 0
    assert moved.any() and np.all(solid.to_trimesh().vertex_normals[moved, 2] > 0.5)

    T = np.eye(4)
    c, s = np.cos(0.6), np.sin(0.6)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = (30.0, -20.0, 5.0)
    here = press(panel, [dent])
    there = press(
        trimesh.Trimesh(apply(T, panel.vertices), panel.faces, process=False),
        [Dent(tuple(apply(T, np.array([dent.center_mm]))[0]), dent.normal, 0.5, 20.0, 8.0)],
    )
    np.testing.assert_allclose(there.vertices, apply(T, here.vertices), atol=1e-9)


def test_no_dents_copy_the_mesh_and_bad_records_are_refused(panel):
    out = press(panel, [Dent((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.0, 10.0)])
    np.testing.assert_array_equal(out.vertices, panel.vertices)
    np.testing.assert_array_equal(out.faces, panel.faces)
    for bad in (
        {"depth_mm": float("nan")},
        {"flat_mm": 20.0},
        {"normal": (0.0, 0.0, 0.0)},
        {"center_mm": (0.0, 0.0)},
    ):
        kwargs = {"center_mm": (0.0, 0.0, 0.0), "normal": (0.0, 0.0, 1.0), "depth_mm": 0.5}
        with pytest.raises(InvalidInput):
            Dent(**(kwargs | {"radius_mm": 10.0} | bad))
    with pytest.raises(InvalidInput, match="touches no surface"):
        press(panel, [Dent((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), 0.5, 10.0)])
    with pytest.raises(InvalidInput):
        press(panel, [(0.0, 0.0, 0.5)])  # type: ignore[list-item]
