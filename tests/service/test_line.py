"""The whole line, in one process and as separate processes, seen from outside."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from pathlib import Path

import pytest
import zenoh
from linekit import LINE, ROOT, STATION, client, free_port

from service import bus
from service.config import load_line_config
from service.line import start_line
from service.protocol import Keys
from service.recorder import read_recording
from service.worker import result_from_json

HERE = Path(__file__).parent
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


@pytest.fixture(scope="module")
def trees(tmp_path_factory) -> Path:
    """One tree cache for the module: the API's trees are built once, then loaded."""
    return tmp_path_factory.mktemp("trees")


def line_file(tmp_path: Path, trees: Path, period_s: float = 0.5) -> Path:
    """A copy of the default line with the repo's parts, a shared tree cache, a faster trigger."""
    text = (ROOT / "configs" / "line.toml").read_text()
    text = text.replace('parts_dir = "parts"', f'parts_dir = "{ROOT / "configs" / "parts"}"')
    text = text.replace('trees_dir = "trees"', f'trees_dir = "{trees}"')
    text = text.replace("trigger_period_s = 2.0", f"trigger_period_s = {period_s}")
    path = tmp_path / "line.toml"
    path.write_text(text)
    return path


def config(tmp_path: Path, trees: Path, port: int, http_port: int):
    return load_line_config(
        line_file(tmp_path, trees),
        overrides={
            ("storage", "data_dir"): str(tmp_path / "data"),
            ("zenoh", "listen"): [f"tcp/127.0.0.1:{port}"],
            ("http", "port"): http_port,
        },
    )


def get_json(url: str):
    """The JSON body of a GET, whatever the status (503 is a valid "not ready yet")."""
    try:
        with urllib.request.urlopen(url, timeout=10) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def read_lines(proc: subprocess.Popen, until: str) -> list[dict]:
    out = []
    for raw in proc.stdout:
        doc = json.loads(raw)
        out.append(doc)
        if doc["kind"] == until:
            break
    return out


def test_line_in_one_process_serves_zenoh_rest_and_mcap(tmp_path, trees):
    port, http_port = free_port(), free_port()
    cfg = config(tmp_path, trees, port, http_port)
    h = start_line(cfg)
    try:
        sub = subprocess.Popen(
            [sys.executable, str(HERE / "doc_subscriber.py"), f"tcp/127.0.0.1:{port}", LINE, "2"],
            stdout=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        try:
            docs = read_lines(sub, "done")
            assert sub.wait(60) == 0
        finally:
            sub.kill()
        assert h.api is not None, "the REST API did not come up"
        base = f"http://127.0.0.1:{h.api.port}"
        code, health = get_json(f"{base}/v1/health")
        assert code in (200, 503) and health["checks"]["zenoh"] is True
        code, page = get_json(f"{base}/v1/inspections?limit=100")
        assert code == 200 and len(page["items"]) >= 2
        code, one = get_json(f"{base}/v1/inspections/{page['items'][0]['id']}")
        assert code == 200 and one["cad_hash"] and one["serial"]
    finally:
        h.close()
    results = [d for d in docs if d["kind"] == "result"]
    frames = [d for d in docs if d["kind"] == "frameset"]
    assert len(results) == 2 and frames
    assert docs[-1]["our_modules"] == []  # the subscriber knows only the documented protocol
    for r in results:
        assert r["line"] == LINE and r["station"] == STATION
        assert r["cad_hash"] and r["tree_hash"] and r["calibration_id"] and r["software_version"]
    # Every result is in the store and in the recording.
    db = sqlite3.connect(cfg.storage.database_path())
    ids = {row[0] for row in db.execute("SELECT id FROM results")}
    db.close()
    _, recorded = read_recording(h.recorder.files)
    assert {r["id"] for r in results} <= ids == {t.result.id for t in recorded}
    assert len(ids) == h.counter.count


def wait_for_token(session: zenoh.Session, key: str, timeout_s: float) -> bool:
    """Wait for a liveliness token (a worker that is ready) to appear."""
    got = threading.Event()
    sub = session.liveliness().declare_subscriber(key, zenoh.handlers.FifoChannel(16), history=True)
    try:
        deadline = threading.Event()
        for _ in range(int(timeout_s / 0.1)):
            if sub.handler.try_recv() is not None:
                got.set()
                break
            deadline.wait(0.1)
    finally:
        sub.undeclare()
    return got.is_set()


def cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "service.cli", *args],
        env=ENV,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def stop(proc: subprocess.Popen) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(60)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise


def test_line_as_separate_processes(tmp_path, trees):
    port, http_port = free_port(), free_port()
    ep = f"tcp/127.0.0.1:{port}"
    cfg_path = str(line_file(tmp_path, trees))
    common = ["--config", cfg_path, "--data-dir", str(tmp_path / "data")]
    keys = Keys(LINE)
    router = cli("router", "--zenoh-listen", ep)
    procs = [router]
    try:
        assert router.stdout.readline().startswith("zenoh router listening")
        with bus.open_session(client(port)) as session:
            got: list = []
            three = threading.Event()

            def on_result(sample):
                got.append(result_from_json(sample.payload.to_bytes()))
                if len(got) >= 3:
                    three.set()

            results = bus.RingSubscriber(session, keys.results(), on_result, capacity=64)
            try:
                worker = cli("worker", *common, "--zenoh-connect", ep)
                api = cli("api", *common, "--zenoh-connect", ep, "--http-port", str(http_port))
                procs += [worker, api]
                assert wait_for_token(session, keys.workers(), 60), worker.stderr.read()
                ingest = cli("ingest", *common, "--zenoh-connect", ep, "--count", "3")
                procs.append(ingest)
                assert three.wait(90), ingest.stderr.read()
                assert ingest.wait(60) == 0
            finally:
                results.close()
        assert [r.seq for r in sorted(got, key=lambda r: r.seq)] == [0, 1, 2]
        assert all(r.status.value != "missed" for r in got)
        for p in (worker, api):
            assert stop(p) == 0, p.stderr.read()[-2000:]
    finally:
        for p in procs:
            if p.poll() is None:
                stop(p)
    assert stop(router) == 0
    db = sqlite3.connect(tmp_path / "data" / "results.sqlite")
    assert db.execute("SELECT count(*) FROM results").fetchone()[0] == 3
    db.close()


def test_cli_run_stops_after_n_parts(tmp_path, trees):
    """``inspection run --parts N`` exits 0 once N results are in, every one stored.

    SIGINT takes the same path as the separate processes above (one handler
    for every command), which that test checks for worker, API and router.
    """
    port = free_port()
    common = ["--config", str(line_file(tmp_path, trees)), "--http-port", str(free_port()),
              "--zenoh-listen", f"tcp/127.0.0.1:{port}"]  # fmt: skip
    done = cli("run", *common, "--data-dir", str(tmp_path / "a"), "--parts", "2")
    assert done.wait(120) == 0, done.stderr.read()[-2000:]
    out = done.stdout.read()
    assert "API docs: http://" in out and "stopped after" in out
    db = sqlite3.connect(tmp_path / "a" / "results.sqlite")
    assert db.execute("SELECT count(*) FROM results").fetchone()[0] >= 2
    db.close()
