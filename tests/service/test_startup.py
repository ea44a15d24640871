"""What a starting station tells: its phases, and the truth about a first start."""

from __future__ import annotations

from pathlib import Path

from service.config import PartSpec
from service.parts import PartRegistry
from service.startup import cached_kernels, kernels_line, preload

# A small generated panel: its tree builds in a second.
SMALL = {"length_mm": 120.0, "width_mm": 80.0, "holes": [], "emboss_size_mm": [30.0, 20.0]}


def start(trees: Path, uploads: Path) -> tuple[dict[str, bool], list[str]]:
    lines: list[str] = []
    with PartRegistry(trees, uploads, alignment=False) as reg:
        reg.add(
            PartSpec(name="small", cad="generated:panel", panel=SMALL, tree={"spacing_mm": 2.0}),
            uploads,
            configured=True,
        )
        built = preload(reg, lines.append)
        assert reg.ready()
    return built, lines


def test_a_first_start_says_it_builds_and_a_second_that_it_loads(tmp_path):
    trees = tmp_path / "trees"
    built, first = start(trees, tmp_path / "uploads")
    assert built == {"small": True}
    assert "part small: loading CAD" in first
    builds = [ln for ln in first if "no cached tree: building it (a first start" in ln]
    # Its progress, every 10 %, rising.
    assert len(builds) >= 2
    pcts = [int(ln.rsplit(" ", 1)[1].rstrip("%")) for ln in builds]
    assert pcts == sorted(pcts) and len(set(pcts)) == len(pcts)
    assert first[-1].startswith("part small: ready in ")

    built, second = start(trees, tmp_path / "uploads")
    assert built == {"small": False}
    assert "part small: tree loaded from the cache" in second
    assert not any("building" in ln for ln in second)


def test_a_part_that_fails_to_load_says_why(tmp_path):
    lines: list[str] = []
    with PartRegistry(tmp_path / "trees", tmp_path / "uploads", alignment=False) as reg:
        reg.add(PartSpec(name="gone", cad="missing.stl"), tmp_path, configured=True)
        assert preload(reg, lines.append) == {"gone": False}
        assert not reg.ready()
    assert len(lines) >= 1 and lines[-1].startswith("part gone: failed: ")
    assert "missing.stl" in lines[-1]


def test_the_kernel_cache_is_read_not_assumed(tmp_path):
    empty = tmp_path / "numba"
    assert cached_kernels(empty) == 0
    assert "none compiled yet" in kernels_line(empty) and "first start" in kernels_line(empty)
    (empty / "x").mkdir(parents=True)
    (empty / "x" / "kernels.fit-12.py311.nbi").write_bytes(b"")
    assert cached_kernels(empty) == 1
    assert "1 compiled kernels cached" in kernels_line(empty)
