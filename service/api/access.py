"""Who may call the API: API keys, and the browser's Origin on writes.

- **Keys.** A request proves itself with ``Authorization: Bearer <key>`` or
  ``X-API-Key: <key>``. Keys come from the environment
  (``INSPECTION_API_KEYS``, comma-separated) or a file named by
  ``[http] api_keys_file`` (one per line, ``#`` comments): never from the
  line file itself, whose contents go into every recording's metadata.
  ``[http] auth`` says what needs a key: ``writes`` (POST, PUT, PATCH,
  DELETE; the default), ``all`` (reads too, ``/metrics`` included) or
  ``none``. Health probes never do, nor the dashboard's pages (their scripts
  send the key a person entered, kept for the browser tab's session). A
  missing or wrong key is 401 with ``WWW-Authenticate: Bearer``; every
  configured key is compared in constant time, so the answer's timing says
  nothing of how close a guess was.
- **No keys configured.** Writes are open only on a server bound to a
  loopback address (the machine's own user, as ``make run`` has it); bound
  anywhere else they are refused (403 ``writes_disabled``) until a key is
  configured.
- **Origin.** A browser names the page that sends a request. A write whose
  ``Origin`` is neither the API's own nor in ``[http] allowed_origins`` is
  refused (403 ``origin_refused``) before its body is read: a page an
  operator happens to open cannot post to the line. Cross-origin reads get
  CORS headers only for the allowed origins.
"""

from __future__ import annotations

import hmac
import ipaddress
import logging
import os
from collections.abc import Mapping
from pathlib import Path

from starlette.types import ASGIApp, Receive, Scope, Send

from .errors import error_response

log = logging.getLogger(__name__)

KEYS_ENV = "INSPECTION_API_KEYS"
WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
OPEN_PATHS = frozenset({"/v1/health", "/v1/health/live"})
"""Answered without a key: probes of orchestrators and load balancers carry none."""

OPEN_PAGES = (frozenset({"/", "/docs", "/redoc"}), ("/ui/", "/static/"))
"""The dashboard's pages and assets (paths, prefixes): they hold no data, and a browser
cannot send a key when it opens a page; their scripts send it with each API request."""


class AccessError(ValueError):
    """The key file cannot be read."""


def load_keys(keys_file: Path | None, environ: Mapping[str, str] | None = None) -> list[bytes]:
    """The configured API keys: from ``$INSPECTION_API_KEYS`` and ``keys_file``."""
    env = os.environ if environ is None else environ
    keys = [k.strip() for k in env.get(KEYS_ENV, "").split(",")]
    if keys_file is not None:
        try:
            lines = keys_file.read_text().splitlines()
        except OSError as exc:
            raise AccessError(f"API key file {keys_file.name}: {exc.strerror}") from exc
        keys += [line.split("#", 1)[0].strip() for line in lines]
    return [k.encode() for k in keys if k]


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Access:
    """ASGI middleware enforcing the rules above.

    Parameters
    ----------
    app : ASGI app
    keys : list of bytes
    auth : {"none", "writes", "all"}
    loopback : bool
        The server listens on a loopback address only.
    allowed_origins : list of str
        Origins (``scheme://host[:port]``) allowed to write, besides the API's own.
    max_drain_bytes : int
        A refused request's body is read and dropped up to this much (the
        upload cap), unparsed, so that the client, still sending, gets the
        answer instead of a reset connection.
    """

    def __init__(
        self,
        app: ASGIApp,
        *,
        keys: list[bytes],
        auth: str,
        loopback: bool,
        allowed_origins: list[str],
        max_drain_bytes: int = 0,
    ) -> None:
        self.app = app
        self.max_drain_bytes = max_drain_bytes
        self.keys = keys
        self.auth = auth
        self.loopback = loopback
        self.allowed = {o.rstrip("/").lower() for o in allowed_origins}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        refusal = self._refusal(scope)
        if refusal is not None:
            status, code, message = refusal
            headers = {"WWW-Authenticate": 'Bearer realm="inspection"'} if status == 401 else None
            await drain(receive, self.max_drain_bytes)
            await error_response(status, code, message, headers)(scope, receive, send)
            return
        await self.app(scope, receive, send)

    def _refusal(self, scope: Scope) -> tuple[int, str, str] | None:
        method = scope["method"]
        write = method in WRITE_METHODS
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        if write:
            origin = headers.get("origin")
            if origin is not None and not self._origin_ok(origin, scope, headers):
                return 403, "origin_refused", (
                    f"writes from the page at {origin[:200]!r} are refused: add it to "
                    "[http] allowed_origins to allow it"
                )  # fmt: skip
        path = scope["path"]
        if path in OPEN_PATHS or method == "OPTIONS":
            return None
        if not write and (path in OPEN_PAGES[0] or path.startswith(OPEN_PAGES[1])):
            return None
        needs_key = self.auth == "all" or (self.auth == "writes" and write)
        if not needs_key:
            return None
        if not self.keys:
            if self.loopback:
                return None
            return 403, "writes_disabled", (
                "no API key is configured and the API listens beyond this machine: set "
                f"{KEYS_ENV} or [http] api_keys_file"
            )  # fmt: skip
        presented = presented_key(headers)
        if presented is None:
            return 401, "unauthorized", (
                "this needs an API key: send 'Authorization: Bearer <key>' or 'X-API-Key: <key>'"
            )  # fmt: skip
        if not self._known(presented):
            return 401, "unauthorized", "the API key is not valid"
        return None

    def _known(self, presented: bytes) -> bool:
        # Every key is compared, whichever matches: the time taken does not
        # depend on which key (if any) it was.
        found = False
        for key in self.keys:
            found |= hmac.compare_digest(key, presented)
        return found

    def _origin_ok(self, origin: str, scope: Scope, headers: Mapping[str, str]) -> bool:
        o = origin.rstrip("/").lower()
        if o in self.allowed:
            return True
        host = headers.get("host")
        if host is None:
            return False
        scheme = scope.get("scheme", "http")
        return o == f"{scheme}://{host}".lower()


async def drain(receive: Receive, max_bytes: int) -> None:
    """Read and drop a request body, up to ``max_bytes`` (then the connection closes)."""
    seen = 0
    while seen <= max_bytes:
        message = await receive()
        if message["type"] != "http.request":
            return
        seen += len(message.get("body", b""))
        if not message.get("more_body", False):
            return


def presented_key(headers: Mapping[str, str]) -> bytes | None:
    auth = headers.get("authorization")
    if auth is not None:
        scheme, _, token = auth.partition(" ")
        if scheme.lower() == "bearer" and token.strip():
            return token.strip().encode()
    key = headers.get("x-api-key")
    if key is not None and key.strip():
        return key.strip().encode()
    return None
