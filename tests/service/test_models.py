"""The shared result model: its JSON contract, validation and schema."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from service.models import (
    SCHEMA_VERSION,
    ErrorBody,
    FieldStats,
    InspectionResult,
    Page,
    PointResult,
    Status,
    make_result_id,
    missed_serial,
    software_version,
)

DESIGN_FIELDS = {
    "schema_version", "id", "line", "station", "part", "serial", "seq", "triggered_ns",
    "status", "reason", "transform", "rms_mm", "inlier_fraction", "comparison", "field",
    "timings_ms", "spec_version", "cad_hash", "tree_hash", "calibration_id", "software_version",
    # The fit's diagnostics ("One measuring sequence"):
    "converged", "stop_reason", "iterations", "observability", "weak_directions", "ambiguous",
    "runner_up_score",
    # The whole surface ("The verdict covers the whole surface"), null where not checked:
    "defects",
    # Which path measured the part (cloud or comparison points):
    "path",
}  # fmt: skip


def result(**kw) -> InspectionResult:
    base = dict(
        id=make_result_id("line1", "st1", 7, 1_700_000_000_000_000_000),
        line="line1",
        station="st1",
        part="demo-panel",
        serial="SN-0001",
        seq=7,
        triggered_ns=1_700_000_000_000_000_000,
        status="pass",
        transform=[[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
        rms_mm=0.02,
        inlier_fraction=0.97,
        comparison=[
            PointResult(
                name="a", deviation_mm=0.1, lower_mm=-0.5, upper_mm=0.5, support=40, verdict="pass"
            )
        ],
        field=FieldStats(points=1000, inliers=970, mean_mm=0.0, std_mm=0.02),
        timings_ms={"align": 4.2, "total": 9.0},
        spec_version="1",
        cad_hash="ab" * 32,
        tree_hash="cd" * 32,
        calibration_id="rig-1",
        software_version=software_version(),
    )
    base.update(kw)
    return InspectionResult(**base)


def test_fields_are_exactly_those_of_the_design():
    assert set(InspectionResult.model_fields) == DESIGN_FIELDS


def test_a_surface_not_checked_is_null_not_none_found():
    unchecked = result(path="comparison_points")
    assert json.loads(unchecked.model_dump_json())["defects"] is None
    checked = result(path="cloud", defects=[])
    assert json.loads(checked.model_dump_json())["defects"] == []
    assert InspectionResult.model_validate_json(unchecked.model_dump_json()) == unchecked
    with pytest.raises(ValueError, match="path"):
        result(path="holes")


def test_a_curves_largest_deviation_says_where_it_lies():
    top = PointResult(
        name="E1.trim_max", deviation_mm=0.3, lower_mm=-0.5, upper_mm=0.5, support=40,
        verdict="pass", kind="trim_edge", at_mm=[1.0, 2.0, 3.0],
    )  # fmt: skip
    r = result(comparison=[top])
    data = json.loads(r.model_dump_json())
    assert data["comparison"][0]["at_mm"] == [1.0, 2.0, 3.0]
    assert json.loads(result().model_dump_json())["comparison"][0]["at_mm"] is None
    assert InspectionResult.model_validate_json(r.model_dump_json()) == r
    with pytest.raises(ValueError, match="at_mm"):
        PointResult(**{**top.model_dump(), "at_mm": [1.0, 2.0]})


def test_json_round_trip_is_identical():
    r = result()
    text = r.model_dump_json()
    back = InspectionResult.model_validate_json(text)
    assert back == r
    data = json.loads(text)
    assert data["schema_version"] == SCHEMA_VERSION
    assert data["status"] == "pass"
    assert data["transform"][0] == [1.0, 0.0, 0.0, 5.0]  # rows first


@pytest.mark.parametrize(
    "change",
    [
        {"status": "ok"},
        {"serial": "bad serial"},
        {"part": "a/b"},
        {"line": ""},
        {"seq": -1},
        {"rms_mm": float("nan")},
        {"inlier_fraction": 1.5},
        {"transform": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        {"transform": [[1, 0, 0, 0]] * 4},
        {"transform": [[1, 0, 0, float("inf")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
        {"unknown_field": 1},
    ],
)
def test_invalid_results_are_rejected(change):
    with pytest.raises(ValidationError):
        result(**change)


def test_missed_result_needs_no_measurement():
    r = result(status=Status.missed, serial=missed_serial(12), seq=12, transform=None, rms_mm=None,
               inlier_fraction=None, comparison=[], field=None, reason="queue full")  # fmt: skip
    assert r.serial == "unknown-12"
    assert InspectionResult.model_validate_json(r.model_dump_json()) == r


def test_ids_are_deterministic_and_safe_in_keys():
    a = make_result_id("line1", "st1", 3, 10)
    assert a == make_result_id("line1", "st1", 3, 10)
    assert a != make_result_id("line1", "st1", 4, 10)
    result(id=a)  # passes the id pattern


def test_ids_do_not_collide_when_names_hold_dots():
    """Names may contain dots: line ``a.b`` station ``c`` and line ``a`` station ``b.c``
    are different triggers, and so are seq 1 at time 23 and seq 12 at time 3."""
    ids = {
        make_result_id("a.b", "c", 1, 23),
        make_result_id("a", "b.c", 1, 23),
        make_result_id("a.b", "c", 12, 3),
        make_result_id("a.b.c", "1", 2, 3),
    }
    assert len(ids) == 4
    line, station, seq, ns = make_result_id("a.b", "c.d", 5, 6).split("~")
    assert (line, station, seq, ns) == ("a.b", "c.d", "5", "6")


def test_json_schema_describes_the_result():
    schema = InspectionResult.model_json_schema()
    assert set(schema["properties"]) == DESIGN_FIELDS
    assert schema["additionalProperties"] is False
    json.dumps(schema)


def test_page_and_error_shapes():
    page = Page[InspectionResult](items=[result()], next=None)
    assert set(json.loads(page.model_dump_json())) == {"items", "next"}
    err = ErrorBody.model_validate({"error": {"code": "unknown_part", "message": "no such part"}})
    assert err.error.code == "unknown_part"


def test_a_trigger_at_every_limit_still_has_a_valid_result():
    """Names of 64 characters, and a time and sequence number just below 2**63:
    the result id they make is within the model's own bound, on the error path too."""
    from service.pipeline import error_result, missed_result

    line, station = "l" * 64, "s" * 64
    big = 2**63 - 1
    for make in (error_result, missed_result):
        r = make(line=line, station=station, seq=big, triggered_ns=big, reason="x")
        assert r.id == make_result_id(line, station, big, big)
        assert InspectionResult.model_validate_json(r.model_dump_json()) == r
