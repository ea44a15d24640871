import importlib.util
import struct

import numpy as np
import pytest
import trimesh

from inspection import CadLoadError, CadModel, InvalidInput, load_cad


def _write_ascii_stl(path, triangles):
    lines = ["solid t"]
    for tri in triangles:
        lines += ["facet normal 0 0 0", "outer loop"]
        lines += [f"vertex {x} {y} {z}" for x, y, z in tri]
        lines += ["endloop", "endfacet"]
    lines.append("endsolid t")
    path.write_text("\n".join(lines))


def test_box_round_trip_through_each_format(tmp_path):
    box = trimesh.creation.box(extents=(30.0, 20.0, 10.0))
    for suffix in ("stl", "obj", "ply"):
        path = tmp_path / f"box.{suffix}"
        box.export(path)
        cad = load_cad(path, scale=2.0)
        np.testing.assert_allclose(cad.extents, [60.0, 40.0, 20.0], atol=1e-5)
        assert len(cad.faces) == 12
        assert cad.name == "box"
        np.testing.assert_allclose(np.linalg.norm(cad.face_normals, axis=1), 1.0)
        np.testing.assert_allclose(cad.area, 2 * (60 * 40 + 60 * 20 + 40 * 20), rtol=1e-6)


def test_model_is_immutable_and_hash_tracks_geometry(tmp_path):
    box = trimesh.creation.box(extents=(30.0, 20.0, 10.0))
    a = CadModel.from_mesh(box)
    b = CadModel.from_mesh(box)
    c = CadModel.from_mesh(box, scale=1.001)
    assert a.hash == b.hash != c.hash
    with pytest.raises(ValueError):
        a.vertices[0, 0] = 1.0


def test_degenerate_faces_are_dropped_and_counted(tmp_path):
    tris = [
        [(0, 0, 0), (10, 0, 0), (0, 10, 0)],
        [(10, 0, 0), (10, 10, 0), (0, 10, 0)],
        [(0, 0, 0), (5, 0, 0), (10, 0, 0)],  # collinear: no area
        [(0, 0, 0), (0, 0, 0), (0, 10, 0)],  # repeated vertex
    ]
    path = tmp_path / "degenerate.stl"
    _write_ascii_stl(path, tris)
    cad = load_cad(path)
    assert len(cad.faces) == 2
    assert cad.report.degenerate_faces_dropped == 2
    assert cad.report.faces_read == 4


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.stl", b"", "empty"),
        ("garbage.stl", bytes(range(256)) * 7, "face"),
        ("garbage.ply", b"\x00\xff" * 300, "PLY"),
        ("garbage.obj", b"\x89PNG\r\n\x1a\n" + bytes(500), "face"),
        ("vertices_only.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "face"),
        ("part.iges", b"anything", "unknown CAD format"),
        ("part", b"anything", "unknown CAD format"),
    ],
)
def test_bad_files_raise_a_readable_error(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(CadLoadError, match=message):
        load_cad(path)


def test_binary_stl_with_nan_vertices_is_refused(tmp_path):
    header = b"\0" * 80 + struct.pack("<I", 1)
    facet = struct.pack("<12fH", 0, 0, 1, 0, 0, 0, 1, 0, 0, float("nan"), 1, 0, 0)
    path = tmp_path / "nan.stl"
    path.write_bytes(header + facet)
    with pytest.raises(CadLoadError, match="non-finite"):
        load_cad(path)


def test_missing_file_and_bad_scale(tmp_path):
    with pytest.raises(CadLoadError, match="no such file"):
        load_cad(tmp_path / "nothing.stl")
    box = trimesh.creation.box()
    path = tmp_path / "box.stl"
    box.export(path)
    for scale in (0.0, -1.0, float("nan")):
        with pytest.raises(InvalidInput):
            load_cad(path, scale=scale)


def test_all_faces_degenerate_is_refused(tmp_path):
    path = tmp_path / "flat.stl"
    _write_ascii_stl(path, [[(0, 0, 0), (1, 0, 0), (2, 0, 0)]])
    with pytest.raises(CadLoadError):
        load_cad(path)


HAS_STEP = importlib.util.find_spec("cascadio") is not None


@pytest.mark.skipif(HAS_STEP, reason="the STEP reader is installed")
def test_step_without_the_extra_names_the_extra(shared_cad):
    with pytest.raises(CadLoadError, match=r"inspection\[step\]"):
        load_cad(shared_cad("featuretype.STEP"))


@pytest.mark.skipif(not HAS_STEP, reason="the STEP reader (extra 'step') is not installed")
def test_step_is_read_in_millimetres(shared_cad):
    step = load_cad(shared_cad("featuretype.STEP"))
    stl = load_cad(shared_cad("featuretype.STL"), scale=25.4)  # the STL is stored in inches
    np.testing.assert_allclose(np.sort(step.extents), np.sort(stl.extents), rtol=0.01)


def test_shared_meshes_load_at_scale(shared_cad):
    counter = load_cad(shared_cad("counter.unitsmm.STL"))
    assert len(counter.faces) == 83750
    np.testing.assert_allclose(counter.extents, [304.8, 304.4, 25.8], atol=0.1)
    fandisk = load_cad(shared_cad("fandisk.obj"), scale=180.0)
    assert 250 < fandisk.extents.max() < 350
