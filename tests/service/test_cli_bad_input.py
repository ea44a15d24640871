"""Every ``inspection`` command on bad input: exit code 2, one message, no traceback.

The console entry point runs in subprocesses (``python -m service.cli``), as a
user or a script runs it; the cases run in parallel, and each fails on its
input before any heavy work (no tree is built, no session opened).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from linekit import ROOT

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
TIMEOUT_S = 120


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *args],
        env=ENV,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        stdin=subprocess.DEVNULL,
    )


def run_many(runs: list[list[str]]) -> list[subprocess.CompletedProcess[str]]:
    """Each argument list in its own process, four at a time."""
    with ThreadPoolExecutor(max_workers=4) as pool:
        return list(pool.map(lambda args: run_cli(*args), runs))


@pytest.fixture(scope="module")
def bad(tmp_path_factory) -> dict[str, Path]:
    """Bad files of every kind the commands read."""
    d = tmp_path_factory.mktemp("bad")
    files: dict[str, Path] = {"dir": d / "a-directory.npy"}
    files["dir"].mkdir()
    (files["dir"] / "view0").mkdir()  # a calibration view without its images

    def write(name: str, data: bytes) -> None:
        files[name] = d / name
        files[name].write_bytes(data)

    write("empty.stl", b"")
    write("junk.stl", b"solid nothing\nthis is not an STL\n")
    write("corrupt.ply", b"ply\nformat ascii 1.0\nelement vertex two\nend_header\n")
    write("empty.npy", b"")
    write("junk.npy", b"certainly not numpy")
    write("truncated.npy", b"\x93NUMPY\x01\x00")
    files["pickled.npy"] = d / "pickled.npy"
    np.save(files["pickled.npy"], np.array([{"x": 1}, None], dtype=object))
    files["pickled.npz"] = d / "pickled.npz"
    np.savez(files["pickled.npz"], meta=np.array([{"format_version": 1}], dtype=object))
    files["cloud.npy"] = d / "cloud.npy"
    np.save(files["cloud.npy"], np.random.default_rng(0).normal(size=(200, 3)))
    write("corrupt.toml", b"name = [unclosed\n")
    write("junk.mcap", b"\x89MCAP0\r")  # the magic, torn
    write("text.mcap", b"not a recording at all\n")
    write("empty.mcap", b"")
    write("empty.json", b"[]")
    write("broken.json", b"[{]")
    write("junk.frameset", b"\x00\x01\x02")
    write("existing.toml", b"# a rig file someone keeps\n")
    write("junk.sqlite", b"not a database, though its name says so")
    return files


def cases(f: dict[str, Path]) -> list[tuple[str, list[str], str]]:
    """(command, arguments, a fragment of the expected message)."""
    s = {k: str(v) for k, v in f.items()}
    tree = "builtin:panel"
    return [
        ("build-tree", ["build-tree", s["empty.stl"], s["dir"] + "/t.npz"], "empty"),
        ("build-tree", ["build-tree", s["junk.stl"], s["dir"] + "/t.npz"], "STL"),
        ("build-tree", ["build-tree", s["dir"], s["dir"] + "/t.npz"], "unknown CAD format"),
        ("build-tree", ["build-tree", tree, s["dir"] + "/t.npz", "--scale", "2"], "--scale"),
        ("info", ["info", s["junk.npy"]], "not a saved GridTree"),
        ("info", ["info", s["dir"]], "a directory"),
        ("info", ["info", s["pickled.npz"]], "Python objects"),
        ("align", ["align", tree, s["pickled.npy"]], "Python objects"),
        ("align", ["align", tree, s["empty.npy"]], "not a NumPy .npy file"),
        ("align", ["align", tree, s["junk.npy"]], "not a NumPy .npy file"),
        ("align", ["align", tree, s["truncated.npy"]], "cannot read as NPY"),
        ("align", ["align", tree, s["dir"]], "a directory"),
        ("align", ["align", tree, s["corrupt.ply"]], "corrupt.ply"),
        ("align", ["align", s["junk.stl"], s["cloud.npy"]], "STL"),
        ("align", ["align", s["pickled.npz"], s["cloud.npy"]], "Python objects"),
        ("check", ["check", tree, s["cloud.npy"], "--points", s["empty.json"]], "no comparison"),
        ("check", ["check", tree, s["cloud.npy"], "--points", s["broken.json"]], "not valid JSON"),
        ("check", ["check", tree, s["cloud.npy"], "--points", s["dir"]], "a-directory"),
        ("measure", ["measure", s["junk.frameset"], "--part", s["corrupt.toml"]], "FrameSet"),
        ("measure", ["measure", s["dir"], "--part", s["corrupt.toml"]], "a-directory"),
        ("calibrate", ["calibrate", "--out", s["existing.toml"]], "--replace"),
        ("calibrate", ["calibrate", "--images", s["dir"], "--out", s["dir"] + "/r.toml"],
         "missing image"),
        ("calibrate", ["calibrate", "--images", s["junk.npy"]], "not a directory"),
        ("run", ["run", "--config", s["corrupt.toml"]], "not valid TOML"),
        ("run", ["run", "--config", s["dir"]], "a-directory"),
        ("run", ["run", "--data-dir", s["junk.npy"]], "is a file, not a directory"),
        ("router", ["router", "--zenoh-listen", "nonsense"], "endpoint"),
        ("router", ["router", "--config", s["corrupt.toml"]], "not valid TOML"),
        ("ingest", ["ingest", "--config", s["empty.json"], "--zenoh-connect", "tcp/127.0.0.1:9"],
         "empty.json"),
        ("worker", ["worker", "--config", s["corrupt.toml"], "--zenoh-connect",
                    "tcp/127.0.0.1:9"], "not valid TOML"),
        ("api", ["api", "--config", s["dir"] + "/missing.toml", "--zenoh-connect",
                 "tcp/127.0.0.1:9"], "missing.toml"),
        ("replay", ["replay", s["junk.mcap"]], "junk.mcap"),
        ("replay", ["replay", s["text.mcap"]], "not an MCAP recording"),
        ("replay", ["replay", s["empty.mcap"]], "empty"),
        ("replay", ["replay", s["dir"]], "no such recording"),
        ("store", ["store", "migrate", "--from", s["junk.sqlite"], "--to",
                   "postgresql://u@127.0.0.1:9/db"], "not a result store"),
        ("store", ["store", "migrate", "--from", s["dir"], "--to", "nonsense"], "--to"),
    ]  # fmt: skip


@pytest.fixture(scope="module")
def outcomes(bad) -> list[tuple[str, list[str], str, subprocess.CompletedProcess[str]]]:
    todo = cases(bad)
    done = run_many([args for _, args, _ in todo])
    return [(*c, r) for c, r in zip(todo, done, strict=True)]


def listed_commands() -> set[str]:
    """The commands ``inspection --help`` lists."""
    out = run_cli("--help").stdout
    listing = out.split("COMMAND\n", 1)[1].split("\n\n", 1)[0]
    names = set(re.findall(r"^ {4}([a-z][a-z-]*)\s", listing, re.MULTILINE))
    assert len(names) >= 13, out
    return names


def test_every_listed_command_is_tried(outcomes):
    assert {c for c, *_ in outcomes} == listed_commands()


def test_bad_input_exits_2_with_one_line_and_no_traceback(outcomes, bad):
    wrong = []
    for command, args, fragment, r in outcomes:
        lines = r.stderr.strip().splitlines()
        ok = (
            r.returncode == 2
            and "Traceback" not in r.stderr + r.stdout
            and len(lines) == 1
            and lines[0].startswith("inspection")
            and fragment in lines[0]
        )
        if not ok:
            wrong.append((command, args[1:], r.returncode, r.stderr[-800:]))
    assert not wrong, json.dumps(wrong, indent=1)
    # Refused, and left as it was: calibrate never overwrites without --replace.
    assert bad["existing.toml"].read_text() == "# a rig file someone keeps\n"


def test_numpy_advice_to_unpickle_never_reaches_the_user(outcomes):
    for _, _, _, r in outcomes:
        assert "allow_pickle" not in r.stderr


def test_usage_errors_exit_2():
    runs = [
        ["no-such-command"],
        ["align"],
        ["check", "builtin:panel", "c.npy"],
        ["store"],
        ["measure", "f", "--part", "p.toml", "--frobnicate"],
    ]
    for args, r in zip(runs, run_many(runs), strict=True):
        assert r.returncode == 2, args
        assert "Traceback" not in r.stderr and "usage:" in r.stderr, args


def test_help_documents_the_exit_codes():
    runs = [["--help"], ["align", "--help"], ["replay", "--help"], ["worker", "--help"]]
    for args, r in zip(runs, run_many(runs), strict=True):
        assert r.returncode == 0
        text = " ".join(r.stdout.split())
        assert "exit codes (the same for every command):" in text
        for code in ("0 done, and what was measured passed", "1 measured, and it did not pass",
                     "2 bad input or usage", "3 internal error"):  # fmt: skip
            assert code in text, (args, code)


def test_errors_are_sorted_into_bad_input_and_defects():
    """What no command catches: our errors about input exit 2, anything else 3."""
    from inspection.errors import CadLoadError, InvalidInput
    from service.cli import describe, is_bad_input
    from service.config import ConfigError
    from service.protocol import ProtocolError

    for exc in (InvalidInput("x"), CadLoadError("x"), ConfigError("x"), ProtocolError("x"),
                FileNotFoundError(2, "No such file or directory", "x.toml"),
                IsADirectoryError(21, "Is a directory", "d")):  # fmt: skip
        assert is_bad_input(exc), exc
    for exc in (RuntimeError("x"), KeyError("x"), ValueError("x"), TypeError("x")):
        assert not is_bad_input(exc), exc
    missing = FileNotFoundError(2, "No such file or directory", "x.toml")
    assert describe(missing, 2) == "x.toml: No such file or directory"
    text = describe(KeyError("stage"), 3)
    assert text == "internal error (KeyError: 'stage'); -vv shows the traceback"
