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


@pytest.fixture(scope="module")
def loaded_by():
    """Import every module in a fresh interpreter of its own (all started at once)."""
    procs = {
        m: subprocess.Popen(
            [sys.executable, "-c", CODE, m],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=PACKAGE.parent,
        )
        for m in MODULES
    }
    out = {}
    for module, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 0, f"importing {module} failed:\n{stderr}"
        out[module] = json.loads(stdout)
    return out


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
