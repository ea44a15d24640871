"""docker/compose.yaml and docker/Dockerfile, checked without pulling or building an image.

Images cannot be pulled everywhere the tests run, so the files are read: the
compose file's services, ports, volumes and health checks, and every command
(the services', the image's and its build-time warm-up) parsed by the CLI's own
argparse parser and turned into the line config the process would run with,
without running it. The health checks' own commands run against small HTTP
servers answering as a ready and a not-ready process would. Where Docker's
compose plugin is installed, ``docker compose config`` validates the file too.
"""

from __future__ import annotations

import argparse
import http.server
import json
import re
import shlex
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

yaml = pytest.importorskip("yaml", reason="the compose file's test reads it with PyYAML")

REPO = Path(__file__).resolve().parents[1]
DOCKER = REPO / "docker"
COMPOSE = DOCKER / "compose.yaml"
DOCKERFILE = DOCKER / "Dockerfile"
OURS = {"worker", "api", "ingest"}
ROUTER = "zenoh"
MONITORING = {"prometheus", "grafana"}


@pytest.fixture(scope="module")
def compose() -> dict:
    doc = yaml.safe_load(COMPOSE.read_text())
    assert isinstance(doc, dict)
    return doc


@pytest.fixture(scope="module")
def dockerfile() -> list[str]:
    """The Dockerfile's instructions, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    lines = (ln.strip() for ln in text.splitlines())
    return [ln for ln in lines if ln and not ln.startswith("#")]


def parse(argv: list[str]) -> argparse.Namespace:
    """``argv`` (``inspection ...``) through the CLI's own parser, without running it."""
    from service.cli import build_parser

    assert argv[0] == "inspection", argv
    try:
        return build_parser().parse_args(argv[1:])
    except SystemExit as exc:
        pytest.fail(f"not a valid invocation of our CLI ({exc.code}): {shlex.join(argv)}")


def image_env(instructions: list[str]) -> dict[str, str]:
    """The INSPECTION_* variables the image sets (ENV lines)."""
    env = {}
    for ins in instructions:
        if ins.startswith("ENV "):
            env.update(re.findall(r"(INSPECTION_\w+)=(\S+)", ins))
    return env


def host_port(published: str) -> tuple[str, int, int]:
    host, outside, inside = published.split(":")
    return host, int(outside), int(inside)


def test_the_services_are_the_router_and_our_three_processes(compose):
    assert set(compose["services"]) == OURS | {ROUTER} | MONITORING
    # A plain `up` starts the line alone; monitoring is asked for.
    profiles = {name: svc.get("profiles", []) for name, svc in compose["services"].items()}
    assert {name for name, p in profiles.items() if p} == MONITORING
    assert all(profiles[name] == ["monitoring"] for name in MONITORING)
    router = compose["services"][ROUTER]
    assert router["image"].startswith("eclipse/zenoh:")
    assert "--no-multicast-scouting" in router["command"]
    listen = router["command"][router["command"].index("-l") + 1]
    assert listen == "tcp/0.0.0.0:7447"


def test_every_process_of_ours_is_the_image_on_the_data_volume(compose):
    assert "data" in compose["volumes"]
    for name in OURS:
        svc = compose["services"][name]
        build = svc["build"]
        assert (COMPOSE.parent / build["context"] / build["dockerfile"]).resolve() == DOCKERFILE
        assert "data:/data" in svc["volumes"], name
        assert svc["restart"] == "unless-stopped"


@pytest.mark.parametrize("name", sorted(OURS))
def test_each_command_is_a_valid_invocation_of_our_cli(compose, dockerfile, name, monkeypatch):
    """The service's command parses, names its own subcommand, connects to the router by
    its service name and port, and gives the config its settings say (ports included)."""
    from service.commands.line import _config

    svc = compose["services"][name]
    args = parse(svc["command"])
    assert args.command == name
    assert args.zenoh_connect == [f"tcp/{ROUTER}:7447"]
    assert args.data_dir == "/data"
    assert (REPO / args.config).is_file()  # the image's WORKDIR holds the repository's configs/
    # The environment the container sees: the image's, then the service's.
    for key, value in {**image_env(dockerfile), **svc.get("environment", {})}.items():
        monkeypatch.setenv(key, str(value))
    monkeypatch.chdir(REPO)
    cfg = _config(args, mode="client")
    assert cfg is not None, "the line config of the command is refused"
    assert cfg.zenoh.mode == "client" and cfg.zenoh.listen == []
    assert cfg.storage.data_dir == "/data"
    published = [host_port(p) for p in svc.get("ports", [])]
    assert all(host == "127.0.0.1" for host, _, _ in published), "published beyond loopback"
    inside = {port for _, _, port in published}
    if name == "api":
        assert inside == {cfg.http.port} and cfg.http.host == "0.0.0.0"
    if name == "worker":
        assert inside == {cfg.station.metrics_port} and cfg.http.host == "0.0.0.0"
    if name == "ingest":
        assert inside == set()


def configs_of(compose: dict, dockerfile: list[str], monkeypatch) -> dict:
    """The line config each process of ours runs with, by service."""
    from service.commands.line import _config

    monkeypatch.chdir(REPO)
    cfgs = {}
    for name in OURS:
        svc = compose["services"][name]
        with monkeypatch.context() as env:
            for key, value in {**image_env(dockerfile), **svc.get("environment", {})}.items():
                env.setenv(key, str(value))
            cfgs[name] = _config(parse(svc["command"]), mode="client")
    return cfgs


def test_prometheus_scrapes_the_workers_port_and_the_apis_metrics(compose, dockerfile, monkeypatch):
    cfgs = configs_of(compose, dockerfile, monkeypatch)
    prometheus = compose["services"]["prometheus"]
    [mount] = [v for v in prometheus["volumes"] if v.endswith(":/etc/prometheus/prometheus.yml:ro")]
    scrape = yaml.safe_load((COMPOSE.parent / mount.split(":")[0]).read_text())
    targets = {
        (job.get("metrics_path", "/metrics"), target)
        for job in scrape["scrape_configs"]
        for group in job["static_configs"]
        for target in group["targets"]
    }
    assert targets == {
        ("/metrics", f"worker:{cfgs['worker'].station.metrics_port}"),
        ("/metrics", f"api:{cfgs['api'].http.port}"),
    }


def test_grafana_is_given_the_dashboard_and_that_prometheus(compose):
    grafana = compose["services"]["grafana"]
    mounts = dict(v.rsplit(":", 1)[0].split(":", 1) for v in grafana["volumes"])
    for source in mounts:
        assert (COMPOSE.parent / source).exists(), source
    [(board, at)] = [(s, t) for s, t in mounts.items() if s.endswith(".json")]
    assert (COMPOSE.parent / board).resolve() == REPO / "docs" / "grafana-dashboard.json"
    provisioning = COMPOSE.parent / next(s for s, t in mounts.items() if t.endswith("provisioning"))
    [provider] = yaml.safe_load((provisioning / "dashboards" / "inspection.yaml").read_text())[
        "providers"
    ]
    assert Path(at).parent == Path(provider["options"]["path"])
    [source] = yaml.safe_load((provisioning / "datasources" / "prometheus.yaml").read_text())[
        "datasources"
    ]
    assert source["type"] == "prometheus" and source["isDefault"] is True
    port = host_port(compose["services"]["prometheus"]["ports"][0])[2]
    assert source["url"] == f"http://prometheus:{port}"


def test_the_ingest_waits_for_a_healthy_worker(compose):
    services = compose["services"]
    assert services["ingest"]["depends_on"]["worker"]["condition"] == "service_healthy"
    for name in ("worker", "api"):
        assert ROUTER in services[name]["depends_on"]


def test_the_health_checks_ask_the_api_and_the_workers_port(compose, dockerfile):
    services = compose["services"]
    api = shlex.join(services["api"]["healthcheck"]["test"])
    assert "http://127.0.0.1:8000/v1/health" in api
    worker = shlex.join(services["worker"]["healthcheck"]["test"])
    assert "http://127.0.0.1:9464/metrics" in worker
    assert services["ingest"]["healthcheck"] == {"disable": True}
    [image] = [ins for ins in dockerfile if ins.startswith("HEALTHCHECK ")]
    assert "/v1/health" in image


@contextmanager
def answering(status: int, body: bytes) -> Iterator[int]:
    """A loopback HTTP server answering every GET with ``status`` and ``body``."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (the stdlib's name)
            self.send_response(status)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)


def run_check(test: list[str], port: int, to_port: int) -> int:
    """A compose health check's command, with its port moved to ``to_port``."""
    assert test[0] == "CMD" and test[1] == "python"
    argv = [sys.executable, *[a.replace(f":{port}/", f":{to_port}/") for a in test[2:]]]
    return subprocess.run(argv, capture_output=True, timeout=30).returncode


def test_the_health_checks_tell_ready_from_not_ready(compose):
    services = compose["services"]
    api = services["api"]["healthcheck"]["test"]
    with answering(200, b'{"ready": true}') as port:
        assert run_check(api, 8000, port) == 0
    with answering(503, b'{"ready": false}') as port:
        assert run_check(api, 8000, port) != 0
    worker = services["worker"]["healthcheck"]["test"]
    ready = b"# TYPE inspection_worker_queue_capacity gauge\ninspection_worker_queue_capacity 4.0\n"
    with answering(200, ready) as port:
        assert run_check(worker, 9464, port) == 0
    with answering(200, b"# parts still loading: no worker series yet\n") as port:
        assert run_check(worker, 9464, port) != 0


def test_the_image_installs_the_step_extra_and_warms_the_kernels_up(dockerfile):
    runs = [ins[4:] for ins in dockerfile if ins.startswith("RUN ")]
    assert any(re.search(r"pip install .*\"\.\[step\]\"", r) for r in runs)
    env = " ".join(ins for ins in dockerfile if ins.startswith("ENV "))
    cache = re.search(r"NUMBA_CACHE_DIR=(\S+)", env).group(1)
    [warm] = [r for r in runs if r.startswith("inspection ")]
    argv = shlex.split(warm.split("&&")[0])
    args = parse(argv)
    # The whole line measures parts and stops by itself: the kernels compile at build time.
    assert args.command == "run" and args.parts is not None and args.parts >= 1
    # As the user the line runs as, so the cache it fills is the one it reads, and before
    # the volumes are declared, so the cache and the trees stay in the image.
    order = [ins.split()[0] for ins in dockerfile]
    at = dockerfile.index(f"RUN {warm}")
    assert "USER" in order[:at] and "VOLUME" not in order[:at]
    assert re.search(rf"chown inspection .*{re.escape(cache)}", " ".join(runs))
    assert f"mv {args.data_dir}/trees /data/trees" in warm
    [cmd] = [ins for ins in dockerfile if ins.startswith("CMD ")]
    assert parse(yaml.safe_load(cmd[4:])).command == "run"


def test_the_readme_runs_the_same_services(compose):
    readme = (REPO / "README.md").read_text()
    section = readme.split("## Run with Docker\n", 1)[1].split("\n## ", 1)[0]
    assert "docker/compose.yaml" in section
    rows = re.findall(r"^\| `([\w-]+)` \|.*\|\s*(`127\.0\.0\.1:(\d+)`)?\s*\|$", section, re.M)
    assert {name for name, _, _ in rows} == set(compose["services"])
    for name, _, port in rows:
        ports = compose["services"][name].get("ports", [])
        published = {str(outside) for _, outside, _ in map(host_port, ports)}
        assert published == ({port} if port else set()), name


def test_docker_compose_accepts_the_file():
    try:
        version = subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=30)
    except FileNotFoundError:
        pytest.skip("docker is not installed: docker compose config not run")
    if version.returncode != 0:
        pytest.skip("docker's compose plugin is not installed: docker compose config not run")
    done = subprocess.run(
        ["docker", "compose", "-f", str(COMPOSE), "config", "--quiet"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr


def test_the_file_is_valid_against_the_compose_specification(compose):
    """Where no compose plugin runs, the Compose Specification's own JSON Schema
    (tests/data/compose-spec.json, from compose-spec/compose-spec, Apache-2.0) checks it."""
    jsonschema = pytest.importorskip("jsonschema", reason="pip install jsonschema")
    schema = json.loads((REPO / "tests" / "data" / "compose-spec.json").read_text())
    validator = jsonschema.Draft7Validator(schema)
    assert [e.message for e in validator.iter_errors(compose)] == []
    broken = {**compose, "services": {**compose["services"], "api": {"imgae": "x"}}}
    assert any("imgae" in e.message for e in validator.iter_errors(broken))
