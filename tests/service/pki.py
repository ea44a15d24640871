"""Throwaway certificate authorities for the TLS tests, made with the ``openssl`` CLI.

Every certificate is EC P-256, valid for a day, usable as server and client
(a zenoh peer both listens and connects) and names ``127.0.0.1`` and
``localhost``, the hosts the tests connect to.
"""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

OPENSSL = shutil.which("openssl")

_LEAF_EXT = (
    "subjectAltName=IP:127.0.0.1,DNS:localhost\n"
    "basicConstraints=critical,CA:FALSE\n"
    "keyUsage=critical,digitalSignature\n"
    "extendedKeyUsage=serverAuth,clientAuth\n"
)


def need_openssl() -> str:
    """The openssl binary, or skip the test saying how to get it."""
    if OPENSSL is None:
        pytest.skip(
            "the TLS tests make their certificates with the openssl CLI, which is not on "
            "PATH: install it (apt-get install openssl, brew install openssl)"
        )
    return OPENSSL


def _run(*args: str) -> None:
    subprocess.run([need_openssl(), *args], check=True, capture_output=True, timeout=30)


@dataclass(frozen=True)
class Authority:
    """A CA in ``root``: ``ca.pem``, and ``<name>.pem`` / ``<name>.key`` per issued name."""

    root: Path

    @property
    def ca(self) -> Path:
        return self.root / "ca.pem"

    def cert(self, name: str) -> Path:
        return self.root / f"{name}.pem"

    def key(self, name: str) -> Path:
        return self.root / f"{name}.key"

    @classmethod
    def create(cls, root: Path, names: list[str], ca_name: str = "test line CA") -> Authority:
        root.mkdir(parents=True, exist_ok=True)
        ca = cls(root)
        ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes")
        _run("req", "-x509", *ec, "-keyout", str(root / "ca.key"), "-out", str(ca.ca),
             "-days", "1", "-subj", f"/CN={ca_name}",
             "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign")  # fmt: skip
        ext = root / "leaf.ext"
        ext.write_text(_LEAF_EXT)
        for name in names:
            csr = root / f"{name}.csr"
            _run("req", *ec, "-keyout", str(ca.key(name)), "-out", str(csr),
                 "-subj", f"/CN={name}")  # fmt: skip
            _run("x509", "-req", "-in", str(csr), "-CA", str(ca.ca),
                 "-CAkey", str(root / "ca.key"), "-CAcreateserial", "-out", str(ca.cert(name)),
                 "-days", "1", "-extfile", str(ext))  # fmt: skip
        return ca
