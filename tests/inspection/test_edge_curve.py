"""A trim edge's points fitted as a curve against the CAD's boundary: its offset and its
largest deviation along the edge, against the known edge they were drawn from."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from inspection.deviations import ComparisonPoint, Verdict, deviations
from inspection.edge_curve import curve_offset, nominal_curve
from inspection.errors import InvalidInput
from inspection.feature_checks import check_features
from inspection.features import boundary_samples
from inspection.grid import GridTree
from inspection.panel import Hole, PanelSpec, sheet_metal_panel, surface_point

HOLE = Hole(113.0, 71.5, 10.4)
SPEC = dataclasses.replace(PanelSpec().scaled(400.0, 260.0), holes=(HOLE,), hole_spacing_mm=0.7)
# The made hole: shifted and larger, so that its rim lies off the drawn one by an
# amount that changes along the rim (mm).
DX, DY, DR = -0.3, 0.25, 0.08


@pytest.fixture(scope="module")
def cad():
    return sheet_metal_panel(SPEC)


def rim(cad, angle_deg: float, radius_mm: float = 5.0):
    """The CAD's boundary samples near the rim point at ``angle_deg`` (out of the material:
    towards the hole's centre)."""
    a = math.radians(angle_deg)
    pos, _ = surface_point(SPEC, HOLE.x_mm + HOLE.radius_mm * math.cos(a),
                           HOLE.y_mm + HOLE.radius_mm * math.sin(a))  # fmt: skip
    return boundary_samples(cad.vertices, cad.faces, cad.face_normals, pos, radius_mm, 0.5)


def true_offset(points: np.ndarray) -> np.ndarray:
    """The made rim's offset from the drawn one along the outward normal (into the hole),
    at nominal points of the rim."""
    d = points[:, :2] - [HOLE.x_mm, HOLE.y_mm]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return -(DX * d[:, 0] + DY * d[:, 1] + DR)


def measured_edge(samples: np.ndarray, n: int, noise_mm: float, seed: int) -> np.ndarray:
    """Points on the made rim at random places along the measured span, with noise in the
    surface and a few gross outliers, in no order."""
    rng = np.random.default_rng(seed)
    d = samples[:, :2] - [HOLE.x_mm, HOLE.y_mm]
    ang = np.arctan2(d[:, 1], d[:, 0])
    a = rng.uniform(ang.min(), ang.max(), n)
    r = HOLE.radius_mm + DR + rng.normal(0.0, noise_mm, n)
    xy = np.column_stack([HOLE.x_mm + DX + r * np.cos(a), HOLE.y_mm + DY + r * np.sin(a)])
    z = np.interp(a, np.sort(ang), samples[np.argsort(ang), 2])
    pts = np.column_stack([xy, z])
    pts[:3, :2] += 1.5 * (xy[:3] - [HOLE.x_mm, HOLE.y_mm]) / HOLE.radius_mm
    return pts


def test_the_nominal_curve_runs_through_the_rims_samples(cad):
    samples, _, _ = rim(cad, 30.0)
    curve = nominal_curve(samples[::-1])
    pts = curve.evaluate(np.linspace(*curve.domain, 200))
    r = np.linalg.norm(pts[:, :2] - [HOLE.x_mm, HOLE.y_mm], axis=1)
    # The rim is drawn by 0.7 mm chords, which cut the circle by up to ~0.006 mm.
    assert np.abs(r - HOLE.radius_mm).max() < 0.01


@pytest.mark.parametrize("angle", [0.0, 120.0, 250.0])
def test_a_shifted_rim_is_recovered_by_the_fitted_curve(cad, angle):
    samples, outward, _ = rim(cad, angle)
    pts = measured_edge(samples, 60, 0.04, seed=int(angle))
    m, why = curve_offset(pts, nominal_curve(samples), samples, outward, min_support=10)
    assert m is not None, why
    truth = true_offset(m.points)
    # The mean over the span and the profile within a small part of the 0.5 mm tolerance.
    assert abs(m.offset_mm - truth.mean()) < 0.03
    # The profile, ends included (the curve is tied to its first and last points there).
    assert np.abs(m.offsets - truth).max() < 0.08
    k = int(np.argmax(np.abs(truth)))
    assert abs(m.max_mm - truth[k]) < 0.05
    # Where the largest offset lies: the offset changes slowly along the rim, so the
    # fitted curve's largest may lie a little way off the true one's.
    assert np.linalg.norm(np.asarray(m.at) - m.points[k]) < 2.5
    # The outliers are dropped, not averaged in.
    assert m.support <= 57 and m.rms_mm < 0.06
    assert 0 < m.sigma_mm < 0.02 and m.span_mm > 6.0


def test_a_bent_edge_is_followed_where_one_offset_is_not(cad):
    """An edge bent within the span: the curve gives its largest offset, where a single
    offset of the points averages it away."""
    samples, outward, _ = rim(cad, 0.0, radius_mm=6.0)
    rng = np.random.default_rng(4)
    nominal = nominal_curve(samples)
    t = rng.uniform(*nominal.domain, 80)
    base = nominal.evaluate(t)
    s = (t - t.mean()) / np.ptp(t)
    bump = 0.3 * np.exp(-((s / 0.15) ** 2))  # mm, out of the material, at the span's middle
    near = np.argmin(((base[:, None] - samples[None]) ** 2).sum(-1), axis=1)
    pts = base + (bump + rng.normal(0.0, 0.02, len(t)))[:, None] * outward[near]
    m, why = curve_offset(pts, nominal, samples, outward, min_support=10)
    assert m is not None, why
    assert m.max_mm == pytest.approx(0.3, abs=0.05)
    assert abs(m.at[1] - HOLE.y_mm) < 1.5
    assert m.offset_mm < 0.2


def test_a_curve_read_over_a_stretch_takes_its_figures_there_alone(cad):
    """Points beyond the stretch read shape the curve, but its offset, its largest and the
    span come from the stretch: an edge turned about the middle of the span."""
    samples, outward, _ = rim(cad, 0.0, radius_mm=8.0)
    nominal = nominal_curve(samples)
    t = np.random.default_rng(5).uniform(*nominal.domain, 120)
    base = nominal.evaluate(t)
    near = np.argmin(((base[:, None] - samples[None]) ** 2).sum(-1), axis=1)
    # 0.1 mm off per mm along the edge from the middle: 0.4 mm at the stretch's ends.
    pts = base + (0.1 * (base[:, 1] - HOLE.y_mm))[:, None] * outward[near]
    read = np.abs(samples[:, 1] - HOLE.y_mm) <= 4.0
    whole, why = curve_offset(pts, nominal, samples, outward, min_support=10)
    assert whole is not None, why
    m, why = curve_offset(pts, nominal, samples, outward, min_support=10, read=read)
    assert m is not None, why
    assert abs(whole.max_mm) > 0.6 and abs(whole.at[1] - HOLE.y_mm) > 6.0
    assert abs(m.max_mm) == pytest.approx(0.4, abs=0.03) and abs(m.at[1] - HOLE.y_mm) <= 4.5
    assert abs(m.offset_mm) < 0.03
    assert m.span_mm < 0.7 * whole.span_mm and m.support == whole.support
    nowhere = np.zeros(len(samples), bool)
    assert curve_offset(pts, nominal, samples, outward, min_support=10, read=nowhere) == (
        None, "the points' curve does not reach the stretch to be measured"
    )  # fmt: skip


def test_too_few_points_give_the_reason(cad):
    samples, outward, _ = rim(cad, 0.0)
    pts = measured_edge(samples, 60, 0.04, seed=1)[3:9]
    m, why = curve_offset(pts, nominal_curve(samples), samples, outward, min_support=10)
    assert m is None and why == "6 edge points for the fitted curve, 10 needed"


def test_a_nominal_needs_samples_along_an_edge():
    with pytest.raises(InvalidInput, match="at least 4"):
        nominal_curve(np.zeros((3, 3)))
    with pytest.raises(InvalidInput, match="one place"):
        nominal_curve(np.ones((10, 3)))


def test_a_character_line_the_cloud_barely_sees_is_not_measurable(cad):
    """Both characteristics of the line get the reason; no number is given."""
    tree = GridTree.build(cad)
    pos, _ = surface_point(SPEC, -60.0, SPEC.character_line_y_mm)
    cp = ComparisonPoint("C1", pos, (0.0, 1.0, 0.0), -0.3, 0.3, 20.0, kind="character_line")
    # A cloud of the CAD's own vertices away from the line, and a few across it.
    v = cad.vertices[cad.vertices[:, 2] > 20.0]
    far = v[np.abs(v[:, 1] - SPEC.character_line_y_mm) > 12.0]
    across = v[(np.abs(v[:, 0] + 60.0) < 0.6) & (np.abs(v[:, 1] - SPEC.character_line_y_mm) < 6)]
    points = np.concatenate([far, across])
    devs = deviations(tree, points, [cp])
    out = check_features(devs, [cp], cad, points, tree=tree)
    entries = {c.name: c for c in out.comparison}
    assert set(entries) == {"C1.line", "C1.line_max"}
    for e in entries.values():
        assert e.verdict is Verdict.NOT_MEASURABLE and math.isnan(e.deviation_mm)
        assert e.kind == "character_line"
        assert e.reason is not None and "sections along the line see it in the cloud" in e.reason
    assert out.verdict is Verdict.NOT_MEASURABLE
