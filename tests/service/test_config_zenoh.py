"""The line file's zenoh TLS and access-control keys: paths, overrides, refusals, the CLI."""

from __future__ import annotations

from pathlib import Path

import pytest
from pki import Authority

from service import bus
from service.cli import main
from service.config import ConfigError, load_line_config
from service.line import bus_settings

TLS_ZENOH = """
[zenoh]
mode = "peer"
listen = ["tls/127.0.0.1:7447"]
tls_ca_certificate = "certs/ca.pem"
tls_certificate = "certs/line.pem"
tls_private_key = "certs/line.key"

[zenoh.access_control]
ingest = ["ingest"]
worker = ["worker", "line"]
subscriber = ["api"]
"""


@pytest.fixture(scope="module")
def line_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A line directory with ``certs/`` beside the line file."""
    root = tmp_path_factory.mktemp("line")
    Authority.create(root / "certs", ["line", "worker"])
    return root


def write_line(line_dir: Path, text: str, name: str = "line.toml") -> Path:
    p = line_dir / name
    p.write_text(text)
    return p


def test_tls_paths_are_relative_to_the_line_file_and_reach_the_bus(line_dir):
    cfg = load_line_config(write_line(line_dir, TLS_ZENOH))
    settings = bus_settings(cfg)
    assert settings.tls == bus.TlsSettings(
        ca_certificate=line_dir / "certs" / "ca.pem",
        certificate=line_dir / "certs" / "line.pem",
        private_key=line_dir / "certs" / "line.key",
    )
    assert settings.access == bus.AccessControl(
        line_prefix="insp/v1/line1",
        ingest=("ingest",),
        worker=("worker", "line"),
        subscriber=("api",),
    )
    assert cfg.effective()["zenoh"]["access_control"]["worker"] == ["worker", "line"]


def test_each_process_gives_its_certificate_in_the_environment(line_dir):
    """One line file, one certificate per process: the worker as a client of the router."""
    env = {
        "INSPECTION_ZENOH_MODE": "client",
        "INSPECTION_ZENOH_LISTEN": "",
        "INSPECTION_ZENOH_CONNECT": "tls/127.0.0.1:7447",
        "INSPECTION_ZENOH_TLS_CERTIFICATE": str(line_dir / "certs" / "worker.pem"),
        "INSPECTION_ZENOH_TLS_PRIVATE_KEY": "certs/worker.key",  # relative: to the line file
    }
    settings = bus_settings(load_line_config(write_line(line_dir, TLS_ZENOH), env=env))
    assert settings.mode == "client" and settings.connect == ("tls/127.0.0.1:7447",)
    assert settings.tls is not None
    assert settings.tls.certificate == line_dir / "certs" / "worker.pem"
    assert settings.tls.private_key == line_dir / "certs" / "worker.key"


def test_without_tls_keys_the_bus_is_plain_as_before(line_dir):
    settings = bus_settings(load_line_config(write_line(line_dir, "")))
    assert settings.tls is None and settings.access is None
    assert settings.listen == ("tcp/127.0.0.1:7447",)


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ('[zenoh]\nlisten = ["tls/127.0.0.1:7447"]\n', "needs tls_ca_certificate"),
        (
            '[zenoh]\nlisten = ["tcp/0.0.0.0:7447"]\ntls_ca_certificate = "certs/ca.pem"\n'
            'tls_certificate = "certs/line.pem"\ntls_private_key = "certs/line.key"\n',
            "'tcp/0.0.0.0:7447' is not a tls/ endpoint",
        ),
        (
            '[zenoh]\nlisten = ["tls/127.0.0.1:7447"]\ntls_ca_certificate = "certs/ca.pem"\n'
            'tls_certificate = "certs/line.pem"\n',
            "tls_certificate and tls_private_key are set together",
        ),
        (
            '[zenoh]\nlisten = ["tls/127.0.0.1:7447"]\ntls_ca_certificate = "certs/ca.pem"\n',
            "tls_certificate and tls_private_key are needed to listen",
        ),
        (
            '[zenoh]\nlisten = ["tls/127.0.0.1:7447"]\ntls_ca_certificate = "certs/nope.pem"\n'
            'tls_certificate = "certs/line.pem"\ntls_private_key = "certs/line.key"\n',
            "zenoh.tls_ca_certificate: no such file",
        ),
        (
            '[zenoh]\nlisten = ["tls/127.0.0.1:7447"]\ntls_ca_certificate = "certs/ca.pem"\n'
            'tls_certificate = "certs/line.pem"\ntls_private_key = "certs/line.key"\n'
            "tls_mutual = false\n[zenoh.access_control]\nworker = ['w']\n",
            "access_control needs tls_ca_certificate and tls_mutual = true",
        ),
        (
            '[zenoh]\nlisten = ["tls/127.0.0.1:7447"]\ntls_ca_certificate = "certs/line.key"\n'
            'tls_certificate = "certs/line.pem"\ntls_private_key = "certs/line.key"\n',
            "zenoh.tls_ca_certificate: line.key is not a PEM certificate",
        ),
        (
            '[zenoh]\nlisten = ["tls/127.0.0.1:7447"]\ntls_ca_certificate = "certs/ca.pem"\n'
            'tls_certificate = "certs/line.pem"\ntls_private_key = "certs/line.pem"\n',
            "zenoh.tls_private_key: line.pem is not a PEM private key",
        ),
        ("[zenoh.access_control]\nworker = ['w']\n", "access_control needs"),
        ("[zenoh.access_control]\nreaders = ['r']\n", "zenoh.access_control.readers"),
        ("[zenoh.access_control]\nworker = ['']\n", "zenoh.access_control.worker.0"),
    ],
)
def test_bad_zenoh_security_keys_fail_with_the_key(line_dir, text, where):
    with pytest.raises(ConfigError, match="invalid configuration") as exc:
        load_line_config(write_line(line_dir, text, "bad.toml"))
    assert where in str(exc.value)


def test_the_router_takes_the_line_file_and_refuses_a_bad_one_with_exit_code_2(line_dir, capsys):
    bad = write_line(line_dir, '[zenoh]\nlisten = ["tls/127.0.0.1:7447"]\n', "bad.toml")
    assert main(["router", "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "needs tls_ca_certificate" in err and "Traceback" not in err
    assert main(["router"]) == 2
    assert "--zenoh-listen or --config" in capsys.readouterr().err


def test_a_bus_that_cannot_open_is_said_without_a_traceback(capsys):
    """An ingest whose router is not there: exit code 2 (what it was told to reach does not
    answer) and zenoh's reason, no traceback."""
    from linekit import ROOT, free_port

    code = main(["ingest", "--config", str(ROOT / "configs" / "line.toml"),
                 "--zenoh-connect", f"tcp/127.0.0.1:{free_port()}", "--count", "1"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2, err
    assert "cannot open a zenoh client session" in err and "Traceback" not in err
