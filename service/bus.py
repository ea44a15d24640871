"""Zenoh sessions, publishers and subscribers as the line uses them.

Rules this module enforces (see the zenoh notes in the project's dependency
notes):

- multicast scouting is off unless asked for, and a session listens only on
  the endpoints it is given;
- with :class:`TlsSettings`, the session speaks TLS only (``tls/`` endpoints,
  zenoh's protocol whitelist set to ``["tls"]``) and trusts only the line's
  CA, not the system's roots; with :class:`AccessControl`, a listening
  session lets each remote process do only what its certificate's common
  name allows (:func:`access_control_config`);
- frames are published with congestion control BLOCK, so a slow subscriber
  slows the publisher down instead of silently losing FrameSets;
- subscribers get a bounded :class:`zenoh.handlers.RingChannel`, read from a
  thread of ours, never a Python callback (a callback subscriber left open
  keeps the interpreter from exiting);
- everything declared is undeclared, and sessions are closed, by ``close()``.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")


class BusError(RuntimeError):
    """A zenoh session could not be opened (nothing to connect to, a refused link)."""


@dataclass(frozen=True)
class TlsSettings:
    """TLS on a session's links, as zenoh's ``transport/link/tls`` keys.

    Attributes
    ----------
    ca_certificate : Path
        PEM certificate of the CA that signs the line's certificates; the
        certificates of the other end are checked against it alone.
    certificate, private_key : Path or None
        This process's PEM certificate and key: needed to listen, and to
        connect when ``mutual``.
    mutual : bool
        Present the certificate when connecting and require one, signed by
        the CA, from whoever connects (zenoh's ``enable_mtls`` does both).
    verify_name : bool
        The certificate of the endpoint connected to must name its host
        (a subjectAltName matching the IP or DNS name of the endpoint).
    """

    ca_certificate: Path
    certificate: Path | None = None
    private_key: Path | None = None
    mutual: bool = True
    verify_name: bool = True

    def __post_init__(self) -> None:
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("a TLS certificate and its private key go together")
        if self.mutual and self.certificate is None:
            raise ValueError("mutual TLS needs this process's certificate and private key")


@dataclass(frozen=True)
class AccessControl:
    """Who may do what on one line's keys, by the common name of their certificate.

    Enforced by the session that has it, on what remote sessions send it and
    on what it forwards to them; its own puts and subscriptions are not
    filtered. Everything not allowed here is denied, including to names in no
    list (a certificate of the line's CA issued to someone else).

    Attributes
    ----------
    line_prefix : str
        ``<prefix>/<line>``: the keys the rules cover.
    ingest : tuple of str
        May put FrameSets (``*/frames``).
    worker : tuple of str
        May put results, status and alarms, answer history queries
        (``*/results``) and hold worker liveliness tokens.
    subscriber : tuple of str
        May only subscribe, query and watch liveliness tokens (what every
        role may do).
    """

    line_prefix: str
    ingest: tuple[str, ...] = ()
    worker: tuple[str, ...] = ()
    subscriber: tuple[str, ...] = ()


def access_control_config(acl: AccessControl) -> dict[str, Any]:
    """The ``access_control`` block of zenoh's config for ``acl``.

    ``ingress`` rules filter what a remote session sends to this one,
    ``egress`` rules what this one forwards to it; a subscriber needs both
    (its declaration in, the samples out).
    """
    p = acl.line_prefix
    everything = [f"{p}/**", f"@{p}/**"]
    rules = [
        {
            "id": "observe",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": [
                "declare_subscriber",
                "query",
                "declare_liveliness_subscriber",
                "liveliness_query",
            ],
            "key_exprs": everything,
        },
        {
            "id": "receive",
            "permission": "allow",
            "flows": ["egress"],
            # Declarations too: without them a publisher never learns of its
            # subscribers (matching status stays false, wait_for_subscribers times out).
            "messages": [
                "put",
                "reply",
                "liveliness_token",
                "declare_subscriber",
                "declare_queryable",
                "declare_liveliness_subscriber",
            ],
            "key_exprs": everything,
        },
        {
            "id": "frames",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["put"],
            "key_exprs": [f"{p}/*/frames", f"{p}/*/fired"],
        },
        {
            "id": "results",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["put"],
            "key_exprs": [f"{p}/*/result/**", f"{p}/*/status", f"{p}/*/alarm"],
        },
        {
            "id": "serve",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["declare_queryable", "reply", "liveliness_token"],
            "key_exprs": [f"{p}/*/results", f"@{p}/*/worker/*"],
        },
        {
            "id": "asked",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["query"],
            "key_exprs": [f"{p}/*/results"],
        },
    ]
    roles = {"ingest": acl.ingest, "worker": acl.worker, "subscriber": acl.subscriber}
    grants = {"ingest": ["frames"], "worker": ["results", "serve", "asked"], "subscriber": []}
    # zenoh refuses a subject with an empty list: a role nobody holds is left out.
    held = [role for role, names in roles.items() if names]
    subjects = [{"id": role, "cert_common_names": list(roles[role])} for role in held]
    policies: list[dict[str, Any]] = []
    if held:
        policies.append({"rules": ["observe", "receive"], "subjects": held})
    policies += [{"rules": grants[r], "subjects": [r]} for r in held if grants[r]]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


@dataclass(frozen=True)
class BusSettings:
    """How to open a zenoh session.

    Attributes
    ----------
    mode : {"peer", "client", "router"}
    listen : tuple of str
        Endpoints to listen on, e.g. ``("tcp/127.0.0.1:7447",)``; empty: none.
    connect : tuple of str
        Endpoints to connect to.
    multicast_scouting : bool
        Off by default: on a shared network it would discover strangers.
    tls : TlsSettings or None
        With it every endpoint must be ``tls/``; without it none may be.
    access : AccessControl or None
        Needs mutual TLS: the common names it names come from the certificates.
    extra : dict
        Further zenoh settings as ``{json5 path: value}``, applied last.
    """

    mode: str = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    tls: TlsSettings | None = None
    access: AccessControl | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"zenoh mode must be one of {MODES}, got {self.mode!r}")
        for ep in (*self.listen, *self.connect):
            if not isinstance(ep, str) or "/" not in ep:
                raise ValueError(f"a zenoh endpoint looks like tcp/127.0.0.1:7447, got {ep!r}")
            if (self.tls is not None) != ep.startswith("tls/"):
                raise ValueError(
                    f"zenoh endpoint {ep!r}: tls/ endpoints go with TLS settings, others without"
                )
        if self.mode == "client" and not self.connect:
            raise ValueError("a zenoh client needs at least one --zenoh-connect endpoint")
        if self.listen and self.tls is not None and self.tls.certificate is None:
            raise ValueError("listening on TLS needs this process's certificate and private key")
        if self.access is not None and (self.tls is None or not self.tls.mutual):
            raise ValueError("access control needs mutual TLS (it goes by certificate names)")


def make_config(settings: BusSettings) -> zenoh.Config:
    """Turn settings into a zenoh Config (nothing left to zenoh's defaults that matters)."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(settings.mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    cfg.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    if settings.tls is not None:
        t = settings.tls
        # Without root_ca_certificate zenoh would trust the system's web roots.
        tls: dict[str, Any] = {
            "root_ca_certificate": str(t.ca_certificate),
            "enable_mtls": t.mutual,
            "verify_name_on_connect": t.verify_name,
        }
        if t.certificate is not None and t.private_key is not None:
            # One certificate for both sides: a peer listens and connects.
            tls |= {
                "listen_certificate": str(t.certificate),
                "listen_private_key": str(t.private_key),
                "connect_certificate": str(t.certificate),
                "connect_private_key": str(t.private_key),
            }
        for key, value in tls.items():
            cfg.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
        # TLS links only: a plain endpoint added later (extra, gossip) is refused, not opened.
        cfg.insert_json5("transport/link/protocols", json.dumps(["tls"]))
    if settings.access is not None:
        cfg.insert_json5("access_control", json.dumps(access_control_config(settings.access)))
    for path, value in settings.extra.items():
        cfg.insert_json5(path, json.dumps(value))
    return cfg


def open_session(settings: BusSettings) -> zenoh.Session:
    """Open a session; raises a ``RuntimeError`` naming the endpoints on failure."""
    try:
        session = zenoh.open(make_config(settings))
    except zenoh.ZError as exc:
        # A certificate refused by either end surfaces as "Unable to connect",
        # exactly like a router that is down; only zenoh's own log says which.
        hint = (
            "; with TLS a certificate refused at either end fails the same way "
            "(RUST_LOG=warn shows zenoh's reason)"
            if settings.tls is not None and settings.connect
            else ""
        )
        raise BusError(
            f"cannot open a zenoh {settings.mode} session "
            f"(listen {list(settings.listen)}, connect {list(settings.connect)}): {exc}{hint}"
        ) from exc
    log.info(
        "zenoh %s session %s (listen %s, connect %s, %s, %s)",
        settings.mode,
        session.zid(),
        list(settings.listen),
        list(settings.connect),
        "no TLS"
        if settings.tls is None
        else ("mutual TLS" if settings.tls.mutual else "TLS (server certificate only)"),
        "access control" if settings.access is not None else "no access control",
    )
    return session


def is_connected(session: zenoh.Session) -> bool:
    """True when the session has at least one peer or router to talk to."""
    if session.is_closed():
        return False
    info = session.info
    return bool(list(info.routers_zid()) or list(info.peers_zid()))


def frame_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """A publisher for FrameSets: BLOCK congestion control, reliable, data priority."""
    return session.declare_publisher(
        key,
        encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM,
        congestion_control=zenoh.CongestionControl.BLOCK,
        priority=zenoh.Priority.DATA,
    )


def put_json(session: zenoh.Session, key: str, payload: bytes | str) -> None:
    """Publish one JSON document (a result, a status) with BLOCK, so it is not dropped."""
    session.put(
        key,
        payload.encode("utf-8") if isinstance(payload, str) else payload,
        encoding=zenoh.Encoding.APPLICATION_JSON,
        congestion_control=zenoh.CongestionControl.BLOCK,
    )


def wait_for_subscribers(publisher: zenoh.Publisher, timeout_s: float) -> bool:
    """Block until some subscriber matches ``publisher`` (or ``timeout_s`` passes)."""
    matched = threading.Event()
    listener = publisher.declare_matching_listener(
        lambda status: matched.set() if status.matching else None
    )
    try:
        if publisher.matching_status.matching:  # type: ignore[attr-defined]  # stub says bool
            return True
        return matched.wait(timeout_s)
    finally:
        listener.undeclare()


class RingSubscriber:
    """A subscriber with a bounded ring buffer, read by a thread of ours.

    When more than ``capacity`` samples wait, zenoh drops the oldest; the
    reader must detect that from the data (the worker sees gaps in ``seq``).

    Parameters
    ----------
    session : zenoh.Session
    key : str
        Key expression or selector.
    on_sample : callable(zenoh.Sample) -> None
        Called on the reading thread, one sample at a time, in order.
        Exceptions are logged and do not stop the thread.
    capacity : int
    name : str
        Thread name, for logs.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        on_sample: Callable[[zenoh.Sample], None],
        *,
        capacity: int = 8,
        name: str = "zenoh-rx",
    ) -> None:
        if capacity < 1:
            raise ValueError("capacity must be at least 1")
        self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(capacity))
        # recv() on the handler, not on the subscriber: undeclaring the
        # subscriber from another thread then ends the blocking recv().
        self._handler = self._sub.handler
        self._on_sample = on_sample
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                sample = self._handler.recv()
            except zenoh.ZError:
                return  # channel closed: undeclared or session closed
            try:
                self._on_sample(sample)
            except Exception:
                log.exception("subscriber handler failed on %s", sample.key_expr)

    def close(self, timeout_s: float = 5.0) -> None:
        """Undeclare and join the reading thread.

        Samples still waiting in the ring are discarded: undeclaring deletes
        zenoh's ring, and the thread ends after the sample it holds, if any.
        """
        if self._closed:
            return
        self._closed = True
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass  # the session was closed first: nothing left to undeclare
        self._thread.join(timeout_s)


class Heartbeat:
    """Publishes a status JSON document periodically and on demand.

    Parameters
    ----------
    session : zenoh.Session
    key : str
    status : callable() -> dict or None
        Returns the current status (``time_ns`` is added), or None: nothing to say yet.
    period_s : float
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        status: Callable[[], dict[str, Any] | None],
        *,
        period_s: float = 1.0,
    ) -> None:
        self._session = session
        self._key = key
        self._status = status
        self._period_s = period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="heartbeat", daemon=True)
        self._thread.start()

    def publish(self) -> None:
        """Publish the status now."""
        status = self._status()
        if status is None:
            return
        doc = dict(status)
        doc["time_ns"] = time.time_ns()
        try:
            put_json(self._session, self._key, json.dumps(doc))
        except zenoh.ZError as exc:
            log.warning("status not published on %s: %s", self._key, exc)

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            self.publish()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)


def worker_id(station: str) -> str:
    """A worker id unique on this host and run: ``<station>-<pid>-<random>``."""
    return f"{station}-{os.getpid()}-{os.urandom(2).hex()}"


def close_all(objs: Iterable[Any]) -> None:
    """Undeclare / close each object, in order, logging failures instead of raising."""
    for obj in objs:
        if obj is None:
            continue
        try:
            if isinstance(obj, zenoh.Session):
                if not obj.is_closed():
                    obj.close()
            elif hasattr(obj, "close"):
                obj.close()
            else:
                obj.undeclare()
        except Exception as exc:  # closing must go on whatever failed before
            log.debug("closing %r: %s", obj, exc)
