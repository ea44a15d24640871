"""An installed wheel has the calibrated rig: ``Rig.default()`` works outside the checkout.

The wheel is built from a copy of the sources (the checkout gets no ``build/``),
installed with ``pip install --target`` into a folder of its own, and imported
by a fresh interpreter whose working directory is outside the checkout and
whose ``PYTHONPATH`` is that folder alone, so the ``inspection`` it imports is
the installed one; the test checks that it is.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from inspection.rig import DEFAULT_RIG_DATA, ENV_RIG, Rig

REPO = Path(__file__).resolve().parents[1]
RIG_DATA = REPO / "inspection" / DEFAULT_RIG_DATA

CODE = (
    "import json, inspection\n"
    "rig = inspection.Rig.default()\n"
    "print(json.dumps({'file': inspection.__file__, 'id': rig.id, 'cameras': len(rig.cameras)}))\n"
)


def pip(*args: str, cwd: Path) -> None:
    subprocess.run(
        [sys.executable, "-m", "pip", "-q", *args, "--no-deps", "--no-index"],
        check=True,
        cwd=cwd,
        timeout=300,
    )


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The project's wheel, built without build isolation (the dev extra has the build system)."""
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    for package in ("inspection", "service"):
        shutil.copytree(REPO / package, src / package, ignore=shutil.ignore_patterns("__pycache__"))
    pip("wheel", "--no-build-isolation", "-w", str(root / "dist"), str(src), cwd=root)
    (built,) = (root / "dist").glob("inspection-*.whl")
    return built


@pytest.fixture(scope="module")
def installed(wheel: Path, tmp_path_factory) -> Path:
    """The folder the wheel is installed into (``pip install --target``)."""
    target = tmp_path_factory.mktemp("site")
    pip("install", "--target", str(target), str(wheel), cwd=target)
    return target


def default_rig_outside_checkout(site: Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``Rig.default()`` in a fresh interpreter that imports ``inspection`` from ``site`` only."""
    env = {k: v for k, v in os.environ.items() if k not in (ENV_RIG, "PYTHONPATH")}
    env["PYTHONPATH"] = str(site)
    return subprocess.run(
        [sys.executable, "-c", CODE],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=300,
    )


def test_the_wheel_carries_the_calibrated_rig_unchanged(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as zf:
        assert zf.read(f"inspection/{DEFAULT_RIG_DATA}") == RIG_DATA.read_bytes()


def test_the_checkout_reads_the_packaged_rig(monkeypatch) -> None:
    monkeypatch.delenv(ENV_RIG, raising=False)
    assert Rig.default().id == Rig.load(RIG_DATA).id


def test_an_installed_wheel_has_the_default_rig(installed: Path, tmp_path) -> None:
    proc = default_rig_outside_checkout(installed, tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert Path(out["file"]).is_relative_to(installed)
    assert out["cameras"] == 4
    assert out["id"] == Rig.load(RIG_DATA).id


def test_the_check_would_see_a_wheel_without_the_rig(installed: Path, tmp_path) -> None:
    # The same installation less its package data: Rig.default() must fail there,
    # not find a rig in the checkout.
    site = tmp_path / "site"
    shutil.copytree(installed, site)
    (site / "inspection" / DEFAULT_RIG_DATA).unlink()
    work = tmp_path / "work"
    work.mkdir()
    proc = default_rig_outside_checkout(site, work)
    assert proc.returncode != 0
    assert "FileNotFoundError" in proc.stderr and "installation is incomplete" in proc.stderr


def test_the_wheel_carries_the_dashboard_and_its_vendored_libraries(wheel: Path) -> None:
    static = REPO / "service" / "web" / "static"
    wanted = sorted(str(p.relative_to(REPO)) for p in static.rglob("*") if p.is_file())
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
    assert [w for w in wanted if w not in names] == []
    # Each vendored library travels with its licence.
    for lib in ("uplot", "swagger-ui", "redoc"):
        assert f"service/web/static/vendor/{lib}/LICENSE" in names
