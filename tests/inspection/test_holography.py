"""The holographic sensor: simulator, reconstruction, calibration, CAD-based unwrapping."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from inspection.errors import InvalidInput
from inspection.holography import (
    CalibrateParams,
    Dent,
    HoloCalibration,
    HoloHead,
    HoloNoise,
    ReferenceWave,
    calibrate_head,
    correlate,
    dent_map,
    describe,
    find_lobes,
    lobe_field,
    measure_shape,
    propagate,
    simulate_hologram,
    spectrum,
    stepped_plate,
)
from inspection.holography.shape import _pose_update

N = 256


@pytest.fixture(scope="module")
def head() -> HoloHead:
    return HoloHead.small_field(N)


@pytest.fixture(scope="module")
def injected(head) -> tuple[ReferenceWave, ReferenceWave]:
    """The head's real reference waves: off the design by a tenth of a mrad and curved."""
    r = head.references
    return (
        ReferenceWave(r[0].tilt_x_mrad + 0.11, r[0].tilt_y_mrad - 0.07, 50_000.0),
        ReferenceWave(r[1].tilt_x_mrad - 0.05, r[1].tilt_y_mrad + 0.09, -70_000.0),
    )


@pytest.fixture(scope="module")
def flat_plate() -> trimesh.Trimesh:
    plate = trimesh.creation.box((30.0, 30.0, 3.0))
    plate.apply_translation((0.0, 0.0, -1.5))
    return plate


@pytest.fixture(scope="module")
def calib(head, injected, flat_plate) -> HoloCalibration:
    image, _ = simulate_hologram(head, flat_plate, np.eye(4), references=injected, seed=1)
    return calibrate_head(head, image)


@pytest.fixture(scope="module")
def part() -> trimesh.Trimesh:
    return stepped_plate()


# The true pose is off the nominal one (identity) by 80 um and a few mrad.
T_TRUE = _pose_update(np.array([0.08, 0.002, -0.003]))
SHALLOW = [Dent(-5.0, 5.0, 0.05, 2.0), Dent(5.0, -4.0, 0.15, 2.0)]
DEEP = Dent(6.0, 5.0, 0.45, 2.0)


@pytest.fixture(scope="module")
def shallow(head, injected, part, calib):
    image, truth = simulate_hologram(
        head, part, T_TRUE, deviation_mm=dent_map(head, SHALLOW), references=injected, seed=5
    )
    return image, truth, measure_shape(calib, image, part, np.eye(4))


@pytest.fixture(scope="module")
def deep(head, injected, part, calib):
    image, truth = simulate_hologram(
        head,
        part,
        T_TRUE,
        deviation_mm=dent_map(head, [*SHALLOW, DEEP]),
        references=injected,
        seed=6,
    )
    return image, truth, measure_shape(calib, image, part, np.eye(4))


# -- head and simulator ------------------------------------------------------------


def test_the_small_field_head_has_the_synthetic_wavelength_and_states_its_noise(head):
    l1, l2 = head.wavelengths_mm
    assert l1 * l2 / (l2 - l1) == pytest.approx(1.1, rel=1e-12)
    assert head.interval_mm == pytest.approx(0.55)
    text = describe(head, HoloNoise())
    for word in ("256x256 px", "NA", "speckle", "12 bit", "linewidths", "synthetic 1.1 mm"):
        assert word in text


def test_a_head_whose_lobes_would_overlap_is_refused(head):
    with pytest.raises(InvalidInput, match="overlap"):
        replace(head, na=3 * head.na)
    with pytest.raises(InvalidInput):
        HoloNoise(bit_depth=20)


def test_the_simulator_is_seeded_and_records_within_its_bit_depth(head, part):
    a, truth = simulate_hologram(head, part, np.eye(4), seed=3)
    b, _ = simulate_hologram(head, part, np.eye(4), seed=3)
    c, _ = simulate_hologram(head, part, np.eye(4), seed=4)
    assert a.dtype == np.uint16 and a.shape == (N, N)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert a.max() <= 4095 and a.std() > 100
    # The truth: the plate at 0, the pad 0.8 mm up (a step deeper than one interval).
    on = np.isfinite(truth.height_mm)
    assert np.isclose(np.nanmin(truth.height_mm), 0.0, atol=1e-9)
    assert np.isclose(np.nanmax(truth.height_mm), 0.8, atol=1e-9)
    assert on.mean() == 1.0


def test_dents_move_the_true_surface_along_the_normal(head, part):
    dev = dent_map(head, [Dent(5.0, 0.0, 0.2, 1.0)])
    _, truth = simulate_hologram(head, part, np.eye(4), deviation_mm=dev, seed=0)
    diff = truth.height_mm - truth.cad_height_mm
    assert np.nanmin(diff) == pytest.approx(-0.2, abs=0.01)
    assert np.allclose(truth.deviation_mm, dev)


def test_a_deviation_map_of_the_wrong_shape_is_refused(head, part):
    with pytest.raises(InvalidInput):
        simulate_hologram(head, part, np.eye(4), deviation_mm=np.zeros((3, 3)))


# -- reconstruction ------------------------------------------------------------


def test_the_lobes_are_found_where_the_reference_waves_put_them(head, injected, flat_plate):
    image, _ = simulate_hologram(head, flat_plate, np.eye(4), references=injected, seed=2)
    for lobe, ref, wavelength in zip(
        find_lobes(head, image), injected, head.wavelengths_mm, strict=True
    ):
        # Bin = cycles per field; the carrier of O R* is minus the tilt / lambda.
        assert lobe.col == pytest.approx(-ref.tilt_x_mrad * 1e-3 / wavelength * 18.0, abs=1.5)
        assert lobe.row == pytest.approx(-ref.tilt_y_mrad * 1e-3 / wavelength * 18.0, abs=1.5)
        assert lobe.radius > head.cutoff * 18.0


def test_propagation_there_and_back_returns_the_field(head, flat_plate):
    image, _ = simulate_hologram(head, flat_plate, np.eye(4), seed=2)
    field = lobe_field(spectrum(image), find_lobes(head, image)[0])
    back = propagate(propagate(field, 25.0, 633e-6, head.pitch_mm), -25.0, 633e-6, head.pitch_mm)
    assert np.allclose(back, field, atol=1e-9 * np.abs(field).max())
    with pytest.raises(InvalidInput):
        propagate(np.abs(field), 1.0, 633e-6, head.pitch_mm)


def test_a_tilted_speckle_field_moves_by_dz_times_its_tilt_when_refocused(head):
    rng = np.random.default_rng(0)
    f = np.fft.fftfreq(N, d=head.pitch_mm)
    pupil = f[:, None] ** 2 + f[None, :] ** 2 <= head.cutoff**2
    speckle = np.fft.ifft2(np.fft.fft2(np.exp(2j * np.pi * rng.random((N, N)))) * pupil)
    x, y = head.grid()
    tilt = 2e-3  # rad along x
    field = speckle * np.exp(1j * 2 * np.pi / 633e-6 * tilt * x)
    a = propagate(field, -20.0, 633e-6, head.pitch_mm)
    b = propagate(field, 20.0, 633e-6, head.pitch_mm)
    d = correlate(np.abs(a) ** 2, np.abs(b) ** 2, window=64)
    good = d.good()
    assert good.sum() > 10
    expected = 40.0 * tilt / head.pitch_mm  # px
    assert np.median(d.dx[good]) == pytest.approx(expected, abs=0.05)
    assert abs(np.median(d.dy[good])) < 0.05


def test_correlation_finds_a_sub_pixel_shift_and_says_when_it_is_a_guess():
    from scipy.ndimage import gaussian_filter, shift

    rng = np.random.default_rng(1)
    a = gaussian_filter(rng.random((256, 256)), 3.0)
    b = shift(a, (1.3, -2.7), order=3, mode="wrap")
    d = correlate(a, b, window=64)
    assert np.median(d.dy) == pytest.approx(1.3, abs=0.03)
    assert np.median(d.dx) == pytest.approx(-2.7, abs=0.03)
    assert np.all(d.peak > 0.9)
    unrelated = correlate(a, gaussian_filter(rng.random((256, 256)), 3.0), window=64)
    assert np.median(unrelated.peak) < 0.5
    assert unrelated.good().mean() < d.good().mean()
    with pytest.raises(InvalidInput):
        correlate(a, b[:100], window=64)
    with pytest.raises(InvalidInput):
        correlate(a, b, window=7)


# -- calibration -----------------------------------------------------------------


def test_calibration_recovers_each_lobes_tilt_and_curvature(calib, injected):
    for lc, ref in zip(calib.lobes, injected, strict=True):
        assert lc.wave.tilt_x_mrad == pytest.approx(ref.tilt_x_mrad, abs=0.05)
        assert lc.wave.tilt_y_mrad == pytest.approx(ref.tilt_y_mrad, abs=0.05)
        assert lc.wave.curvature_per_m == pytest.approx(ref.curvature_per_m, rel=0.25)
        assert lc.displacement_rms_px < 0.5
    assert calib.residual.coherence > 0.95


def test_the_calibration_holds_on_another_plate_hologram(head, injected, flat_plate, calib):
    image, _ = simulate_hologram(head, flat_plate, np.eye(4), references=injected, seed=9)
    g = calib.difference(image)
    coherent = np.sum(g)
    assert abs(coherent) / np.abs(g).sum() > 0.95
    assert abs(np.angle(coherent)) < 0.05  # height 0 measured as 0


def test_the_calibration_round_trips_through_toml_and_refuses_edits(calib, tmp_path):
    path = calib.save(tmp_path / "holo.toml")
    back = HoloCalibration.load(path)
    assert back == calib and back.id == calib.id
    text = path.read_text()
    edited = text.replace(f"a = {calib.residual.a!r}", f"a = {calib.residual.a + 1e-3!r}")
    assert edited != text
    with pytest.raises(InvalidInput, match="does not match"):
        HoloCalibration.from_toml(edited)
    with pytest.raises(InvalidInput, match="unknown keys"):
        HoloCalibration.from_toml(text.replace("[residual]", "[residual]\nextra = 1"))
    with pytest.raises(InvalidInput, match="format"):
        HoloCalibration.from_toml(text.replace("inspection-holography/1", "other/1"))


# -- shape against the CAD ---------------------------------------------------------------


@pytest.fixture(scope="module")
def astigmatic(head, injected, flat_plate):
    """Laser 2's reference wave with astigmatism along x/y and the diagonals, its plate
    hologram calibrated with the spheres-only model and with the general quadratic."""
    waves = (injected[0], replace(injected[1], astigmatism_rad=1.0, astigmatism45_rad=-0.5))
    image, _ = simulate_hologram(head, flat_plate, np.eye(4), references=waves, seed=1)
    spheres = calibrate_head(head, image, params=CalibrateParams(astigmatism=False))
    return waves, spheres, calibrate_head(head, image)


def test_calibration_recovers_a_reference_waves_astigmatism(astigmatic):
    waves, spheres, general = astigmatic
    w = general.lobes[1].wave
    # The speckle displacements see most of it; the phase difference's residual the rest.
    assert w.astigmatism_rad == pytest.approx(1.0, abs=0.4)
    assert w.astigmatism45_rad == pytest.approx(-0.5, abs=0.4)
    assert spheres.lobes[1].wave.astigmatism_rad == spheres.lobes[1].wave.astigmatism45_rad == 0
    assert general.residual.coherence > 0.98 > spheres.residual.coherence


def test_modelling_astigmatism_gives_the_unaberrated_shape_back(head, astigmatic, part):
    waves, spheres, general = astigmatic
    image, truth = simulate_hologram(
        head, part, T_TRUE, deviation_mm=dent_map(head, SHALLOW), references=waves, seed=5
    )
    rms = {}
    for name, cal in (("spheres", spheres), ("general", general)):
        shape = measure_shape(cal, image, part, np.eye(4))
        err = (shape.height_mm - truth.height_mm)[shape.measured]
        rms[name] = float(np.sqrt(np.mean(err**2)))
    assert rms["general"] < 0.012 and rms["spheres"] > 2 * rms["general"], rms


def test_a_calibration_written_before_astigmatism_was_modelled_still_loads(calib):
    spheres = replace(
        calib,
        lobes=tuple(
            replace(lc, wave=replace(lc.wave, astigmatism_rad=0.0, astigmatism45_rad=0.0))
            for lc in calib.lobes
        ),
        residual=replace(calib.residual, e=0.0, f=0.0),
    )
    # Such a file has none of the astigmatism keys, and its id was computed without them.
    text = "\n".join(
        ln
        for ln in spheres.to_toml().splitlines()
        if not ln.startswith(("astigmatism_rad = ", "astigmatism45_rad = ", "e = ", "f = "))
    )
    assert "astigmatism" not in text
    old = HoloCalibration.from_toml(text)
    assert old == spheres and old.id == spheres.id
    assert calib.lobes[1].wave.astigmatism_rad != 0.0 and calib.id != spheres.id


def test_the_shape_is_right_across_the_step(shallow):
    _, truth, shape = shallow
    m = shape.measured
    err = shape.height_mm - truth.height_mm
    assert m.mean() > 0.75
    assert np.sqrt(np.mean(err[m] ** 2)) < 0.020
    # Both sides of the 0.8 mm step (1.45 phase intervals) are in their own order.
    low = m & (truth.height_mm < 0.4)
    high = m & (truth.height_mm > 0.6)
    assert low.sum() > 1000 and high.sum() > 1000
    assert abs(np.median(err[low])) < 0.005 and abs(np.median(err[high])) < 0.005
    assert not shape.flagged.any() and shape.regions == ()


def test_deviations_along_the_normal_match_the_dents(shallow):
    _, truth, shape = shallow
    m = shape.measured
    # The pose is fitted: the deviations are against the CAD where the part lies.
    err = shape.deviation_mm[m] - truth.deviation_mm[m]
    assert np.sqrt(np.mean(err**2)) < 0.020
    x, y = np.meshgrid(*(2 * [(np.arange(N) - (N - 1) / 2) * 18.0 / N]))
    for dent in SHALLOW:
        # The head sees the dent through its aperture (a speckle is 0.8 mm at this
        # pixel count) and the phase is averaged over half a speckle: the dent's
        # bottom comes out a little shallower.
        near = m & (np.hypot(x - dent.x_mm, y - dent.y_mm) < 0.5)
        assert np.median(shape.deviation_mm[near]) == pytest.approx(-dent.depth_mm, rel=0.2)


def test_the_pose_is_fitted_from_the_phase(shallow):
    _, _, shape = shallow
    assert shape.pose_converged
    # Heights at the field's corners under the fitted and the true pose.
    corners = np.array([[-9.0, -9.0, 0.0], [9.0, -9.0, 0.0], [-9.0, 9.0, 0.0], [9.0, 9.0, 0.0]])
    fitted = corners @ shape.T_head_part[:3, :3].T + shape.T_head_part[:3, 3]
    true = corners @ T_TRUE[:3, :3].T + T_TRUE[:3, 3]
    assert np.max(np.abs(fitted[:, 2] - true[:, 2])) < 0.01  # the start was 0.125 mm off


def test_a_dent_beyond_a_quarter_synthetic_wavelength_is_flagged_not_unwrapped(deep):
    _, truth, shape = deep
    assert shape.limit_mm == pytest.approx(1.1 / 4)
    err = shape.height_mm - truth.height_mm
    # Nothing is unwrapped into a wrong order (that would be 0.55 mm off).
    assert np.max(np.abs(err[shape.measured])) < 0.1
    # Beyond the limit (by more than the blur of the aperture and the average at the
    # dent's rim) nothing passes for a measurement, and most of it is flagged.
    beyond = np.abs(truth.deviation_mm) > shape.limit_mm + 0.05
    assert beyond.sum() > 200
    assert not (shape.measured & beyond).any()
    assert (shape.flagged & beyond).sum() > 0.8 * beyond.sum()
    assert len(shape.regions) == 1
    region = shape.regions[0]
    assert math.dist(region.centroid_mm, (DEEP.x_mm, DEEP.y_mm)) < 0.5
    assert region.order == -1
    assert region.estimate_mm == pytest.approx(-DEEP.depth_mm, abs=0.05)
    # The rest of the part is still measured right.
    assert np.sqrt(np.mean(err[shape.measured] ** 2)) < 0.020


def _pressed(head, depth_mm, radius_mm, at):
    """The deviation (mm) of a smoothstep dent as the line's simulated head presses it."""
    from inspection.defects import Dent as Pressed

    x, y = head.grid()
    dent = Pressed((*at, 0.0), (0.0, 0.0, 1.0), depth_mm, radius_mm)
    return -depth_mm * dent.profile(np.hypot(x - at[0], y - at[1]))


# Steep dents beyond the range: the flank's ring blurs out (its phase turns within the
# average), cutting the core off the pad (0.6 mm); the whole dent is unmeasurable (0.8 mm
# at 2 mm); the bottom, read 30 um shallow through the aperture, sits at the limit (0.3 mm).
@pytest.mark.parametrize(
    ("depth_mm", "radius_mm", "at"),
    [
        (0.6, 3.0, (6.0, 5.0)),
        (0.8, 2.0, (6.0, 5.0)),
        (0.6, 2.5, (-5.0, 4.0)),
        (0.3, 2.0, (6.0, 5.0)),
    ],
)
def test_a_steep_dent_beyond_the_range_is_reported_and_never_read_an_order_off(
    head, injected, part, calib, depth_mm, radius_mm, at
):
    deviation = _pressed(head, depth_mm, radius_mm, at)
    image, truth = simulate_hologram(
        head, part, T_TRUE, deviation_mm=deviation, references=injected, seed=2
    )
    shape = measure_shape(calib, image, part, np.eye(4))
    err = shape.height_mm - truth.height_mm
    assert np.max(np.abs(err[shape.measured])) < 0.1  # an order off is 0.55 mm
    near = [r for r in shape.regions if math.dist(r.centroid_mm, at) < 1.0]
    assert near, shape.regions
    # Whatever is measured there is no deeper than the limit: the rest is reported.
    x, y = head.grid()
    core = shape.measured & (np.hypot(x - at[0], y - at[1]) < 0.5 * radius_mm)
    assert np.all(np.abs(shape.deviation_mm[core]) <= shape.limit_mm)
    assert np.isfinite(shape.uncertainty_mm[shape.measured]).all()
    assert not np.isfinite(shape.uncertainty_mm[~shape.measured]).any()


@pytest.mark.parametrize(("depth_mm", "radius_mm"), [(0.2, 2.0), (0.2, 3.0), (0.15, 2.0)])
def test_a_dent_well_within_the_range_is_measured_and_not_reported(
    head, injected, part, calib, depth_mm, radius_mm
):
    at = (-5.0, 4.0)
    deviation = _pressed(head, depth_mm, radius_mm, at)
    image, truth = simulate_hologram(
        head, part, T_TRUE, deviation_mm=deviation, references=injected, seed=3
    )
    shape = measure_shape(calib, image, part, np.eye(4))
    assert shape.regions == () and not shape.flagged.any()
    x, y = head.grid()
    core = np.hypot(x - at[0], y - at[1]) < 0.5
    assert shape.measured[core].all()
    err = shape.height_mm - truth.height_mm
    assert np.sqrt(np.mean(err[shape.measured] ** 2)) < 0.020


def test_a_dent_beyond_the_range_fails_the_part_with_the_reason(
    plate_part, calib, head, injected, part
):
    from inspection.deviations import Verdict
    from inspection.measure import measure_hologram

    deviation = _pressed(head, 0.6, 3.0, (6.0, 5.0))
    image, _ = simulate_hologram(
        head, part, T_TRUE, deviation_mm=deviation, references=injected, seed=2
    )
    m = measure_hologram(plate_part, calib, image, np.eye(4))
    assert m.verdict is Verdict.FAIL
    assert "beyond the holographic range (+-0.275 mm) or possibly so" in m.reason


def test_the_spatial_unwrapper_fails_across_the_step_where_the_cad_does_not(shallow):
    skimage = pytest.importorskip(
        "skimage.restoration", reason="the peer unwrapper: pip install scikit-image (dev extra)"
    )
    _, truth, shape = shallow
    m = shape.measured
    z = np.asarray(skimage.unwrap_phase(shape.wrapped_phase)) * 1.1 / (4 * np.pi)
    # The peer knows no absolute order: give it the best one.
    z += np.round(np.median((truth.height_mm - z)[m]) / 0.55) * 0.55
    peer = np.abs(z - truth.height_mm)[m]
    ours = np.abs(shape.height_mm - truth.height_mm)[m]
    assert np.mean(peer > 0.1) > 0.2
    assert np.mean(ours > 0.1) == 0.0


def test_measuring_refuses_an_image_of_another_head(calib, part):
    with pytest.raises(InvalidInput):
        measure_shape(calib, np.zeros((N + 2, N + 2), np.uint16), part, np.eye(4))
    with pytest.raises(InvalidInput):
        measure_shape(calib, np.full((N, N), np.nan), part, np.eye(4))
    with pytest.raises(InvalidInput):
        measure_shape(calib, np.zeros((N, N), np.uint16), part, np.eye(3))


def test_orders_find_a_region_cut_off_by_a_closed_wrap_contour():
    from inspection.holography import orders, wrap

    yy, xx = np.mgrid[0:80, 0:80].astype(np.float64)
    # A smooth bump 1.6 pi high: its top, above pi, wraps to order +1.
    true = 1.6 * np.pi * np.exp(-((xx - 40) ** 2 + (yy - 40) ** 2) / 15.0**2)
    valid = np.ones(true.shape, dtype=bool)
    valid[:, 70:72] = False  # a masked CAD edge splits off a second segment
    o = orders(wrap(true), valid, min_region_px=10)
    above = true > np.pi + 0.05
    below = (true < np.pi - 0.05) & valid
    assert np.all(o.order[above] == 1)
    assert np.all(o.order[below] == 0)
    assert o.known[valid].all() and not o.known[~valid].any()
    # Undo the order: the bump comes back exactly.
    assert np.allclose((wrap(true) + 2 * np.pi * o.order)[valid], true[valid])


def test_orders_leave_a_core_cut_off_by_unmeasurable_pixels_unreached():
    from inspection.holography import orders, wrap

    yy, xx = np.mgrid[0:80, 0:80].astype(np.float64)
    r = np.hypot(xx - 40, yy - 40)
    # A dent 2.2 pi deep: its core wraps to near 0, its flank (where the 2 pi contour
    # lies) is unmeasurable all round.
    true = -2.2 * np.pi * np.clip(1.0 - r / 25.0, 0.0, 1.0)
    valid = (r < 8) | (r > 16)
    one_surface = np.zeros(true.shape, dtype=np.int64)
    o = orders(wrap(true), valid, min_region_px=10, groups=one_surface)
    core, outside = r < 8, r > 16
    assert o.unreached[core].all() and not o.known[core].any()
    assert o.known[outside].all() and np.all(o.order[outside] == 0)
    assert not o.unreached[~valid].any()
    # Without the CAD's groups, each measurable piece is its own: the core reads order 0.
    alone = orders(wrap(true), valid, min_region_px=10)
    assert alone.known[core].all() and np.all(alone.order[core] == 0)


def test_measuring_is_deterministic_and_leaves_its_inputs_alone(calib, part, shallow):
    image, _, shape = shallow
    before = image.copy()
    vertices = part.vertices.copy()
    T = np.eye(4)
    again = measure_shape(calib, image, part, T)
    assert np.array_equal(image, before) and np.array_equal(part.vertices, vertices)
    assert np.array_equal(T, np.eye(4))
    assert np.array_equal(again.height_mm, shape.height_mm, equal_nan=True)
    assert np.array_equal(again.T_head_part, shape.T_head_part)
    assert again.calibration_id == calib.id


# -- the measuring sequence's branch ------------------------------------------------


@pytest.fixture(scope="module")
def plate_part(part):
    from inspection.cad import CadModel
    from inspection.deviations import ComparisonPoint
    from inspection.measure import PartModel

    points = [
        # On the pad, at the 150 um dent: out of a +-0.1 mm tolerance.
        ComparisonPoint("pad", (5.0, -4.0, 0.8), (0.0, 0.0, 1.0), -0.1, 0.1, 1.0),
        # On the plate, away from every dent.
        ComparisonPoint("plate", (-5.0, -1.0, 0.0), (0.0, 0.0, 1.0), -0.1, 0.1, 1.0),
    ]
    cad = CadModel.from_mesh(part, name="stepped-plate")
    return PartModel.build(cad, points, spacing_mm=0.25, band_mm=2.0, alignment=False)


def test_the_sequence_measures_a_hologram_to_a_verdict(plate_part, calib, shallow):
    from inspection.deviations import Verdict
    from inspection.measure import measure_hologram

    image, truth, _ = shallow
    m = measure_hologram(plate_part, calib, image, np.eye(4))
    assert m.frame == "data" and m.passes[0].name == "hologram"
    assert m.quality is not None and m.quality.converged
    by_name = {c.name: c for c in m.deviations.comparison}
    assert by_name["pad"].verdict is Verdict.FAIL
    assert -0.16 < by_name["pad"].deviation_mm < -0.1
    assert by_name["plate"].verdict is Verdict.PASS
    assert abs(by_name["plate"].deviation_mm) < 0.01
    assert m.verdict is Verdict.FAIL and "pad" in m.reason
    # The fit keeps the plate's height where the phase put it: T_cad_head maps the
    # measured points onto the CAD, and the CAD's top face onto the true one.
    top = np.array([[x, y, 0.0] for x in (-8.0, -4.0) for y in (-8.0, 8.0)])
    true = top @ T_TRUE[:3, :3].T + T_TRUE[:3, 3]
    T_head_cad = np.linalg.inv(m.transform)
    fitted = top @ T_head_cad[:3, :3].T + T_head_cad[:3, 3]
    assert np.max(np.abs(fitted[:, 2] - true[:, 2])) < 0.01


def test_a_region_beyond_the_range_fails_the_part_and_is_named(plate_part, calib, deep):
    from dataclasses import replace as copy

    from inspection.deviations import Verdict
    from inspection.measure import measure_hologram

    image, _, _ = deep
    only_plate = copy(plate_part, comparison_points=plate_part.comparison_points[1:])
    m = measure_hologram(only_plate, calib, image, np.eye(4))
    assert [c.verdict for c in m.deviations.comparison] == [Verdict.PASS]
    assert m.verdict is Verdict.FAIL
    assert "beyond the holographic range (+-0.275 mm)" in m.reason
    assert "(5.9, 4.9) mm" in m.reason or "(6.0, 5.0) mm" in m.reason


@pytest.mark.parametrize("node_mm", [2.0, 0.25])
def test_a_dent_between_the_points_is_found_on_a_grid_as_fine_as_the_field(
    plate_part, calib, shallow, node_mm
):
    """The 150 um dent lies away from the one comparison point kept. On the defect search's
    default grid (2 mm cells, 4 mm edges) nearly all of the 18 mm field is edge; on a grid
    scaled to the head's field the dent is a defect that fails the part."""
    from dataclasses import replace as copy

    from inspection.deviations import Verdict
    from inspection.measure import MeasureParams, PartModel, measure_hologram
    from inspection.surface import SurfaceParams

    part = PartModel(plate_part.cad, plate_part.tree, None, plate_part.comparison_points[1:],
                     surface_node_mm=node_mm)  # fmt: skip
    params = copy(MeasureParams(), surface=SurfaceParams(-0.08, 0.08, min_area_mm2=2.0))
    m = measure_hologram(part, calib, shallow[0], np.eye(4), params)
    assert [c.verdict for c in m.deviations.comparison] == [Verdict.PASS]
    dents = [d for d in m.deviations.defects if d.kind == "dent"]
    if node_mm == 2.0:
        assert dents == [] and m.verdict is Verdict.PASS
        return
    assert len(dents) == 1 and m.verdict is Verdict.FAIL and "dent" in m.reason
    assert np.hypot(dents[0].center_mm[0] - 5.0, dents[0].center_mm[1] + 4.0) < 1.0
    assert -0.17 < dents[0].peak_mm < -0.1


# -- the gradient field and the coarse pose ------------------------------------------

# Tilted by 4 and 2.3 degrees: the field's corner (-9, 9) mm lies 1.07 mm off the start,
# the part's slope is two phase intervals over the field.
T_TILTED = _pose_update(np.array([0.08, -0.07, 0.04]))


@pytest.fixture(scope="module")
def tilted(head, injected, part):
    return simulate_hologram(
        head, part, T_TILTED, deviation_mm=dent_map(head, SHALLOW), references=injected, seed=7
    )


def test_the_gradient_field_reads_a_tilt_of_several_intervals_unwrapped(calib, tilted):
    from inspection.holography import gradient_field

    image, truth = tilted
    g = gradient_field(calib, image)
    n = truth.normals
    true_gx = (-n[..., 0] / n[..., 2])[np.rint(g.rows).astype(int), np.rint(g.cols).astype(int)]
    plate = g.good & (np.abs(true_gx + 0.07) < 1e-3)  # windows on the tilted plate
    assert plate.sum() > 20
    assert np.median(g.gx[plate]) == pytest.approx(-0.07, abs=0.005)
    assert np.median(g.gy[plate]) == pytest.approx(0.04, abs=0.005)
    with pytest.raises(InvalidInput, match="planes"):
        gradient_field(calib, image, planes_mm=(100.0, 100.0))


def test_a_start_tilted_beyond_the_phase_range_is_found_only_with_the_coarse_pose(
    calib, part, tilted
):
    from inspection.holography import ShapeParams

    image, truth = tilted
    corners = np.array([[-9.0, -9.0, 0.0], [9.0, -9.0, 0.0], [-9.0, 9.0, 0.0], [9.0, 9.0, 0.0]])
    true = corners @ T_TILTED[:3, :3].T + T_TILTED[:3, 3]
    assert np.max(np.abs(true[:, 2])) > 1.0  # the start (identity) is > 1 mm off there
    wrong = {}
    for coarse in (False, True):
        shape = measure_shape(calib, image, part, np.eye(4), ShapeParams(coarse_pose=coarse))
        err = np.abs(shape.height_mm - truth.height_mm)[shape.measured]
        wrong[coarse] = float(np.mean(err > 0.1))
        if coarse:
            assert shape.coarse is not None and shape.coarse.converged
            assert shape.coarse.slope == pytest.approx((-0.07, 0.04), abs=0.005)
            fitted = corners @ shape.T_head_part[:3, :3].T + shape.T_head_part[:3, 3]
            assert np.max(np.abs(fitted[:, 2] - true[:, 2])) < 0.01
            assert np.sqrt(np.mean(err**2)) < 0.020
        else:
            assert shape.coarse is None
    assert wrong[True] == 0.0 and wrong[False] > 0.3, wrong


def test_a_start_whole_intervals_off_in_height_is_measured_in_the_wrong_order(calib, part, shallow):
    """The height's order is in no part of the hologram: lifted by two phase intervals
    the part gives the same phase difference and the same gradients, so the shape
    comes out exactly two intervals off, flagged nowhere."""
    from inspection.holography import ShapeParams

    image, truth, _ = shallow
    start = _pose_update(np.array([-1.1, 0.0, 0.0]))
    shape = measure_shape(calib, image, part, start, ShapeParams(coarse_pose=True))
    err = (shape.height_mm - truth.height_mm)[shape.measured]
    assert shape.pose_converged and not shape.flagged.any()
    assert np.median(err) == pytest.approx(-1.1, abs=0.005)
    assert np.sqrt(np.mean((err - np.median(err)) ** 2)) < 0.020


def test_the_in_plane_shift_is_found_where_the_steps_lower_the_coherence(
    head, injected, part, calib, flat_plate
):
    from inspection.holography import step_shift

    moved = np.eye(4)
    moved[:2, 3] = (0.5, -0.4)
    image, _ = simulate_hologram(head, part, moved @ T_TRUE, references=injected, seed=8)
    found = step_shift(calib, image, part, np.eye(4))
    assert found is not None
    # Along x the pad's and the facet's steps tell; along y only the facet's side, a
    # step rising from 0 to 0.4 mm, seen through 0.8 mm speckles at this pixel count.
    assert found[0] == pytest.approx(0.5, abs=0.1)
    assert found[1] == pytest.approx(-0.4, abs=0.2)
    # Where the CAD has no step, nothing tells the shift: none is made up.
    plate, _ = simulate_hologram(head, flat_plate, np.eye(4), references=injected, seed=8)
    assert step_shift(calib, plate, flat_plate, np.eye(4)) is None


# -- the lobe cut ----------------------------------------------------------------------


def test_the_lobe_cut_follows_a_lobe_the_spectrum_peak_misses(head, injected, flat_plate):
    """Laser 2's reference wave 1.06 mrad off the design (30 bins): the peak's search
    window clips its lobe; the cut centred by the speckle displacements does not."""
    from inspection.holography import minimise_cut

    l2 = head.wavelengths_mm[1]
    knocked = replace(injected[1], tilt_x_mrad=injected[1].tilt_x_mrad + 30 / 18.0 * l2 * 1e3)
    waves = (injected[0], knocked)
    image, _ = simulate_hologram(head, flat_plate, np.eye(4), references=waves, seed=1)
    carriers = [
        (-w.tilt_y_mrad * 1e-3 / lam * 18.0, -w.tilt_x_mrad * 1e-3 / lam * 18.0)
        for w, lam in zip(waves, head.wavelengths_mm, strict=True)
    ]
    cut = minimise_cut(head, image)
    assert cut.converged
    off_peak = math.dist((cut.start[1].row, cut.start[1].col), carriers[1])
    off_cut = [math.dist((lb.row, lb.col), c) for lb, c in zip(cut.lobes, carriers, strict=True)]
    assert off_peak > 2.0 and max(off_cut) < 0.5, (off_peak, off_cut)
    assert cut.between_px < 0.5 * cut.start_between_px
    peak = calibrate_head(head, image, params=CalibrateParams(minimise_cut=False))
    ours = calibrate_head(head, image)
    assert ours.lobes[1].lobe == cut.lobes[1]
    assert ours.residual.coherence > peak.residual.coherence + 0.005
