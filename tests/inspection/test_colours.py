"""The one colour scale of deviations (the API's map, the PLY pictures)."""

from __future__ import annotations

import numpy as np

from inspection.colours import deviation_colours


def test_deviation_colours_run_blue_white_red_and_grey_for_nan():
    rgb = deviation_colours(np.array([-1.0, 0.0, 1.0, np.nan]), 0.5)
    assert rgb.dtype == np.uint8
    assert rgb.tolist() == [[0, 0, 255], [255, 255, 255], [255, 0, 0], [128, 128, 128]]


def test_deviation_colours_are_symmetric_and_saturate_at_the_limit():
    v = np.random.default_rng(0).uniform(-0.4, 0.4, 200)
    pos, neg = deviation_colours(v, 0.2), deviation_colours(-v, 0.2)
    np.testing.assert_array_equal(pos, neg[:, ::-1])  # red <-> blue mirror
    np.testing.assert_array_equal(deviation_colours([0.2, 5.0], 0.2)[0], [255, 0, 0])
    np.testing.assert_array_equal(deviation_colours([0.2, 5.0], 0.2)[1], [255, 0, 0])
