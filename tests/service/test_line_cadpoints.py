"""The line on the comparison-point path (``[station] path = "comparison_points"``).

One ``inspection run`` for the module (small images, one matching pass, the
demo panel with a surface that does not fail parts) measures a few parts: a
subscriber on zenoh, the REST API and the MCAP recording all say the parts
were measured on that path with their surface not checked (``defects``
null), the defect chart leaves them out, and replaying the recording
re-measures them on the path it names, identically. A part whose surface
fails parts is refused for that path when the line loads and when uploaded.
"""

from __future__ import annotations

import csv
import io
import json
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from linekit import LINE, PART, ROOT, client, free_port
from test_line import cli, get_json, line_file, stop

from inspection.panel import PanelSpec, sheet_metal_panel
from inspection.rig import Rig
from service import bus
from service.cli import main as cli_main
from service.models import InspectionResult
from service.protocol import Keys
from service.recorder import read_recording
from service.replay import recorded_stages, replay

SIZE = (640, 512)
PARTS = 2
PATH = "comparison_points"


def parts_dir(tmp: Path, *, fails_part: bool) -> Path:
    """The repo's demo panel spec, its surface failing parts or not."""
    text = (ROOT / "configs" / "parts" / f"{PART}.toml").read_text()
    old = "fails_part = true "
    assert old in text
    folder = tmp / ("parts-failing" if fails_part else "parts")
    folder.mkdir()
    (folder / f"{PART}.toml").write_text(
        text if fails_part else text.replace(old, "fails_part = false ", 1)
    )
    return folder


def post_part(url: str, spec: dict, stl: bytes) -> tuple[int, dict]:
    """POST a part (spec and CAD file) as the API's multipart form; the status and JSON body."""
    boundary = "cadpoints-part"
    body = (
        (
            f'--{boundary}\r\nContent-Disposition: form-data; name="spec"\r\n\r\n'
            f"{json.dumps(spec)}\r\n--{boundary}\r\nContent-Disposition: form-data; "
            f'name="cad"; filename="p.stl"\r\nContent-Type: model/stl\r\n\r\n'
        ).encode()
        + stl
        + f"\r\n--{boundary}--\r\n".encode()
    )
    request = urllib.request.Request(
        url, body, {"Content-Type": f"multipart/form-data; boundary={boundary}"}, method="POST"
    )
    try:
        with urllib.request.urlopen(request, timeout=30) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def cadpoints_line(tmp: Path, trees: Path, parts: Path) -> Path:
    """The default line on the comparison-point path, small images, one matching pass."""
    rig_file = tmp / "rig.toml"
    if not rig_file.exists():
        Rig.default().with_image_size(*SIZE).save(rig_file)
    config = line_file(tmp, trees, period_s=1.0, queue_size=8)
    text = config.read_text()
    for old, new in [
        ("[station]\n", f'[station]\nrig_calibration = "{rig_file}"\n'),
        ('path = "cloud"', f'path = "{PATH}"'),
        ("guided_matching = true", "guided_matching = false"),
        (f'parts_dir = "{ROOT / "configs" / "parts"}"', f'parts_dir = "{parts}"'),
    ]:
        assert old in text, old
        text = text.replace(old, new, 1)
    config.write_text(text)
    return config


@pytest.fixture(scope="module")
def line(tmp_path_factory, trees) -> Iterator[dict]:
    """The line's results as a zenoh subscriber got them, what its REST API answered, and
    its recording once stopped."""
    tmp = tmp_path_factory.mktemp("cadpoints-line")
    parts = parts_dir(tmp, fails_part=False)
    config = cadpoints_line(tmp, trees, parts)
    port, http_port = free_port(), free_port()
    data = tmp / "data"
    run = cli("run", "--config", str(config), "--data-dir", str(data),
              "--http-port", str(http_port), "--zenoh-listen", f"tcp/127.0.0.1:{port}")  # fmt: skip
    got: dict = {"parts": parts, "tmp": tmp}
    try:
        for out in run.stdout:
            if out.strip().startswith("data:"):
                break
        else:
            pytest.fail(f"the line did not start: {run.stderr.read()[-3000:]}")
        published: list[InspectionResult] = []
        arrived = threading.Semaphore(0)

        def on_result(sample) -> None:
            published.append(InspectionResult.model_validate_json(sample.payload.to_bytes()))
            arrived.release()

        with bus.open_session(client(port)) as session:
            sub = bus.RingSubscriber(session, Keys(LINE).results(), on_result, capacity=16)
            try:
                for _ in range(PARTS):
                    assert arrived.acquire(timeout=180), "no result from the line"
            finally:
                sub.close()
        got["zenoh"] = list(published)
        base = f"http://127.0.0.1:{http_port}"
        got["rest"] = get_json(f"{base}/v1/inspections?limit=100")
        got["chart"] = get_json(f"{base}/v1/parts/{PART}/charts/defects")
        with urllib.request.urlopen(
            urllib.request.Request(
                f"{base}/v1/inspections?limit=100", headers={"Accept": "text/csv"}
            ),
            timeout=30,
        ) as r:
            got["csv"] = r.read().decode()
        failing = sheet_metal_panel(PanelSpec().scaled(120.0, 80.0))
        stl = tmp / "failing.stl"
        failing.to_trimesh().export(stl)
        spec = {"name": "failing", "version": "1", "points": [], "surface": {"fails_part": True}}
        got["upload"] = post_part(f"{base}/v1/parts", spec, stl.read_bytes())
        got["upload_parts"] = get_json(f"{base}/v1/parts")
    finally:
        code = stop(run)
    assert code == 0, run.stderr.read()[-3000:]
    got["recording"] = sorted((data / "mcap").glob("*.mcap"))
    yield got


def test_zenoh_results_say_the_path_and_that_the_surface_was_not_checked(line):
    measured = [r for r in line["zenoh"] if r.status.value in ("pass", "fail", "not_measurable")]
    assert measured, [(r.status, r.reason) for r in line["zenoh"]]
    for r in measured:
        assert r.path == PATH and r.defects is None
        assert r.comparison and r.transform is not None
        # Local photogrammetry measured the points: some with a deviation, never a defect.
        assert any(c.deviation_mm is not None for c in r.comparison)


def test_rest_serves_them_the_same_and_charts_no_defect_count(line):
    code, page = line["rest"]
    assert code == 200
    measured = [r for r in page["items"] if r["transform"] is not None]
    assert measured
    assert all(r["path"] == PATH and r["defects"] is None for r in measured)
    by_id = {r.id: r for r in line["zenoh"]}
    for r in measured:
        if r["id"] in by_id:
            assert InspectionResult.model_validate(r) == by_id[r["id"]]
    code, chart = line["chart"]
    assert code == 200, chart
    assert chart["points"] == []  # no part of this path has a defect count, not even zero
    rows = list(csv.DictReader(io.StringIO(line["csv"])))
    assert rows and all(row["defects"] == "" for row in rows)


def test_an_upload_whose_surface_fails_parts_is_refused(line):
    code, body = line["upload"]
    assert code == 422, body
    assert body["error"]["code"] == "path_conflict"
    assert "comparison_points" in body["error"]["message"]
    code, parts = line["upload_parts"]
    assert code == 200 and [p["name"] for p in parts["items"]] == [PART]


def test_the_recording_replays_on_its_own_path(line, trees):
    files = line["recording"]
    assert files
    meta, triggers = read_recording(files)
    assert meta["rig"]["path"] == PATH and recorded_stages(meta).path == PATH
    logged = [t.result for t in triggers if t.frameset is not None]
    assert logged and all(r.path == PATH and r.defects is None for r in logged)
    replayed: list[InspectionResult] = []
    report = replay(
        files, parts_dir=line["parts"], trees_dir=trees,
        on_result=lambda new, old: replayed.append(new),
    )  # fmt: skip
    assert report.ok, report.summary()
    assert report.replayed == len(logged) and report.same == len(logged)
    assert replayed and all(r.path == PATH for r in replayed)


def test_a_spec_whose_surface_fails_parts_stops_the_line_at_start_up(tmp_path, trees, capsys):
    config = cadpoints_line(tmp_path, trees, parts_dir(tmp_path, fails_part=True))
    assert cli_main(["run", "--config", str(config), "--data-dir", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "comparison_points" in err and PART in err and "fails_part" in err


def test_recordings_from_before_the_path_replay_on_the_cloud():
    assert recorded_stages({"rig": {"stages": "flash"}}).path == "cloud"
    from service.replay import ReplayError

    with pytest.raises(ReplayError, match="path"):
        recorded_stages({"rig": {"stages": "flash", "path": "holes"}})
