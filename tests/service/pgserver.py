"""A throwaway PostgreSQL server for the tests: initdb, start on loopback, stop, delete.

The server refuses to run as root, so as root (CI) every server command runs
as the ``postgres`` user, in a directory that user owns. Trust authentication
on 127.0.0.1 only; the unix socket lives in the server's own directory. The
server is a child of the test process and stops when it ends, even killed.
"""

from __future__ import annotations

import contextlib
import glob
import itertools
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import psycopg

HOW_TO_GET = (
    "PostgreSQL's server binaries (initdb, pg_ctl, postgres) were not found on PATH or in "
    "/usr/lib/postgresql/*/bin; install them with `apt-get install postgresql`"
)


class ServerUnavailable(RuntimeError):
    """No server can be run here; the message says why and what to install."""


class ServerFailed(RuntimeError):
    """The server is installed but did not start: a failure, not a reason to skip."""


def find_bindir() -> Path | None:
    """The directory holding initdb and pg_ctl: PATH first, then Debian's versioned ones."""
    on_path = shutil.which("pg_ctl")
    if on_path and shutil.which("initdb"):
        return Path(on_path).parent
    for d in sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=_version_key, reverse=True):
        if (Path(d) / "pg_ctl").is_file() and (Path(d) / "initdb").is_file():
            return Path(d)
    return None


def _version_key(path: str) -> tuple[int, str]:
    name = Path(path).parent.name
    return (int(name), name) if name.isdigit() else (-1, name)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class PgServer:
    """One running server; :meth:`new_database` hands each test its own database."""

    bindir: Path
    root: Path
    port: int
    _as_user: list[str]
    _names: itertools.count = field(default_factory=lambda: itertools.count(1))
    _proc: subprocess.Popen = field(init=False)

    @classmethod
    def start(cls) -> PgServer:
        """initdb in a fresh directory and start the server.

        Raises :class:`ServerUnavailable` when nothing here can run one, and
        :class:`ServerFailed` when it is installed but does not start.
        """
        bindir = find_bindir()
        if bindir is None:
            raise ServerUnavailable(HOW_TO_GET)
        as_user: list[str] = []
        root = Path(tempfile.mkdtemp(prefix="inspection-pg-"))
        if os.geteuid() == 0:
            try:
                pw = pwd.getpwnam("postgres")
            except KeyError:
                shutil.rmtree(root)
                raise ServerUnavailable(
                    "running as root, and there is no `postgres` user to run the server as; "
                    "`apt-get install postgresql` creates it"
                ) from None
            os.chown(root, pw.pw_uid, pw.pw_gid)
            as_user = ["runuser", "-u", "postgres", "--"]
        server = cls(bindir, root, 0, as_user)
        try:
            server._run(
                "initdb", "-D", str(root / "data"), "--auth=trust", "-U", "postgres",
                "-E", "UTF8", "--locale=C", "--no-sync",
            )  # fmt: skip
            server._start_on_a_free_port()
        except BaseException:
            shutil.rmtree(root, ignore_errors=True)
            raise
        return server

    def _run(self, tool: str, *args: str) -> None:
        cmd = [*self._as_user, str(self.bindir / tool), *args]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        if done.returncode != 0:
            raise ServerFailed(f"{tool} failed ({done.returncode}): {done.stderr.strip()}")

    def _start_on_a_free_port(self) -> None:
        # A port found free can be taken before the server binds it: try a few.
        for attempt in range(3):
            self.port = _free_port()
            self._proc = subprocess.Popen(
                self._server_command(),
                stdout=(self.root / "log").open("ab"),
                stderr=subprocess.STDOUT,
            )
            if self._wait_ready(60.0):
                return
            if attempt == 2:
                raise ServerFailed(
                    f"the server did not start: {(self.root / 'log').read_text()[-2000:]}"
                )

    def _server_command(self) -> list[str]:
        postgres = [
            str(self.bindir / "postgres"), "-D", str(self.root / "data"), "-p", str(self.port),
            "-c", "listen_addresses=127.0.0.1", "-c", f"unix_socket_directories={self.root}",
            # Durability is of no use to a server deleted at the end of the session.
            "-c", "fsync=off", "-c", "synchronous_commit=off", "-c", "full_page_writes=off",
        ]  # fmt: skip
        if not shutil.which("setpriv"):
            return [*self._as_user, *postgres]
        # The server goes when the tests go, even killed: a parent-death signal to
        # runuser (which passes SIGTERM on) and one to the server, whose own
        # parent is runuser. SIGINT is the server's fast shutdown.
        if self._as_user:
            return ["setpriv", "--pdeathsig", "TERM", *self._as_user,
                    "setpriv", "--pdeathsig", "INT", *postgres]  # fmt: skip
        return ["setpriv", "--pdeathsig", "INT", *postgres]

    def _wait_ready(self, timeout_s: float) -> bool:
        """Connect until the server answers (True) or exits or ``timeout_s`` passes (False)."""
        deadline = time.monotonic() + timeout_s
        while self._proc.poll() is None and time.monotonic() < deadline:
            try:
                psycopg.connect(self.url(), connect_timeout=5).close()
                return True
            except psycopg.OperationalError:  # not listening yet, or it has stopped
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self._proc.wait(0.05)
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        return False

    def url(self, dbname: str = "postgres") -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/{dbname}"

    def new_database(self) -> str:
        """A new, empty database; returns its URL."""
        name = f"test_{next(self._names)}"
        with psycopg.connect(self.url(), autocommit=True) as db:
            db.execute(f"CREATE DATABASE {name}")
        return self.url(name)

    def stop(self) -> None:
        try:
            self._run("pg_ctl", "-D", str(self.root / "data"), "-m", "immediate", "-w", "stop")
            self._proc.wait(60)
        finally:
            shutil.rmtree(self.root, ignore_errors=True)
