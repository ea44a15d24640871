"""Part specs name holes, trim edges and gap/flush points, and a datum alignment (RPS)."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.config import ConfigError, load_part_spec
from service.parts import comparison_points, rps_scheme

HEAD = 'name = "bracket"\ncad = "bracket.stl"\n'


def point(name: str, pos: str, normal: str = "[0, 0, 1]", extra: str = "") -> str:
    return (
        f'[[points]]\nname = "{name}"\nposition_mm = {pos}\nnormal = {normal}\n'
        f"lower_mm = -0.5\nupper_mm = 0.5\nradius_mm = 5\n{extra}"
    )


POINTS = (
    point("H1", "[10, 20, 1]", extra='kind = "hole"\ndiameter_mm = 8.0\n'
          "tolerances = { d = [-0.1, 0.2] }\n")
    + point("S2", "[-40, 20, 1]", extra='kind = "hole"\ndiameter_mm = 6.0\nlength_mm = 20.0\n'
            "axis = [0, 1, 0]\n")
    + point("E1", "[50, 0, 1]", "[1, 0, 0]", 'kind = "trim_edge"\n')
    + point("G1", "[50, 10, 1]", "[1, 0, 0]", 'kind = "gap_flush"\nmate_mm = [54, 10, 1]\n')
    + point("C1", "[0, 30, 1]", "[0, 1, 0]", 'kind = "character_line"\n'
            "tolerances = { line_max = [-1.0, 1.0] }\n")
    + point("Z1", "[-40, -30, 1]") + point("Z2", "[40, -30, 1]") + point("Z3", "[0, 40, 1]")
)  # fmt: skip

RPS = """
[alignment]
method = "{method}"
datums = [
    {{ point = "H1", fixes = ["x", "y"] }},
    {slot}
    {{ point = "Z1", fixes = ["z"] }},
    {{ point = "Z2", fixes = ["z"] }},
    {{ point = "Z3", fixes = ["z"], weight = 2.0 }},
]
"""
SLOT = '{ point = "S2", fixes = [[0, 1, 0]] },'


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bracket.toml"
    path.write_text(text)
    return path


def test_feature_points_and_their_tolerances(tmp_path):
    spec = load_part_spec(write(tmp_path, HEAD + POINTS))
    cps = {cp.name: cp for cp in comparison_points(spec)}
    assert cps["H1"].characteristics() == ("x", "y", "d")
    assert cps["H1"].limits("d") == (-0.1, 0.2) and cps["H1"].limits("x") == (-0.5, 0.5)
    assert cps["S2"].characteristics() == ("x", "y", "d", "len")
    assert cps["S2"].axis == (0.0, 1.0, 0.0)
    assert cps["G1"].mate == (54.0, 10.0, 1.0) and cps["G1"].characteristics() == ("gap", "flush")
    assert cps["E1"].characteristics() == ("trim", "trim_max")
    assert cps["C1"].characteristics() == ("line", "line_max")
    assert cps["C1"].limits("line_max") == (-1.0, 1.0) and cps["C1"].limits("line") == (-0.5, 0.5)
    assert rps_scheme(spec) is None


def test_an_rps_alignment(tmp_path):
    spec = load_part_spec(write(tmp_path, HEAD + RPS.format(method="rps", slot=SLOT) + POINTS))
    scheme = rps_scheme(spec)
    assert scheme is not None and scheme.mode == "rps"
    assert [d.name for d in scheme.datums] == ["H1", "S2", "Z1", "Z2", "Z3"]
    assert scheme.datums[-1].weight == 2.0


@pytest.mark.parametrize(
    "text, match",
    [
        (HEAD + RPS.format(method="rps", slot="") + POINTS, "rotation about z"),
        (HEAD + RPS.format(method="rps", slot='{ point = "E1", fixes = ["y"] },') + POINTS,
         "surface or hole"),
        (HEAD + '[alignment]\nmethod = "rps"\n' + POINTS, "needs datums"),
        (HEAD + POINTS.replace("diameter_mm = 8.0\n", ""), "diameter_mm"),
        (HEAD + POINTS.replace("{ d = [-0.1, 0.2] }", "{ gap = [-0.1, 0.2] }"), "gap"),
        (HEAD + POINTS.replace("mate_mm = [54, 10, 1]\n", ""), "mate"),
    ],
)  # fmt: skip
def test_bad_feature_specs_are_refused_with_the_reason(tmp_path, text, match):
    with pytest.raises(ConfigError, match=match):
        load_part_spec(write(tmp_path, text))


def test_best_fit_held_to_an_incomplete_scheme_is_allowed(tmp_path):
    text = HEAD + RPS.format(method="best_fit_rps", slot="") + POINTS
    scheme = rps_scheme(load_part_spec(write(tmp_path, text)))
    assert scheme is not None and scheme.mode == "best_fit_rps"


def test_the_features_demo_line_loads_its_part_with_checks_and_rps():
    from service.config import load_line_config

    root = Path(__file__).resolve().parents[2] / "configs"
    cfg = load_line_config(root / "line-features.toml")
    assert cfg.simulator.hole_shift_mm > 0
    (path,) = cfg.part_spec_paths()
    spec = load_part_spec(path)
    kinds = {cp.name: cp.kind for cp in comparison_points(spec)}
    assert {kinds[n] for n in ("H1", "S2", "H3")} == {"hole"} and kinds["E1"] == "trim_edge"
    assert kinds["C1"] == "character_line"
    scheme = rps_scheme(spec)
    assert scheme is not None and scheme.mode == "rps"
    # The line file is line.toml but for its part, alone, and a slower trigger (the
    # features and the RPS take their time); the default line sends it beside demo-panel.
    base = (root / "line.toml").read_text().splitlines()
    other = (root / "line-features.toml").read_text().splitlines()
    changed = {b for b, o in zip(base[4:], other[4:], strict=True) if b != o}
    assert {c.split("=")[0].strip() for c in changed} == {"parts", "trigger_period_s"}
    default = load_line_config(root / "line.toml")
    assert {p.stem for p in default.part_spec_paths()} == {"demo-panel", spec.name}
    assert default.simulator.hole_shift_mm == cfg.simulator.hole_shift_mm
