"""One rule for names, read from service.names and held by every place that accepts one."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from pydantic import ValidationError

from service import names
from service.config import LineConfig, PartSpecBase
from service.models import InspectionResult
from service.protocol import Keys, ProtocolError, validate_name

ROOT = Path(__file__).resolve().parents[2]

GOOD = ["a", "demo-panel", "line1", "st_1", ".hidden", "a..b", "v1.2", "-", "_", "x" * 64]
BAD = [".", "..", "...", "." * 64, "", "a/..", "../a", "%2e%2e", "a b", "a*", "x" * 65, "é"]


@pytest.mark.parametrize("value", GOOD + BAD)
def test_every_edge_applies_the_same_rule(value):
    ok = value in GOOD
    assert names.is_valid_name(value) is ok
    assert (re.fullmatch(names.NAME_PATTERN, value) is not None and len(value) <= 64) is ok

    def accepted(make) -> bool:
        try:
            make()
        except (ValidationError, ProtocolError):
            return False
        return True

    assert accepted(lambda: validate_name(value, "part")) is ok
    assert accepted(lambda: PartSpecBase(name=value)) is ok
    assert accepted(lambda: LineConfig.model_validate({"line": {"name": value}})) is ok
    assert accepted(lambda: LineConfig.model_validate({"station": {"name": value}})) is ok
    assert accepted(lambda: Keys("line1").result("st1", "p", value)) is ok


def test_a_prefix_is_names_joined_by_slashes():
    assert LineConfig.model_validate({"zenoh": {"prefix": "plant.a/insp/v1"}})
    for bad in ("insp/../v1", "insp/./v1", "..", "insp//v1", "/insp"):
        with pytest.raises(ValidationError):
            LineConfig.model_validate({"zenoh": {"prefix": bad}})


def test_the_result_model_publishes_the_rule_in_its_schema():
    schema = InspectionResult.model_json_schema()["properties"]
    for field in ("line", "station", "part", "serial"):
        assert schema[field]["pattern"] == names.NAME_PATTERN
        assert schema[field]["maxLength"] == names.NAME_MAX_LEN


@pytest.mark.parametrize(
    "path", ["docs/protocol.md", "configs/line.toml", "configs/parts/demo-panel.toml"]
)
def test_the_docs_and_configs_state_the_rule(path):
    text = " ".join((ROOT / path).read_text().replace("#", " ").split())
    assert names.NAME_RULE in text
    if path.endswith(".md"):
        assert names.NAME_PATTERN in text
