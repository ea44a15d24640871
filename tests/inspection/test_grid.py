"""GridTree against an exact brute-force oracle, on generated and shared CAD meshes."""

from __future__ import annotations

import json
import zipfile

import numba
import numpy as np
import pytest
import trimesh
from _fitcases import measure

from inspection.cad import CadModel, load_cad
from inspection.errors import InvalidInput, TreeMismatch
from inspection.grid import FORMAT_VERSION, Closest, GridTree, warmup
from inspection.panel import PanelSpec, sheet_metal_panel

# The fast path reads float32 face records (planes and corners relative to a
# home point near the face): its answers are exact up to that rounding, a few
# nanometres. The slow path (far from the surface) is exact in float64.
FAST_TOL_MM = 1e-5


# ---------------------------------------------------------------------- oracle
def brute_closest(points: np.ndarray, cad: CadModel) -> tuple[np.ndarray, np.ndarray]:
    """Exact closest points and unsigned distances by testing every face (numpy only)."""
    return _brute(points, cad.vertices[cad.faces], cad.face_normals)


def _brute(points: np.ndarray, tri: np.ndarray, n: np.ndarray, chunk: int = 16):
    """The closest point of a triangle is the foot on its plane when that lies
    inside, else the closest point of one of its three edges."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2 = b - a, c - a
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    det = g11 * g22 - g12 * g12
    out_pts = np.empty_like(points)
    out_d = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk, None, :]  # (m, 1, 3)
        r = p - a
        d = (r * n).sum(-1)
        foot = p - d[..., None] * n
        rf = foot - a
        r1, r2 = (rf * e1).sum(-1), (rf * e2).sum(-1)
        u = (g22 * r1 - g12 * r2) / det
        v = (g11 * r2 - g12 * r1) / det
        inside = (u >= 0) & (v >= 0) & (u + v <= 1)
        best = np.where(inside[..., None], foot, np.nan)
        best_d2 = np.where(inside, d * d, np.inf)
        for s0, s1 in ((a, b), (b, c), (c, a)):
            e = s1 - s0
            t = np.clip(((p - s0) * e).sum(-1) / (e * e).sum(-1), 0.0, 1.0)
            q = s0 + t[..., None] * e
            d2 = ((p - q) ** 2).sum(-1)
            better = d2 < best_d2
            best = np.where(better[..., None], q, best)
            best_d2 = np.where(better, d2, best_d2)
        k = best_d2.argmin(axis=1)
        rows = np.arange(len(k))
        out_pts[s : s + chunk] = best[rows, k]
        out_d[s : s + chunk] = np.sqrt(best_d2[rows, k])
    return out_pts, out_d


def surface_samples(
    cad: CadModel, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform random points on the surface and their faces."""
    tri = cad.vertices[cad.faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    f = rng.choice(len(area), n, p=area / area.sum())
    uv = rng.random((n, 2))
    flip = uv.sum(1) > 1
    uv[flip] = 1 - uv[flip]
    p = tri[f, 0] + uv[:, :1] * (tri[f, 1] - tri[f, 0]) + uv[:, 1:] * (tri[f, 2] - tri[f, 0])
    return p, f


def offset_queries(cad, n, lo, hi, rng):
    """Points at a distance in [lo, hi] mm along the face normal, on both sides."""
    p, f = surface_samples(cad, n, rng)
    dist = rng.uniform(lo, hi, n) * rng.choice([-1.0, 1.0], n)
    return p + cad.face_normals[f] * dist[:, None]


def check_against_oracle(tree: GridTree, cad: CadModel, q: np.ndarray, *, mean_mm, p99_mm, max_mm):
    got = tree.query(q)
    ref_pts, ref_d = brute_closest(q, cad)
    err = np.abs(np.abs(got.distances) - ref_d)
    assert err.mean() <= mean_mm, f"mean |error| {err.mean() * 1e3:.3f} um"
    assert np.percentile(err, 99) <= p99_mm, f"p99 |error| {np.percentile(err, 99) * 1e3:.3f} um"
    assert err.max() <= max_mm, f"max |error| {err.max() * 1e3:.3f} um"
    # The returned point is at the returned distance, and lies on the returned face.
    np.testing.assert_allclose(
        np.linalg.norm(q - got.points, axis=1), np.abs(got.distances), atol=1e-9
    )
    tri = cad.vertices[cad.faces]
    for p, f in zip(got.points[:50], got.face[:50], strict=True):
        _, on_face = _brute(p[None], tri[[f]], cad.face_normals[[f]])
        assert on_face[0] < FAST_TOL_MM
    return got, ref_pts, ref_d


# -------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def small_panel() -> CadModel:
    # A smaller panel of the same design keeps the brute-force oracle quick.
    return sheet_metal_panel(PanelSpec().scaled(240.0, 160.0), name="small-panel")


@pytest.fixture(scope="module")
def panel_tree(small_panel) -> GridTree:
    return GridTree.build(small_panel)


@pytest.fixture(scope="module")
def sphere() -> CadModel:
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    return CadModel.from_mesh(mesh, name="sphere")


@pytest.fixture(scope="module")
def sphere_tree(sphere) -> GridTree:
    return GridTree.build(sphere, spacing_mm=1.0, band_mm=3.0)


# ----------------------------------------------------------------------- tests
def test_warmup_compiles_and_returns_seconds():
    assert warmup() >= 0.0


def test_near_queries_match_oracle_on_panel(panel_tree, small_panel):
    rng = np.random.default_rng(1)
    q = offset_queries(small_panel, 400, 0.0, 3.0, rng) + rng.normal(0, 0.2, (400, 3))
    check_against_oracle(panel_tree, small_panel, q, mean_mm=1e-3, p99_mm=0.02, max_mm=0.1)


def test_near_queries_exact_but_for_a_rare_face(panel_tree, small_panel):
    """Many near points, held to the float32 rounding of the face records at
    the 99th percentile: over the panel's bends a query in a cell with a
    candidate list often has its closest face among none of the candidates
    (a third of them), and the walk or the sharp-edge check must still find
    it. Only the rare face closest at no corner of a finely meshed bend
    (see the accuracy notes of inspection.grid) may be missed: here 4
    points of 3000 by 3-50 um."""
    rng = np.random.default_rng(5)
    q = offset_queries(small_panel, 3000, 0.0, 3.0, rng)
    check_against_oracle(panel_tree, small_panel, q, mean_mm=1e-4, p99_mm=FAST_TOL_MM, max_mm=0.1)


def test_far_queries_are_exact(panel_tree, small_panel):
    rng = np.random.default_rng(2)
    q = offset_queries(small_panel, 200, 10.0, 30.0, rng)
    got, ref_pts, ref_d = check_against_oracle(
        panel_tree, small_panel, q, mean_mm=1e-9, p99_mm=1e-9, max_mm=1e-9
    )
    # Ties aside (equidistant points), the closest point itself is the same.
    assert np.median(np.linalg.norm(got.points - ref_pts, axis=1)) < 1e-9
    assert np.percentile(np.linalg.norm(got.points - ref_pts, axis=1), 95) < 0.1


def test_queries_outside_the_bounding_box(panel_tree, small_panel):
    rng = np.random.default_rng(3)
    centre = small_panel.bounds.mean(axis=0)
    direction = rng.normal(size=(50, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    q = centre + direction * rng.uniform(200, 2000, (50, 1))
    check_against_oracle(panel_tree, small_panel, q, mean_mm=1e-9, p99_mm=1e-9, max_mm=1e-9)
    # Points beyond the int64 range of grid cells must not wrap around into it.
    huge = np.array([[1e20, 0.0, 0.0], [-3e19, 2e19, -1e19]])
    got = panel_tree.query(huge)
    np.testing.assert_allclose(np.abs(got.distances), np.linalg.norm(huge, axis=1), rtol=1e-9)
    assert np.all((got.face >= 0) & (got.face < len(small_panel.faces)))


@pytest.mark.parametrize("within_mm", [2.0, 12.0])
def test_a_query_within_a_reach_answers_the_nearer_points_as_the_full_query(
    panel_tree, small_panel, within_mm
):
    """Inside the band (2 mm) nothing beyond the fast path is searched; past it
    (12 mm) the exact search stops at the reach. Either way every point nearer
    than the reach gets the full query's answer to the bit, and the others
    that one or beyond reach: face -1, an infinite distance, NaN point and normal."""
    rng = np.random.default_rng(11)
    q = np.vstack(
        [
            offset_queries(small_panel, 300, 0.0, 3.0, rng),
            offset_queries(small_panel, 300, 5.0, 30.0, rng),
        ]
    )
    full = panel_tree.query(q)
    got = panel_tree.query_within(q, within_mm)
    beyond = got.face < 0
    assert beyond.sum() > 100
    if within_mm > panel_tree.params.band_mm:
        # Points between the band and the reach are searched, not left.
        assert ((~beyond) & (np.abs(full.distances) > panel_tree.params.band_mm)).sum() > 20
    assert not (beyond & (np.abs(full.distances) < within_mm)).any()
    for a, b in (
        (got.points, full.points),
        (got.normals, full.normals),
        (got.distances, full.distances),
        (got.face, full.face),
    ):
        np.testing.assert_array_equal(a[~beyond], b[~beyond])
    assert np.isposinf(got.distances[beyond]).all()
    assert np.isnan(got.points[beyond]).all() and np.isnan(got.normals[beyond]).all()


@pytest.mark.parametrize("reach", [0.0, -1.0, float("nan"), float("inf"), "2", True, None])
def test_a_query_within_refuses_a_reach_that_is_not_a_positive_number(sphere_tree, reach):
    with pytest.raises(InvalidInput, match="within_mm"):
        sphere_tree.query_within(np.zeros((3, 3)), reach)


def test_a_query_within_refuses_points_that_are_not_finite(sphere_tree):
    with pytest.raises(InvalidInput):
        sphere_tree.query_within(np.array([[0.0, np.nan, 0.0], [90.0, 0.0, 0.0]]), 2.0)


def test_signed_distance_both_sides_of_the_panel(panel_tree, small_panel):
    rng = np.random.default_rng(4)
    p, f = surface_samples(small_panel, 400, rng)
    d = rng.uniform(0.05, 1.0, 400) * rng.choice([-1.0, 1.0], 400)
    got = panel_tree.query(p + small_panel.face_normals[f] * d[:, None])
    # Small offsets along the normal of a gently curved sheet keep their side.
    agree = np.sign(got.distances) == np.sign(d)
    assert agree.mean() > 0.99
    np.testing.assert_allclose(np.linalg.norm(got.normals, axis=1), 1.0, atol=1e-12)


def test_signed_distance_inside_and_outside_a_closed_surface(sphere_tree, sphere):
    rng = np.random.default_rng(5)
    direction = rng.normal(size=(500, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(5.0, 80.0, 500)  # inside, near, and far outside
    q = direction * radius[:, None]
    got = sphere_tree.query(q)
    _, ref_d = brute_closest(q, sphere)
    inside = trimesh.Trimesh(sphere.vertices, sphere.faces).contains(q)
    np.testing.assert_allclose(np.abs(got.distances), ref_d, atol=FAST_TOL_MM)
    assert np.all((got.distances < 0) == inside)


def test_signed_distance_off_edges_and_corners_of_a_box():
    box = CadModel.from_mesh(trimesh.creation.box(extents=(60.0, 40.0, 20.0)), name="box")
    tree = GridTree.build(box, spacing_mm=1.0, band_mm=3.0)
    rng = np.random.default_rng(6)
    q = rng.uniform(-35.0, 35.0, (3000, 3)) * [1.0, 0.75, 0.5]
    inside = (np.abs(q) < [30.0, 20.0, 10.0]).all(axis=1)
    outside_d = np.linalg.norm(np.maximum(np.abs(q) - [30.0, 20.0, 10.0], 0.0), axis=1)
    inside_d = np.min([30.0, 20.0, 10.0] - np.abs(q), axis=1)
    expected = np.where(inside, -inside_d, outside_d)
    got = tree.query(q)
    np.testing.assert_allclose(got.distances, expected, atol=FAST_TOL_MM)


@pytest.mark.parametrize(
    ("max_edge", "points"),
    [
        (1.1709, [[0.983551, 19.86388, -14.937223], [0.674559, 19.840005, -14.970782],
                  [-1.581037, 19.964349, 7.29809]]),
        (0.8542, [[-1.589689, -14.795942, 14.918618], [-1.598272, -0.122164, 14.992888]]),
    ],
)  # fmt: skip
def test_points_just_inside_a_plates_edge_get_the_nearer_side(max_edge, points):
    """Inside a 3.2 mm plate, a few hundredths of a millimetre below one face
    and some tenths from the face across the edge: a subcell by the edge whose
    corners all have one face closest, but whose points' feet leave it, must
    not answer with the farther face."""
    half = np.array([1.6, 20.0, 15.0])
    mesh = trimesh.creation.box(extents=2.0 * half).subdivide_to_size(max_edge=max_edge)
    tree = GridTree.build(CadModel.from_mesh(mesh, name="plate"))
    q = np.array(points)
    assert (np.abs(q) < half).all()
    got = tree.query(q)
    np.testing.assert_allclose(got.distances, -np.min(half - np.abs(q), axis=1), atol=FAST_TOL_MM)


@pytest.mark.parametrize("max_edge", [1.1709, 0.8542, 2.3975])
def test_every_point_about_a_plates_surface_gets_its_closest_face(max_edge):
    """Points within a few hundredths of a millimetre of a 3.2 mm plate's
    surface, inside and out: by its edges the face across the edge can be
    closest at none of a subcell's corners (from inside), and a strip of
    slivers along an edge takes many steps to cross."""
    half = np.array([1.6, 20.0, 15.0])
    mesh = trimesh.creation.box(extents=2.0 * half).subdivide_to_size(max_edge=max_edge)
    tree = GridTree.build(CadModel.from_mesh(mesh, name="plate"))
    rng = np.random.default_rng(3)
    on, face = trimesh.sample.sample_surface(mesh, 20000, seed=3)
    q = on + mesh.face_normals[face] * rng.normal(0.0, 0.05, len(on))[:, None]
    inside = (np.abs(q) < half).all(axis=1)
    expected = np.where(
        inside,
        -np.min(half - np.abs(q), axis=1),
        np.linalg.norm(np.maximum(np.abs(q) - half, 0.0), axis=1),
    )
    got = tree.query(q)
    np.testing.assert_allclose(got.distances, expected, atol=FAST_TOL_MM)


@pytest.mark.parametrize(
    ("name", "scale"),
    [
        ("plate_holes.STL", 1.0),
        ("plate_holes.STL", 0.5),
        ("fandisk.obj", 180.0),
        ("fandisk.obj", 60.0),
        ("busted.STL", 30.0),
        ("featuretype.STL", 60.0),
        ("1002_tray_bottom.STL", 1.0),
        ("counter.unitsmm.STL", 1.0),
    ],
)
def test_shared_meshes_match_oracle(shared_cad, name, scale):
    cad = load_cad(shared_cad(name), scale=scale)
    tree = GridTree.build(cad)
    rng = np.random.default_rng(7)
    # Near the surface trimesh's exact closest point is quick enough for a
    # statistically meaningful sample; far away the brute-force oracle is.
    near = offset_queries(cad, 1500, 0.0, 3.0, rng) + rng.normal(0, 0.1, (1500, 3))
    got = tree.query(near)
    ref_pts, ref_d, _ = trimesh.proximity.closest_point(cad.to_trimesh(), near)
    err = np.abs(np.abs(got.distances) - ref_d)
    assert err.mean() <= 1e-3, f"mean |error| {err.mean() * 1e3:.3f} um"
    assert np.percentile(err, 99) <= 0.02, f"p99 |error| {np.percentile(err, 99) * 1e3:.3f} um"
    # Known tail: where a wall thinner than the cell passes between a cell's
    # corners, a point beside it may get the wall's far side (well under 1 mm).
    assert err.max() <= 1.0
    far = offset_queries(cad, 40, 10.0, 30.0, rng)
    # Where the part folds back, a point 10-30 mm off one face can lie within
    # the band of another and take the fast path.
    check_against_oracle(
        tree, cad, far, mean_mm=FAST_TOL_MM, p99_mm=FAST_TOL_MM, max_mm=FAST_TOL_MM
    )


@pytest.mark.parametrize("seed", [1, 2])
def test_faces_across_sharp_edges_are_not_missed(shared_cad, seed):
    """Points within a few tenths of a mm of the featured block: in the
    subcells of mixed cells, a face across a sharp edge of the subcell's face
    (closest at none of its corners) must still be found. Exact, not within
    the tolerance of the thin-wall tail above."""
    cad = load_cad(shared_cad("featuretype.STL"), scale=60.0)
    tree = GridTree.build(cad)
    rng = np.random.default_rng(seed)
    pts, _ = measure(cad, np.eye(4), 4000, noise_mm=0.0, seed=seed)
    q = pts + rng.normal(0.0, 0.3, pts.shape)
    got = tree.query(q)
    _, ref_d, _ = trimesh.proximity.closest_point(cad.to_trimesh(), q)
    err = np.abs(np.abs(got.distances) - ref_d)
    assert err.max() <= 1e-6, f"max |error| {err.max() * 1e3:.3f} um at {q[np.argmax(err)]}"


def test_save_load_round_trip(tmp_path, panel_tree, small_panel):
    path = panel_tree.save(tmp_path / "trees" / "panel.npz")
    assert path.is_file()
    assert not list(path.parent.glob("*.tmp"))
    loaded = GridTree.load(path)
    assert loaded.cad is None
    assert loaded.hash == panel_tree.hash
    assert loaded.cad_hash == small_panel.hash == panel_tree.cad_hash
    assert loaded.params == panel_tree.params
    assert loaded.nbytes == panel_tree.nbytes
    np.testing.assert_array_equal(loaded.bounds, small_panel.bounds)
    q = offset_queries(small_panel, 300, 0.0, 20.0, np.random.default_rng(8))
    a, b = panel_tree.query(q), loaded.query(q)
    for field in ("points", "normals", "distances", "face"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    with_cad = GridTree.load(path, cad=small_panel)
    assert with_cad.cad is small_panel


def test_load_refuses_another_cad(tmp_path, panel_tree, sphere):
    path = panel_tree.save(tmp_path / "panel.npz")
    with pytest.raises(TreeMismatch, match="built for CAD"):
        GridTree.load(path, cad=sphere)


def _rewrite(path, edit_arrays=None, edit_meta=None):
    """Rewrite a saved tree with its arrays and metadata edited in place."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays["meta"].tobytes())
    if edit_meta is not None:
        edit_meta(meta)
    if edit_arrays is not None:
        edit_arrays(arrays)
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(path, **arrays)


@pytest.mark.parametrize("version", [FORMAT_VERSION + 1, FORMAT_VERSION - 1, 1, None])
def test_load_refuses_another_format_version(tmp_path, sphere_tree, version):
    path = sphere_tree.save(tmp_path / "sphere.npz")
    _rewrite(path, edit_meta=lambda m: m.update(format_version=version))
    with pytest.raises(TreeMismatch, match="format version"):
        GridTree.load(path)


def test_load_refuses_a_first_version_file(tmp_path, sphere_tree):
    # Version 1 files had no face hierarchy.
    path = sphere_tree.save(tmp_path / "sphere.npz")

    def drop_bvh(arrays):
        for key in [k for k in arrays if k.startswith("bvh_")]:
            del arrays[key]

    _rewrite(path, drop_bvh, lambda m: m.update(format_version=1))
    with pytest.raises(TreeMismatch, match="format version 1"):
        GridTree.load(path)


@pytest.mark.parametrize(
    ("edit_arrays", "edit_meta", "message"),
    [
        (lambda a: a.pop("bvh_order"), None, "missing array.*bvh_order"),
        (lambda a: a.update(extra=np.zeros(3)), None, "unknown array.*extra"),
        (None, lambda m: m.pop("cad_hash"), "missing metadata field.*cad_hash"),
        (None, lambda m: m.update(colour="red"), "unknown metadata field.*colour"),
        (None, lambda m: m["params"].pop("block"), "missing parameter.*block"),
        (None, lambda m: m["params"].update(depth=3), "unknown parameter.*depth"),
    ],
)
def test_load_refuses_missing_or_unknown_fields(
    tmp_path, sphere_tree, edit_arrays, edit_meta, message
):
    path = sphere_tree.save(tmp_path / "sphere.npz")
    _rewrite(path, edit_arrays, edit_meta)
    with pytest.raises(TreeMismatch, match=message):
        GridTree.load(path)


def test_load_rejects_files_that_are_not_trees(tmp_path):
    with pytest.raises(InvalidInput, match="no such"):
        GridTree.load(tmp_path / "missing.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a tree at all")
    with pytest.raises(InvalidInput, match="not a saved GridTree"):
        GridTree.load(garbage)
    other = tmp_path / "other.npz"
    with zipfile.ZipFile(other, "w"):
        pass
    with pytest.raises(InvalidInput, match="not a saved GridTree"):
        GridTree.load(other)


def test_tree_hash_depends_on_parameters(sphere, sphere_tree):
    other = GridTree.build(sphere, spacing_mm=1.5, band_mm=3.0)
    assert other.cad_hash == sphere_tree.cad_hash
    assert other.hash != sphere_tree.hash
    # Same CAD and parameters: same tree, bit for bit.
    assert GridTree.build(sphere, spacing_mm=1.0, band_mm=3.0).hash == sphere_tree.hash


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros(3),
        np.zeros((4, 2)),
        np.zeros((2, 3, 1)),
        np.array([[0.0, 0.0, np.nan]]),
        np.array([[np.inf, 0.0, 0.0]]),
        # one bad row among points near and far from the surface
        np.vstack([np.zeros((100, 3)), [[0.0, -np.inf, 1.0]], np.full((5, 3), 300.0)]),
        [["a", "b", "c"]],
        None,
    ],
)
def test_invalid_points_raise(sphere_tree, bad):
    with pytest.raises(InvalidInput):
        sphere_tree.query(bad)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"spacing_mm": 0.0},
        {"spacing_mm": -1.0},
        {"spacing_mm": float("nan")},
        {"band_mm": -1.0},
        {"band_mm": float("inf")},
        {"spacing_mm": "x"},
    ],
)
def test_invalid_build_parameters_raise(sphere, kwargs):
    with pytest.raises(InvalidInput):
        GridTree.build(sphere, **kwargs)


def test_build_refuses_non_models_and_huge_grids(sphere):
    with pytest.raises(InvalidInput, match="CadModel"):
        GridTree.build(sphere.to_trimesh())  # type: ignore[arg-type]
    with pytest.raises(InvalidInput, match="in mm"):
        GridTree.build(sphere, spacing_mm=1e-3)


def test_empty_query_and_list_input(sphere_tree):
    empty = sphere_tree.query(np.zeros((0, 3)))
    assert isinstance(empty, Closest)
    assert empty.points.shape == (0, 3) and empty.face.shape == (0,)
    one = sphere_tree.query([[0.0, 0.0, 45.0]])
    assert one.face.dtype == np.int64 and one.distances[0] == pytest.approx(45.0 - 40.0, abs=0.1)


def test_inputs_not_mutated_and_order_irrelevant(sphere_tree):
    rng = np.random.default_rng(9)
    q = rng.uniform(-50, 50, (400, 3))
    q_copy = q.copy()
    q.setflags(write=False)
    a = sphere_tree.query(q)
    np.testing.assert_array_equal(q, q_copy)
    perm = rng.permutation(len(q))
    b = sphere_tree.query(q[perm])
    np.testing.assert_array_equal(a.distances[perm], b.distances)
    np.testing.assert_array_equal(a.points[perm], b.points)
    # Non-contiguous and float32 input give the same answer.
    c = sphere_tree.query(np.asfortranarray(q))
    np.testing.assert_array_equal(a.distances, c.distances)


def test_same_answer_on_one_or_two_threads(panel_tree, small_panel):
    q = offset_queries(small_panel, 3000, 0.0, 6.0, np.random.default_rng(12))
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = panel_tree.query(q)
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = panel_tree.query(q)
    finally:
        numba.set_num_threads(before)
    for field in ("points", "normals", "distances", "face"):
        np.testing.assert_array_equal(getattr(one, field), getattr(two, field))


def test_faces_stay_in_the_cad_order(panel_tree, small_panel, tmp_path):
    # The tree numbers faces its own way inside; what it shows is the CAD's.
    loaded = GridTree.load(panel_tree.save(tmp_path / "panel.npz"))
    for tree in (panel_tree, loaded):
        np.testing.assert_array_equal(tree.faces, small_panel.faces)
        np.testing.assert_array_equal(tree.face_normals, small_panel.face_normals)
    p, f = surface_samples(small_panel, 500, np.random.default_rng(13))
    inside = p + 0.3 * small_panel.face_normals[f]
    got = panel_tree.query(inside)
    # Each returned point lies on the returned face of the CAD, and just off
    # a face along its normal that face is nearly always the closest.
    tri = small_panel.vertices[small_panel.faces]
    for k in range(len(got.face)):
        _, d = _brute(
            got.points[k : k + 1],
            tri[got.face[k : k + 1]],
            small_panel.face_normals[got.face[k : k + 1]],
        )
        assert d[0] < FAST_TOL_MM
    assert (got.face == f).mean() > 0.9


def test_info_reports_sizes(panel_tree, small_panel):
    info = panel_tree.info()
    assert info["format_version"] == FORMAT_VERSION
    assert info["cad_hash"] == small_panel.hash
    assert info["faces"] == len(small_panel.faces)
    assert info["nbytes"] == panel_tree.nbytes > 0
    assert info["blocks"] == panel_tree.n_blocks > 0
    # Sparse: far fewer fine cells than a dense grid over the bounding box.
    dense = np.prod(np.ceil(small_panel.extents / panel_tree.params.spacing_mm) + 1)
    assert info["fine_cells"] < dense
    assert "GridTree" in repr(panel_tree)


def test_progress_reaches_one(sphere):
    seen: list[float] = []
    GridTree.build(sphere, spacing_mm=1.0, band_mm=2.0, progress=seen.append)
    assert seen and seen[-1] == pytest.approx(1.0)
    assert all(b >= a for a, b in zip(seen, seen[1:], strict=False))


def test_queries_beside_a_crack_reach_the_face_across_it():
    """A flat sheet with a crack that opens from a vertex (two boundary edges
    a few degrees apart, as a mesher leaves at a T-junction): a cell across
    the crack stores the face on one side, and a point on the other side
    must still get its own face, around the crack's corner, not a point on
    the first face's edge up to a millimetre away."""
    vertices = np.array(
        [[0, 0, 0], [-0.5, 8, 0], [0.5, 8, 0], [-8, 0, 0], [8, 0, 0], [0, -8, 0], [-8, 8, 0],
         [8, 8, 0]],
        dtype=np.float64,
    )  # fmt: skip
    faces = np.array([[0, 1, 3], [0, 4, 2], [3, 5, 0], [0, 5, 4], [1, 6, 3], [2, 4, 7]])
    cad = CadModel.from_mesh(trimesh.Trimesh(vertices, faces, process=False), name="crack")
    tree = GridTree.build(cad, spacing_mm=1.0, band_mm=3.0)
    rng = np.random.default_rng(0)
    n = 2000
    y = rng.uniform(0.5, 7.5, n)
    side = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    x = side * (y / 16.0 + rng.uniform(0.0, 0.8, n))  # the crack spans |x| < y / 16
    q = np.stack([x, y, rng.normal(0.0, 0.05, n)], axis=1)
    check_against_oracle(tree, cad, q, mean_mm=1e-6, p99_mm=FAST_TOL_MM, max_mm=FAST_TOL_MM)
