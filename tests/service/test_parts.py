"""The part registry: trees cached by CAD hash + build parameters + format version."""

from __future__ import annotations

from pathlib import Path

import pytest

from inspection.errors import CadLoadError
from inspection.panel import PanelSpec, sheet_metal_panel
from service.config import PartSpec
from service.models import JobState, PartState
from service.parts import (
    PartConflict,
    PartNotReady,
    PartRegistry,
    PathConflict,
    UnknownPart,
    load_part_cad,
    panel_spec,
    tree_cache_path,
)

SMALL = {"length_mm": 120.0, "width_mm": 80.0, "holes": [], "emboss_center_mm": [-20.0, -15.0],
         "emboss_size_mm": [30.0, 20.0], "character_line_y_mm": 15.0}  # fmt: skip


def spec(name="p", **tree) -> PartSpec:
    return PartSpec(name=name, cad="generated:panel", panel=SMALL, tree=tree)


def test_panel_parameters_map_onto_the_generator():
    hole = {"x_mm": 1.0, "y_mm": 2.0, "radius_mm": 3.0}
    ps = panel_spec({"length_mm": 100.0, "holes": [hole], "emboss_size_mm": [10, 5]})
    assert ps.length_mm == 100.0 and ps.holes[0].radius_mm == 3.0 and ps.emboss_size_mm == (10, 5)
    with pytest.raises(ValueError, match="panel parameters"):
        panel_spec({"colour": "red"})


def test_generated_cad_is_deterministic():
    a = load_part_cad(spec(), Path("."))
    b = load_part_cad(spec(), Path("."))
    assert a.hash == b.hash and len(a.faces) > 1000


def test_tree_is_built_once_then_loaded(tmp_path):
    trees = tmp_path / "trees"
    with PartRegistry(trees, tmp_path / "uploads", alignment=False) as reg:
        reg.add(spec(spacing_mm=2.0), tmp_path, configured=True)
        assert not reg.ready()
        with pytest.raises(PartNotReady):
            reg.get("p")
        reg.preload()
        assert reg.ready() and reg.states() == {"p": "ready"}
        first = reg.get("p")
    files = list(trees.glob("*.npz"))
    assert len(files) == 1 and files[0] == tree_cache_path(trees, first.cad, spec(spacing_mm=2.0))
    mtime = files[0].stat().st_mtime_ns
    with PartRegistry(trees, tmp_path / "uploads", alignment=False) as reg:
        reg.add(spec(spacing_mm=2.0), tmp_path, configured=True)
        reg.preload()
        again = reg.get("p")
    assert files[0].stat().st_mtime_ns == mtime  # loaded, not rebuilt
    assert again.tree_hash == first.tree_hash
    # Other build parameters: another cache entry.
    with PartRegistry(trees, tmp_path / "uploads", alignment=False) as reg:
        reg.add(spec(spacing_mm=2.5), tmp_path, configured=True)
        reg.preload()
        other = reg.get("p")
    assert other.tree_hash != first.tree_hash
    assert len(list(trees.glob("*.npz"))) == 2


def test_a_corrupt_cached_tree_is_rebuilt(tmp_path):
    trees = tmp_path / "trees"
    s = spec(spacing_mm=2.0)
    cad = load_part_cad(s, tmp_path)
    path = tree_cache_path(trees, cad, s)
    trees.mkdir()
    path.write_bytes(b"not a tree")
    with PartRegistry(trees, tmp_path / "uploads", alignment=False) as reg:
        reg.add(s, tmp_path, configured=True)
        reg.preload()
        assert reg.ready()
    assert path.stat().st_size > 1000


def test_a_failing_part_does_not_stop_the_others(tmp_path):
    with PartRegistry(tmp_path / "trees", tmp_path / "uploads", alignment=False) as reg:
        reg.add(spec("good", spacing_mm=2.0), tmp_path, configured=True)
        reg.add(PartSpec(name="bad", cad="missing.stl"), tmp_path, configured=True)
        reg.preload()
        assert reg.states() == {"bad": "failed", "good": "ready"}
        assert not reg.ready()
        with pytest.raises(PartNotReady, match="no such file"):
            reg.get("bad")
        pub = reg.public("bad")
        assert pub.state == PartState.failed
        assert reg.job(pub.job).state == JobState.failed
        with pytest.raises(UnknownPart):
            reg.get("nope")


def test_uploads_survive_a_restart_and_bad_ones_leave_nothing(tmp_path):
    stl = tmp_path / "u.stl"
    sheet_metal_panel(PanelSpec().scaled(100.0, 70.0)).to_trimesh().export(stl)
    uploads = tmp_path / "uploads"
    base = PartSpec(name="x", cad="generated:panel").model_dump()
    del base["cad"], base["panel"]
    from service.models import PartCreate

    with PartRegistry(tmp_path / "trees", uploads, alignment=False) as reg:
        job = reg.create(
            PartCreate(**{**base, "name": "up", "tree": {"spacing_mm": 2.0}}),
            stl.read_bytes(),
            "u.stl",
        )
        assert reg.wait(job.id).state == JobState.done
        with pytest.raises(CadLoadError):
            reg.create(PartCreate(**{**base, "name": "broken"}), b"solid\nendsolid\n", "b.stl")
        assert reg.names() == ["up"]
        assert not (uploads / "broken").exists()
        with pytest.raises(PartConflict):
            reg.create(PartCreate(**{**base, "name": "up"}), stl.read_bytes(), "u.stl")
    with PartRegistry(tmp_path / "trees", uploads, alignment=False) as reg:
        reg.add_uploaded()
        reg.preload()
        assert reg.states() == {"up": "ready"}
        reg.delete("up")
        assert reg.names() == [] and not (uploads / "up").exists()


def _upload_spec(name: str):
    from service.models import PartCreate

    return PartCreate(name=name, tree={"spacing_mm": 2.0})


def _files(*roots: Path) -> dict[str, bytes]:
    return {str(p): p.read_bytes() for r in roots for p in r.rglob("*") if p.is_file()}


def test_uploads_touch_only_what_the_registry_wrote(tmp_path):
    """A failed creation removes its staging folder alone; a delete removes its own files.

    A folder in the way that the registry did not make stays as it is, and
    so does a file someone left inside a part's folder.
    """
    stl = tmp_path / "u.stl"
    sheet_metal_panel(PanelSpec().scaled(100.0, 70.0)).to_trimesh().export(stl)
    uploads = tmp_path / "uploads"
    (uploads / "foreign").mkdir(parents=True)
    (uploads / "foreign" / "notes.txt").write_text("not ours")
    (uploads / "stray.txt").write_text("not ours either")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "spec.json").write_text(PartSpec(name="linked", cad="cad.stl").model_dump_json())
    (uploads / "linked").symlink_to(outside, target_is_directory=True)
    before = _files(uploads, outside)
    with PartRegistry(tmp_path / "trees", uploads, alignment=False) as reg:
        reg.add_uploaded()
        assert reg.names() == []  # a linked folder is not one the registry made
        with pytest.raises(CadLoadError):
            reg.create(_upload_spec("broken"), b"solid\nendsolid\n", "b.stl")
        with pytest.raises(CadLoadError):
            reg.create(_upload_spec("named"), stl.read_bytes(), "u.exe")
        with pytest.raises(PartConflict):
            reg.create(_upload_spec("foreign"), stl.read_bytes(), "u.stl")
        with pytest.raises(PartConflict):
            reg.create(_upload_spec("linked"), stl.read_bytes(), "u.stl")
        assert _files(uploads, outside) == before
        assert sorted(p.name for p in uploads.iterdir()) == ["foreign", "linked", "stray.txt"]

        reg.wait(reg.create(_upload_spec("up"), stl.read_bytes(), "u.stl").id)
        assert sorted(p.name for p in (uploads / "up").iterdir()) == ["cad.stl", "spec.json"]
        (uploads / "up" / "operator-notes.txt").write_text("kept")
        reg.delete("up")
        assert sorted(p.name for p in (uploads / "up").iterdir()) == ["operator-notes.txt"]
        (uploads / "up" / "operator-notes.txt").unlink()
        (uploads / "up").rmdir()
        assert _files(uploads, outside) == before


def test_the_alignment_model_is_cached_beside_the_trees(tmp_path):
    """Computed once, written beside the trees; a later load (another process, or
    a registry of its own) reads it back unchanged; a corrupt file is recomputed;
    models the caller keeps in memory are reused and filled."""
    from inspection.alignment import AlignmentModel
    from service.parts import alignment_model_path, load_part

    trees = tmp_path / "trees"
    s = spec(spacing_mm=2.0)
    kept: dict[str, AlignmentModel] = {}
    first = load_part(s, tmp_path, trees, models=kept)
    path = alignment_model_path(trees, first.cad)
    assert path.is_file()
    assert kept == {first.cad.hash: first.model.alignment}
    assert load_part(s, tmp_path, trees, models=kept).model.alignment is first.model.alignment
    mtime = path.stat().st_mtime_ns
    again = load_part(s, tmp_path, trees).model.alignment
    assert again is not first.model.alignment
    assert path.stat().st_mtime_ns == mtime  # read, not recomputed
    assert len(again.poses) == len(first.model.alignment.poses)
    for a, b in zip(again.poses, first.model.alignment.poses, strict=True):
        assert a.transform.tobytes() == b.transform.tobytes()
        assert a.template.tobytes() == b.template.tobytes()
        assert (a.axis_rad, a.elongation) == (b.axis_rad, b.elongation)
    assert again.surface.samples.tobytes() == first.model.alignment.surface.samples.tobytes()
    assert isinstance(AlignmentModel.load(path, key=first.cad.hash), AlignmentModel)
    path.write_bytes(b"not a model")
    assert len(load_part(s, tmp_path, trees).model.alignment.poses) == len(again.poses)
    assert path.stat().st_size > 1000


def test_the_line_and_the_benchmarks_measure_with_the_same_parameters():
    """The service maps configs/ onto the sequence's parameters; the benchmarks (and the
    end-to-end test) take the line's defaults: the two must be the same."""
    from bench import bench_endtoend
    from service.config import load_line_config, load_part_spec
    from service.parts import measure_params

    cfg = load_line_config(Path(__file__).resolve().parents[2] / "configs" / "line.toml")
    for path in cfg.part_spec_paths():
        got = measure_params(load_part_spec(path), guided=cfg.station.guided_matching)
        assert got == bench_endtoend.params(), path


def test_a_station_on_the_comparison_points_refuses_a_surface_that_fails_parts(tmp_path):
    failing = spec("failing")  # a [surface] fails parts by default
    lenient = PartSpec(name="lenient", cad="generated:panel", panel=SMALL,
                       surface={"fails_part": False})  # fmt: skip
    with PartRegistry(tmp_path / "t", tmp_path / "u", path="comparison_points") as reg:
        with pytest.raises(PathConflict, match="fails_part"):
            reg.add(failing, tmp_path, configured=True)
        reg.add(lenient, tmp_path, configured=True)
        with pytest.raises(PathConflict, match="comparison_points"):
            reg.create(failing, b"solid x\nendsolid x\n", "x.stl")
        assert not (tmp_path / "u" / "failing").exists()  # refused before anything is written
    with PartRegistry(tmp_path / "t", tmp_path / "u") as reg:
        reg.add(failing, tmp_path, configured=True)  # the cloud path checks the surface


def test_uploads_are_kept_in_the_store_where_other_processes_take_them(tmp_path, store_target):
    """An API writes a part it creates to the store; an API elsewhere (its own uploads folder)
    takes it from there at its start; a delete retires it, and the copies elsewhere go at
    their next start. An upload of a data directory from before is written to the store."""
    from service.store import ResultStore

    stl = tmp_path / "u.stl"
    sheet_metal_panel(PanelSpec().scaled(100.0, 70.0)).to_trimesh().export(stl)
    here, there = tmp_path / "here", tmp_path / "there"
    with PartRegistry(tmp_path / "trees", here, alignment=False) as reg:  # before the store
        reg.wait(reg.create(_upload_spec("legacy"), stl.read_bytes(), "u.stl").id)

    def registry(uploads: Path, store) -> PartRegistry:
        reg = PartRegistry(tmp_path / "trees", uploads, alignment=False, store=store)
        reg.add_uploaded()
        reg.sync_store()
        return reg

    with ResultStore(store_target) as store:
        with registry(here, store) as a:
            assert sorted(store.part_keys()) == ["legacy"]
            a.wait(a.create(_upload_spec("up"), stl.read_bytes(), "u.stl").id)
            stored = store.part("up")
            assert stored.cad == stl.read_bytes() and PartSpec.model_validate_json(stored.spec)
            assert PartSpec.model_validate_json(stored.spec).cad == "cad.stl"
            with registry(there, store) as b:
                assert b.names() == ["legacy", "up"]
                assert (there / "up" / "cad.stl").read_bytes() == stl.read_bytes()
            a.delete("up")
            assert store.part_keys().keys() == {"legacy"} and store.part("up", 1).retired_ns
            # Created again: a second revision, which the copy elsewhere gives way to.
            second = _upload_spec("up").model_copy(update={"version": "2"})
            a.wait(a.create(second, stl.read_bytes(), "u.stl").id)
        assert store.part("up").revision == 2
        with registry(there, store) as b:
            assert b.names() == ["legacy", "up"] and b.public("up").version == "2"
            assert (
                PartSpec.model_validate_json((there / "up" / "spec.json").read_text()).version
                == "2"
            )
        with registry(here, store) as a:
            a.preload()  # trees from the cache: a part being built is not deleted
            a.delete("up")
        with registry(there, store) as b:
            assert b.names() == ["legacy"] and not (there / "up").exists()
            store.add_part("x", "{}", b"x")  # created through another API meanwhile
            with pytest.raises(PartConflict, match="exists"):
                b.create(_upload_spec("x"), stl.read_bytes(), "u.stl")
            assert not (there / "x").exists()


def test_an_upload_the_store_has_no_copy_of_is_never_deleted_for_the_store_s_part(tmp_path, caplog):
    """Two stations' data directories each hold an upload "bracket" from before the store
    kept parts, of other CADs; both APIs then start on one plant database. The first's is
    written to the store; the second's stays, files and all, with an error that names the
    conflict, and no worker of that station writes the store's part over it."""
    from service.store import ResultStore

    folders = {}
    for station, width in (("st1", 70.0), ("st2", 72.0)):
        folder = tmp_path / station / "bracket"
        folder.mkdir(parents=True)
        sheet_metal_panel(PanelSpec().scaled(100.0, width)).to_trimesh().export(folder / "cad.stl")
        full = PartSpec(**_upload_spec("bracket").model_dump(), cad="cad.stl")
        (folder / "spec.json").write_text(full.model_dump_json())
        folders[station] = {p.name: p.read_bytes() for p in folder.iterdir()}
    with ResultStore(tmp_path / "plant.sqlite") as plant:
        for station in ("st1", "st2"):
            with PartRegistry(tmp_path / "trees", tmp_path / station, store=plant) as reg:
                reg.add_uploaded()
                reg.sync_store()
                assert reg.names() == ["bracket"]
                if station == "st2":
                    with pytest.raises(PartConflict, match="has no copy of it"):
                        reg.adopt(plant.part("bracket"))
        assert plant.part_revisions() == [("bracket", 1)]
        assert plant.part("bracket").cad == folders["st1"]["cad.stl"]
    for station in ("st1", "st2"):
        got = {p.name: p.read_bytes() for p in (tmp_path / station / "bracket").iterdir()}
        assert got == folders[station], station
    assert "'bracket': the upload in" in caplog.text and "has no copy of it" in caplog.text
