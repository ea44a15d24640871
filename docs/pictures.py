"""Regenerate the README's pictures: ``.venv/bin/python docs/pictures.py``.

The rig layout and one trigger's frames come from :mod:`inspection.pictures`;
the deviation map is one simulated part with a 1 mm dent, rendered with the
nominal rig, measured by the line's own sequence (``inspection.measure_frames``
with the calibrated rig) and drawn the way the API draws it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import inspection
from inspection.defects import Dent, press
from inspection.panel import panel_height
from inspection.pictures import write_rig_pictures
from service.api.colormap import Marker, render_top_view

OUT = Path(__file__).parent / "images"


def deviation_map(path: Path) -> None:
    spec = inspection.PanelSpec().scaled(400.0, 260.0)
    cad = inspection.sheet_metal_panel(spec, name="panel")
    # A 1 mm dent, 15 mm in radius, pressed into the top near one corner, as the
    # line's simulator presses its defects.
    x, y = 110.0, -60.0
    z = float(panel_height(spec, np.array([x]), np.array([y]))[0])
    dented = press(cad, [Dent((x, y, z), (0.0, 0.0, 1.0), depth_mm=1.0, radius_mm=15.0)])

    a = np.deg2rad(20.0)
    T_rig_part = np.eye(4)
    T_rig_part[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T_rig_part[:3, 3] = (40.0, -20.0, 0.0)
    frames = inspection.simulate(inspection.Rig.nominal(), dented, T_rig_part, seed=1)
    part = inspection.PartModel.build(cad)
    m = inspection.measure_frames(part, inspection.Rig.default(), frames)
    if m.deviations is None:
        raise SystemExit(f"the picture's part was not measured: {m.reason}")
    markers = [
        Marker(tuple(f.center_mm), f.area_mm2, f"{f.kind} {f.peak_mm:+.2f} mm")
        for f in m.deviations.defects
    ]
    png = render_top_view(
        m.points_cad(), m.deviations.distances, limit_mm=0.5, size_px=560,
        title="deviation from CAD, mm", markers=markers,
    )  # fmt: skip
    path.write_bytes(png)


def main() -> None:
    OUT.mkdir(exist_ok=True)
    for p in write_rig_pictures(OUT):
        print(p)
    deviation_map(OUT / "deviation_map.png")
    print(OUT / "deviation_map.png")


if __name__ == "__main__":
    main()
