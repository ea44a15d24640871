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


def test_compiling_kernels_are_counted_and_told():
    """numba's own compile events: two specialisations of a new kernel compile (and
    are told), a third call of a known one compiles nothing."""
    import numba

    from service.startup import kernel_compiles

    @numba.njit
    def plus_one(x):
        return x + 1

    lines: list[str] = []
    with kernel_compiles(lines.append, every_s=0.0, ours=(plus_one.py_func.__module__,)) as k:
        plus_one(1)
        plus_one(1.5)
        plus_one(2)
    assert k.compiled == 2
    counts = [ln for ln in lines if ln.startswith("kernels: compiling, ")]
    assert counts[0].startswith("kernels: compiling, 1 done in ") and "plus_one" in counts[0]
    assert lines[-1].startswith("kernels: 2 compiled in ")
    quiet: list[str] = []
    with kernel_compiles(quiet.append, ours=(plus_one.py_func.__module__,)) as k:
        plus_one(3)
    assert k.compiled == 0 and quiet == []


def test_a_kernel_compiling_long_is_told_while_it_compiles():
    """One kernel can compile for minutes: the ticker names it, with its time so far."""
    import numba
    from numba.core import event

    from service.startup import kernel_compiles

    @numba.njit
    def slow(x):
        return x * 2

    lines: list[str] = []
    with kernel_compiles(lines.append, every_s=0.0, ours=(slow.py_func.__module__,)) as k:
        # numba's own start event, as its dispatcher sends it when a compile begins.
        k.on_start(event.Event("numba:compile", event.EventStatus.START, {"dispatcher": slow}))
        k.tick()
    assert any(ln.startswith("kernels: compiling ") and ".slow for " in ln for ln in lines)
