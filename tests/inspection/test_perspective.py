"""Perspective maps: exact against ray casting on the moved mesh, inside and beyond the range."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from inspection.errors import InvalidInput
from inspection.panel import PanelSpec, sheet_metal_panel
from inspection.perspective import (
    PerspectiveMap,
    RayCaster,
    camera_rays,
    face_neighbours,
)
from inspection.rig import Rig, belt_pose
from inspection.transforms import apply

# A patch of cam0 over the panel's corner: part, outline and belt in one view.
SHAPE = (90, 120)


@pytest.fixture(scope="module")
def panel():  # type: ignore[no-untyped-def]
    return sheet_metal_panel(PanelSpec().scaled(200.0, 130.0))


@pytest.fixture(scope="module")
def pmap(panel):  # type: ignore[no-untyped-def]
    cam = Rig.nominal().cameras[0]
    T = belt_pose(20.0, -10.0, 25.0)
    corner_mm = apply(T, np.array([[95.0, 60.0, 20.0]]))
    c = cam.project(corner_mm)[0]
    corner = (int(c[0]) - SHAPE[1] // 2, int(c[1]) - SHAPE[0] // 2)
    o, d = camera_rays(cam, corner, SHAPE)
    return PerspectiveMap.build(RayCaster(panel), T, o, d, SHAPE, corner=corner)


def motion(seed: int, deg: float, mm: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    axis = rng.normal(size=3)
    T[:3, :3] = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
    t = rng.normal(size=3)
    T[:3, 3] = mm * t / np.linalg.norm(t)
    return T


def first_hits(vertices, faces, origins, directions):  # type: ignore[no-untyped-def]
    """Brute force in float64 (Moller-Trumbore over every facet): the oracle."""
    tri = vertices[faces]
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    out = np.full((len(origins), 3), np.nan)
    for k, (o, d) in enumerate(zip(origins, directions, strict=True)):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = o - tri[:, 0]
            u = np.einsum("ij,ij->i", s, p) * inv
            q = np.cross(s, e1)
            v = (q @ d) * inv
            t = np.einsum("ij,ij->i", e2, q) * inv
        ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        if ok.any():
            out[k] = o + t[ok].min() * d
    return out


def test_the_map_sees_part_outline_and_belt(pmap) -> None:  # type: ignore[no-untyped-def]
    seen = pmap.face >= 0
    assert 0.2 < seen.mean() < 0.95  # the patch straddles the panel's outline
    assert pmap.step[~seen].any() and pmap.step[seen].any()
    assert not pmap.step.all()
    normals = pmap.normals[seen]
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", normals, pmap.points[seen]),
                               pmap.offsets[seen], atol=1e-9)  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("deg", "mm"), [(0.05, 0.2), (0.2, 1.0)])
def test_query_is_exact_within_the_range(pmap, panel, seed, deg, mm) -> None:  # type: ignore[no-untyped-def]
    T = motion(seed, deg, mm)
    assert pmap.motion_mm(T) <= pmap.max_motion_mm
    pts, face, cast = pmap.query(np.arange(pmap.size), T)
    moved = apply(T @ pmap.T_rig_cad, panel.vertices)
    mesh = trimesh.Trimesh(moved, panel.faces, process=False)
    loc, ray, _ = mesh.ray.intersects_location(pmap.origins, pmap.directions, multiple_hits=False)
    ref = np.full_like(pts, np.nan)
    ref[ray] = loc
    assert (np.isfinite(ref[:, 0]) == np.isfinite(pts[:, 0])).all()
    hit = np.isfinite(ref[:, 0])
    assert np.abs(ref[hit] - pts[hit]).max() < 1e-3  # Embree's float32 rounding
    assert cast < 0.25 * pmap.size  # most pixels answered by the map itself
    # The float64 oracle, on a sample that includes the ray-cast pixels.
    rng = np.random.default_rng(seed)
    sample = np.unique(np.r_[rng.choice(pmap.size, 60, replace=False),
                             np.flatnonzero(pmap.step & (pmap.face >= 0))[:20]])  # fmt: skip
    exact = first_hits(moved, panel.faces, pmap.origins[sample], pmap.directions[sample])
    np.testing.assert_array_equal(np.isfinite(exact[:, 0]), np.isfinite(pts[sample, 0]))
    ok = np.isfinite(exact[:, 0])
    assert np.abs(exact[ok] - pts[sample][ok]).max() < 1e-6
    assert (face[hit] >= 0).all() and (face[~hit] == -1).all()


def test_beyond_the_range_every_pixel_is_cast_and_still_exact(pmap, panel) -> None:  # type: ignore[no-untyped-def]
    T = motion(5, 1.5, 6.0)
    assert pmap.motion_mm(T) > pmap.max_motion_mm
    idx = np.sort(np.random.default_rng(5).choice(pmap.size, 60, replace=False))
    pts, _, cast = pmap.query(idx, T)
    assert cast == len(idx)
    exact = first_hits(apply(T @ pmap.T_rig_cad, panel.vertices), panel.faces,
                       pmap.origins[idx], pmap.directions[idx])  # fmt: skip
    ok = np.isfinite(exact[:, 0])
    assert ok.sum() >= 10
    np.testing.assert_array_equal(ok, np.isfinite(pts[:, 0]))
    assert np.abs(exact[ok] - pts[ok]).max() < 1e-6


def test_no_motion_gives_the_map_itself(pmap) -> None:  # type: ignore[no-untyped-def]
    pts, face, _ = pmap.query(np.arange(pmap.size), np.eye(4))
    seen = pmap.face >= 0
    np.testing.assert_array_equal(face[seen], pmap.face[seen])
    assert np.abs(pts[seen] - pmap.points[seen]).max() < 1e-9


def test_bad_queries_are_refused(pmap) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InvalidInput):
        pmap.query(np.array([pmap.size]), np.eye(4))
    with pytest.raises(InvalidInput):
        pmap.query(np.array([0]), np.full((4, 4), np.nan))
    with pytest.raises(InvalidInput):
        PerspectiveMap.build(pmap.caster, np.eye(4), pmap.origins[:5], pmap.directions[:5], (2, 2))


def test_face_neighbours_cross_the_shared_edge() -> None:
    faces = np.array([[0, 1, 2], [2, 1, 3]])
    nb = face_neighbours(faces)
    # Edge 1-2 is opposite vertex 0 of facet 0 and opposite vertex 3 (slot 2) of facet 1.
    assert nb[0, 0] == 1 and nb[1, 2] == 0
    assert (nb[0, 1:] == -1).all() and (nb[1, :2] == -1).all()
