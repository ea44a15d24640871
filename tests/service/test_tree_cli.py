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
    # Bad input, as every command exits on it: 2.
    assert main(["info", str(out), "--cad", box]) == 2
    assert "built for CAD" in capsys.readouterr().err
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"junk")
    assert main(["info", str(junk)]) == 2
    assert "not an .npz archive" in capsys.readouterr().err
    assert main(["build-tree", str(tmp_path / "missing.stl"), str(out)]) == 2
    assert capsys.readouterr().err.startswith("inspection build-tree: ")


def _build_tree_on(stderr_tty: bool, tmp_path, *extra: str) -> str:
    """Run build-tree in a process whose stderr is a terminal (a pty) or a pipe; its stderr."""
    import fcntl
    import os
    import pty
    import struct
    import subprocess
    import sys
    import termios
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    cad = _stl(tmp_path / "ball.stl", trimesh.creation.icosphere(subdivisions=2, radius=30.0))
    cmd = [sys.executable, "-m", "service.cli", "build-tree", cad, str(tmp_path / "b.npz"), *extra]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    if not stderr_tty:
        r = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        return r.stderr
    leader, follower = pty.openpty()
    # A terminal of 24 x 100 characters (a new pty has none, and a bar fits in no width).
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    try:
        proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.DEVNULL, stderr=follower)
        os.close(follower)
        chunks = []
        while True:
            try:
                data = os.read(leader, 4096)
            except OSError:  # the pty closes with the process
                break
            if not data:
                break
            chunks.append(data)
        assert proc.wait(120) == 0
    finally:
        os.close(leader)
    return b"".join(chunks).decode(errors="replace")


def test_tree_build_progress_bar_only_on_a_terminal(tmp_path):
    """tqdm draws the bar where someone watches (stderr a terminal), never into a pipe or
    a log, and not with --quiet."""
    on_tty = _build_tree_on(True, tmp_path)
    assert "building the tree of ball" in on_tty and "100%" in on_tty
    assert "building the tree" not in _build_tree_on(False, tmp_path)
    assert "building the tree" not in _build_tree_on(True, tmp_path, "--quiet")
