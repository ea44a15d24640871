"""The colour map's defect markers: outlined and labelled legibly, the label on the map."""

from __future__ import annotations

import cv2
import numpy as np

from service.api.colormap import Marker, render_top_view


def _amber(img: np.ndarray) -> np.ndarray:
    return (img[:, :, 0] < 60) & (img[:, :, 1] > 170) & (img[:, :, 2] > 220)


def _map(markers: list[Marker]) -> np.ndarray:
    # A flat 400 x 200 mm panel in place: the map is white where the labels go.
    x, y = np.meshgrid(np.linspace(0.0, 400.0, 401), np.linspace(0.0, 200.0, 201))
    pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    png = render_top_view(pts, np.zeros(len(pts)), limit_mm=0.5, size_px=400, markers=markers)
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def test_a_defect_s_label_stands_on_a_dark_halo_over_a_pale_map() -> None:
    img = _map([Marker((100.0, 100.0, 0.0), 300.0, "dent 0.34 mm")])
    amber = _amber(img)
    assert amber.sum() > 50
    ys, xs = np.nonzero(amber)
    # The label, right of the circle: in its box, the text's amber lies on black.
    box = img[ys.min() : ys.max() + 1, 150 : xs.max() + 1]
    dark = (box.max(axis=2) < 40).sum()
    assert dark > 0.5 * _amber(box).sum(), "no halo behind the label"


def test_a_label_that_would_leave_the_map_goes_left_of_its_circle() -> None:
    # 400 px for 400 mm: the map spans x 20..420 px, the colour bar lies beyond.
    img = _map([Marker((392.0, 100.0, 0.0), 300.0, "bump 1.20 mm")])
    ys, xs = np.nonzero(_amber(img))
    assert xs.max() < 20 + 401 + 20, "the label runs onto the colour bar"
    centre_px = 20 + 392
    assert xs.min() < centre_px - 60, "the label is not left of the circle"
