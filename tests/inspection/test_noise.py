"""The cloud's own noise, estimated without a CAD, against clouds of known noise."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from inspection.alignment import sample_facing
from inspection.cad import CadModel
from inspection.errors import InvalidInput
from inspection.noise import surface_noise_mm


@pytest.mark.parametrize("sigma", [0.005, 0.02, 0.1])
def test_a_noisy_plane_gives_its_noise(sigma):
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(0, 200, (20_000, 2)), rng.normal(0, sigma, 20_000)]
    assert surface_noise_mm(pts) == pytest.approx(sigma, rel=0.1)


def test_edges_and_curvature_do_not_inflate_it():
    """A stepped block seen from above with 0.02 mm of noise: its edges are a few
    per cent of the local planes, which the median leaves out."""
    mesh = trimesh.util.concatenate(
        [trimesh.creation.box((120.0, 80.0, 20.0)), trimesh.creation.icosphere(3, radius=25.0)]
    )
    cad = CadModel.from_mesh(mesh)
    pts, _ = sample_facing(cad.vertices, cad.faces, cad.face_normals, np.eye(4), 20_000, seed=0)
    pts += np.random.default_rng(0).normal(scale=0.02, size=pts.shape)
    assert surface_noise_mm(pts) == pytest.approx(0.02, rel=0.2)


def test_it_is_seeded_and_leaves_the_input_alone():
    pts = np.random.default_rng(2).normal(size=(3000, 3))
    before = pts.copy()
    assert surface_noise_mm(pts, seed=3) == surface_noise_mm(pts, seed=3)
    assert np.array_equal(pts, before)


def test_bad_input_is_refused():
    with pytest.raises(InvalidInput, match="too few"):
        surface_noise_mm(np.zeros((10, 3)))
    with pytest.raises(InvalidInput, match="neighbours"):
        surface_noise_mm(np.zeros((100, 3)), neighbours=3)
    with pytest.raises(InvalidInput):
        surface_noise_mm(np.zeros((100, 2)))
