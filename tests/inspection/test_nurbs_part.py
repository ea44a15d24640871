"""A part whose CAD is NURBS: its tree on the sampled faces, its deviations to the exact faces.

The part is a crowned panel written by our STEP writer and read back as a
part's CAD is; its tree is built on a coarse sampling (20 mm cells), whose
chords lie up to 0.14 mm inside the surface, so that a deviation measured to
the tessellation and one measured to the design differ visibly. Frames are
rendered from a 1 mm sampling (chord error below 1 um) at a quarter of the
rig's pixels.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench.bench_nurbs_part import panel, truth_field
from inspection.errors import InvalidInput
from inspection.measure import PartModel, measure_cloud, measure_frames
from inspection.nurbs import (
    Curve,
    ExactTree,
    closest_points,
    fit_edge,
    read_step_faces,
    read_step_nurbs,
    step_length_units,
    tessellate_faces,
    write_step_surfaces,
)
from inspection.reconstruct import Reconstructor
from inspection.rig import Rig, belt_pose
from inspection.simulate import simulate
from inspection.transforms import apply

SIZE = (640, 512)


@pytest.fixture(scope="module")
def faces(tmp_path_factory):
    path = write_step_surfaces(tmp_path_factory.mktemp("nurbs") / "panel.step", [panel()])
    return read_step_nurbs(path)


@pytest.fixture(scope="module")
def part(faces) -> PartModel:
    return PartModel.build(tessellate_faces(faces, cell_mm=20.0))


def test_a_step_of_bare_surfaces_is_read_as_the_whole_part(faces):
    ((surface, trim),) = faces
    assert trim is None
    np.testing.assert_array_equal(surface.control_points, panel().control_points)


def test_a_step_with_faces_of_other_kinds_is_not_a_nurbs_part(shared_cad):
    path = shared_cad("featuretype.STEP")  # one B-spline face among planes and cylinders
    assert len(read_step_faces(path)) == 1
    assert read_step_nurbs(path) == []
    assert set(step_length_units(path)) == {"m", "INCH"}


def test_our_step_declares_no_unit(tmp_path):
    path = write_step_surfaces(tmp_path / "p.step", [panel()])
    assert step_length_units(path) == ()


def test_a_nurbs_part_measures_to_its_faces_and_a_mesh_part_to_its_tree(part):
    assert isinstance(part.exact, ExactTree) and part.exact.tree is part.tree
    mesh = PartModel(part.cad, part.tree, None)
    assert mesh.nurbs is None and mesh.exact is mesh.tree


def test_a_nurbs_model_of_another_cad_is_refused(part, faces):
    other = tessellate_faces(faces, cell_mm=25.0)
    with pytest.raises(InvalidInput, match="tessellation"):
        PartModel(part.cad, part.tree, None, nurbs=other)
    with pytest.raises(InvalidInput, match="tree"):
        PartModel(other.cad, part.tree, None, nurbs=other)


def test_the_faces_hash_follows_the_geometry_not_the_sampling(faces):
    a = tessellate_faces(faces, cell_mm=20.0)
    b = tessellate_faces(faces, cell_mm=25.0)
    assert a.faces_hash() == b.faces_hash() and a.cad.hash != b.cad.hash
    s = panel()
    cp = s.control_points.copy()
    cp[2, 2, 2] += 1e-6
    moved = type(s)(3, 3, s.knots_u, s.knots_v, cp, s.weights)
    assert tessellate_faces([(moved, None)], cell_mm=20.0).faces_hash() != a.faces_hash()


def exact_distances(part: PartModel, points_cad: np.ndarray) -> np.ndarray:
    return closest_points(part.nurbs.surfaces[0], points_cad).distances


def test_a_cloud_is_measured_to_the_exact_surface(part):
    rng = np.random.default_rng(3)
    s = part.nurbs.surfaces[0]
    uv = rng.uniform(0.05, 0.95, (5000, 2))
    on, su, sv = s.evaluate(uv[:, 0], uv[:, 1], 1)
    n = np.cross(su, sv)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pts = on + truth_field(uv)[:, None] * n
    m = measure_cloud(part, pts, frame="cad")
    cad_pts = apply(m.transform, pts)
    np.testing.assert_allclose(m.deviations.distances, exact_distances(part, cad_pts), atol=1e-9)
    # The same cloud against the tessellation: its chords' error, tenths of a millimetre.
    plain = measure_cloud(dataclasses.replace(part, nurbs=None), pts, frame="cad")
    chord = plain.deviations.distances - exact_distances(part, apply(plain.transform, pts))
    assert np.abs(chord).max() > 0.05


@pytest.fixture(scope="module")
def frames(faces):
    fine = tessellate_faces(faces, cell_mm=1.0)
    return simulate(Rig.nominal(*SIZE), fine.cad, belt_pose(20.0, -10.0, 15.0), seed=3)


@pytest.fixture(scope="module")
def rec():
    with Reconstructor.build(Rig.default().with_image_size(*SIZE)) as r:
        yield r


def test_frames_are_measured_to_the_exact_surface(part, frames, rec):
    m = measure_frames(part, rec, frames)
    assert m.deviations is not None, m.reason
    cad_pts = apply(m.transform, m.points)
    exact = exact_distances(part, cad_pts)
    np.testing.assert_allclose(m.deviations.distances, exact, atol=1e-9)
    # The tree alone answers with the chords, up to 0.14 mm inside the surface.
    gap = part.tree.query(cad_pts).distances - exact
    assert np.median(gap) > 0.03


# ----------------------------------------------------------------------------- edges


def nominal_edge() -> Curve:
    """A rational cubic 300 mm edge, gently curved, in the CAD frame."""
    t = np.linspace(0.0, 1.0, 7)
    cp = np.stack([300.0 * t, 20.0 * np.sin(np.pi * t), 5.0 * t**2], axis=1)
    knots = np.r_[np.zeros(4), [0.25, 0.5, 0.75], np.ones(4)]
    return Curve(3, knots, cp, np.array([1.0, 1.1, 0.9, 1.2, 1.0, 0.95, 1.0]))


def test_an_edge_measured_out_of_order_gives_its_smooth_deviation():
    nominal = nominal_edge()
    rng = np.random.default_rng(8)
    t = np.sort(rng.uniform(0.1, 0.9, 300))
    pts, d1 = nominal.evaluate(t, 1)
    side = np.cross(d1, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    offset = 0.2 + 0.1 * np.sin(2 * np.pi * t)  # the edge's true deviation, mm
    noisy = pts + offset[:, None] * side + rng.normal(0.0, 0.01, pts.shape)
    order = rng.permutation(len(t))
    e = fit_edge(noisy[order], nominal, spans=6)
    assert e.fit.converged
    np.testing.assert_array_equal(np.sort(e.order), np.arange(len(t)))
    assert np.all(np.diff(e.nominal_params) >= 0)
    lo, hi = e.deviation.params[[0, -1]]
    assert lo == pytest.approx(t[0], abs=1e-3) and hi == pytest.approx(t[-1], abs=1e-3)
    # The fitted curve follows the true offset to a fraction of the points' noise
    # (0.01 mm), but at its ends, which are tied to the first and last points.
    want = 0.2 + 0.1 * np.sin(2 * np.pi * e.deviation.params)
    err = np.abs(e.deviation.distances - want)
    assert np.sqrt(np.mean(err[20:-20] ** 2)) < 0.003 and err.max() < 0.02
    assert e.max_mm == pytest.approx(0.3, abs=0.01)


@pytest.mark.parametrize(
    "points, kw, match",
    [
        (np.zeros((20, 2)), {}, "finite"),
        (np.full((20, 3), np.nan), {}, "finite"),
        (np.zeros((5, 3)), {}, "at least"),
        (np.tile([[150.0, 20.0, 1.25]], (20, 1)), {}, "one place"),
        (np.zeros((20, 3)), {"spans": 0}, "spans"),
    ],
)
def test_bad_edges_are_refused(points, kw, match):
    with pytest.raises(InvalidInput, match=match):
        fit_edge(points, nominal_edge(), **kw)


def test_a_saved_nurbs_part_loads_with_its_faces(part, tmp_path):
    part.save(tmp_path / "part")
    again = PartModel.load(tmp_path / "part", cad=part.cad, nurbs=part.nurbs)
    assert isinstance(again.exact, ExactTree) and again.tree.hash == part.tree.hash
    mesh = PartModel.load(tmp_path / "part", cad=part.cad)
    assert mesh.nurbs is None and mesh.exact is mesh.tree
