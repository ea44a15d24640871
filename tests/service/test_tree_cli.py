"""``inspection build-tree`` and ``inspection info`` end to end on small generated meshes."""

from __future__ import annotations

import json

import trimesh

from service.cli import main


def _stl(path, mesh):
    mesh.export(path)
    return str(path)


def test_build_tree_then_info(tmp_path, capsys):
    cad = _stl(tmp_path / "ball.stl", trimesh.creation.icosphere(subdivisions=2, radius=30.0))
    out = tmp_path / "trees" / "ball.npz"
    assert main(["build-tree", cad, str(out), "--spacing-mm", "1.5", "--band-mm", "3"]) == 0
    built = capsys.readouterr().out
    assert "faces" in built and "MB" in built and out.is_file()

    assert main(["info", str(out), "--cad", cad, "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format_version"] >= 1
    assert info["params"]["spacing_mm"] == 1.5 and info["params"]["band_mm"] == 3.0
    assert info["cad_check"] == "matches"
    assert info["nbytes"] > 0 and len(info["cad_hash"]) == 64

    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "CAD hash" in text and "spacing 1.5 mm" in text


def test_info_refuses_another_cad_and_bad_files(tmp_path, capsys):
    ball = _stl(tmp_path / "ball.stl", trimesh.creation.icosphere(subdivisions=1, radius=20.0))
    box = _stl(tmp_path / "box.stl", trimesh.creation.box(extents=(30.0, 20.0, 10.0)))
    out = tmp_path / "ball.npz"
    assert main(["build-tree", ball, str(out), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["info", str(out), "--cad", box]) == 1
    assert "built for CAD" in capsys.readouterr().err
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"junk")
    assert main(["info", str(junk)]) == 1
    assert main(["build-tree", str(tmp_path / "missing.stl"), str(out)]) == 1
    assert "error:" in capsys.readouterr().err
