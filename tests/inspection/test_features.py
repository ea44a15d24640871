"""Holes, slots, trim edges and gap/flush measured from flash frames against the simulator's truth.

The frames are rendered with ``Rig.nominal()`` from a panel whose holes lie
off their drawn places (and one is larger), and measured with
``Rig.default()`` against the drawn panel through ``measure_frames``, as on
the line: the entries' shape, kinds, tolerances and reasons, and the holes
against the truth less the fit's pose error. The edge model on its own: a
speckled step synthesised as a camera forms it, and a hole through a thick
sheet seen 17 degrees off vertical, at the true pose. The bench
(``make bench BENCH=features``) reports the errors over poses and seeds.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from inspection.alignment.rps import Datum, RpsScheme
from inspection.defects import Dent, press
from inspection.deviations import ComparisonPoint, Verdict
from inspection.errors import InvalidInput
from inspection.feature_checks import hole_spec
from inspection.features import (
    EdgeParams,
    Flash,
    HoleSpec,
    _edge_model_grid,
    _edge_normal_equations,
    _fit_edges,
    hole_frame,
    measure_hole,
)
from inspection.measure import MeasureParams, PartModel, measure_frames
from inspection.panel import Hole, PanelSpec, sheet_metal_panel, surface_point
from inspection.reconstruct import Reconstructor
from inspection.rig import Rig, belt_pose
from inspection.simulate import simulate
from inspection.transforms import apply

NOMINAL = (
    Hole(113.0, 71.5, 10.4),
    Hole(100.0, -65.0, 6.5, length_mm=26.0, angle_deg=20.0),
    Hole(-133.0, 78.0, 7.0),
)
# The truth: each hole's shift (x, y) and change of radius, mm.
SHIFTS = ((0.5, -0.4, 0.1), (-0.4, 0.3, 0.0), (0.0, 0.5, -0.1))


def spec_with(holes: tuple[Hole, ...]) -> PanelSpec:
    return dataclasses.replace(PanelSpec().scaled(400.0, 260.0), holes=holes, hole_spacing_mm=0.7)


def truth_holes() -> tuple[Hole, ...]:
    return tuple(
        dataclasses.replace(h, x_mm=h.x_mm + dx, y_mm=h.y_mm + dy, radius_mm=h.radius_mm + dr)
        for h, (dx, dy, dr) in zip(NOMINAL, SHIFTS, strict=True)
    )


def hole_point(name: str, spec: PanelSpec, h: Hole, **kw) -> ComparisonPoint:
    pos, n = surface_point(spec, h.x_mm, h.y_mm)
    a = math.radians(h.angle_deg)
    return ComparisonPoint(
        name, pos, kw.pop("normal", n), -0.5, 0.5, 5.0, kind="hole",
        diameter_mm=2 * h.radius_mm, length_mm=h.length_mm,
        axis=(math.cos(a), math.sin(a), 0.0), **kw,
    )  # fmt: skip


def rim_point(name: str, spec: PanelSpec, h: Hole, kind: str, **kw) -> ComparisonPoint:
    """A point on a round hole's rim at +x: its edge's out-of-material normal is -x."""
    pos, _ = surface_point(spec, h.x_mm + h.radius_mm, h.y_mm)
    return ComparisonPoint(name, pos, (-1.0, 0.0, 0.0), -0.5, 0.5, 5.0, kind=kind, **kw)


# The line's truth: the frames' pose (fitted poses are judged against it).
POSE = belt_pose(30.0, -20.0, 25.0)


@pytest.fixture(scope="module")
def scene():
    spec = spec_with(NOMINAL)
    cps = [
        hole_point("H1", spec, NOMINAL[0], tolerances=(("d", -0.1, 0.1),)),
        hole_point("S2", spec, NOMINAL[1]),
        hole_point("H3", spec, NOMINAL[2]),
        hole_point("H1-below", spec, NOMINAL[0], normal=(0.0, 0.0, -1.0)),
        rim_point("E1", spec, NOMINAL[0], "trim_edge", min_support=5),
        rim_point(
            "G1",
            spec,
            NOMINAL[0],
            "gap_flush",
            mate=tuple(np.array(surface_point(spec, NOMINAL[0].x_mm + 7.4, NOMINAL[0].y_mm)[0])),
        ),  # fmt: skip
        *(
            ComparisonPoint(name, *surface_point(spec, x, y), -0.5, 0.5, 8.0)
            for name, x, y in (("Z1", -150.0, -90.0), ("Z2", 150.0, 0.0), ("Z3", -60.0, 100.0))
        ),
    ]
    part = PartModel.build(sheet_metal_panel(spec), cps)
    truth = sheet_metal_panel(spec_with(truth_holes()))
    frames = simulate(Rig.nominal(), truth, POSE, seed=3)
    return part, Reconstructor.build(Rig.default()), frames


def measure(scene, rps: RpsScheme | None = None):
    part, rec, frames = scene
    if rps is not None:
        part = dataclasses.replace(part, rps=rps)
    return measure_frames(part, rec, frames, MeasureParams(guided=False))


@pytest.fixture(scope="module")
def measured(scene):
    m = measure(scene)
    assert m.deviations is not None, m.reason
    return {c.name: c for c in m.deviations.comparison}, m


def test_every_characteristic_is_its_own_entry_with_the_kind(measured):
    entries, m = measured
    want = {"H1.x", "H1.y", "H1.d", "S2.len", "E1.trim", "E1.trim_max", "G1.gap", "G1.flush"}
    assert want <= set(entries)
    assert "H1" not in entries and "H3.len" not in entries and "G1.gap_max" not in entries
    assert entries["H1.x"].kind == "hole" and entries["E1.trim"].kind == "trim_edge"
    assert entries["Z1"].kind == "surface"
    assert "features" in m.timings_ms


@pytest.mark.parametrize("name", ["H1", "S2", "H3"])
def test_every_seen_hole_is_measured_with_support_and_uncertainty(measured, name):
    """Accuracy against the truth is the bench's to report (see the module notes):
    here, what every measurement must carry."""
    entries, _ = measured
    for key in ("x", "y", "d"):
        e = entries[f"{name}.{key}"]
        assert e.verdict is not Verdict.NOT_MEASURABLE, e.reason
        assert math.isfinite(e.deviation_mm) and e.support >= 20
        assert 0 < e.sigma_mm < 1.0


@pytest.mark.parametrize("name", ["H1", "S2", "H3"])
def test_every_hole_is_measured_where_the_fit_puts_the_true_one(scene, measured, name):
    """Within 0.05 mm in position and diameter, once the fit's own pose error at the hole
    (the cloud's fit, not the hole's measurement) is taken off."""
    entries, m = measured
    cp = {c.name: c for c in scene[0].comparison_points}[name]
    dx, dy, dr = SHIFTS[("H1", "S2", "H3").index(name)]
    x, y, _ = hole_frame(cp.normal, hole_spec(cp).axis)
    at = np.asarray(cp.position)
    displaced = apply(m.transform @ POSE, at[None])[0] - at
    for key, axis in (("x", x), ("y", y)):
        want = float(np.dot([dx, dy, 0.0], axis) + displaced @ axis)
        assert abs(entries[f"{name}.{key}"].deviation_mm - want) < 0.05, key
    assert abs(entries[f"{name}.d"].deviation_mm - 2 * dr) < 0.05


def test_a_slot_has_a_length_entry(measured):
    e = measured[0]["S2.len"]
    assert e.kind == "hole" and math.isfinite(e.deviation_mm) and e.sigma_mm > 0


def test_own_tolerance_of_the_diameter(measured):
    e = measured[0]["H1.d"]
    assert (e.lower_mm, e.upper_mm) == (-0.1, 0.1)
    assert e.verdict is (Verdict.PASS if abs(e.deviation_mm) <= 0.1 else Verdict.FAIL)
    assert measured[0]["H1.x"].upper_mm == 0.5


def test_a_hole_the_cameras_cannot_see_is_not_measurable_with_the_reason(measured):
    entries, m = measured
    for key in ("x", "y", "d"):
        e = entries[f"H1-below.{key}"]
        assert e.verdict is Verdict.NOT_MEASURABLE
        assert e.reason == "no camera sees its rim"
    assert m.verdict in (Verdict.NOT_MEASURABLE, Verdict.FAIL)
    assert "H1-below.x (no camera sees its rim)" in (m.reason or "") or m.verdict is Verdict.FAIL


def test_gap_is_the_trim_edge_seen_from_the_mate(measured):
    entries, _ = measured
    trim, gap = entries["E1.trim"], entries["G1.gap"]
    assert trim.kind == "trim_edge" and gap.kind == "gap_flush"
    assert trim.verdict is not Verdict.NOT_MEASURABLE, trim.reason
    assert abs(gap.deviation_mm + trim.deviation_mm) < 1e-9
    # The fitted curve's largest offset, at least its mean's size, and where on the rim.
    top = entries["E1.trim_max"]
    assert top.kind == "trim_edge" and top.at_mm is not None and trim.at_mm is None
    assert abs(top.deviation_mm) >= abs(trim.deviation_mm) - 1e-9
    centre = np.array(surface_point(spec_with(NOMINAL), NOMINAL[0].x_mm, NOMINAL[0].y_mm)[0])
    assert abs(np.linalg.norm((np.asarray(top.at_mm) - centre)[:2]) - NOMINAL[0].radius_mm) < 0.05
    flush = entries["G1.flush"]
    assert flush.verdict is not Verdict.NOT_MEASURABLE and abs(flush.deviation_mm) < 0.1


def test_feature_points_are_checked_on_construction():
    with pytest.raises(InvalidInput, match="diameter_mm"):
        ComparisonPoint("H", (0, 0, 0), (0, 0, 1), -1, 1, 5.0, kind="hole")
    with pytest.raises(InvalidInput, match="no characteristic 'gap'"):
        ComparisonPoint("H", (0, 0, 0), (0, 0, 1), -1, 1, 5.0, kind="hole", diameter_mm=8.0,
                        tolerances=(("gap", -1, 1),))  # fmt: skip
    with pytest.raises(InvalidInput, match="mate"):
        ComparisonPoint("G", (0, 0, 0), (1, 0, 0), -1, 1, 5.0, kind="gap_flush")
    cp = ComparisonPoint("S", (0, 0, 0), (0, 0, 1), -1, 1, 5.0, kind="hole", diameter_mm=8.0,
                         length_mm=20.0, tolerances=(("len", -0.2, 0.3),))  # fmt: skip
    assert cp.characteristics() == ("x", "y", "d", "len")
    assert cp.limits("len") == (-0.2, 0.3) and cp.limits("x") == (-1.0, 1.0)
    assert ComparisonPoint.from_dict(cp.to_dict()) == cp


def scheme(part: PartModel, *, slot: bool = True, mode: str = "rps", below: bool = False):
    """H1 fixes x and y, the slot S2 the direction across its axis, Z1-Z3 fix z."""
    at = {cp.name: cp.position for cp in part.comparison_points}
    a = math.radians(NOMINAL[1].angle_deg)
    datums = [Datum("H1-below" if below else "H1", at["H1"], ("x", "y"))]
    if slot:
        datums.append(Datum("S2", at["S2"], ((-math.sin(a), math.cos(a), 0.0),)))
    datums += [Datum(n, at[n], ("z",)) for n in ("Z1", "Z2", "Z3")]
    return RpsScheme(tuple(datums), mode)


def test_rps_holds_the_datum_hole_on_its_nominal(scene, measured):
    best = measured[0]
    m = measure(scene, scheme(scene[0]))
    assert m.rps is not None and m.rps.exact and m.deviations is not None, m.reason
    assert max(r.max_abs_mm for r in m.rps.residuals) < 1e-6
    after = {c.name: c for c in m.deviations.comparison}
    # Measured again at the RPS pose (other rim samples, so within the measurement's own
    # uncertainty), the datum hole sits on its nominal, where the best fit had it off.
    for key in ("x", "y"):
        e = after[f"H1.{key}"]
        assert abs(e.deviation_mm) < 3 * e.sigma_mm, (key, e.deviation_mm, e.sigma_mm)
    off = math.hypot(best["H1.x"].deviation_mm, best["H1.y"].deviation_mm)
    assert off > 3 * max(after["H1.x"].sigma_mm, after["H1.y"].sigma_mm)
    assert not np.allclose(m.transform, measured[1].transform, atol=1e-3)
    assert "rps" in m.timings_ms


def test_best_fit_held_to_an_incomplete_scheme_keeps_the_free_turn(scene, measured):
    m = measure(scene, scheme(scene[0], slot=False, mode="best_fit_rps"))
    assert m.rps is not None and not m.rps.exact, m.reason
    assert any("rotation about z" in f for f in m.rps.free_directions)
    assert max(r.max_abs_mm for r in m.rps.residuals) < 1e-6


def test_a_dent_on_a_datum_is_found_where_it_is_not_spread_over_the_part(scene):
    part, rec, _ = scene
    z3 = next(cp for cp in part.comparison_points if cp.name == "Z3")
    dent = Dent(z3.position, z3.normal, 0.5, 16.0, 6.0)
    dented = press(sheet_metal_panel(spec_with(truth_holes())).to_trimesh(), [dent])
    frames = simulate(Rig.nominal(), dented, POSE, seed=3)
    best = measure_frames(part, rec, frames, MeasureParams(guided=False))
    m = measure_frames(
        dataclasses.replace(part, rps=scheme(part)), rec, frames, MeasureParams(guided=False)
    )
    assert m.rps is not None and m.deviations is not None, m.reason
    assert best.deviations is not None and best.deviations.defects, best.reason
    # The datum Z3 lies in the dent: held on its nominal, it tilts the part by the
    # dent's depth in the datums' frame. The defects are the surface's own shape all the
    # same: the dent, where it is, and nothing as large as the part.
    assert not np.allclose(m.transform, best.transform, atol=1e-3)
    got = m.deviations.defects
    assert got is not None
    assert [(d.kind, d.peak_mm, d.area_mm2, d.nearest_point) for d in got] == [
        (d.kind, d.peak_mm, d.area_mm2, d.nearest_point) for d in best.deviations.defects
    ]
    assert all(d.area_mm2 < math.pi * 16.0**2 for d in got), got
    at_dent = [d for d in got if np.linalg.norm(d.center_mm - np.asarray(z3.position)) < 5.0]
    assert len(at_dent) == 1 and abs(at_dent[0].peak_mm + 0.5) < 0.1, got
    assert m.verdict is Verdict.FAIL, m.reason
    assert f"dent {abs(at_dent[0].peak_mm):.2f} mm" in (m.reason or ""), m.reason


def test_an_under_determined_scheme_names_its_free_direction(scene):
    with pytest.raises(InvalidInput, match="rotation about z"):
        scheme(scene[0], slot=False)


def test_an_unseen_datum_leaves_the_part_unmeasured_with_the_reason(scene):
    m = measure(scene, scheme(scene[0], below=True))
    assert m.verdict is None
    assert m.reason == "RPS datum H1-below not measurable: no camera sees its rim"


def _speckled_profiles(edge_px: np.ndarray, seed: int) -> tuple[np.ndarray, ...]:
    """Profiles across a dark air into speckled material as a camera forms them: the sharp
    light (the slide's binary grain, blurred by its lens, times a gain, over a dark floor)
    cut at ``edge_px``, averaged over each pixel, blurred by the lens (0.6 px), read at
    the pixels and interpolated between them, with shot and read noise."""
    rng = np.random.default_rng(seed)
    fine = np.arange(-12.0, 12.0, 0.01)
    grain = rng.standard_normal((len(edge_px), len(fine) // 20 + 2))
    coarse = np.arange(grain.shape[1]) * 0.2 - 12.0
    slide = np.array([np.interp(fine, coarse, g) for g in grain]) > 0
    kernel = np.exp(-0.5 * (np.arange(-60, 61) * 0.01 / 0.35) ** 2)
    slide = np.array([np.convolve(row, kernel / kernel.sum(), "same") for row in slide])
    slide = 0.2 + 0.8 * slide
    light = np.where(fine[None, :] >= edge_px[:, None], 30.0 + 170.0 * slide, 4.0)
    box = np.ones(100) / 100
    blur = np.exp(-0.5 * (np.arange(-300, 301) * 0.01 / 0.6) ** 2)
    psf = np.convolve(box, blur / blur.sum())
    image = np.array([np.convolve(row, psf, "same") for row in light])
    phase = rng.uniform(-0.5, 0.5, len(edge_px))
    t = np.arange(-4.0, 4.0 + 1e-9, 0.25)
    prof = np.empty((len(edge_px), len(t)))
    for i, row in enumerate(image):
        pixels = np.arange(-8.0, 9.0) + phase[i]
        values = np.interp(pixels, fine, row)
        values += rng.normal(0.0, np.sqrt(0.3 * values + 1.44))
        prof[i] = np.interp(t, pixels, values)
    model = _edge_model_grid(EdgeParams())
    along = np.array([np.interp(model, fine, row) for row in slide])
    return prof, t, along, model


def test_the_edge_model_finds_a_speckled_step_to_the_noise():
    """The speckle's grain is as fine as the blur: with the slide predicted on the
    material, a profile's edge is off by what the sensor's noise leaves (a twentieth of a
    pixel on the median, a hundredth without noise); taking the material as unpatterned,
    a grain by the edge moves it by several times that."""
    rng = np.random.default_rng(1)
    edge = rng.uniform(-1.5, 1.5, 400)
    prof, t, slide, model = _speckled_profiles(edge, seed=2)
    found, blur, ok = _fit_edges(prof, t, slide, model, EdgeParams())
    err = np.abs(found - edge)[ok]
    assert ok.mean() > 0.9 and 0.6 <= blur <= 0.9
    assert np.median(err) < 0.08 and np.quantile(err, 0.9) < 0.2
    assert abs(np.mean((found - edge)[ok])) < 0.02
    plain, _, ok_plain = _fit_edges(prof, t, None, model, EdgeParams())
    assert np.median(np.abs(plain - edge)[ok_plain]) > 2.5 * np.median(err)


@pytest.mark.parametrize("with_slide", [True, False])
def test_the_edge_fits_normal_equations_are_those_of_their_columns(with_slide):
    """The edge model's least squares, taken as sums over the model's cells, are the
    ones of its columns written out over the profile's samples: what each candidate
    explains of each profile, and the coefficients at the chosen candidates."""
    from scipy.special import ndtr

    rng = np.random.default_rng(4)
    edge = rng.uniform(-1.5, 1.5, 60)
    prof, t, slide, model = _speckled_profiles(edge, seed=5)
    slide = slide if with_slide else None
    scan = np.flatnonzero(np.abs(model) <= EdgeParams().search_px + 1e-9)
    h = 0.5 * (model[1] - model[0])
    kern = ndtr((model[None, :] + h - t[:, None]) / 0.7) - ndtr(
        (model[None, :] - h - t[:, None]) / 0.7
    )
    # The columns at candidate c, over t: 1; sum over m < c of kern (model[m] - model[c]);
    # sum over m >= c of kern; and with the slide, sum over m >= c of kern slide.
    n, S = len(prof), len(scan)
    cols = np.empty((n, len(t), S, 3 if slide is None else 4))
    for s, c in enumerate(scan):
        cols[:, :, s, 0] = 1.0
        cols[:, :, s, 1] = kern[:, :c] @ (model[:c] - model[c])
        cols[:, :, s, 2] = kern[:, c:].sum(axis=1)
        if slide is not None:
            cols[:, :, s, 3] = slide[:, c:] @ kern[:, c:].T
    A = np.einsum("ntsi,ntsj->nsij", cols, cols) + 1e-9 * np.eye(cols.shape[-1])
    B = np.einsum("ntsi,nt->nsi", cols, prof)
    explained = np.einsum("nsi,nsi->ns", B, np.linalg.solve(A, B[..., None])[..., 0])

    system = _edge_normal_equations(prof, kern, model, scan, slide)
    scale = (prof * prof).sum(axis=1)[:, None]
    np.testing.assert_allclose(system.explained() / scale, explained / scale, atol=1e-9)
    k = rng.integers(1, S - 1, n)
    expected = np.linalg.solve(A[np.arange(n), k], B[np.arange(n), k][..., None])[..., 0]
    np.testing.assert_allclose(system.solve(k), expected, rtol=1e-6, atol=1e-6)


def _holed_sheet(centre, radius_mm, thickness_mm, top_mm):
    """A round sheet 40 mm across with a round hole, its top at ``top_mm``: top and bottom
    faces, the hole's wall and the outer rim (0.06 mm faces at the hole, finer than a
    pixel)."""
    import trimesh

    th = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    rr = np.r_[
        np.linspace(radius_mm, radius_mm + 3.0, 31)[:-1], np.geomspace(radius_mm + 3, 40, 40)
    ]
    R, A = np.meshgrid(rr, th, indexing="ij")
    xy = np.column_stack([centre[0] + (R * np.cos(A)).ravel(), centre[1] + (R * np.sin(A)).ravel()])
    idx = np.arange(R.size).reshape(R.shape)
    a, b = idx[:-1], idx[1:]
    c, d = np.roll(b, -1, axis=1), np.roll(a, -1, axis=1)
    top = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    n = R.size
    V = np.concatenate([np.column_stack([xy, np.full(n, top_mm)]),
                        np.column_stack([xy, np.full(n, top_mm - thickness_mm)])])  # fmt: skip
    i0, o0 = idx[0], idx[-1]
    i1, o1 = np.roll(i0, -1), np.roll(o0, -1)
    walls = [np.stack([i0, i1 + n, i1], -1), np.stack([i0, i0 + n, i1 + n], -1),
             np.stack([o0, o1, o1 + n], -1), np.stack([o0, o1 + n, o0 + n], -1)]  # fmt: skip
    mesh = trimesh.Trimesh(V, np.concatenate([top, top[:, ::-1] + n, *walls]), process=False)
    trimesh.repair.fix_normals(mesh)
    return mesh


@pytest.mark.parametrize("at", [(-150.0, 100.0), (150.0, -120.0)])
def test_a_hole_through_a_thick_sheet_seen_17_degrees_off_vertical_within_0_05_mm(at):
    """A 1.5 mm sheet 40 mm above the belt: the cameras, 17-22 degrees off vertical, see
    the hole's wall on its far side, dark under the flash overhead: the edge is the top
    rim's. The hole lies 0.3 mm and -0.2 mm off its drawn place, 0.1 mm larger across."""
    rig = Rig.nominal()
    radius, (dx, dy, dr) = 7.0, (0.3, -0.2, 0.05)
    sheet = _holed_sheet((at[0] + dx, at[1] + dy), radius + dr, 1.5, 40.0)
    frames = simulate(rig, sheet, np.eye(4), seed=5)
    hole = HoleSpec((at[0], at[1], 40.0), (0.0, 0.0, 1.0), 2 * radius)
    m, why = measure_hole(hole, rig.cameras, frames, np.eye(4), flash=Flash.build(rig.projector))
    assert m is not None, why
    assert abs(m.offset_mm[0] - dx) < 0.05 and abs(m.offset_mm[1] - dy) < 0.05
    assert abs(m.diameter_mm - 2 * (radius + dr)) < 0.05
    assert m.cameras >= 3
