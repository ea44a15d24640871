"""The line's metrics as Prometheus and Grafana read them.

One ``inspection run`` for the module (small images, one matching pass) measures
a few parts; its REST API's ``/metrics`` then carries the worker's series beside
the API's own, parsed with ``prometheus_client``'s own text parser. The Grafana
dashboard in docs/ is checked against that scrape: every series an expression
names is one the line exports, with the labels the expression uses. Missed
triggers and the queue are counted on a worker of quick stages. (The worker on
its own, on its metrics port: tests/service/test_line.py.)
"""

from __future__ import annotations

import json
import re
import threading
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from linekit import LINE, PART, PARTS_DIR, ROOT, STATION, client, free_port, rig
from prometheus_client.parser import text_string_to_metric_families
from test_line import cli, line_file, stop
from test_worker import QUICK, job, pipeline

from inspection.measure import PartModel
from inspection.panel import sheet_metal_panel
from inspection.rig import Rig
from service import bus
from service.config import load_part_spec
from service.metrics import Metrics, worker_collector
from service.parts import LoadedPart, measure_params
from service.protocol import Keys
from service.worker import JobQueue, Worker

DASHBOARD = ROOT / "docs" / "grafana-dashboard.json"
SIZE = (640, 512)
PARTS = 2

# PromQL words that are not series: functions are told apart by the "(" after them.
KEYWORDS = {"by", "without", "on", "ignoring", "group_left", "group_right", "offset", "bool",
            "and", "or", "unless", "inf", "nan"}  # fmt: skip


@pytest.fixture(scope="module")
def scrape(tmp_path_factory, trees) -> Iterator[dict]:
    """The text of the line's ``/metrics`` once the worker has answered ``PARTS`` triggers."""
    tmp = tmp_path_factory.mktemp("metrics")
    rig_file = tmp / "rig.toml"
    Rig.default().with_image_size(*SIZE).save(rig_file)
    config = line_file(tmp, trees, period_s=1.0, queue_size=8)
    text = config.read_text()
    for old, new in [
        ("[station]\n", f'[station]\nrig_calibration = "{rig_file}"\n'),
        ("guided_matching = true", "guided_matching = false"),
    ]:
        assert old in text, old
        text = text.replace(old, new, 1)
    config.write_text(text)
    port, http_port = free_port(), free_port()
    run = cli("run", "--config", str(config), "--data-dir", str(tmp / "data"),
              "--http-port", str(http_port), "--zenoh-listen", f"tcp/127.0.0.1:{port}")  # fmt: skip
    try:
        for out in run.stdout:
            if out.strip().startswith("data:"):
                break
        else:
            pytest.fail(f"the line did not start: {run.stderr.read()[-3000:]}")
        arrived = threading.Semaphore(0)
        with bus.open_session(client(port)) as session:
            sub = bus.RingSubscriber(
                session, Keys(LINE).results(), lambda s: arrived.release(), capacity=16
            )
            try:
                # The worker counts and times a result before it publishes it.
                for _ in range(PARTS):
                    assert arrived.acquire(timeout=180), "no result from the line"
            finally:
                sub.close()
        base = f"http://127.0.0.1:{http_port}"
        # As a scraper finds it: some requests answered already (their series are made
        # on the first one).
        with urllib.request.urlopen(f"{base}/v1/health", timeout=30) as r:
            assert r.status == 200
        with urllib.request.urlopen(f"{base}/metrics", timeout=30) as r:
            body = r.read().decode()
            ctype = r.headers["content-type"]
        yield {"text": body, "content_type": ctype}
    finally:
        code = stop(run)
    assert code == 0, run.stderr.read()[-3000:]


def families(text: str) -> dict:
    return {f.name: f for f in text_string_to_metric_families(text)}


def exported(text: str) -> dict[str, set[str]]:
    """Every series name a scrape shows (``_total``, ``_bucket``, ...) and the labels seen
    on it; a family without samples yet names its series all the same."""
    names: dict[str, set[str]] = {}
    suffixes = {"counter": ("_total",), "histogram": ("_bucket", "_count", "_sum"),
                "gauge": ("",), "summary": ("", "_count", "_sum")}  # fmt: skip
    for f in text_string_to_metric_families(text):
        for suffix in suffixes.get(f.type, ("",)):
            names.setdefault(f.name + suffix, set())
        for s in f.samples:
            names.setdefault(s.name, set()).update(s.labels)
    return names


def selectors(expr: str) -> list[tuple[str, set[str]]]:
    """The series an expression selects, each with the label names it matches on."""
    found = []
    bare = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)  # no identifiers inside strings
    bare = re.sub(r"\[[^\]]*\]", "", bare)  # range durations
    # Label lists of aggregations and vector matching are labels, not series.
    bare = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", " ", bare)
    for m in re.finditer(r"([A-Za-z_:][A-Za-z0-9_:]*)\s*(\{[^}]*\})?\s*(\()?", bare):
        name, matchers, call = m.group(1), m.group(2), m.group(3)
        if call or name.lower() in KEYWORDS:
            continue
        labels = set(re.findall(r"([A-Za-z_][A-Za-z0-9_]*)\s*(?:=~|!~|!=|=)", matchers or ""))
        found.append((name, labels))
    return found


def dashboard_exprs(dash: dict) -> list[str]:
    exprs = [t["expr"] for p in dash["panels"] for t in p.get("targets", [])]
    for v in dash["templating"]["list"]:
        if v["type"] == "query":
            query = v["query"]["query"]
            exprs.append(re.fullmatch(r"label_values\((.*),\s*\w+\)", query).group(1))
    return exprs


def unknown(exprs: list[str], names: dict[str, set[str]]) -> list[str]:
    """What in ``exprs`` names a series (or a label of one) that ``names`` lacks."""
    bad = []
    for expr in exprs:
        picked = selectors(expr)
        if not picked:
            bad.append(f"{expr!r} selects no series")
        for name, labels in picked:
            if name not in names:
                bad.append(f"{expr!r}: no series {name}")
            elif names[name] and not labels <= names[name] | {"le"}:
                bad.append(f"{expr!r}: {name} has no label {sorted(labels - names[name])}")
    return bad


def test_the_apis_metrics_carry_the_workers_series_per_station(scrape):
    assert scrape["content_type"].startswith("text/plain; version=")
    fams = families(scrape["text"])
    own = {"line": LINE, "station": STATION}
    results = fams["inspection_worker_results"]
    assert results.type == "counter"
    answered = [s for s in results.samples if s.name.endswith("_total")]
    assert all(s.labels.keys() == {"line", "station", "status"} for s in answered)
    assert sum(s.value for s in answered if s.labels.items() >= own.items()) >= PARTS
    stages = {s.labels["stage"]: s.value for s in fams["inspection_stage_seconds"].samples
              if s.name.endswith("_count") and s.labels.items() >= own.items()}  # fmt: skip
    assert stages and all(n >= 1 for n in stages.values()), stages
    latency = {s.name: s.value for s in fams["inspection_latency_seconds"].samples
               if s.labels == own}  # fmt: skip
    n, total_s = (
        latency["inspection_latency_seconds_count"],
        latency["inspection_latency_seconds_sum"],
    )
    assert n >= PARTS and 0 < total_s < 60 * n  # seconds, not nanoseconds or milliseconds
    [capacity] = fams["inspection_worker_queue_capacity"].samples
    assert capacity.labels == own and capacity.value == 8
    [info] = fams["inspection_executor_info"].samples
    assert info.labels == {**own, "kind": "in-process"}
    jobs = [s for s in fams["inspection_executor_job_seconds"].samples
            if s.name.endswith("_count")]  # fmt: skip
    assert [s.labels["worker"] for s in jobs] == ["in-process"] and jobs[0].value >= PARTS
    # The API's own series, on the same registry.
    assert fams["inspection_ready"].samples[0].value == 1
    assert sum(s.value for s in fams["inspection_results_stored"].samples) >= PARTS


def test_missed_triggers_and_the_queue_are_counted_per_station_and_cause():
    """A full queue and a gap in the seq numbers, on a worker of quick stages: each missed
    trigger under its cause, with the station's labels; the queue's depth as it stands."""
    spec = load_part_spec(PARTS_DIR / f"{PART}.toml")
    model = PartModel.build(sheet_metal_panel(name=PART), spacing_mm=5.0, alignment=False)
    part = LoadedPart(spec, model, "quick-tree", measure_params(spec))
    sim = rig(QUICK, part, seed=3)
    sets = [sim.capture(seq, 1_800_000_000_000_000_000 + seq * 10**9) for seq in range(6)]
    metrics = Metrics()
    q = JobQueue(2)
    w = Worker(pipeline(part), q, [], line=LINE, station=STATION, metrics=metrics)
    metrics.collector(worker_collector(w.stats, q.depth, q.capacity, line=LINE, station=STATION))
    for fs in sets[:4]:  # two more than the queue holds: the oldest two are dropped
        q.put(job(fs))
    waiting = families(metrics.render().decode())["inspection_worker_queue_depth"].samples
    assert [(s.labels, s.value) for s in waiting] == [({"line": LINE, "station": STATION}, 2)]
    while (item := q.get(0)) is not None:
        w.handle(item)
    w.handle(job(sets[5]))  # seq 4 never arrives
    fams = families(metrics.render().decode())
    missed = {s.labels["cause"]: s.value for s in fams["inspection_worker_missed"].samples
              if s.name.endswith("_total")}  # fmt: skip
    assert missed == {"queue_full": 2, "never_arrived": 1}
    by_status = {s.labels["status"]: s.value for s in fams["inspection_worker_results"].samples
                 if s.name.endswith("_total")}  # fmt: skip
    assert by_status == {"missed": 3, "pass": 3}
    assert {s.labels["station"] for f in fams.values() for s in f.samples} == {STATION}
    # Missed triggers were never measured: they have no stage times.
    timed = {s.labels["stage"]: s.value for s in fams["inspection_stage_seconds"].samples
             if s.name.endswith("_count")}  # fmt: skip
    assert timed == {"reconstruct": 3, "total": 3}


def test_every_dashboard_expr_names_a_series_the_line_exports(scrape):
    dash = json.loads(DASHBOARD.read_text())
    exprs = dashboard_exprs(dash)
    assert len(exprs) > 20
    assert unknown(exprs, exported(scrape["text"])) == []


def test_the_expr_check_finds_a_misnamed_series_or_label():
    names = {"inspection_latency_seconds_bucket": {"line", "station", "le"}, "up": set()}
    good = 'histogram_quantile(0.5, sum by (le) (rate(inspection_latency_seconds_bucket{station=~"$s"}[5m])))'  # noqa: E501
    assert unknown([good, "min(up)"], names) == []
    assert unknown(["rate(inspection_latency_second_bucket[5m])"], names)
    assert unknown(['inspection_latency_seconds_bucket{cell="a"}'], names)
    assert unknown(["sum(rate(x[5m])) or vector(0)"], {"x": set()}) == []
    assert unknown(["vector(1)"], names)  # names no series at all


def test_the_dashboard_is_a_grafana_json_model():
    dash = json.loads(DASHBOARD.read_text())
    assert dash["title"] and re.fullmatch(r"[A-Za-z0-9_-]{1,40}", dash["uid"])
    assert isinstance(dash["schemaVersion"], int) and dash["schemaVersion"] >= 36
    variables = {v["name"]: v for v in dash["templating"]["list"]}
    assert variables["datasource"]["type"] == "datasource"
    assert variables["datasource"]["query"] == "prometheus"
    ids = [p["id"] for p in dash["panels"]]
    assert len(ids) == len(set(ids))
    cells: set[tuple[int, int]] = set()
    for p in dash["panels"]:
        assert p["type"] in {"row", "timeseries", "stat", "table", "heatmap", "gauge"}, p
        g = p["gridPos"]
        assert all(isinstance(g[k], int) for k in "xywh") and 0 <= g["x"] and g["x"] + g["w"] <= 24
        here = {(g["x"] + dx, g["y"] + dy) for dx in range(g["w"]) for dy in range(g["h"])}
        assert not here & cells, f"panel {p['title']!r} overlaps another"
        cells |= here
        if p["type"] == "row":
            assert p["panels"] == [] and not p.get("targets")
            continue
        assert p["datasource"] == {"type": "prometheus", "uid": "${datasource}"}
        refs = [t["refId"] for t in p["targets"]]
        assert refs and len(refs) == len(set(refs))
        for t in p["targets"]:
            assert t["datasource"] == p["datasource"] and t["expr"].strip()
            used = set(re.findall(r"\$(\w+)", t["expr"]))
            assert used <= set(variables), (p["title"], used)


def test_the_readme_points_at_the_dashboard():
    readme = (ROOT / "README.md").read_text()
    assert str(DASHBOARD.relative_to(ROOT)) in readme
    assert Path(DASHBOARD).is_file()
