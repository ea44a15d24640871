"""The REST API, through the app factory (TestClient) and through a real uvicorn server.

The parts are real: the project's generated panel (small, so its tree builds
in about a second), a SQLite file, the deviation archive. Bad input of every
kind must get a clear 4xx error body and leave earlier results intact.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import http.client
import io
import json
import re
import socket
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import psycopg
import pytest
from fastapi.testclient import TestClient
from linekit import uvicorn_server

from inspection.deviations import Verdict
from inspection.panel import PanelSpec, panel_height, sheet_metal_panel
from inspection.rig import belt_pose
from inspection.transforms import apply
from service.api import ResultHub, create_app
from service.config import PartSpec, PartSpecBase, load_line_config
from service.models import (
    InspectionResult,
    PointResult,
    Status,
    make_result_id,
    software_version,
)
from service.parts import PartRegistry
from service.store import DeviationArchive, ResultStore, encode_cursor

PART = "panel-s"
SMALL = PanelSpec().scaled(150.0, 100.0)


def _panel_params() -> dict:
    d = dataclasses.asdict(SMALL)
    d["holes"] = [dataclasses.asdict(h) for h in SMALL.holes]
    d["emboss_center_mm"] = list(d["emboss_center_mm"])
    d["emboss_size_mm"] = list(d["emboss_size_mm"])
    return d


def _toml_value(v) -> str:
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    return json.dumps(v)


def surface_point(x: float, y: float) -> tuple[list[float], list[float]]:
    """A point on the small panel's top surface and its upward normal."""
    h = 1e-4
    z = float(panel_height(SMALL, np.array([x]), np.array([y]))[0])

    def z_at(u: float, v: float) -> float:
        return float(panel_height(SMALL, np.array([u]), np.array([v]))[0])

    gx = (z_at(x + h, y) - z_at(x - h, y)) / (2 * h)
    gy = (z_at(x, y + h) - z_at(x, y - h)) / (2 * h)
    n = np.array([-gx, -gy, 1.0])
    return [x, y, z], [float(c) for c in n / np.linalg.norm(n)]


def write_line(root: Path) -> Path:
    parts = root / "configs" / "parts"
    parts.mkdir(parents=True)
    lines = [f'name = "{PART}"', 'version = "3"', 'cad = "generated:panel"', "[panel]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in _panel_params().items()]
    lines += ["[tree]", "spacing_mm = 1.0"]
    for name, (x, y) in {"c": (0.0, -10.0), "e": (30.0, 30.0), "w": (-40.0, -30.0)}.items():
        pos, n = surface_point(x, y)
        lines += [
            "[[points]]",
            f'name = "{name}"',
            f"position_mm = {pos}",
            f"normal = {n}",
            "lower_mm = -0.3",
            "upper_mm = 0.3",
            "radius_mm = 6.0",
        ]
    (parts / f"{PART}.toml").write_text("\n".join(lines) + "\n")
    line = root / "configs" / "line.toml"
    line.write_text(
        f"""
[station]
parts = ["{PART}"]
[storage]
data_dir = "{(root / "data").as_posix()}"
[http]
max_upload_mb = 1.0
trend_window = 10
[spc]
baseline_parts = 20
"""
    )
    return line


@pytest.fixture(scope="module")
def line(tmp_path_factory):
    root = tmp_path_factory.mktemp("line")
    cfg = load_line_config(write_line(root))
    with PartRegistry.from_config(cfg) as reg:
        reg.preload()
        assert reg.ready(), reg.states()
        assert reg.get(PART).model.alignment is not None  # computed at load, not per upload
        yield cfg, reg


@pytest.fixture
def api_store_target(request, tmp_path):
    """The API's store: an SQLite file, or with ``indirect`` parametrization
    ``"postgresql"``, a database of its own on the session's server."""
    if getattr(request, "param", "sqlite") == "sqlite":
        return tmp_path / "results.sqlite"
    return request.getfixturevalue("pg_server").new_database()


BOTH_STORES = pytest.mark.parametrize("api_store_target", ["sqlite", "postgresql"], indirect=True)


@pytest.fixture
def app_parts(line, tmp_path, api_store_target, upload_measurer):
    """A fresh store, archive and app per test, sharing the module's built part."""
    cfg, reg = line
    store = ResultStore(api_store_target)
    archive = DeviationArchive(tmp_path / "deviations")
    hub = ResultHub()
    zenoh_up = {"value": True}
    app = create_app(
        cfg,
        store=store,
        parts=reg,
        bus=hub,
        archive=archive,
        checks={"zenoh": lambda: zenoh_up["value"]},
        measurer=upload_measurer,
    )
    yield app, store, archive, hub, zenoh_up
    store.close()


@pytest.fixture
def client(app_parts):
    with TestClient(app_parts[0]) as c:
        yield c


def stored_result(seq: int, *, status="pass", dev=0.1) -> InspectionResult:
    t = 1_700_000_000_000_000_000 + seq * 10**9
    return InspectionResult(
        id=make_result_id("line1", "st1", seq, t),
        line="line1",
        station="st1",
        part=PART,
        serial=f"SN{seq}",
        seq=seq,
        triggered_ns=t,
        status=status,
        comparison=[
            PointResult(
                name="c", deviation_mm=dev, lower_mm=-0.3, upper_mm=0.3, support=50, verdict="pass"
            )
        ],
        software_version=software_version(),
    )  # fmt: skip


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def assert_error(resp, status: int, code: str) -> dict:
    assert resp.status_code == status, resp.text
    body = resp.json()
    assert set(body) == {"error"} and set(body["error"]) == {"code", "message"}, body
    assert body["error"]["code"] == code, body
    assert body["error"]["message"]
    return body["error"]


# ----------------------------------------------------------------------------- parts


def test_parts_list_and_show(client):
    page = client.get("/v1/parts").json()
    assert page["next"] is None
    assert [p["name"] for p in page["items"]] == [PART]
    p = client.get(f"/v1/parts/{PART}").json()
    assert p["state"] == "ready" and p["version"] == "3"
    assert len(p["cad_hash"]) == 64 and p["tree_hash"]
    assert [c["name"] for c in p["points"]] == ["c", "e", "w"]
    assert_error(client.get("/v1/parts/nope"), 404, "unknown_part")


def test_create_part_builds_tree_as_a_job_then_delete(client, line, tmp_path):
    cad = sheet_metal_panel(PanelSpec().scaled(120.0, 80.0))
    stl = tmp_path / "p.stl"
    cad.to_trimesh().export(stl)
    spec = {"name": "uploaded", "version": "1", "points": []}
    r = client.post(
        "/v1/parts",
        files={"cad": ("p.stl", stl.read_bytes(), "model/stl")},
        data={"spec": json.dumps(spec)},
    )
    assert r.status_code == 202, r.text
    job_url = r.headers["location"]
    assert r.json()["state"] in ("building", "ready")
    _, reg = line
    job_id = job_url.rsplit("/", 1)[1]
    reg.wait(job_id, timeout_s=120)
    job = client.get(job_url).json()
    assert job["state"] == "done" and job["progress"] == 1.0
    assert client.get("/v1/parts/uploaded").json()["state"] == "ready"
    again = client.post(
        "/v1/parts", files={"cad": ("p.stl", stl.read_bytes())}, data={"spec": json.dumps(spec)}
    )
    assert_error(again, 409, "part_conflict")
    assert client.delete("/v1/parts/uploaded").status_code == 204
    assert_error(client.get("/v1/parts/uploaded"), 404, "unknown_part")
    assert_error(client.delete(f"/v1/parts/{PART}"), 409, "part_conflict")  # configured
    assert_error(client.get("/v1/jobs/job-0"), 404, "unknown_job")


@BOTH_STORES
def test_a_part_created_over_the_api_is_kept_in_the_store_for_every_process(
    line, tmp_path, api_store_target
):
    """The API writes a part it creates to its store, spec and CAD bytes, where an API with
    uploads of its own (another host) finds it; a delete retires it there, kept for the
    results measured with it."""
    cfg, _ = line
    stl = tmp_path / "p.stl"
    sheet_metal_panel(PanelSpec().scaled(120.0, 80.0)).to_trimesh().export(stl)
    spec = {"name": "stored", "version": "7", "tree": {"spacing_mm": 2.0}}
    with (
        ResultStore(api_store_target) as store,
        PartRegistry.from_config(cfg, store=store) as reg,
        TestClient(create_app(cfg, store=store, parts=reg, archive=None)) as c,
    ):
        r = c.post(
            "/v1/parts",
            files={"cad": ("p.stl", stl.read_bytes(), "model/stl")},
            data={"spec": json.dumps(spec)},
        )
        assert r.status_code == 202, r.text
        reg.wait(r.headers["location"].rsplit("/", 1)[1], timeout_s=120)
        kept = store.part("stored")
        assert kept.revision == 1 and kept.cad == stl.read_bytes()
        assert PartSpec.model_validate_json(kept.spec).version == "7"
        elsewhere = tmp_path / "elsewhere"
        with PartRegistry.from_config(cfg, store=store, uploads_dir=elsewhere) as other:
            assert "stored" in other.names() and other.public("stored").version == "7"
            assert (elsewhere / "stored" / "cad.stl").read_bytes() == stl.read_bytes()
        assert c.delete("/v1/parts/stored").status_code == 204
        assert "stored" not in store.part_keys() and store.part("stored", 1).retired_ns


def test_a_point_off_the_cad_surface_is_refused_with_its_distance(client, tmp_path):
    small = PanelSpec().scaled(120.0, 80.0)
    stl = tmp_path / "p.stl"
    sheet_metal_panel(small).to_trimesh().export(stl)
    top = float(panel_height(small, np.array([10.0]), np.array([5.0]))[0])
    points = [
        {"name": n, "position_mm": [10.0, 5.0, top + dz], "normal": [0, 0, 1], "lower_mm": -0.2,
         "upper_mm": 0.2, "radius_mm": 5.0}
        for n, dz in (("on", 0.0), ("above", 3.0))
    ]  # fmt: skip
    spec = {"name": "offset", "points": points}
    r = client.post("/v1/parts", files={"cad": ("p.stl", stl.read_bytes())},
                    data={"spec": json.dumps(spec)})  # fmt: skip
    err = assert_error(r, 422, "point_off_surface")
    assert "'above' at 3." in err["message"] and "'on'" not in err["message"]
    assert [p["name"] for p in client.get("/v1/parts").json()["items"]] == [PART]


@pytest.mark.parametrize(
    "files, data, status, code",
    [
        (
            {"cad": ("p.stl", b"solid x\nendsolid x\n")},
            {"spec": '{"name": "bad1"}'},
            422,
            "invalid_cad",
        ),
        ({"cad": ("p.txt", b"hello")}, {"spec": '{"name": "bad2"}'}, 415, "unsupported_cad_format"),
        ({"cad": ("p.stl", b"x")}, {"spec": '{"name": "bad name"}'}, 422, "invalid_spec"),
        ({"cad": ("p.stl", b"x")}, {"spec": "{not json"}, 422, "invalid_spec"),
        (
            {"cad": ("p.stl", b"x")},
            {
                "spec": json.dumps(
                    {"name": "bad4", "registration": {"loss": "l2", "seen_from_above": True}}
                )
            },
            422,
            "invalid_spec",
        ),
        ({"cad": ("p.stl", b"x")}, {}, 422, "validation_error"),
        ({}, {"spec": '{"name": "bad3"}'}, 415, "unsupported_media_type"),  # no file: not multipart
    ],
)
def test_bad_part_uploads(client, files, data, status, code):
    assert_error(client.post("/v1/parts", files=files or None, data=data), status, code)
    assert [p["name"] for p in client.get("/v1/parts").json()["items"]] == [PART]


# ----------------------------------------------------------------------------- inspections


@BOTH_STORES
def test_list_filters_and_pagination(client, app_parts):
    store = app_parts[1]
    for i in range(7):
        store.put(stored_result(i, status="fail" if i % 3 == 0 else "pass"))
    seen, url = [], "/v1/inspections?limit=3"
    while url:
        page = client.get(url).json()
        seen += page["items"]
        url = f"/v1/inspections?limit=3&cursor={page['next']}" if page["next"] else None
    assert [r["seq"] for r in seen] == [6, 5, 4, 3, 2, 1, 0]
    fails = client.get("/v1/inspections", params={"status": "fail"}).json()["items"]
    assert [r["seq"] for r in fails] == [6, 3, 0]
    since = client.get(
        "/v1/inspections", params={"since": str(1_700_000_000_000_000_000 + 5 * 10**9)}
    )
    assert [r["seq"] for r in since.json()["items"]] == [6, 5]
    iso = client.get("/v1/inspections", params={"since": "2023-11-14T22:13:25Z"}).json()["items"]
    assert [r["seq"] for r in iso] == [6, 5]
    # Calendar times beyond what the store's 64-bit times hold ask for everything or nothing.
    ancient = client.get("/v1/inspections", params={"since": "0001-01-01"})
    assert ancient.status_code == 200 and len(ancient.json()["items"]) == 7
    future = client.get("/v1/inspections", params={"since": "9999-12-31T23:59:59"})
    assert future.status_code == 200 and future.json()["items"] == []
    assert client.get("/v1/inspections", params={"part": "other"}).json() == {
        "items": [],
        "next": None,
    }
    one = client.get(f"/v1/inspections/{seen[0]['id']}").json()
    assert InspectionResult.model_validate(one) == store.get(seen[0]["id"])
    by_serial = client.get("/v1/inspections", params={"serial": "SN4"}).json()["items"]
    assert [r["seq"] for r in by_serial] == [4]
    until = client.get("/v1/inspections", params={"until": str(1_700_000_000_000_000_000 + 10**9)})
    assert [r["seq"] for r in until.json()["items"]] == [1, 0]
    assert client.get("/v1/inspections", params={"station": "st9"}).json()["items"] == []


def test_csv_in_long_format(client, app_parts):
    store = app_parts[1]
    two = stored_result(1, status="fail").model_copy(
        update={"comparison": [*stored_result(1).comparison,
                               stored_result(1).comparison[0].model_copy(update={"name": "e"})],
                "reason": "=HYPERLINK(1)"}
    )  # fmt: skip
    store.put(two)
    store.put(stored_result(2).model_copy(update={"comparison": [], "status": Status.error}))
    resp = client.get("/v1/inspections", headers={"Accept": "text/csv"})
    assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(resp.text)))
    assert [(r["serial"], r["point"]) for r in rows] == [("SN2", ""), ("SN1", "c"), ("SN1", "e")]
    assert rows[1]["deviation_mm"] == "0.1" and rows[1]["lower_mm"] == "-0.3"
    assert rows[1]["reason"] == "'=HYPERLINK(1)"  # never a formula in a spreadsheet
    page = client.get("/v1/inspections", params={"limit": 1}, headers={"Accept": "text/csv"})
    assert page.headers["x-next-cursor"]
    assert client.get("/v1/inspections").headers["content-type"] == "application/json"


def test_recording_of_an_unrecorded_inspection_is_404(client, app_parts):
    app_parts[1].put(stored_result(1))
    assert_error(client.get(f"/v1/inspections/{stored_result(1).id}/recording"), 404,
                 "not_recorded")  # fmt: skip


@pytest.mark.parametrize("api_store_target", ["postgresql"], indirect=True)
def test_a_database_out_of_reach_is_a_503_and_the_api_goes_on(client, app_parts, pg_server):
    store = app_parts[1]
    store.put(stored_result(1))
    name = store.where.rsplit("/", 1)[1]
    with psycopg.connect(pg_server.url(), autocommit=True) as admin:
        admin.execute(f"ALTER DATABASE {name} WITH ALLOW_CONNECTIONS false")
        admin.execute(
            "SELECT pg_terminate_backend(pid, 10000) FROM pg_stat_activity WHERE datname = %s",
            (name,),
        )
        err = assert_error(client.get("/v1/inspections"), 503, "store_unavailable")
        assert "127.0.0.1" not in err["message"]  # where the database is stays in the log
        assert client.get(f"/v1/parts/{PART}").status_code == 200
        admin.execute(f"ALTER DATABASE {name} WITH ALLOW_CONNECTIONS true")
    assert [r["seq"] for r in client.get("/v1/inspections").json()["items"]] == [1]


@pytest.mark.parametrize(
    "params, code",
    [
        ({"status": "great"}, "validation_error"),
        ({"limit": 0}, "validation_error"),
        ({"limit": 5000}, "validation_error"),
        ({"since": "yesterday"}, "validation_error"),
        ({"since": "99999999999999999999999"}, "validation_error"),
        ({"since": str(2**63)}, "validation_error"),
        ({"cursor": "garbage!"}, "invalid_cursor"),
        ({"cursor": encode_cursor(2**64, "x.1")}, "invalid_cursor"),
        ({"part": "a/b"}, "validation_error"),
        ({"serial": "a b"}, "validation_error"),
        ({"until": "tomorrow"}, "validation_error"),
        ({"serail": "SN1"}, "unknown_parameter"),
        ({"status": "pass", "colour": "red"}, "unknown_parameter"),
    ],
)
def test_list_bad_queries(client, params, code):
    assert_error(client.get("/v1/inspections", params=params), 422, code)


def test_unknown_ids_and_routes_are_404(client):
    assert_error(client.get("/v1/inspections/nope"), 404, "unknown_inspection")
    assert_error(client.get("/v1/inspections/nope/colormap.png"), 404, "unknown_inspection")
    assert_error(client.get("/v1/nothing-here"), 404, "not_found")
    assert_error(client.put("/v1/parts"), 405, "method_not_allowed")


def test_colormap_renders_the_archived_deviations(client, app_parts):
    _, store, archive, *_ = app_parts
    r = stored_result(1)
    store.put(r)
    rng = np.random.default_rng(0)
    pts = np.column_stack(
        [rng.uniform(-75, 75, 5000), rng.uniform(-50, 50, 5000), rng.uniform(0, 30, 5000)]
    )
    d = pts[:, 0] / 100.0
    d[:100] = np.nan
    archive.save(r.id, pts, d)
    resp = client.get(f"/v1/inspections/{r.id}/colormap.png", params={"size_px": 300})
    assert resp.status_code == 200 and resp.headers["content-type"] == "image/png"
    import cv2

    img = cv2.imdecode(np.frombuffer(resp.content, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[1] >= 300

    # Left (negative deviations) is blue, right (positive) is red: BGR.
    def mean_colour(region):
        px = region.reshape(-1, 3).astype(int)
        drawn = px[(px != 40).any(axis=1) & (px != 150).any(axis=1)]
        return drawn.mean(axis=0)

    left, right = mean_colour(img[40:160, 25:60]), mean_colour(img[40:160, 260:300])
    assert left[0] > left[2] + 100 and right[2] > right[0] + 100
    store.put(stored_result(2))
    assert_error(
        client.get(f"/v1/inspections/{stored_result(2).id}/colormap.png"), 404, "no_deviations"
    )


@BOTH_STORES
def test_trends_name_each_capability_for_its_sigma(client, app_parts):
    store = app_parts[1]
    devs = np.random.default_rng(3).normal(0.05, 0.02, 40)
    for i, d in enumerate(devs):
        store.put(stored_result(i, dev=float(d)))
    t = client.get(f"/v1/parts/{PART}/trends").json()
    assert t["window"] == 10 and t["parts"] == 10
    (p,) = t["points"]
    assert p["n"] == 10 and p["mean_mm"] == pytest.approx(devs[-10:].mean())
    # Too few for a capability figure: none, and the reason.
    assert p["cp"] is p["cpk"] is p["pp"] is p["ppk"] is None
    assert "10 values" in p["capability_note"]
    (p,) = client.get(f"/v1/parts/{PART}/trends", params={"window": 40}).json()["points"]
    overall = devs.std(ddof=1)
    within = np.abs(np.diff(devs)).mean() / 1.128
    assert p["n"] == 40 and p["capability_note"] is None
    assert p["ppk"] == pytest.approx((0.3 - devs.mean()) / (3 * overall))
    assert p["pp"] == pytest.approx(0.6 / (6 * overall))
    assert p["cp"] == pytest.approx(0.6 / (6 * within))
    assert p["cpk_ci"]["low"] < p["cpk"] < p["cpk_ci"]["high"]
    assert client.get(f"/v1/parts/{PART}/trends", params={"window": 4}).json()["parts"] == 4
    assert_error(client.get("/v1/parts/nope/trends"), 404, "unknown_part")


def test_control_chart_flags_the_rule_and_a_frozen_baseline_moves_its_limits(client, app_parts):
    store = app_parts[1]
    rng = np.random.default_rng(4)
    devs = [*rng.normal(0.0, 0.01, 20), 0.0, 0.2]  # a part far beyond three sigma
    for i, d in enumerate(devs):
        store.put(stored_result(i, dev=float(d)))
    ch = client.get(f"/v1/parts/{PART}/charts/c").json()
    assert ch["limits"]["frozen"] is False and ch["limits"]["n"] == 20
    assert ch["rules"] == ["nelson1"]
    assert [p["rules"] for p in ch["points"]][-2:] == [[], ["nelson1"]]
    assert ch["points"][-1]["serial"] == "SN21"
    assert ch["lower_mm"] == -0.3 and ch["capability"]["n"] == 22
    # Frozen over the whole period (the excursion included), the limits widen.
    t_end = stored_result(21).triggered_ns
    frozen = client.post(f"/v1/parts/{PART}/baseline", json={"until_ns": t_end, "by": "qe"})
    assert frozen.status_code == 201, frozen.text
    assert frozen.json()["frozen_by"].startswith("qe")
    ch2 = client.get(f"/v1/parts/{PART}/charts/c").json()
    assert ch2["limits"]["frozen"] is True and ch2["limits"]["ucl"] > ch["limits"]["ucl"]
    assert client.get(f"/v1/parts/{PART}/charts/fit_rms").json()["feature"] == "fit_rms"
    assert_error(client.get(f"/v1/parts/{PART}/charts/nope"), 404, "unknown_feature")
    assert client.delete(f"/v1/parts/{PART}/baseline").status_code == 204
    assert_error(client.get(f"/v1/parts/{PART}/baseline"), 404, "no_baseline")
    assert_error(
        client.post(f"/v1/parts/{PART}/baseline", json={"until_ns": 5}), 422, "too_few_results"
    )


def test_few_parts_give_no_limits_and_say_why(client, app_parts):
    for i in range(3):
        app_parts[1].put(stored_result(i))
    ch = client.get(f"/v1/parts/{PART}/charts/c").json()
    assert ch["limits"] is None and "3 of the 20" in ch["limits_note"]
    assert all(p["rules"] == [] for p in ch["points"])


def test_alarms_are_listed_and_acknowledged_once(client, app_parts):
    from service.models import Alarm

    a = Alarm(kind="spc_rule", message="c beyond 3 sigma", triggered_ns=1, line="line1",
              station="st1", raised_ns=2, part=PART, feature="c", rule="nelson1")  # fmt: skip
    app_parts[1].put_alarm(a)
    assert [x["id"] for x in client.get("/v1/alarms", params={"open": True}).json()] == [a.id]
    acked = client.post(f"/v1/alarms/{a.id}/ack", json={"by": "Ann"}, headers={"X-API-Key": "k1"})
    assert acked.status_code == 200, acked.text
    body = acked.json()
    assert body["acknowledged_by"].startswith("Ann (key ") and body["acknowledged_ns"] > 0
    again = client.post(f"/v1/alarms/{a.id}/ack", json={"by": "Bob"}).json()
    assert again["acknowledged_by"] == body["acknowledged_by"]
    assert client.get("/v1/alarms", params={"open": True}).json() == []
    assert_error(client.post("/v1/alarms/nope/ack", json={}), 404, "unknown_alarm")


# ----------------------------------------------------------------------------- bad uploads


def post_cloud(
    client, payload: bytes, *, part=PART, name="c.npy", ctype="application/octet-stream", **data
):
    return client.post(
        "/v1/inspections", files={"file": (name, payload, ctype)}, data={"part": part, **data}
    )


@pytest.mark.parametrize(
    "make, status, code",
    [
        (lambda: post_cloud_args(npy_bytes(np.full((100, 3), np.nan))), 422, "invalid_input"),
        (lambda: post_cloud_args(npy_bytes(np.zeros((0, 3)))), 422, "invalid_input"),
        (lambda: post_cloud_args(npy_bytes(np.zeros((100, 2)))), 422, "invalid_input"),
        (lambda: post_cloud_args(npy_bytes(np.ones((1000, 3)))[:-500]), 422, "invalid_input"),
        (
            lambda: post_cloud_args(
                b"ply\nformat binary_little_endian 1.0\nelement vertex 100\n"
                b"property float x\nproperty float y\nproperty float z\nend_header\n" + b"\0" * 600
            ),
            422,
            "invalid_input",
        ),  # fmt: skip
        (lambda: post_cloud_args(b"GIF89a not a cloud"), 415, "unsupported_cloud_format"),
        (lambda: post_cloud_args(b""), 422, "empty_file"),
        (lambda: post_cloud_args(npy_bytes(np.ones((100, 3))), part="nope"), 404, "unknown_part"),
        (
            lambda: post_cloud_args(npy_bytes(np.ones((100, 3))), part="bad part"),
            404,
            "unknown_part",
        ),
        (
            lambda: post_cloud_args(npy_bytes(np.ones((100, 3))), frame="world"),
            422,
            "validation_error",
        ),
        (
            lambda: post_cloud_args(npy_bytes(np.ones((100, 3))), serial="a b"),
            422,
            "validation_error",
        ),
        (
            lambda: post_cloud_args(npy_bytes(np.array([["a", "b", "c"]] * 20))),
            422,
            "invalid_input",
        ),
        (lambda: post_cloud_args(npy_bytes(np.full((100, 3), 1e308))), 422, "invalid_input"),
    ],
)
def test_bad_clouds_give_clear_errors_and_keep_results(client, app_parts, make, status, code):
    store = app_parts[1]
    earlier = stored_result(1)
    store.put(earlier)
    kwargs = make()
    assert_error(post_cloud(client, **kwargs), status, code)
    assert store.count() == 1 and store.get(earlier.id) == earlier


def post_cloud_args(payload: bytes, **kw) -> dict:
    return {"payload": payload, **kw}


def test_wrong_content_types_are_415(client):
    r = client.post("/v1/inspections", json={"part": PART, "points": [[0, 0, 0]]})
    assert_error(r, 415, "unsupported_media_type")
    r = client.post(
        "/v1/parts", content=b"abc", headers={"content-type": "application/octet-stream"}
    )
    assert_error(r, 415, "unsupported_media_type")


def test_oversized_upload_is_413_declared_or_streamed(client, app_parts):
    big = npy_bytes(np.zeros((60_000, 3)))  # 1.44 MB > 1 MB limit
    assert_error(post_cloud(client, big), 413, "payload_too_large")

    def chunks():
        for i in range(0, len(big), 65536):
            yield big[i : i + 65536]

    r = client.post(
        "/v1/inspections",
        content=chunks(),
        headers={"content-type": "multipart/form-data; boundary=x"},
    )
    assert_error(r, 413, "payload_too_large")
    assert app_parts[1].count() == 0


def test_malformed_multipart_is_400(client):
    body = (
        b'--xyz\r\nContent-Disposition: form-data; name="part"\r\n\r\npanel-s\r\n'
        b"--xyz\r\nContent-Disp"
    )
    r = client.post(
        "/v1/inspections",
        content=body,
        headers={"content-type": "multipart/form-data; boundary=xyz"},
    )
    assert r.status_code in (400, 422), r.text
    assert "error" in r.json()


# ----------------------------------------------------------------------------- system


def test_health_follows_the_checks(client, app_parts):
    zenoh_up = app_parts[4]
    r = client.get("/v1/health")
    assert r.status_code == 200 and r.json()["checks"] == {"parts": True, "zenoh": True}
    zenoh_up["value"] = False
    r = client.get("/v1/health")
    assert r.status_code == 503 and r.json()["ready"] is False and r.json()["alive"] is True
    assert client.get("/v1/health/live").status_code == 200


def test_metrics_in_prometheus_text_format(client, app_parts):
    from prometheus_client.parser import text_string_to_metric_families

    app_parts[1].put(stored_result(1))
    client.get("/v1/parts")
    text = client.get("/metrics")
    assert text.headers["content-type"].startswith("text/plain; version=")
    families = {f.name: f for f in text_string_to_metric_families(text.text)}
    samples = {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for f in families.values()
        for s in f.samples
    }
    assert samples[("inspection_results_stored", (("status", "pass"),))] == 1
    key = (("code", "200"), ("method", "GET"), ("route", "/v1/parts"))
    assert samples[("http_requests_total", key)] == 1
    assert families["http_request_duration_seconds"].type == "histogram"
    assert samples[("inspection_parts", (("part", PART), ("state", "ready")))] == 1


def test_openapi_documents_the_routes(client):
    spec = client.get("/openapi.json").json()
    for path in ("/v1/parts", "/v1/parts/{name}", "/v1/inspections", "/v1/inspections/{id}",
                 "/v1/inspections/{id}/colormap.png", "/v1/parts/{name}/trends", "/v1/stream",
                 "/v1/health", "/metrics", "/v1/jobs/{job_id}"):  # fmt: skip
        assert path in spec["paths"], path
    assert (
        "multipart/form-data" in spec["paths"]["/v1/inspections"]["post"]["requestBody"]["content"]
    )
    assert client.get("/docs").status_code == 200
    schemas = spec["components"]["schemas"]
    assert {"PartCreate", "ComparisonPointSpec"} <= set(schemas)
    assert "subgroup_size" in schemas["PartCreate"]["properties"]


# ----------------------------------------------------------------------------- real server


@pytest.fixture
def server(app_parts):
    """The app on a real uvicorn server on a free loopback port."""
    open_after = []  # clients to close only once the server has stopped
    with uvicorn_server(app_parts[0], before_stop=app_parts[3].close) as port:
        yield SimpleNamespace(port=port, close_after=open_after)
    for c in open_after:
        c.close()


def call(port: int, method: str, path: str, body: bytes | None = None, headers=None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        r = conn.getresponse()
        return r.status, dict(r.getheaders()), r.read()
    finally:
        conn.close()


def test_real_server_answers_and_streams(server, app_parts):
    port = server.port
    hub = app_parts[3]
    status, _, body = call(port, "GET", "/v1/health")
    assert status == 200 and json.loads(body)["ready"] is True
    status, _, body = call(port, "GET", "/v1/inspections/none")
    assert status == 404 and json.loads(body)["error"]["code"] == "unknown_inspection"

    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    server.close_after.append(conn)
    conn.request("GET", f"/v1/stream?part={PART}")
    resp = conn.getresponse()
    assert resp.status == 200 and resp.getheader("content-type").startswith("text/event-stream")
    assert resp.readline() == b"event: ready\n"  # subscribed from here on
    resp.readline(), resp.readline()
    other = stored_result(1).model_copy(update={"part": "other", "id": "x.1"})
    hub.publish(other)  # filtered out
    wanted = stored_result(2)
    hub.publish(wanted)
    event = [resp.readline() for _ in range(4)]
    assert event[0] == b"event: result\n"
    assert event[1] == f"id: {wanted.id}\n".encode()
    assert InspectionResult.model_validate_json(event[2][len(b"data: ") :]) == wanted
    # The stream stays open: closing the hub must still let the server stop (teardown).


def test_real_server_refuses_a_truncated_upload(server, app_parts):
    """A client that declares more bytes than it sends, then goes away, changes nothing."""
    port = server.port
    store = app_parts[1]
    store.put(stored_result(1))
    boundary = "b0undary"
    payload = npy_bytes(np.ones((1000, 3)))
    body = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="part"\r\n\r\n{PART}\r\n'
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="c.npy"\r\n\r\n'
    ).encode() + payload
    s = socket.create_connection(("127.0.0.1", port), timeout=60)
    head = (
        "POST /v1/inspections HTTP/1.1\r\nHost: x\r\n"
        f"Content-Type: multipart/form-data; boundary={boundary}\r\n"
        f"Content-Length: {len(body) + 1000}\r\n\r\n"
    ).encode()
    s.sendall(head + body)
    s.shutdown(socket.SHUT_WR)  # the rest never comes
    reply = b""
    while chunk := s.recv(65536):
        reply += chunk
    s.close()
    assert not reply.startswith(b"HTTP/1.1 200")
    # The server is still up, and the earlier result intact.
    status, _, body_ = call(port, "GET", "/v1/inspections")
    assert status == 200 and [r["seq"] for r in json.loads(body_)["items"]] == [1]


# ----------------------------------------------------------------------------- measuring


def visible_cloud(cad, n: int, seed: int) -> np.ndarray:
    """Points on the faces that look up (what a rig above the conveyor sees), CAD frame."""
    rng = np.random.default_rng(seed)
    up = cad.face_normals[:, 2] > 0.3
    tri = cad.vertices[cad.faces[up]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(tri), size=n, p=area / area.sum())
    a, b = rng.random((2, n))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[pick]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])


def test_uploaded_clouds_are_measured_and_stored(client, app_parts, line):
    _, reg = line
    part = reg.get(PART)
    store, archive = app_parts[1], app_parts[2]
    T_rig_cad = belt_pose(40.0, -25.0, 37.0)
    pts_cad = visible_cloud(part.cad, 20_000, seed=1)
    pts_rig = apply(T_rig_cad, pts_cad)

    r = post_cloud(client, payload=npy_bytes(pts_rig), serial="SN-1")
    assert r.status_code == 200, r.text
    res = InspectionResult.model_validate(r.json())
    assert res.status == "pass", res
    assert res.part == PART and res.serial == "SN-1" and res.spec_version == "3"
    assert res.cad_hash == part.cad.hash and res.tree_hash == part.tree_hash
    T = np.array(res.transform)
    np.testing.assert_allclose(T @ T_rig_cad, np.eye(4), atol=1e-3)
    assert [c.name for c in res.comparison] == ["c", "e", "w"]
    assert all(abs(c.deviation_mm) < 0.05 for c in res.comparison)
    assert {"align", "deviations", "total"} <= set(res.timings_ms)
    assert store.get(res.id) == res
    assert archive.load(res.id) is not None
    assert client.get(f"/v1/inspections/{res.id}/colormap.png").status_code == 200

    # A dent of +0.6 mm around comparison point "c" fails the part.
    c = next(p for p in part.spec.points if p.name == "c")
    near = np.linalg.norm(pts_cad - np.array(c.position_mm), axis=1) < 10.0
    dented = pts_cad + np.where(near[:, None], 0.6 * np.array(c.normal), 0.0)
    dented_rig = apply(T_rig_cad, dented)
    r = post_cloud(client, payload=npy_bytes(dented_rig), serial="SN-2")
    res2 = InspectionResult.model_validate(r.json())
    assert res2.status == "fail", res2.reason
    verdicts = {p.name: p.verdict for p in res2.comparison}
    assert verdicts["c"] == "fail" and verdicts["e"] == "pass"
    # The same bump is a surface defect, in the result and outlined on the colour map.
    assert [(f.kind, f.nearest_point) for f in res2.defects] == [("bump", "c")]
    assert res2.defects[0].peak_mm == pytest.approx(0.6, abs=0.05)
    assert "surface defect: bump 0.6" in res2.reason
    assert store.get(res2.id).defects == res2.defects
    png = client.get(f"/v1/inspections/{res2.id}/colormap.png", params={"size_px": 300})
    img = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_COLOR)
    amber = (img[:, :, 0] < 30) & (img[:, :, 1] > 180) & (img[:, :, 2] > 230)
    assert amber.sum() > 50, "the defect is outlined"
    assert store.count() == 2

    # The same cloud, already in the CAD frame: only the fine registration.
    r = post_cloud(client, payload=npy_bytes(pts_cad), frame="cad")
    res3 = InspectionResult.model_validate(r.json())
    assert res3.status == "pass"
    np.testing.assert_allclose(np.array(res3.transform), np.eye(4), atol=1e-3)


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_ply_and_npy_uploads_parse_to_the_same_points(encoding):
    import trimesh

    from service.api.clouds import cloud_format, parse_cloud

    pts = np.random.default_rng(5).normal(size=(500, 3)) * 100
    ply = trimesh.PointCloud(pts).export(file_type="ply", encoding=encoding)
    assert cloud_format(ply) == "ply"
    np.testing.assert_allclose(parse_cloud(ply), pts, rtol=1e-6, atol=1e-4)  # float32 in PLY
    np.testing.assert_array_equal(parse_cloud(npy_bytes(pts)), pts)
    structured = np.zeros(500, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("i", "f4")])
    structured["x"], structured["y"], structured["z"] = pts.T
    np.testing.assert_array_equal(parse_cloud(npy_bytes(structured)), pts)


# ----------------------------------------------------------------------------- hostile names

HOSTILE_NAMES = ["..", ".", "...", "%2e%2e", "a/.."]


def tree_digest(*roots: Path) -> dict[str, str]:
    """Every file below ``roots`` with a hash of its bytes: what a request must not touch.

    SQLite's ``-shm`` file is its readers' shared index, rewritten by any
    read; it holds no data and is left out.
    """
    out = {}
    for root in roots:
        for p in sorted(root.rglob("*")):
            if p.is_file() and not p.name.endswith("-shm"):
                out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def multipart(fields: dict[str, str], files: dict[str, tuple[str, bytes]]) -> tuple[bytes, dict]:
    boundary = "h0stile"
    chunks = []
    for k, v in fields.items():
        chunks.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n')
    body = "".join(chunks).encode()
    for k, (filename, data) in files.items():
        body += (
            (
                f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"; '
                f'filename="{filename}"\r\nContent-Type: application/octet-stream\r\n\r\n'
            ).encode()
            + data
            + b"\r\n"
        )
    body += f"--{boundary}--\r\n".encode()
    return body, {"Content-Type": f"multipart/form-data; boundary={boundary}"}


def test_dot_names_touch_no_file_of_the_data_directory(server, app_parts, line, tmp_path):
    """Names of dots, encoded dots and a climbing path, sent raw to a real server.

    The data directory holds a real store, an archived deviation, a cached
    tree and an uploaded part, so that a delete of the root, of the uploads
    folder or of a sibling would show as a changed digest.
    """
    cfg, reg = line
    _, store, archive, _, _ = app_parts
    store.put(stored_result(1))
    archive.save(stored_result(1).id, np.zeros((3, 3)), np.zeros(3))
    stl = tmp_path / "valid.stl"
    sheet_metal_panel(PanelSpec().scaled(120.0, 80.0)).to_trimesh().export(stl)
    valid = stl.read_bytes()
    reg.wait(reg.create(_spec_base("kept"), valid, "p.stl").id, timeout_s=120)
    data_dir = Path(cfg.storage.data_dir)
    roots = (data_dir, tmp_path)
    before = tree_digest(*roots)
    assert any("/parts/kept/" in p for p in before) and any("/trees/" in p for p in before)
    assert any(p.endswith("results.sqlite") for p in before)

    def check(status: int, body: bytes, what: str) -> None:
        assert 400 <= status < 500, (what, status, body)
        err = json.loads(body)["error"]
        assert err["code"] and err["message"], what
        assert tree_digest(*roots) == before, what

    try:
        for name in HOSTILE_NAMES:
            for cad in (b"x", valid):  # unreadable, then a mesh that would be accepted
                body, headers = multipart(
                    {"spec": json.dumps({"name": name})}, {"cad": ("p.stl", cad)}
                )
                status, _, reply = call(server.port, "POST", "/v1/parts", body, headers)
                check(status, reply, f"POST {name!r} ({len(cad)} bytes)")
            for method in ("DELETE", "GET"):
                status, _, reply = call(server.port, method, f"/v1/parts/{name}")
                check(status, reply, f"{method} /v1/parts/{name}")
            for path in (f"/v1/parts/{name}/trends", f"/v1/inspections/{name}/colormap.png"):
                status, _, reply = call(server.port, "GET", path)
                check(status, reply, f"GET {path}")
        names = [p["name"] for p in json.loads(call(server.port, "GET", "/v1/parts")[2])["items"]]
        assert sorted(names) == sorted([PART, "kept"])
    finally:
        reg.delete("kept")
    assert not (data_dir / "parts" / "kept").exists()
    assert (data_dir / "parts").is_dir()  # the uploads root itself stays


def _spec_base(name: str) -> PartSpecBase:
    return PartSpecBase(name=name)


def test_stream_resumes_after_the_last_event_id_and_carries_alarms(server, app_parts):
    from service.api.routes.system import BACKLOG_PAGE
    from service.models import Alarm

    store, hub = app_parts[1], app_parts[3]
    missed = 2 * BACKLOG_PAGE + 50  # more than a page of the store: every one comes back
    store.put_many([stored_result(i) for i in range(missed + 2)])
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=60)
    server.close_after.append(conn)
    conn.request("GET", "/v1/stream", headers={"Last-Event-ID": stored_result(1).id})
    resp = conn.getresponse()
    assert resp.readline() == b"event: ready\n"
    resp.readline(), resp.readline()
    ids = []
    for _ in range(missed):
        event = [resp.readline() for _ in range(4)]
        assert event[0] == b"event: result\n"
        ids.append(event[1].decode().strip().removeprefix("id: "))
    # What it missed, oldest first.
    assert ids == [stored_result(i).id for i in range(2, missed + 2)]
    alarm = Alarm(kind="spc_rule", message="x", triggered_ns=1, line="line1", station="st1",
                  raised_ns=2)  # fmt: skip
    hub.publish(alarm)
    event = [resp.readline() for _ in range(3)]
    assert event[0] == b"event: alarm\n"
    assert Alarm.model_validate_json(event[1][len(b"data: ") :]) == alarm


def test_report_of_a_failed_part_as_html_and_pdf(client, app_parts):
    pypdf = pytest.importorskip("pypdf")
    try:
        import weasyprint  # noqa: F401
    except (ImportError, OSError) as exc:
        pytest.skip(
            f"PDF reports need WeasyPrint and Pango ({exc}): pip install weasyprint; "
            "apt-get install libpango-1.0-0 libpangoft2-1.0-0 fonts-dejavu-core"
        )
    _, store, archive, *_ = app_parts
    for i in range(25):
        store.put(stored_result(i, dev=0.01 * (i % 3)))
    bad = stored_result(25, status="fail", dev=0.45)
    bad = bad.model_copy(
        update={"comparison": [bad.comparison[0].model_copy(update={"verdict": Verdict.FAIL})]}
    )
    store.put(bad)
    xy = np.random.default_rng(0).uniform(-60, 60, (4000, 2))
    archive.save(bad.id, np.c_[xy, np.zeros(len(xy))], np.where(xy[:, 0] > 0, 0.45, 0.0))
    page = client.get(f"/v1/inspections/{bad.id}/report.html")
    assert page.status_code == 200 and "data:image/png;base64," in page.text
    # Nothing to fetch: no script, and no address outside the images' own data URIs (whose
    # base64 may spell anything).
    body = re.sub(r"data:[\w/+.-]+;base64,[A-Za-z0-9+/=]+", "", page.text.split("<body>")[1])
    assert "<script" not in page.text and "http" not in body
    resp = client.get(f"/v1/inspections/{bad.id}/report.pdf")
    assert resp.status_code == 200 and resp.headers["content-type"] == "application/pdf"
    pdf = pypdf.PdfReader(io.BytesIO(resp.content))
    assert 1 <= len(pdf.pages) <= 4
    text = " ".join(p.extract_text() for p in pdf.pages)
    assert "SN25" in text and "FAIL" in text and "failing: c" in text
    assert "nelson1" in text  # the trend context: this part breaks the chart's limits
    assert_error(client.get("/v1/inspections/nope/report.pdf"), 404, "unknown_inspection")
