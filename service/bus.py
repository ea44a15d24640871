"""Zenoh sessions, publishers and subscribers as the line uses them.

Rules this module enforces (see the zenoh notes in the project's dependency
notes):

- multicast scouting is off unless asked for, and a session listens only on
  the endpoints it is given;
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
from typing import Any

import zenoh

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")


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
    extra : dict
        Further zenoh settings as ``{json5 path: value}``, applied last.
    """

    mode: str = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"zenoh mode must be one of {MODES}, got {self.mode!r}")
        for ep in (*self.listen, *self.connect):
            if not isinstance(ep, str) or "/" not in ep:
                raise ValueError(f"a zenoh endpoint looks like tcp/127.0.0.1:7447, got {ep!r}")
        if self.mode == "client" and not self.connect:
            raise ValueError("a zenoh client needs at least one --zenoh-connect endpoint")


def make_config(settings: BusSettings) -> zenoh.Config:
    """Turn settings into a zenoh Config (nothing left to zenoh's defaults that matters)."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(settings.mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    cfg.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    for path, value in settings.extra.items():
        cfg.insert_json5(path, json.dumps(value))
    return cfg


def open_session(settings: BusSettings) -> zenoh.Session:
    """Open a session; raises a ``RuntimeError`` naming the endpoints on failure."""
    try:
        session = zenoh.open(make_config(settings))
    except zenoh.ZError as exc:
        raise RuntimeError(
            f"cannot open a zenoh {settings.mode} session "
            f"(listen {list(settings.listen)}, connect {list(settings.connect)}): {exc}"
        ) from exc
    log.info(
        "zenoh %s session %s (listen %s, connect %s)",
        settings.mode,
        session.zid(),
        list(settings.listen),
        list(settings.connect),
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
    status : callable() -> dict
        Returns the current status; ``time_ns`` is added.
    period_s : float
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        status: Callable[[], dict[str, Any]],
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
        doc = dict(self._status())
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
