"""Robust fine registration: recovery of known poses, robustness, the trust
region's monotone cost, observability, determinism and input validation."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from _fitcases import add_blobs, apply, holed_disc, measure, perturbation, pose_errors, rig_views
from scipy.spatial.transform import Rotation

from inspection.cad import CadModel, load_cad
from inspection.errors import InsufficientOverlap, InvalidInput
from inspection.grid import GridTree
from inspection.panel import PanelSpec, sheet_metal_panel
from inspection.registration import (
    LOSSES,
    CadFaces,
    RegisterParams,
    Registration,
    StopReason,
    register,
)

# The tree's default build parameters: what the line uses.
TREE: dict[str, float] = {}


@pytest.fixture(scope="module")
def panel():
    cad = sheet_metal_panel(PanelSpec().scaled(300.0, 200.0))
    return cad, GridTree.build(cad, **TREE)


@pytest.fixture(scope="module")
def shared(shared_cad):
    cache = {}

    def get(name: str, scale: float):
        if name not in cache:
            cad = load_cad(shared_cad(name), scale=scale)
            cache[name] = (cad, GridTree.build(cad, **TREE))
        return cache[name]

    return get


def scenario(cad, *, n=50_000, deg=10.0, mm=20.0, seed=0, noise_mm=0.02, views=None):
    """Measured points (data frame), their normals, and the true T_cad_data."""
    pts, normals = measure(cad, np.eye(4), n, noise_mm=noise_mm, seed=seed, views=views)
    T_data_cad = perturbation(np.random.default_rng(seed), deg, mm, pts.mean(axis=0))
    return apply(T_data_cad, pts), normals @ T_data_cad[:3, :3].T, np.linalg.inv(T_data_cad)


# ----------------------------------------------------------------- accuracy
@pytest.mark.parametrize("seed", [0, 1])
def test_recovers_panel_pose_from_10deg_20mm(panel, seed):
    cad, tree = panel
    data, _, T_true = scenario(cad, seed=seed)
    reg = register(tree, data)
    rot, disp = pose_errors(reg.transform, T_true, data)
    assert reg.converged and reg.stop_reason is StopReason.CONVERGED
    assert rot <= 0.005
    assert disp <= 0.005
    assert 0.015 < reg.rms_mm < 0.025  # the noise, 0.02 mm
    assert reg.inlier_fraction > 0.95
    assert not reg.degenerate


# The shared meshes as stored, seen from above (+z), scaled to ~300 mm.
SHARED_SCALE = {
    "busted.STL": 30.0,
    "featuretype.STL": 60.0,
    "fandisk.obj": 180.0,
    "counter.unitsmm.STL": 1.0,
    "plate_holes.STL": 1.0,
    "1002_tray_bottom.STL": 1.0,
}
_NOISE_LIMIT = (
    "seen from above, the faces turned to the sensor leave one horizontal direction "
    "unconstrained (featuretype's are all parallel to y: their normal matrix is singular; "
    "fandisk's nearly so): only the outline places the part along it, through points that "
    "the noise carries over the edge onto the end walls. With 0.02 mm noise that is good "
    "to 5-25 um (featuretype misses 5 um on 11 of 20 seeds, fandisk on 2), started at the "
    "truth as from 10 deg off: a limit of the data, which the fit reports (featuretype's "
    "is flagged degenerate; see the noise-limit test)"
)
_THROUGH_SLAB = (
    "a thin part tilted through its own thickness: the points below it fit its bottom "
    "face, a local minimum 3.5-4 deg and ~8 mm off; view_direction (the sensor's side) "
    "escapes it, and without it the fit says so (see the thin-wall test)"
)
_EDGE_ON = (
    "the tray is a 3.2 mm plate stored standing on its edge: seen from above, under 1% of "
    "its surface faces the sensor (the 3 mm strip of that edge, the rims of its holes); "
    "from this start the fit settles against the plate's sides, ~11 mm off"
)
SHARED_CASES = [
    pytest.param("busted.STL", 3, None),
    pytest.param("busted.STL", 4, None),
    pytest.param(
        "featuretype.STL", 3, None, marks=pytest.mark.xfail(reason="11.2 um: " + _NOISE_LIMIT)
    ),
    pytest.param("featuretype.STL", 4, None),
    pytest.param("fandisk.obj", 3, None),
    pytest.param(
        "fandisk.obj", 4, None, marks=pytest.mark.xfail(reason="5.06 um: " + _NOISE_LIMIT)
    ),
    pytest.param(
        "counter.unitsmm.STL", 3, None, marks=pytest.mark.xfail(reason="3.9 deg: " + _THROUGH_SLAB)
    ),
    pytest.param("counter.unitsmm.STL", 3, "up"),
    # Seen from above, the disc's turn rests on its ring of holes alone: from
    # these starts it was left free, 12 and 18 deg off, until the escape.
    pytest.param("counter.unitsmm.STL", 0, "up"),
    pytest.param("counter.unitsmm.STL", 14, "up"),
    pytest.param("counter.unitsmm.STL", 4, None),
    pytest.param("counter.unitsmm.STL", 4, "up"),
    pytest.param("counter.unitsmm.STL", 6, "up"),
    pytest.param(
        "plate_holes.STL", 3, None, marks=pytest.mark.xfail(reason="3.6 deg: " + _THROUGH_SLAB)
    ),
    pytest.param("plate_holes.STL", 3, "up"),
    pytest.param("plate_holes.STL", 4, None),
    pytest.param(
        "1002_tray_bottom.STL", 3, None, marks=pytest.mark.xfail(reason="3.3 deg: " + _EDGE_ON)
    ),
    pytest.param(
        "1002_tray_bottom.STL", 3, "up", marks=pytest.mark.xfail(reason="3.3 deg: " + _EDGE_ON)
    ),
    pytest.param("1002_tray_bottom.STL", 4, None),
]


@pytest.mark.parametrize(("name", "seed", "view"), SHARED_CASES)
def test_shared_meshes_from_10deg_20mm(shared, name, seed, view):
    """Fine registration on the shared meshes: 50k points of the side facing
    a single sensor straight above, 0.02 mm noise, 10 deg and 20 mm off:
    0.005 deg and 5 um. (The rig's four cameras see more: see the next test.)"""
    cad, tree = shared(name, SHARED_SCALE[name])
    data, _, T_true = scenario(cad, seed=seed)
    kwargs = {} if view is None else {"view_direction": (0.0, 0.0, 1.0)}
    reg = register(tree, data, **kwargs)
    rot, disp = pose_errors(reg.transform, T_true, data)
    assert reg.converged
    assert rot <= 0.005, (rot, disp)
    assert disp <= 0.005, (rot, disp)


@pytest.mark.parametrize(
    ("name", "seed", "view", "through"),
    [
        ("counter.unitsmm.STL", 3, None, True),
        ("plate_holes.STL", 3, None, True),
        ("counter.unitsmm.STL", 3, "up", False),
        ("plate_holes.STL", 3, "up", False),
        ("counter.unitsmm.STL", 4, None, False),
        ("busted.STL", 3, None, False),
    ],
)
def test_a_fit_through_a_thin_wall_says_so(shared, name, seed, view, through):
    """Without the sensor's side, a thin part started 10 deg / 20 mm off can settle with
    the cloud laid through its thickness: not a silent wrong fit, the share of the cloud
    on the wall's far side says so (and is nil on the fits that found the part)."""
    from inspection.measure.judging import TWO_SIDED_FRACTION

    cad, tree = shared(name, SHARED_SCALE[name])
    data, _, T_true = scenario(cad, seed=seed)
    kwargs = {} if view is None else {"view_direction": (0.0, 0.0, 1.0)}
    reg = register(tree, data, **kwargs)
    rot, _ = pose_errors(reg.transform, T_true, data)
    assert (rot > 1.0) == through, rot  # the cases are what they say
    assert (reg.opposed_fraction > TWO_SIDED_FRACTION) == through, reg.opposed_fraction


def test_measuring_through_a_thin_wall_is_an_error_not_a_verdict(shared):
    from inspection.measure import PartModel, measure_cloud

    cad, _ = shared("counter.unitsmm.STL", SHARED_SCALE["counter.unitsmm.STL"])
    data, _, _ = scenario(cad, seed=3)
    m = measure_cloud(PartModel.build(cad, alignment=False), data, frame="cad")
    assert m.verdict is None and "through a thin wall" in m.reason, m.reason


@pytest.mark.parametrize("seed", [0, 8])
@pytest.mark.parametrize("name", list(SHARED_SCALE))
def test_shared_meshes_seen_by_the_rig_from_10deg_20mm(shared, name, seed):
    """The line's sensor is the rig: four cameras 17 deg off the vertical,
    one on each side, so a face turned towards any of them is measured,
    walls included. Every shared mesh, as stored: 0.005 deg and 5 um from
    10 deg and 20 mm off. (The counter's outer wall is toothed, 5.8 deg
    apart: from seed 0 and 8 the fit settled one to three teeth off, with
    a fifth of its points off the CAD, until the escape turned it back.)"""
    cad, tree = shared(name, SHARED_SCALE[name])
    data, _, T_true = scenario(cad, seed=seed, views=rig_views())
    reg = register(tree, data, view_direction=(0.0, 0.0, 1.0))
    rot, disp = pose_errors(reg.transform, T_true, data)
    assert reg.converged
    assert rot <= 0.005, (rot, disp)
    assert disp <= 0.005, (rot, disp)
    assert reg.inlier_fraction > 0.95


@pytest.mark.parametrize(("name", "scale"), [("featuretype.STL", 60.0), ("fandisk.obj", 180.0)])
def test_weakly_observable_meshes_reach_the_noise_limit(shared, name, scale):
    """Seen from above, the faces of these parts turned to the sensor leave one
    horizontal direction (nearly) unconstrained: only the outline places the
    part along it, through the points that noise carries over the edge onto
    the end walls, so 50k points with 0.02 mm noise cannot place it to 5 um.
    The fit must still resolve what its own normal matrix (those wall points
    included) says it can: the error stays within three times
    noise * sqrt(sum 1/lambda_i / N) of the observability eigenvalues, and the
    rotation within 0.005 deg. Featuretype's direction is weak enough to be
    flagged as degenerate."""
    cad, tree = shared(name, scale)
    data, _, T_true = scenario(cad, seed=3)
    reg = register(tree, data)
    rot, disp = pose_errors(reg.transform, T_true, data)
    bound = 0.02 * np.sqrt(np.sum(1.0 / reg.observability) / len(data))
    assert reg.converged
    if name == "featuretype.STL":
        assert reg.degenerate  # the user is told: y rests on the outline alone
    assert rot <= 0.005
    assert disp <= max(0.005, 3.0 * bound), (disp, bound)


# ------------------------------------------- escape along a free rotation
# Ten holes 36 deg apart on a 120 mm circle, and one more that breaks the
# symmetry: seen from above, only their rims fix the disc's turn.
DISC_HOLES = tuple((120.0, float(a), 8.0) for a in range(0, 360, 36)) + ((80.0, 18.0, 5.0),)


@pytest.fixture(scope="module")
def discs():
    out = {}
    for name, holes in (("holed", DISC_HOLES), ("plain", ())):
        cad = holed_disc(holes=holes)
        out[name] = (cad, GridTree.build(cad))
    return out


def _turned(deg: float) -> np.ndarray:
    """A start turned about the disc's axis and shifted: T_cad_data."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(deg)]).as_matrix()
    T[:3, 3] = (3.0, -4.0, 1.0)
    return T


@pytest.mark.parametrize("deg", [20.0, -25.0])
def test_a_turn_out_of_the_holes_reach_is_found_by_the_escape(discs, deg, caplog):
    """Turned further than its holes are wide, the disc's turn is free where
    the fit ends (no hole meets a hole): without the escape the fit stays
    there and says so; with it, the scan about that axis finds the turn at
    which the holes meet, and the fit from there lands on the truth."""
    cad, tree = discs["holed"]
    data, _ = measure(cad, np.eye(4), 50_000, seed=1)
    up = (0.0, 0.0, 1.0)
    stuck = register(tree, data, init=_turned(deg), view_direction=up, escape_deg=None)
    rot, _ = pose_errors(stuck.transform, np.eye(4), data)
    assert rot > 10.0 and stuck.degenerate
    with caplog.at_level("INFO", logger="inspection.registration"):
        reg = register(tree, data, init=_turned(deg), view_direction=up)
    assert "fits better" in caplog.text  # the operator is told
    rot, disp = pose_errors(reg.transform, np.eye(4), data)
    # Only the holes' rims hold the turn (their walls face away from the
    # sensor): good to a few hundredths of a degree with 0.02 mm noise.
    assert rot <= 0.05 and disp <= 0.1, (rot, disp)
    assert reg.inlier_fraction > stuck.inlier_fraction + 0.02


class _EveryPoint:
    """A tree that only answers every point with its closest face."""

    def __init__(self, tree: GridTree) -> None:
        self.tree = tree
        self.beyond = 0

    def query(self, points):
        return self.tree.query(points)


class _Searching(_EveryPoint):
    """A tree that answers a reach-bounded query too (as a ``GridTree`` does) and
    counts the points it answered as beyond that reach."""

    def query_within(self, points, within_mm):
        got = self.tree.query_within(points, within_mm)
        self.beyond += int((got.face < 0).sum())
        return got


def test_the_escapes_scan_fits_the_same_whether_far_points_are_searched_or_not(discs):
    """The scan truncates each point's distance at a few millimetres, so it asks
    the tree for the points within that reach only; the scanned angles put
    thousands of points beyond it, and a tree that searches each of those on
    to its face gives the same fit, to the bit."""
    cad, tree = discs["holed"]
    data, _ = measure(cad, np.eye(4), 50_000, seed=1)
    up = (0.0, 0.0, 1.0)
    faces = CadFaces.of(tree)
    bounded = _Searching(tree)
    reg = register(bounded, data, init=_turned(20.0), view_direction=up, faces=faces)
    assert bounded.beyond > 1000
    full = register(_EveryPoint(tree), data, init=_turned(20.0), view_direction=up, faces=faces)
    np.testing.assert_array_equal(reg.transform, full.transform)
    np.testing.assert_array_equal(reg.residuals, full.residuals)


@pytest.mark.parametrize(
    "deg",
    [
        3.0,
        -3.0,
    ],
)
def test_a_plate_turned_in_its_plane_about_a_corner_is_found_by_the_escape(shared, deg):
    """The tray, a 3.2 mm plate standing on its edge, seen by the rig, started
    turned in its own plane about one of its corners: the fit settles there
    (the outline's points lie on the plate's own faces), its turn left free.
    Turned about the centroid the outline lands millimetres off; the scan of
    the turn with the shift fitted at each angle finds the plate again."""
    cad, tree = shared("1002_tray_bottom.STL", SHARED_SCALE["1002_tray_bottom.STL"])
    data, _ = measure(cad, np.eye(4), 50_000, seed=0, views=rig_views())
    init = np.eye(4)  # the corner at the CAD's origin stays where it is
    init[:3, :3] = Rotation.from_rotvec([0.0, np.radians(deg), 0.0]).as_matrix()
    up = (0.0, 0.0, 1.0)
    stuck = register(tree, data, init=init, view_direction=up, escape_deg=None)
    assert pose_errors(stuck.transform, np.eye(4), data)[0] > 1.0
    reg = register(tree, data, init=init, view_direction=up)
    rot, disp = pose_errors(reg.transform, np.eye(4), data)
    assert rot <= 0.005 and disp <= 0.005, (rot, disp)


def test_on_a_plain_disc_the_escape_keeps_what_the_points_fix(discs):
    """A plain disc fits equally well at every turn. From a start that fits
    it already, the scan finds nothing better and the fit comes back
    unchanged; from one turned and shifted, the fit has the height and the
    tilt right, and is flagged degenerate (seen from above, only the rim's
    points hold the disc in its plane, and nothing holds its turn)."""
    cad, tree = discs["plain"]
    data, _ = measure(cad, np.eye(4), 20_000, seed=2)
    up = (0.0, 0.0, 1.0)
    reg = register(tree, data, view_direction=up)
    plain = register(tree, data, view_direction=up, escape_deg=None)
    np.testing.assert_array_equal(reg.transform, plain.transform)
    for T in (reg, register(tree, data, init=_turned(20.0), view_direction=up)):
        assert T.degenerate
        normal = T.transform[:3, :3] @ np.array([0.0, 0.0, 1.0])
        assert np.degrees(np.arccos(min(normal[2], 1.0))) <= 0.005
        assert abs(apply(T.transform, data)[:, 2].mean() - data[:, 2].mean()) <= 0.005


@pytest.mark.parametrize("bad", [0.0, -5.0, 181.0, float("nan"), "30", True])
def test_escape_span_is_checked(discs, bad):
    cad, tree = discs["plain"]
    data, _ = measure(cad, np.eye(4), 2000, seed=2)
    with pytest.raises(InvalidInput, match="escape_deg"):
        register(tree, data, escape_deg=bad)


# --------------------------------------------------------------- robustness
def test_redescending_losses_ignore_clustered_outliers_and_l2_does_not(panel):
    cad, tree = panel
    data, normals, T_true = scenario(cad, seed=5)
    bad, moved = add_blobs(data, normals, fraction=0.25, seed=5)
    assert moved.mean() == pytest.approx(0.25, abs=0.001)
    errors = {}
    for loss in ("tukey", "welsch", "cauchy", "l2"):
        reg = register(tree, bad, loss=loss)
        errors[loss] = pose_errors(reg.transform, T_true, data)
        if loss == "tukey":
            # The blobs are recognised as outliers: weight ~0, inliers ~1.
            assert np.median(reg.weights[moved]) < 0.01
            assert np.median(reg.weights[~moved]) > 0.8
            assert reg.inlier_fraction == pytest.approx(0.75, abs=0.03)
    for loss in ("tukey", "welsch", "cauchy"):
        rot, disp = errors[loss]
        assert rot <= 0.02, (loss, errors)
        assert disp <= 0.020, (loss, errors)
    worst_robust = max(max(errors[k][1] for k in ("tukey", "welsch", "cauchy")), 1e-4)
    assert errors["l2"][1] >= 5.0 * worst_robust, errors


def test_input_weights_remove_known_outliers(panel):
    cad, tree = panel
    data, normals, T_true = scenario(cad, n=20_000, deg=3.0, mm=5.0, seed=6)
    bad, moved = add_blobs(data, normals, fraction=0.25, seed=6)
    reg = register(tree, bad, loss="l2", weights=(~moved).astype(float))
    rot, disp = pose_errors(reg.transform, T_true, data)
    assert rot <= 0.005 and disp <= 0.005
    assert np.all(reg.weights[moved] == 0.0)


@pytest.mark.parametrize("max_subset", [64, 512])
def test_small_last_subsets_fit_a_large_cloud(panel, max_subset):
    """A last subset smaller than the cloud's first sample of 1024 points
    (checked against the CAD's box before any query) still fits; the rest of
    the points get their figures at the final pose."""
    cad, tree = panel
    data, _, T_true = scenario(cad, n=5000, deg=3.0, mm=5.0, seed=11)
    reg = register(tree, data, initial_subset=64, max_subset=max_subset, uncertainty_mm=None)
    rot, disp = pose_errors(reg.transform, T_true, data)
    assert reg.converged
    assert rot <= 0.05 and disp <= 0.05
    assert reg.subset_sizes.max() <= max_subset
    assert reg.weights.shape == (5000,) and reg.inlier_fraction > 0.95


def test_a_subset_that_would_leave_out_few_points_grows_to_all_of_them(panel):
    """64, 512, then 4096 of 5000 points would leave 904 out, fewer than it holds: the fit
    goes from 512 points to all 5000 and lands as well."""
    cad, tree = panel
    data, _, T_true = scenario(cad, n=5000, deg=3.0, mm=5.0, seed=11)
    reg = register(tree, data, initial_subset=64, max_subset=None, uncertainty_mm=None)
    rot, disp = pose_errors(reg.transform, T_true, data)
    assert reg.converged and rot <= 0.005 and disp <= 0.005
    assert sorted(set(reg.subset_sizes.tolist())) == [64, 512, 5000]


@pytest.mark.parametrize("seed", [3, 4, 10, 15])
def test_a_loose_first_subset_does_not_wander(panel, seed):
    """Points on the panel's top alone (what a rig sees of it without its
    walls): its turn and shift in its plane rest on a few points of the
    bends, and the first subset of 512 holds only a handful of them. There
    the fit used to crawl along that loose direction, each damped step
    lowering the cost by a trifle, until it ran out of iterations 0.07-0.16
    deg and 0.3-0.5 mm off. A step that gains less than the subset's noise
    resolves ends the stage; the larger subsets then place the part."""
    cad, tree = panel
    pts, _ = measure(cad, np.eye(4), 100_000, noise_mm=0.1, seed=seed, min_cos=0.97)
    T_data_cad = perturbation(np.random.default_rng(seed), 0.05, 0.3, pts.mean(axis=0))
    data = apply(T_data_cad, pts)
    reg = register(tree, data)
    rot, disp = pose_errors(reg.transform, np.linalg.inv(T_data_cad), data)
    assert reg.stop_reason is StopReason.CONVERGED
    assert np.sum(reg.subset_sizes == 512) <= 15
    assert rot <= 0.02 and disp <= 0.1, (rot, disp)


# ------------------------------------------------------------- trust region
@pytest.mark.parametrize("seed", range(24))
def test_cost_never_rises(panel, seed):
    cad, tree = panel
    rng = np.random.default_rng(seed)
    loss = sorted(LOSSES)[seed % len(LOSSES)]
    data, normals, _ = scenario(
        cad, n=3000, deg=rng.uniform(0.5, 12.0), mm=rng.uniform(0.5, 25.0), seed=100 + seed
    )
    if seed % 2:
        data, _ = add_blobs(data, normals, fraction=0.2, n_blobs=4, seed=seed)
    reg = register(tree, data, loss=loss, seed=seed, initial_subset=256, max_subset=1024)
    h = reg.cost_history
    assert len(h) == reg.iterations == len(reg.subset_sizes)
    # Within an iteration: an accepted step lowers the cost, else it stays.
    assert np.all(h[:, 1] <= h[:, 0])
    assert reg.accepted_steps == int(np.sum(h[:, 1] < h[:, 0]))
    # Across iterations on the same points: the scale only shrinks, so the
    # next iteration starts no higher than the last one ended.
    same = reg.subset_sizes[1:] == reg.subset_sizes[:-1]
    assert np.all(h[1:, 0][same] <= h[:-1, 1][same] * (1 + 1e-12))


def test_stop_reasons(panel):
    cad, tree = panel
    data, _, _ = scenario(cad, n=5000, seed=7)
    short = register(tree, data, max_iterations=2)
    assert short.stop_reason is StopReason.MAX_ITERATIONS
    assert not short.converged and short.iterations == 2
    full = register(tree, data)
    assert full.stop_reason is StopReason.CONVERGED and full.converged
    assert str(full.stop_reason) == "converged"


# ------------------------------------------------------------ observability
def test_flat_plate_reports_its_three_free_directions():
    plate = CadModel.from_mesh(trimesh.creation.box((300.0, 200.0, 4.0)), name="plate")
    tree = GridTree.build(plate, **TREE)
    data, _, T_true = scenario(plate, n=5000, deg=0.5, mm=0.5, seed=8)
    reg = register(tree, data)
    assert reg.degenerate
    assert len(reg.degenerate_directions) == 3
    # The free motions are in-plane: x and y translation and rotation about z
    # (components 3, 4 and 2 of the twist), no tilt and no lift.
    free = reg.degenerate_directions
    assert np.allclose(np.linalg.norm(free[:, [2, 3, 4]], axis=1), 1.0, atol=0.05)
    # What the data do fix is fixed: the plane (tilt and height).
    n_est = reg.transform[:3, :3].T @ [0.0, 0.0, 1.0]
    n_true = T_true[:3, :3].T @ [0.0, 0.0, 1.0]
    assert np.degrees(np.arccos(min(1.0, n_est @ n_true))) < 0.005


def test_panel_is_fully_observable(panel):
    cad, tree = panel
    data, _, _ = scenario(cad, n=5000, deg=1.0, mm=1.0, seed=9)
    reg = register(tree, data)
    assert reg.observability.shape == (6,)
    assert np.all(np.diff(reg.observability) >= 0)
    assert reg.observability[0] > 1e-3 * reg.observability[-1]
    assert reg.degenerate_directions.shape == (0, 6)


# -------------------------------------------------------------- determinism
def test_bit_identical_results(panel):
    cad, tree = panel
    data, normals, _ = scenario(cad, n=20_000, deg=5.0, mm=10.0, seed=10)
    data, _ = add_blobs(data, normals, fraction=0.05, seed=10)
    a = register(tree, data)
    b = register(tree, data.copy())
    assert a.transform.tobytes() == b.transform.tobytes()
    assert a.weights.tobytes() == b.weights.tobytes()
    assert a.cost_history.tobytes() == b.cost_history.tobytes()


def test_order_of_points_does_not_change_the_fit(panel):
    """Another order means another random subset: the fits differ by no more
    than the noise leaves uncertain, and the weights of every point agree."""
    cad, tree = panel
    data, _, T_true = scenario(cad, n=20_000, deg=5.0, mm=10.0, seed=11)
    perm = np.random.default_rng(0).permutation(len(data))
    a = register(tree, data)
    b = register(tree, data[perm])
    for reg in (a, b):
        rot, disp = pose_errors(reg.transform, T_true, data)
        assert rot <= 0.005 and disp <= 0.005
    assert pose_errors(a.transform, b.transform, data)[1] < 0.005
    assert np.allclose(a.weights[perm], b.weights, atol=0.05)


def test_inputs_are_not_mutated(panel):
    cad, tree = panel
    data, _, _ = scenario(cad, n=3000, seed=12)
    init = np.eye(4)
    w = np.ones(len(data))
    copies = data.copy(), init.copy(), w.copy()
    register(tree, data, init=init, weights=w)
    for before, after in zip(copies, (data, init, w), strict=True):
        assert np.array_equal(before, after)


def test_init_is_used(panel):
    cad, tree = panel
    data, _, T_true = scenario(cad, n=5000, deg=30.0, mm=60.0, seed=13)
    near = T_true.copy()
    near[:3, 3] += [0.5, -0.3, 0.2]
    reg = register(tree, data, init=near)
    assert pose_errors(reg.transform, T_true, data)[1] < 0.01


# --------------------------------------------------------------- validation
@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((100, 2)), "shape"),
        (np.zeros((0, 3)), "at least"),
        (np.full((100, 3), np.nan), "non-finite"),
        ([[1, 2, "x"]] * 100, "numbers"),
    ],
)
def test_bad_points_raise(panel, points, message):
    with pytest.raises(InvalidInput, match=message):
        register(panel[1], points)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"loss": "bogus"},
        {"init": np.zeros((4, 4))},
        {"init": np.eye(3)},
        {"init": np.diag([1.0, 1.0, -1.0, 1.0])},
        {"weights": -np.ones(3000)},
        {"weights": np.ones(10)},
        {"weights": np.zeros(3000)},
        {"max_iterations": 0},
        {"residual": "point"},
        {"subset_growth": 1},
        {"uncertainty_mm": -1.0},
        {"view_direction": (0.0, 0.0, 0.0)},
        {"view_direction": (0.0, 0.0, 1.0), "loss": "l2"},
    ],
)
def test_bad_parameters_raise(panel, kwargs):
    cad, tree = panel
    data, _, _ = scenario(cad, n=3000, seed=14)
    with pytest.raises(InvalidInput):
        register(tree, data, **kwargs)


def test_cloud_far_from_the_cad_is_insufficient_overlap(panel):
    cad, tree = panel
    data, _, _ = scenario(cad, n=3000, deg=0.0, mm=0.0, seed=15)
    with pytest.raises(InsufficientOverlap):
        register(tree, data + [0.0, 0.0, 500.0])


def test_result_is_a_frozen_registration(panel):
    cad, tree = panel
    data, _, _ = scenario(cad, n=3000, seed=16)
    reg = register(tree, data)
    assert isinstance(reg, Registration)
    with pytest.raises(AttributeError):
        reg.rms_mm = 0.0  # type: ignore[misc]
    assert reg.weights.shape == (3000,) and reg.residuals.shape == (3000,)
    assert np.allclose(reg.transform[3], [0, 0, 0, 1])


def test_per_point_figures_describe_every_point_at_the_final_pose(panel):
    """The fit runs on a subset; weights, residuals, RMS and inlier fraction
    (computed when the fit ends) cover every input point at the final pose."""
    cad, tree = panel
    data, normals, _ = scenario(cad, n=30_000, deg=2.0, mm=3.0, seed=17)
    data, moved = add_blobs(data, normals, fraction=0.1, seed=17)
    reg = register(tree, data)
    assert reg.subset_sizes.max() < len(data)
    d = tree.query(apply(reg.transform, data)).distances
    # The fit's last residuals come partly from each point's kept face in
    # float64 and partly from the tree's float32 face records: nanometres apart.
    assert np.allclose(reg.residuals, d, atol=1e-6)
    inl = np.abs(d) <= 3.0 * reg.scale_mm
    assert reg.inlier_fraction == pytest.approx(inl.mean())
    assert reg.rms_mm == pytest.approx(np.sqrt(np.mean(d[inl] ** 2)))
    assert np.median(reg.weights[moved]) == 0.0 and np.median(reg.weights[~moved]) > 0.8
    assert not reg.weights.flags.writeable and not reg.residuals.flags.writeable
    # From the points as they were passed in: a buffer reused after the fit changes nothing.
    buffer = data.copy()
    late = register(tree, buffer)
    buffer[:] = 0.0
    assert np.array_equal(late.residuals, reg.residuals)


# --------------------------------------------------------------- parameters
def test_params_and_keywords_are_one_fit(panel):
    """``register(tree, points, params)`` and the keywords that build the same
    params give the same fit, bit for bit; keywords replace fields of params."""
    cad, tree = panel
    data, _, _ = scenario(cad, n=5000, deg=3.0, mm=5.0, seed=18)
    by_params = register(tree, data, RegisterParams(loss="huber", seed=3, max_subset=2048))
    by_keywords = register(tree, data, loss="huber", seed=3, max_subset=2048)
    mixed = register(tree, data, RegisterParams(loss="huber", max_subset=2048), seed=3)
    for other in (by_keywords, mixed):
        assert other.transform.tobytes() == by_params.transform.tobytes()
        assert other.weights.tobytes() == by_params.weights.tobytes()
        assert other.cost_history.tobytes() == by_params.cost_history.tobytes()


def test_faces_built_once_fit_as_those_built_per_fit(panel):
    """The faces a caller builds once (from the CAD or the tree) are those a
    fit builds for itself from the tree: the same fit, bit for bit."""
    cad, tree = panel
    data, _, _ = scenario(cad, n=5000, deg=3.0, mm=5.0, seed=19)
    alone = register(tree, data)
    for faces in (CadFaces.of(cad), CadFaces.of(tree)):
        given = register(tree, data, faces=faces)
        assert given.transform.tobytes() == alone.transform.tobytes()
        assert given.residuals.tobytes() == alone.residuals.tobytes()


@pytest.mark.parametrize(
    "kwargs",
    [
        {"loss": "bogus"},
        {"residual": "point"},
        {"max_iterations": 0},
        {"max_iterations": 2.5},
        {"initial_subset": 5},
        {"max_subset": 100},
        {"subset_growth": 1},
        {"uncertainty_mm": 0.0},
        {"max_distance_mm": float("inf")},
        {"min_scale_mm": -1.0},
        {"escape_deg": 0.0},
        {"view_direction": (0.0, 0.0, 1.0), "loss": "huber"},
    ],
)
def test_params_fail_fast(kwargs):
    with pytest.raises(InvalidInput):
        RegisterParams(**kwargs)


def test_params_store_a_unit_view_direction():
    assert RegisterParams(view_direction=(0.0, 0.0, 2.0)).view_direction == (0.0, 0.0, 1.0)
    assert RegisterParams().view_direction is None


def _plate_like_normal_matrix() -> np.ndarray:
    """A normal matrix (normalised by the weight total) with three stiff directions and
    three loose ones a hundred times weaker, as a flat sheet gives: tilts and the
    normal's shift stiff, the in-plane slide and spin loose."""
    rotation = Rotation.from_euler("xyz", [20.0, -35.0, 50.0], degrees=True).as_matrix()
    basis = np.zeros((6, 6))
    basis[:3, :3] = rotation
    basis[3:, 3:] = rotation.T
    return basis @ np.diag([1.0, 1.0, 0.01, 0.01, 0.01, 1.0]) @ basis.T, basis


@pytest.mark.parametrize(
    ("direction", "length_mm", "within"),
    [
        # sigma 0.01 mm on a weight total of 1e4: the pose's standard deviation is
        # 0.1 um along a stiff direction, 1 um along a loose one.
        (0, 0.5e-4, True),
        (0, 2e-4, True),  # within the six parameters' chi-square (squared length 4)
        (0, 3e-4, False),  # beyond it (9)
        (0, 1e-3, False),  # as long as the loose direction's uncertainty, but along a stiff one
        (5, 1e-3, False),
        (2, 0.5e-3, True),
        (3, 0.9e-3, True),
        (4, 3e-3, False),
    ],
)
def test_a_gauss_newton_step_is_judged_in_the_metric_of_the_poses_covariance(
    direction: int, length_mm: float, within: bool
) -> None:
    from inspection.registration.solver import gauss_newton_step_within_noise

    H, basis = _plate_like_normal_matrix()
    delta = basis[:, direction] * length_mm
    g = -H @ delta
    assert gauss_newton_step_within_noise(H, g, 0.01, 1e4, 1e-6) is within


def test_a_gauss_newton_step_without_a_minimum_or_a_noise_is_not_within_it() -> None:
    from inspection.registration.solver import gauss_newton_step_within_noise

    H, basis = _plate_like_normal_matrix()
    g = -H @ (basis[:, 2] * 0.5e-3)
    assert gauss_newton_step_within_noise(H, g, 0.01, 1e4, 1e-6)
    # A direction the points do not constrain: no minimum, however short the step.
    free = basis @ np.diag([1.0, 1.0, 0.01, 0.01, 1e-5, 1.0]) @ basis.T
    assert not gauss_newton_step_within_noise(free, -free @ (basis[:, 2] * 1e-5), 0.01, 1e4, 1e-6)
    # No noise estimate: only the tolerance counts.
    assert not gauss_newton_step_within_noise(H, g, 0.0, 1e4, 1e-6)
    assert gauss_newton_step_within_noise(H, g, 0.0, 1e4, 1e-3)
    assert not gauss_newton_step_within_noise(H, np.full(6, np.nan), 0.01, 1e4, 1e-6)
