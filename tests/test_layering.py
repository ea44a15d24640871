"""inspection/ is pure computation: importing it must not load the service side."""

import json
import pkgutil
import subprocess
import sys

import pytest

import inspection

FORBIDDEN = ("service", "fastapi", "zenoh", "mcap", "pydantic", "uvicorn", "starlette")
MODULES = ["inspection"] + [f"inspection.{m.name}" for m in pkgutil.iter_modules(inspection.__path__)]


@pytest.mark.parametrize("module", MODULES)
def test_inspection_module_loads_no_service_dependency(module):
    code = (
        "import importlib, json, sys\n"
        f"importlib.import_module({module!r})\n"
        "print(json.dumps(sorted(sys.modules)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    loaded = json.loads(out.stdout)
    bad = [m for m in loaded if m.split(".")[0] in FORBIDDEN]
    assert not bad, f"{module} loads {bad}"
