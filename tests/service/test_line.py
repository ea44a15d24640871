"""The whole line, in one process and as separate processes, seen from outside."""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from pathlib import Path

import psycopg
import pytest
import zenoh
from linekit import LINE, ROOT, STATION, client, free_port

from service import bus
from service.protocol import Keys
from service.recorder import read_recording
from service.worker import result_from_json

HERE = Path(__file__).parent
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


def line_file(
    tmp_path: Path,
    trees: Path,
    period_s: float = 2.0,
    queue_size: int = 4,
    metrics_port: int = 0,
    parts: tuple[str, ...] = ("demo-panel",),
    sends: tuple[str, ...] | None = None,
) -> Path:
    """A copy of the default line with the repo's parts and the session's tree cache; a
    worker on its own serves its metrics on ``metrics_port`` (0: any free port). The
    station holds ``parts`` (the default line's first alone: its plumbing is the same)
    and the simulator sends ``sends`` (None: all of them)."""
    text = (ROOT / "configs" / "line.toml").read_text()
    held = 'parts = ["demo-panel", "demo-panel-features"]\n'
    assert held in text, "the default line's parts changed: update line_file"
    text = text.replace(held, f"parts = {json.dumps(list(parts))}\n")
    if sends is not None:
        text = text.replace('# parts = ["demo-panel"]', f"parts = {json.dumps(list(sends))}")
    text = text.replace('parts_dir = "parts"', f'parts_dir = "{ROOT / "configs" / "parts"}"')
    text = text.replace('trees_dir = "trees"', f'trees_dir = "{trees}"')
    text = text.replace("trigger_period_s = 2.0", f"trigger_period_s = {period_s}")
    text = text.replace("queue_size = 4 ", f"queue_size = {queue_size} ")
    text = text.replace("metrics_port = 9464 ", f"metrics_port = {metrics_port} ")
    path = tmp_path / "line.toml"
    path.write_text(text)
    return path


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


def get_bytes(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as resp:
            return resp.status, resp.headers.get("content-type", ""), resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers.get("content-type", ""), exc.read()


def test_cli_run_serves_zenoh_rest_and_mcap(tmp_path, trees):
    """``inspection run``: the whole line in one process on the flash rig.

    A subscriber written from docs/protocol.md receives frames and results;
    the REST API is ready (parts loaded and warmed up) as soon as it answers,
    serves the results and their colour maps; SIGINT stops the line with exit
    code 0, every result stored and recorded.
    """
    port, http_port = free_port(), free_port()
    data = tmp_path / "data"
    # A short queue: SIGINT lets the worker finish what it accepted, and no more
    # than one part waits (the flash rig takes seconds per part on this machine).
    # make run's parts, the simulator sending the one with holes, trim edges and an RPS.
    features = "demo-panel-features"
    config = line_file(tmp_path, trees, period_s=3.0, queue_size=1,
                       parts=("demo-panel", features), sends=(features,))  # fmt: skip
    run = cli("run", "--config", str(config), "--data-dir", str(data),
              "--http-port", str(http_port), "--zenoh-listen", f"tcp/127.0.0.1:{port}")  # fmt: skip
    try:
        for text in run.stdout:
            if text.strip().startswith("data:"):
                break  # the line is up: parts loaded, API started, ingest triggering
        else:
            pytest.fail(f"the line did not start: {run.stderr.read()[-3000:]}")
        base = f"http://127.0.0.1:{http_port}"
        code, health = get_json(f"{base}/v1/health")
        assert code == 200 and health["checks"]["zenoh"] is True, health
        sub = subprocess.Popen(
            [sys.executable, str(HERE / "doc_subscriber.py"), f"tcp/127.0.0.1:{port}", LINE, "1"],
            stdout=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        try:
            docs = read_lines(sub, "done")
            assert sub.wait(120) == 0
        finally:
            sub.kill()
        code, page = get_json(f"{base}/v1/inspections?limit=100")
        assert code == 200 and page["items"]
        measured = [r for r in page["items"] if r["status"] in ("pass", "fail", "not_measurable")]
        assert measured, page["items"]
        code, one = get_json(f"{base}/v1/inspections/{measured[0]['id']}")
        assert code == 200 and one["cad_hash"] and one["serial"] and one["tree_hash"]
        code, ctype, png = get_bytes(f"{base}/v1/inspections/{measured[0]['id']}/colormap.png")
        assert code == 200 and ctype == "image/png" and png[:8] == b"\x89PNG\r\n\x1a\n"
        assert one["part"] == features and one["status"] in ("pass", "fail"), one["reason"]
        code, part = get_json(f"{base}/v1/parts/{features}")
        assert code == 200 and part["state"] == "ready" and part["tree_hash"] == one["tree_hash"]
        kinds = {c["name"]: c["kind"] for c in one["comparison"]}
        for name in ("H1.x", "H1.y", "H1.d", "S2.len", "H3.d"):
            assert kinds[name] == "hole"
        assert kinds["E1.trim"] == kinds["E3.trim_max"] == "trim_edge"
        holes = [c for c in one["comparison"] if c["kind"] in ("hole", "trim_edge")]
        assert all(c["verdict"] in ("pass", "fail") for c in holes), holes
        # The RPS places H1 on its nominal (it fixes x and y, 3-2-1): measured again at the
        # pose it gave, it is found there within the edge search's repeatability.
        assert all(abs(c["deviation_mm"]) < 0.02 for c in holes if c["name"] in ("H1.x", "H1.y"))
    finally:
        code = stop(run)
    assert code == 0, run.stderr.read()[-3000:]
    out = run.stdout.read()
    assert "stopped after" in out
    results = [d for d in docs if d["kind"] == "result"]
    framed = {d["serial"] for d in docs if d["kind"] == "frameset"}
    # The subscriber may join between a part's frames and its result; it stops at
    # the first result of a part whose frames it saw.
    assert results and results[-1]["serial"] in framed
    assert all(r["serial"] not in framed for r in results[:-1])
    assert docs[-1]["our_modules"] == []  # the subscriber knows only the documented protocol
    for r in results:
        assert r["line"] == LINE and r["station"] == STATION
        assert r["cad_hash"] and r["tree_hash"] and r["calibration_id"] and r["software_version"]
    # Every result is in the store and in the recording; measured ones kept their deviations.
    db = sqlite3.connect(data / "results.sqlite")
    rows = dict(db.execute("SELECT id, status FROM results").fetchall())
    db.close()
    assert len(rows) >= 1
    _, recorded = read_recording(sorted((data / "mcap").glob("*.mcap")))
    assert {r["id"] for r in results} <= set(rows) == {t.result.id for t in recorded}
    for id_, status in rows.items():
        kept = (data / "deviations" / f"{id_}.npz").is_file()
        assert kept == (status in ("pass", "fail", "not_measurable")), (id_, status)


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


def cli(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "service.cli", *args],
        env={**ENV, **(env or {})},
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
    port, http_port, metrics_port = free_port(), free_port(), free_port()
    ep = f"tcp/127.0.0.1:{port}"
    cfg_path = str(line_file(tmp_path, trees, metrics_port=metrics_port))
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
                assert wait_for_token(session, keys.workers(), 300), worker.stderr.read()
                ingest = cli("ingest", *common, "--zenoh-connect", ep, "--count", "3")
                procs.append(ingest)
                assert three.wait(180), ingest.stderr.read()
                assert ingest.wait(60) == 0
            finally:
                results.close()
        assert [r.seq for r in sorted(got, key=lambda r: r.seq)] == [0, 1, 2]
        assert all(r.status.value != "missed" for r in got)
        # The worker has no API of its own: its metrics are on a port of their own.
        from prometheus_client.parser import text_string_to_metric_families

        with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10) as r:
            families = {f.name: f for f in text_string_to_metric_families(r.read().decode())}
        answered = sum(s.value for s in families["inspection_worker_results"].samples)
        assert answered == 3  # the three triggers; the warm-up is not counted
        assert families["inspection_stage_seconds"].type == "histogram"
        assert families["inspection_worker_queue_capacity"].samples[0].value == 4
        own = {"line": LINE, "station": STATION}
        latency = {s.name: s for s in families["inspection_latency_seconds"].samples
                   if s.labels == own}  # fmt: skip
        assert latency["inspection_latency_seconds_count"].value == 3
        assert latency["inspection_latency_seconds_sum"].value > 0
        [info] = families["inspection_executor_info"].samples
        assert info.labels == {**own, "kind": "in-process"}
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


@pytest.mark.parametrize("store", ["sqlite", "postgresql"])
def test_cli_run_stops_by_itself_after_n_parts(tmp_path, trees, store, request):
    """``inspection run --parts N``: the line stops on its own after N results, exit
    code 0, with every result it counted stored (in the SQLite file, or in the
    PostgreSQL database that ``$INSPECTION_STORAGE_URL`` names) and recorded."""
    port, http_port = free_port(), free_port()
    data = tmp_path / "data"
    config = line_file(tmp_path, trees, period_s=1.0, queue_size=1)
    url = request.getfixturevalue("pg_server").new_database() if store == "postgresql" else None
    first_start = not [p for p in trees.glob("*.npz") if "-align-" not in p.name]
    run = cli("run", "--config", str(config), "--data-dir", str(data), "--parts", "2",
              "--http-port", str(http_port), "--zenoh-listen", f"tcp/127.0.0.1:{port}",
              env={"INSPECTION_STORAGE_URL": url} if url else None)  # fmt: skip
    try:
        out, err = run.communicate(timeout=300)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, err[-3000:]
    # Start-up names its phases, and tells a first start (no cached tree) from a later one.
    assert "kernels: " in out and "part demo-panel: loading CAD" in out
    assert "warm-up: measured in " in out
    for k in (1, 2, 3):  # the kernels' warm-up, step by step: minutes on a first start
        assert f"part demo-panel: warm-up {k}/3: " in out, out
    ready = re.search(r"station \S+: parts ready in [\d.]+ s; (.*)", out)
    assert ready is not None, out
    if first_start:
        assert ready.group(1) == "trees built for demo-panel (first start)", out
        assert "part demo-panel: no cached tree: building it (a first start" in out
    else:
        assert ready.group(1) == "every tree loaded from the cache", out
        assert "part demo-panel: tree loaded from the cache" in out and "building it" not in out
    counted = re.search(r"stopped after (\d+) results", out)
    assert counted is not None, out
    n = int(counted.group(1))
    assert n >= 2
    if url is None:
        db = sqlite3.connect(data / "results.sqlite")
        rows = {r[0] for r in db.execute("SELECT id FROM results").fetchall()}
        db.close()
    else:
        assert f"results: {url}" in out and not (data / "results.sqlite").exists()
        with psycopg.connect(url) as pg:
            rows = {r[0] for r in pg.execute("SELECT id FROM results").fetchall()}
    _, recorded = read_recording(sorted((data / "mcap").glob("*.mcap")))
    assert len(rows) == n and {t.result.id for t in recorded} == rows
