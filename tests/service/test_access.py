"""Who may call the API, and how much it measures at once: a real uvicorn server each.

Keys on writes (401 without, constant-time compare), reads open or not, no
key configured beyond loopback (403), the browser's Origin on writes (403
for a stranger's page), CORS for the allowed origins, and uploads beyond the
API's measuring capacity refused at once (503 with Retry-After).
"""

from __future__ import annotations

import os
import select
import signal
import threading
from contextlib import contextmanager

import httpx2
import numpy as np
import pytest
from linekit import uvicorn_server
from test_api import PART, line, npy_bytes  # noqa: F401 - the module's built part

from service.api import ResultHub, create_app
from service.api.access import KEYS_ENV
from service.api.gate import NICE
from service.api.measurer import UploadMeasurer
from service.results import measure_upload
from service.store import DeviationArchive, ResultStore

KEY = "k3y-0f-the-line"


@contextmanager
def serve(cfg, reg, tmp_path, *, pipeline=None, measurer=None, **http):
    """The API with ``[http]`` changed by ``http``, on a real server on a loopback port;
    uploads measured by ``pipeline`` on a thread, or by ``measurer``'s processes."""
    cfg = cfg.model_copy(
        update={"http": type(cfg.http).model_validate(cfg.http.model_dump() | http)}
    )
    store = ResultStore(tmp_path / "results.sqlite")
    hub = ResultHub()
    app = create_app(cfg, store=store, parts=reg, bus=hub, pipeline=pipeline, measurer=measurer,
                     archive=DeviationArchive(tmp_path / "deviations"))  # fmt: skip
    try:
        with uvicorn_server(app, before_stop=hub.close) as port:
            base = f"http://127.0.0.1:{port}"
            with httpx2.Client(base_url=base, timeout=60) as client:
                yield client, base
    finally:
        store.close()


def upload(client, headers=None, n=2000):
    rng = np.random.default_rng(0)
    cloud = npy_bytes(rng.uniform(-50, 50, (n, 3)))
    return client.post("/v1/inspections", files={"file": ("c.npy", cloud)},
                       data={"part": PART}, headers=headers or {})  # fmt: skip


def code(r) -> str:
    return r.json()["error"]["code"]


def test_writes_need_a_key_reads_do_not(line, tmp_path, monkeypatch, upload_measurer):  # noqa: F811
    monkeypatch.setenv(KEYS_ENV, f"other-key, {KEY}")
    with serve(*line, tmp_path, measurer=upload_measurer) as (client, _):
        r = upload(client)
        assert r.status_code == 401 and code(r) == "unauthorized"
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert code(upload(client, {"Authorization": "Bearer not-it"})) == "unauthorized"
        assert client.delete(f"/v1/parts/{PART}").status_code == 401
        assert client.get(f"/v1/parts/{PART}").status_code == 200  # the part is still there
        assert upload(client, {"Authorization": f"Bearer {KEY}"}).status_code == 200
        assert upload(client, {"X-API-Key": KEY}).status_code == 200
        assert client.get("/v1/inspections").json()["items"]  # reads are open
        assert client.get("/metrics").status_code == 200


def test_with_auth_all_reads_need_a_key_too_but_probes_do_not(line, tmp_path, monkeypatch):  # noqa: F811
    monkeypatch.setenv(KEYS_ENV, KEY)
    with serve(*line, tmp_path, auth="all") as (client, _):
        assert client.get("/v1/inspections").status_code == 401
        assert client.get("/metrics").status_code == 401
        assert client.get("/v1/health/live").status_code == 200
        r = client.get("/v1/inspections", headers={"Authorization": f"Bearer {KEY}"})
        assert r.status_code == 200


def test_without_keys_writes_are_refused_beyond_loopback(
    line,  # noqa: F811
    tmp_path,
    monkeypatch,
    upload_measurer,
):
    monkeypatch.delenv(KEYS_ENV, raising=False)
    with serve(*line, tmp_path, host="0.0.0.0", measurer=upload_measurer) as (client, _):
        r = upload(client)
        assert r.status_code == 403 and code(r) == "writes_disabled"
        assert KEYS_ENV in r.json()["error"]["message"]
    with serve(*line, tmp_path, host="127.0.0.1", measurer=upload_measurer) as (client, _):
        assert upload(client).status_code == 200  # this machine's own user, as `make run` has it


def test_a_write_from_another_origin_is_refused(line, tmp_path, monkeypatch, upload_measurer):  # noqa: F811
    """A page an operator opens cannot post to the line, key or not; the API's own pages
    and the configured origins can, and only those get CORS headers on reads."""
    monkeypatch.setenv(KEYS_ENV, KEY)
    auth = {"Authorization": f"Bearer {KEY}"}
    friend = "https://qa-desk.plant.example"
    with serve(*line, tmp_path, allowed_origins=[friend], measurer=upload_measurer) as (
        client,
        base,
    ):
        r = upload(client, {**auth, "Origin": "https://evil.example"})
        assert r.status_code == 403 and code(r) == "origin_refused"
        r = client.delete(f"/v1/parts/{PART}", headers={"Origin": "null"})
        assert r.status_code == 403 and code(r) == "origin_refused"
        assert upload(client, {**auth, "Origin": base}).status_code == 200
        assert upload(client, {**auth, "Origin": friend}).status_code == 200
        r = client.get("/v1/inspections", headers={"Origin": friend})
        assert r.headers["access-control-allow-origin"] == friend
        r = client.get("/v1/inspections", headers={"Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in r.headers


def test_uploads_beyond_the_capacity_get_503_at_once(line, tmp_path, monkeypatch):  # noqa: F811
    """One measuring, none waiting: a second upload is refused before its body is read,
    and the first one's result comes back when it is done."""
    monkeypatch.delenv(KEYS_ENV, raising=False)
    started, release = threading.Event(), threading.Event()

    def slow(part, points, trigger, *, frame):
        started.set()
        release.wait(60)
        return measure_upload(part, points, trigger, frame=frame)

    with serve(*line, tmp_path, pipeline=slow, max_measurements=1,
               max_waiting_measurements=0) as (client, _):  # fmt: skip
        first: dict = {}
        t = threading.Thread(target=lambda: first.setdefault("r", upload(client)))
        t.start()
        try:
            assert started.wait(30)
            r = upload(client)
            assert r.status_code == 503 and code(r) == "busy"
            assert int(r.headers["retry-after"]) > 0
        finally:
            release.set()
            t.join(60)
        assert first["r"].status_code == 200
        assert upload(client).status_code == 200  # the place was given back


def post_whole(url: str, n: int) -> tuple[int, str]:
    """An upload as urllib sends it: the whole body before reading any answer."""
    import json
    import urllib.error
    import urllib.request

    rng = np.random.default_rng(1)
    payload = npy_bytes(rng.uniform(-50, 50, (n, 3)))
    boundary = "b0undary"
    body = (
        (
            f'--{boundary}\r\nContent-Disposition: form-data; name="part"\r\n\r\n{PART}\r\n'
            f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="c.npy"\r\n'
            "Content-Type: application/octet-stream\r\n\r\n"
        ).encode()
        + payload
        + f"\r\n--{boundary}--\r\n".encode()
    )
    req = urllib.request.Request(
        url, data=body, method="POST",
        headers={"Content-Type": f"multipart/form-data; boundary={boundary}"},
    )  # fmt: skip
    try:
        with urllib.request.urlopen(req, timeout=60) as resp:
            return resp.status, ""
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())["error"]["code"]


def test_a_large_upload_refused_unparsed_still_gets_its_answer(line, tmp_path, monkeypatch):  # noqa: F811
    """Refused before it is parsed, a 14 MB upload's body is read and dropped, so that a
    client that sends it whole before reading gets the 401 or 503, not a reset connection."""
    monkeypatch.setenv(KEYS_ENV, KEY)
    with serve(*line, tmp_path, max_upload_mb=30.0) as (_, base):
        assert post_whole(f"{base}/v1/inspections", 600_000) == (401, "unauthorized")
    monkeypatch.delenv(KEYS_ENV)
    started, release = threading.Event(), threading.Event()

    def held(part, points, trigger, *, frame):
        started.set()
        release.wait(60)
        return measure_upload(part, points, trigger, frame=frame)

    with serve(*line, tmp_path, pipeline=held, max_upload_mb=30.0, max_measurements=1,
               max_waiting_measurements=0) as (client, base):  # fmt: skip
        t = threading.Thread(target=upload, args=(client,))
        t.start()
        try:
            assert started.wait(30)  # the first upload holds the one place
            assert post_whole(f"{base}/v1/inspections", 600_000) == (503, "busy")
        finally:
            release.set()
            t.join(60)


@pytest.mark.parametrize("origin", ["ftp://x", "https://host/path", "evil"])
def test_allowed_origins_are_checked_in_the_config(line, origin):  # noqa: F811
    from pydantic import ValidationError

    cfg, _ = line
    with pytest.raises(ValidationError, match="not a web origin"):
        type(cfg.http).model_validate({"allowed_origins": [origin]})


def test_the_schema_states_what_access_asks_for(line, tmp_path, monkeypatch):  # noqa: F811
    monkeypatch.setenv(KEYS_ENV, KEY)
    with serve(*line, tmp_path) as (client, _):
        spec = client.get("/openapi.json").json()
    post = spec["paths"]["/v1/inspections"]["post"]
    assert post["security"] == [{"bearer": []}, {"apiKey": []}]
    assert {"401", "403", "503"} <= set(post["responses"])
    assert "security" not in spec["paths"]["/v1/inspections"]["get"]
    assert "security" not in spec["paths"]["/v1/health"]["get"]
    assert spec["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"
    monkeypatch.delenv(KEYS_ENV)
    with serve(*line, tmp_path) as (client, _):  # loopback without keys: nothing is asked
        spec = client.get("/openapi.json").json()
    assert "security" not in spec["paths"]["/v1/inspections"]["post"]
    assert "securitySchemes" not in spec.get("components", {})


def test_an_upload_is_measured_in_a_process_of_its_own_at_a_lower_priority(
    line,  # noqa: F811
    tmp_path,
    monkeypatch,
    upload_measurer,
):
    """The line shares its process with the API: an upload measured there would hold the
    interpreter's lock the line's threads need. It is measured in a measuring process,
    niced, with the same result as on a thread of the API's own."""
    monkeypatch.delenv(KEYS_ENV, raising=False)
    with serve(*line, tmp_path, measurer=upload_measurer) as (client, _):
        r = upload(client, n=5000)
        assert r.status_code == 200, r.text
        by_process = r.json()
    (pid,) = upload_measurer.pids()
    assert pid != os.getpid()
    lowest = 19  # the kernel's cap: a niced test run's child ends there
    assert os.getpriority(os.PRIO_PROCESS, pid) == min(
        os.getpriority(os.PRIO_PROCESS, 0) + NICE, lowest
    )
    with serve(*line, tmp_path / "thread", pipeline=measure_upload) as (client, _):
        by_thread = upload(client, n=5000).json()
    for key in ("status", "transform", "rms_mm", "comparison", "defects", "field"):
        assert by_process[key] == by_thread[key], key


def _kill_and_wait(pid: int) -> None:
    fd = os.pidfd_open(pid)
    try:
        os.kill(pid, signal.SIGKILL)
        assert select.select([fd], [], [], 60.0)[0], "a killed process did not end"
    finally:
        os.close(fd)


def _cpu_s(pid: int) -> float:
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_a_measuring_process_that_dies_costs_its_own_upload_a_503_and_no_other(
    line,  # noqa: F811
    tmp_path,
    monkeypatch,
):
    """Killed while it measures, a measuring process answers that upload 503; killed
    while idle, it costs nothing; the API goes on measuring either way."""
    monkeypatch.delenv(KEYS_ENV, raising=False)
    measurer = UploadMeasurer(1)
    try:
        with serve(*line, tmp_path, measurer=measurer, max_upload_mb=60.0) as (client, _):
            assert upload(client).status_code == 200
            (pid,) = measurer.pids()
            _kill_and_wait(pid)
            assert upload(client).status_code == 200  # started again for it
            (pid,) = measurer.pids()
            # A large cloud, killed once its process has spent a second measuring it.
            answer: dict = {}
            t = threading.Thread(target=lambda: answer.setdefault("r", upload(client, n=1_500_000)))
            before = _cpu_s(pid)
            t.start()
            try:
                while _cpu_s(pid) < before + 1.0 and t.is_alive():
                    t.join(0.05)  # the upload's answer, or a second of measuring
                _kill_and_wait(pid)
            finally:
                t.join(120)
            assert not t.is_alive(), "the upload was not answered"
            r = answer["r"]
            assert r.status_code == 503 and code(r) == "measurer_died", r.text
            assert int(r.headers["retry-after"]) > 0
            assert upload(client).status_code == 200  # a new process, the place given back
            assert measurer.pids() and measurer.pids() != [pid]
            assert client.get("/v1/health/live").status_code == 200
    finally:
        measurer.close()


def test_a_measurer_closed_mid_upload_answers_it_and_leaves_no_process(
    line,  # noqa: F811
    tmp_path,
    monkeypatch,
):
    """An API stopping while an upload is measured waits for it only so long: past that
    the upload is answered 503, its process is gone, and later uploads are refused."""
    monkeypatch.delenv(KEYS_ENV, raising=False)
    measurer = UploadMeasurer(1, close_s=0.0)
    try:
        with serve(*line, tmp_path, measurer=measurer, max_upload_mb=60.0) as (client, _):
            assert upload(client).status_code == 200
            (pid,) = measurer.pids()
            answer: dict = {}
            t = threading.Thread(target=lambda: answer.setdefault("r", upload(client, n=1_500_000)))
            before = _cpu_s(pid)
            t.start()
            try:
                while _cpu_s(pid) < before + 1.0 and t.is_alive():
                    t.join(0.05)  # the upload's answer, or a second of measuring
                measurer.close()
            finally:
                t.join(120)
            assert not t.is_alive(), "the upload was not answered"
            r = answer["r"]
            assert r.status_code == 503 and code(r) == "measurer_died", r.text
            assert measurer.pids() == []
            with pytest.raises(ProcessLookupError):
                os.kill(pid, 0)  # ended and reaped
            r = upload(client)
            assert r.status_code == 503 and code(r) == "measurer_died", r.text
            assert client.get("/v1/health/live").status_code == 200
    finally:
        measurer.close()
