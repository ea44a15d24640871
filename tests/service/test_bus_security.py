"""zenoh with mutual TLS and access control, on loopback, with certificates made by the test.

A router in mTLS mode with the line's CA; clients with and without the line's
certificates; access control by certificate common name keeping a process
from putting what its role does not allow. Multicast scouting stays off
(``bus.make_config``); every wait is on an event or a matching status.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh
from linekit import free_port
from pki import Authority

from service import bus
from service.protocol import Keys

KEYS = Keys("line1")
STATION = "st1"
ACCESS = bus.AccessControl(
    line_prefix="insp/v1/line1",
    ingest=("ingest",),
    worker=("worker",),
    subscriber=("api", "dashboard"),
)
LINE_NAMES = ["router", "worker", "ingest", "api", "dashboard", "stranger"]


@pytest.fixture(scope="module")
def line_ca(tmp_path_factory: pytest.TempPathFactory) -> Authority:
    return Authority.create(tmp_path_factory.mktemp("line-ca"), LINE_NAMES)


@pytest.fixture(scope="module")
def other_ca(tmp_path_factory: pytest.TempPathFactory) -> Authority:
    """Another CA issuing the same names: a name alone proves nothing."""
    return Authority.create(tmp_path_factory.mktemp("other-ca"), ["router", "worker"], "other CA")


def tls(ca: Authority, name: str, *, trust: Authority | None = None) -> bus.TlsSettings:
    """``name``'s certificate from ``ca``, trusting ``trust`` (default: ``ca``)."""
    return bus.TlsSettings(
        ca_certificate=(trust or ca).ca, certificate=ca.cert(name), private_key=ca.key(name)
    )


def endpoint(port: int) -> str:
    return f"tls/127.0.0.1:{port}"


def client(port: int, settings: bus.TlsSettings) -> bus.BusSettings:
    return bus.BusSettings(mode="client", connect=(endpoint(port),), tls=settings)


@pytest.fixture
def router(line_ca: Authority) -> Iterator[tuple[int, zenoh.Session]]:
    """A router with mutual TLS and no access control."""
    port = free_port()
    settings = bus.BusSettings(mode="router", listen=(endpoint(port),), tls=tls(line_ca, "router"))
    with bus.open_session(settings) as session:
        yield port, session


@pytest.fixture
def acl_router(line_ca: Authority) -> Iterator[tuple[int, zenoh.Session]]:
    """A router with mutual TLS and the line's access control (:data:`ACCESS`)."""
    port = free_port()
    settings = bus.BusSettings(
        mode="router", listen=(endpoint(port),), tls=tls(line_ca, "router"), access=ACCESS
    )
    with bus.open_session(settings) as session:
        yield port, session


class Inbox:
    """Payloads of a bounded subscriber, and an event per expected payload."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.got: list[bytes] = []
        self._cond = threading.Condition()
        self.sub = bus.RingSubscriber(session, key, self._on, capacity=64, name="inbox")

    def _on(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.got.append(sample.payload.to_bytes())
            self._cond.notify_all()

    def wait_for(self, payload: bytes, timeout_s: float = 10.0) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: payload in self.got, timeout_s)


def result_doc(status: str, by: str) -> bytes:
    return json.dumps({"status": status, "by": by}).encode()


def wait_until(condition: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    """Poll ``condition`` until true or ``timeout_s`` passes (zenoh has no event for it)."""
    deadline = time.monotonic() + timeout_s
    pause = threading.Event()
    while not condition():
        if time.monotonic() > deadline:
            return False
        pause.wait(0.01)
    return True


def wait_matched(session: zenoh.Session, key: str, timeout_s: float = 10.0) -> bool:
    """Whether a subscriber of ``key`` becomes known to ``session`` within ``timeout_s``."""
    pub = session.declare_publisher(key)
    try:
        return bus.wait_for_subscribers(pub, timeout_s)
    finally:
        pub.undeclare()


# --------------------------------------------------------------------------- TLS


def test_line_certificates_connect_and_carry_results(line_ca, router):
    port, _ = router
    key = KEYS.result(STATION, "demo-panel", "S1")
    with (
        bus.open_session(client(port, tls(line_ca, "api"))) as api,
        bus.open_session(client(port, tls(line_ca, "worker"))) as worker,
    ):
        assert bus.is_connected(api) and bus.is_connected(worker)
        inbox = Inbox(api, KEYS.results())
        assert wait_matched(worker, key)
        bus.put_json(worker, key, result_doc("pass", "worker"))
        assert inbox.wait_for(result_doc("pass", "worker"))
        inbox.sub.close()


def test_session_without_a_certificate_is_refused(line_ca, router):
    """Trusting the line's CA is not enough: the router asks for a client certificate and
    ends the handshake (its log: "peer sent no certificates"; the client's: "received fatal
    alert: CertificateRequired"). ``zenoh.open`` raises at once, as for a router that is down."""
    port, hub = router
    no_cert = bus.TlsSettings(ca_certificate=line_ca.ca, mutual=False)
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="cannot open a zenoh client session") as exc:
        bus.open_session(client(port, no_cert))
    assert time.monotonic() - t0 < 5.0  # refused, not timed out (measured: ~0.1 s)
    assert "Unable to connect" in str(exc.value) and "certificate refused" in str(exc.value)
    assert len(list(hub.info.transports())) == 0


def test_plain_tcp_to_a_tls_router_is_refused(router):
    port, hub = router
    with pytest.raises(RuntimeError, match="cannot open a zenoh client session"):
        bus.open_session(bus.BusSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
    assert len(list(hub.info.transports())) == 0


def test_certificate_of_another_ca_is_refused(line_ca, other_ca, router):
    """The same common name ("worker") signed by another CA: the router refuses the
    signature ("invalid peer certificate: BadSignature")."""
    port, hub = router
    with pytest.raises(RuntimeError, match="cannot open a zenoh client session"):
        bus.open_session(client(port, tls(other_ca, "worker", trust=line_ca)))
    assert len(list(hub.info.transports())) == 0


def test_client_refuses_a_router_outside_the_line_ca(line_ca, other_ca):
    """A router impersonating the line's (certificate from another CA): the client refuses
    it ("invalid peer certificate: UnknownIssuer") instead of sending it frames."""
    port = free_port()
    impostor = bus.BusSettings(mode="router", listen=(endpoint(port),), tls=tls(other_ca, "router"))
    with bus.open_session(impostor) as hub:
        with pytest.raises(RuntimeError, match="cannot open a zenoh client session"):
            bus.open_session(client(port, tls(line_ca, "worker")))
        assert len(list(hub.info.transports())) == 0


# --------------------------------------------------------------------------- access control


@pytest.mark.parametrize(
    ("forger", "delivered"),
    [
        ("dashboard", False),  # a subscriber's certificate: may watch, may not publish
        ("ingest", False),  # may publish frames only
        ("worker", True),  # the control: the role that may publish results
    ],
)
def test_access_control_keeps_other_roles_from_publishing_results(
    line_ca, acl_router, forger, delivered
):
    """A line process whose role does not allow it cannot put a result the API receives.

    Ordering makes this deterministic: the router handles what one link sends in
    order, so once the forger's subscriber declaration (sent after its put) has
    reached the worker, the put has been handled; and what the router forwards to
    the API arrives in order, so a forwarded forged result would precede the
    genuine result put after that point.
    """
    port, _ = acl_router
    forged_key = KEYS.result(STATION, "demo-panel", "FORGED")
    genuine_key = KEYS.result(STATION, "demo-panel", "S1")
    barrier_key = KEYS.status(STATION)
    forged, genuine = result_doc("pass", forger), result_doc("fail", "worker-genuine")
    with (
        bus.open_session(client(port, tls(line_ca, "api"))) as api,
        bus.open_session(client(port, tls(line_ca, "worker"))) as worker,
        bus.open_session(client(port, tls(line_ca, forger))) as rogue,
    ):
        inbox = Inbox(api, KEYS.results())
        assert wait_matched(rogue, forged_key)  # the forger knows the API listens
        assert wait_matched(worker, genuine_key)
        bus.put_json(rogue, forged_key, forged)
        barrier = rogue.declare_subscriber(barrier_key, zenoh.handlers.RingChannel(1))
        assert wait_matched(worker, barrier_key)
        bus.put_json(worker, genuine_key, genuine)
        assert inbox.wait_for(genuine)
        barrier.undeclare()
        inbox.sub.close()
    assert (forged in inbox.got) is delivered
    assert inbox.got.index(genuine) == (1 if delivered else 0)


def test_access_control_gives_a_stranger_of_the_line_ca_nothing(line_ca, acl_router):
    """A certificate of the line's CA whose name is in no role connects (mTLS accepts it)
    but can neither subscribe nor put: the worker never learns of its subscriber, and the
    API receives the genuine result alone."""
    port, hub = acl_router
    key = KEYS.result(STATION, "demo-panel", "S2")
    with (
        bus.open_session(client(port, tls(line_ca, "api"))) as api,
        bus.open_session(client(port, tls(line_ca, "worker"))) as worker,
        bus.open_session(client(port, tls(line_ca, "stranger"))) as stranger,
    ):
        # mTLS let the stranger in: what stops it below is access control.
        assert wait_until(lambda: len(list(hub.info.transports())) == 3)
        spy = Inbox(stranger, KEYS.frames(STATION))
        inbox = Inbox(api, KEYS.results())
        assert wait_matched(worker, key)
        # The stranger's subscription is denied at the router: no one ever matches it.
        assert not wait_matched(worker, KEYS.frames(STATION), timeout_s=0.5)
        bus.put_json(stranger, key, result_doc("pass", "stranger"))
        bus.put_json(worker, key, result_doc("fail", "worker"))
        assert inbox.wait_for(result_doc("fail", "worker"))
        spy.sub.close()
        inbox.sub.close()
    assert inbox.got == [result_doc("fail", "worker")]
    assert spy.got == []


def test_access_control_lets_each_role_do_its_part(line_ca, acl_router):
    """Ingest -> worker frames, worker -> API results, the worker's history queryable and
    liveliness token seen by the API; a subscriber's queryable and token are not."""
    port, _ = acl_router
    history = KEYS.history(STATION)
    with (
        bus.open_session(client(port, tls(line_ca, "ingest"))) as ingest,
        bus.open_session(client(port, tls(line_ca, "worker"))) as worker,
        bus.open_session(client(port, tls(line_ca, "api"))) as api,
        bus.open_session(client(port, tls(line_ca, "dashboard"))) as dashboard,
    ):
        frames = Inbox(worker, KEYS.frames(STATION))
        pub = bus.frame_publisher(ingest, KEYS.frames(STATION))
        assert bus.wait_for_subscribers(pub, 10)
        pub.put(b"frameset-0")
        assert frames.wait_for(b"frameset-0")

        token = worker.liveliness().declare_token(KEYS.worker_token(STATION, "w1"))
        fake = dashboard.liveliness().declare_token(KEYS.worker_token(STATION, "w2"))
        queryable = worker.declare_queryable(history, zenoh.handlers.FifoChannel(4))
        rogue_q = dashboard.declare_queryable(history, zenoh.handlers.FifoChannel(4))

        def answer(q: zenoh.Queryable, text: bytes) -> None:
            try:
                query = q.handler.recv()
            except zenoh.ZError:
                return  # undeclared before any query reached it
            query.reply(query.key_expr, text)
            query.drop()

        threads = [
            threading.Thread(target=answer, args=(queryable, b"worker"), daemon=True),
            threading.Thread(target=answer, args=(rogue_q, b"dashboard"), daemon=True),
        ]
        for t in threads:
            t.start()
        # Declarations reach the API through the router a moment later: wait until the
        # worker's queryable matches and its token is seen, then ask once.
        querier = api.declare_querier(history, timeout=5.0)
        assert wait_until(lambda: querier.matching_status.matching)
        replies = [r.ok.payload.to_bytes() for r in querier.get() if r.ok]
        querier.undeclare()

        def tokens_now() -> list[str]:
            replies = api.liveliness().get(KEYS.workers(), timeout=5.0)
            return sorted(str(r.ok.key_expr) for r in replies if r.ok)

        assert wait_until(lambda: KEYS.worker_token(STATION, "w1") in tokens_now())
        tokens = tokens_now()
        for obj in (queryable, rogue_q, token, fake, pub):
            obj.undeclare()
        for t in threads:
            t.join(5.0)
        frames.sub.close()
    assert replies == [b"worker"]
    assert tokens == [KEYS.worker_token(STATION, "w1")]


# --------------------------------------------------------------------------- settings


def test_tls_settings_are_checked_and_mapped_onto_zenoh_keys(line_ca: Authority, tmp_path: Path):
    t = tls(line_ca, "worker")
    cfg = bus.make_config(client(7447, t))
    got = json.loads(cfg.get_json("transport/link/tls"))
    assert got["root_ca_certificate"] == str(line_ca.ca)
    assert got["enable_mtls"] is True and got["verify_name_on_connect"] is True
    assert got["listen_certificate"] == got["connect_certificate"] == str(line_ca.cert("worker"))
    assert got["listen_private_key"] == got["connect_private_key"] == str(line_ca.key("worker"))
    assert json.loads(cfg.get_json("transport/link/protocols")) == ["tls"]
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(bus.make_config(client(7447, t)).get_json("access_control/enabled")) is False

    with pytest.raises(ValueError, match="tls/ endpoints go with TLS"):
        bus.BusSettings(mode="client", connect=("tcp/127.0.0.1:7447",), tls=t)
    with pytest.raises(ValueError, match="tls/ endpoints go with TLS"):
        bus.BusSettings(mode="client", connect=("tls/127.0.0.1:7447",))
    with pytest.raises(ValueError, match="mutual TLS needs"):
        bus.TlsSettings(ca_certificate=line_ca.ca)
    with pytest.raises(ValueError, match="go together"):
        bus.TlsSettings(ca_certificate=line_ca.ca, certificate=line_ca.cert("api"))
    server_only = bus.TlsSettings(ca_certificate=line_ca.ca, mutual=False)
    with pytest.raises(ValueError, match="listening on TLS needs"):
        bus.BusSettings(mode="router", listen=("tls/127.0.0.1:7447",), tls=server_only)
    with pytest.raises(ValueError, match="access control needs mutual TLS"):
        bus.BusSettings(mode="client", connect=("tls/127.0.0.1:7447",), tls=server_only,
                        access=ACCESS)  # fmt: skip


def test_access_control_config_leaves_out_roles_nobody_holds():
    """zenoh refuses a subject with no names; an empty role is dropped, and with no role at
    all every remote message is denied."""
    only_workers = bus.access_control_config(bus.AccessControl("insp/v1/line1", worker=("w",)))
    assert [s["id"] for s in only_workers["subjects"]] == ["worker"]
    assert only_workers["default_permission"] == "deny"
    sealed = bus.access_control_config(bus.AccessControl("insp/v1/line1"))
    assert sealed["subjects"] == [] and sealed["policies"] == []
    cfg = zenoh.Config()
    cfg.insert_json5("access_control", json.dumps(sealed))  # zenoh accepts it
    cfg.insert_json5("access_control", json.dumps(only_workers))
