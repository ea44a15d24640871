"""inspection/ is pure computation: importing it must not load the service side."""

import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "inspection"
FORBIDDEN = ("service", "fastapi", "zenoh", "mcap", "pydantic", "uvicorn", "starlette")
MODULES = ["inspection"] + [f"inspection.{m.name}" for m in pkgutil.iter_modules([str(PACKAGE)])]

CODE = (
    "import importlib, json, sys\n"
    "importlib.import_module(sys.argv[1])\n"
    "print(json.dumps(sorted(sys.modules)))\n"
)
EACH = (
    "import importlib, json, sys\n"
    "out = {}\n"
    "for name in sys.argv[1:]:\n"
    "    before = set(sys.modules)\n"
    "    importlib.import_module(name)\n"
    "    out[name] = sorted(set(sys.modules) - before)\n"
    "print(json.dumps(out))\n"
)


@pytest.fixture(scope="module")
def loaded_by():
    """What each module adds to ``sys.modules``, imported one after the other in one fresh
    interpreter: a forbidden module is blamed on the first module that loads it, and
    every module's imports are covered, since together they load all there is."""
    done = subprocess.run(
        [sys.executable, "-c", EACH, *MODULES],
        capture_output=True,
        text=True,
        cwd=PACKAGE.parent,
        timeout=300,
    )
    assert done.returncode == 0, f"importing inspection failed:\n{done.stderr}"
    return json.loads(done.stdout)


@pytest.mark.parametrize("module", MODULES)
def test_inspection_module_loads_no_service_dependency(loaded_by, module):
    bad = [m for m in loaded_by[module] if m.split(".")[0] in FORBIDDEN]
    assert not bad, f"{module} loads {bad}"


def test_the_check_would_see_a_forbidden_import():
    loaded = json.loads(
        subprocess.run(
            [sys.executable, "-c", CODE, "service.config"],
            capture_output=True,
            text=True,
            check=True,
            cwd=PACKAGE.parent,
        ).stdout
    )
    assert "pydantic" in {m.split(".")[0] for m in loaded}
