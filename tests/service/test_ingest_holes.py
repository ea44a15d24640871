"""The simulated rig makes a generated panel's holes off their drawn place, part by part,
and writes how far into the FrameSet's truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from inspection.panel import HoleShift, PanelSpec, sheet_metal_panel
from inspection.rig import Rig
from service.ingest import SimPart, SimulatedRig, SimulationSettings
from service.pipeline import flash_stages
from service.protocol import ProtocolError, Truth, decode_frameset, encode_frameset

SIZE = (320, 256)


@pytest.fixture(scope="module")
def setup():
    stages = flash_stages(Rig.default().with_image_size(*SIZE), truth=Rig.nominal(*SIZE))
    spec = PanelSpec(hole_spacing_mm=0.7).scaled(400.0, 260.0)
    part = SimPart.from_cad("demo-panel", sheet_metal_panel(spec), panel=spec)
    return stages, part


def capture(setup, seq: int, **settings):
    stages, part = setup
    settings_ = SimulationSettings(defect_rate=0.0, seed=4, **settings)
    sim = SimulatedRig(stages, [part], line="l", station="s", settings=settings_)
    return sim.capture(seq, 1_700_000_000_000_000_000)


def test_holes_are_made_off_their_place_and_the_truth_says_how_far(setup):
    a = capture(setup, 3, hole_shift_mm=0.4, hole_radius_mm=0.1)
    again = capture(setup, 3, hole_shift_mm=0.4, hole_radius_mm=0.1)
    other = capture(setup, 4, hole_shift_mm=0.4, hole_radius_mm=0.1)
    as_drawn = capture(setup, 3)
    assert a.truth is not None and as_drawn.truth is not None and other.truth is not None
    holes = a.truth.holes
    assert len(holes) == 3 and holes == again.truth.holes and holes != other.truth.holes
    assert all(abs(h.dx_mm) <= 0.4 and abs(h.dy_mm) <= 0.4 and abs(h.dr_mm) <= 0.1 for h in holes)
    assert as_drawn.truth.holes == ()
    # The part rendered is the one the truth describes: its holes moved, its pose did not.
    np.testing.assert_array_equal(a.truth.T_rig_part, as_drawn.truth.T_rig_part)
    assert any((x != y).any() for x, y in zip(a.images, as_drawn.images, strict=True))
    # The truth travels in the FrameSet header.
    back = decode_frameset(encode_frameset(a))
    assert back.truth is not None and back.truth.holes == holes


def test_the_holes_truth_reads_back_and_is_checked():
    t = Truth(np.eye(4), (), (HoleShift(0.1, -0.2, 0.03),))
    doc = json.loads(json.dumps(t.to_json()))
    assert doc["holes"] == [{"dx_mm": 0.1, "dy_mm": -0.2, "dr_mm": 0.03}]
    assert Truth.from_json(doc).holes == t.holes
    del doc["holes"]  # written before holes were varied
    assert Truth.from_json(doc).holes == ()
    with pytest.raises(ProtocolError, match="holes"):
        Truth.from_json(dict(doc, holes=[{"dx_mm": 0.1}]))
    with pytest.raises(ProtocolError, match="holes"):
        Truth.from_json(dict(doc, holes=[{"dx_mm": float("nan"), "dy_mm": 0, "dr_mm": 0}]))
