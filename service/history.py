"""A station's stored results on zenoh: a queryable, and the query that reads it.

zenoh does not deliver what was put while a subscriber or the router was
away. A subscriber that comes back asks ``<prefix>/<line>/<station>/results``
for what it missed, by seq or by trigger time, and gets each stored result
as one reply (InspectionResult JSON, on the query's own key). The worker
that stores the station's results serves the queryable.

Selector parameters (zenoh's ``;``-separated ``name=value``):

==========  ====================================================================
``seq``     ``A..B``, ``A..`` or ``..B``: first and last seq, both included
``since``   trigger time, ns since the epoch, included
``until``   trigger time, ns since the epoch, included
``limit``   at most this many replies (1..1000, default 1000), lowest seq first
==========  ====================================================================

A selector that cannot be read is answered with one error reply (JSON
``{"error": {"code": "bad_selector", "message": ...}}``).
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass

import zenoh

from .models import InspectionResult
from .protocol import Keys
from .store import MAX_LIMIT, ResultStore

log = logging.getLogger(__name__)

INT64_MAX = 2**63 - 1


@dataclass(frozen=True)
class HistoryQuery:
    """What a query asks for: a seq range, a time range and a page size."""

    first_seq: int = 0
    last_seq: int = INT64_MAX
    since_ns: int = 0
    until_ns: int = INT64_MAX
    limit: int = MAX_LIMIT

    def parameters(self) -> str:
        """The selector parameters that ask for this."""
        out = [f"seq={self.first_seq}..{self.last_seq}", f"limit={self.limit}"]
        if self.since_ns:
            out.append(f"since={self.since_ns}")
        if self.until_ns != INT64_MAX:
            out.append(f"until={self.until_ns}")
        return ";".join(out)

    @classmethod
    def parse(cls, params: zenoh.Parameters) -> HistoryQuery:
        """Read the selector's parameters; raises ValueError naming what is wrong."""
        first, last = 0, INT64_MAX
        seq = params.get("seq")
        if seq is not None:
            lo, sep, hi = seq.partition("..")
            if not sep:
                lo = hi = seq
            first = _int(lo, "seq", 0) if lo else 0
            last = _int(hi, "seq", INT64_MAX) if hi else INT64_MAX
        since = params.get("since")
        until = params.get("until")
        limit = params.get("limit")
        q = cls(
            first_seq=first,
            last_seq=last,
            since_ns=_int(since, "since", 0) if since else 0,
            until_ns=_int(until, "until", INT64_MAX) if until else INT64_MAX,
            limit=_int(limit, "limit", MAX_LIMIT) if limit else MAX_LIMIT,
        )
        if not 1 <= q.limit <= MAX_LIMIT:
            raise ValueError(f"limit must be within 1..{MAX_LIMIT}, got {q.limit}")
        return q


def _int(text: str, name: str, default: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{name} must be an integer (or A..B for seq), got {text!r}") from None
    if not 0 <= value <= INT64_MAX:
        raise ValueError(f"{name} must be within 0..2**63-1, got {text!r}")
    return value


class HistoryQueryable:
    """Serves ``<prefix>/<line>/<station>/results`` from ``store``, on a thread of its own.

    Parameters
    ----------
    session : zenoh.Session
    keys : Keys
    station : str
    store : ResultStore
    """

    def __init__(self, session: zenoh.Session, keys: Keys, station: str, store: ResultStore):
        self.keys = keys
        self.station = station
        self.store = store
        self._q = session.declare_queryable(keys.history(station), zenoh.handlers.FifoChannel(64))
        self._handler = self._q.handler
        self._thread = threading.Thread(target=self._run, name="history", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                query = self._handler.recv()
            except zenoh.ZError:
                return  # undeclared or session closed
            try:
                self._answer(query)
            except Exception:
                log.exception("history query %s failed", query.selector)
            finally:
                query.drop()

    def _answer(self, query: zenoh.Query) -> None:
        try:
            q = HistoryQuery.parse(query.parameters)
        except ValueError as exc:
            err = {"error": {"code": "bad_selector", "message": str(exc)}}
            query.reply_err(json.dumps(err), encoding=zenoh.Encoding.APPLICATION_JSON)
            return
        for r in self.store.station_results(
            self.keys.line, self.station, seq=(q.first_seq, q.last_seq),
            since_ns=q.since_ns, until_ns=q.until_ns, limit=q.limit,
        ):  # fmt: skip
            query.reply(
                query.key_expr, r.model_dump_json(), encoding=zenoh.Encoding.APPLICATION_JSON
            )

    def close(self) -> None:
        try:
            self._q.undeclare()
        except zenoh.ZError:
            pass
        self._thread.join(5.0)


class HistoryError(RuntimeError):
    """The queryable answered with an error, or nobody answered."""


def fetch_results(
    session: zenoh.Session,
    keys: Keys,
    station: str,
    query: HistoryQuery | None = None,
    *,
    timeout_s: float = 10.0,
) -> list[InspectionResult]:
    """Every stored result the query selects, lowest seq first, fetched a page at a time.

    Raises
    ------
    HistoryError
        No queryable serves the station within ``timeout_s``, or it refused the query.
    """
    q = query or HistoryQuery()
    querier = session.declare_querier(
        keys.history(station),
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout_s,
    )
    try:
        waited = threading.Event()
        for _ in range(max(1, int(timeout_s / 0.05))):
            if querier.matching_status.matching:  # type: ignore[attr-defined]  # stub says bool
                break
            waited.wait(0.05)
        else:
            raise HistoryError(f"no queryable serves {keys.history(station)}")
        out: list[InspectionResult] = []
        seen: set[str] = set()
        first = q.first_seq
        while True:
            page_q = HistoryQuery(first, q.last_seq, q.since_ns, q.until_ns, q.limit)
            page = _get(querier, page_q.parameters())
            fresh = [r for r in page if r.id not in seen]
            seen.update(r.id for r in fresh)
            out.extend(fresh)
            if len(page) < q.limit or not fresh:
                return sorted(out, key=lambda r: (r.seq, r.triggered_ns, r.id))
            # The next page starts at the last seq of this one: results sharing a
            # seq may straddle the pages, and the ids already seen are skipped.
            first = max(r.seq for r in page)
    finally:
        querier.undeclare()


def _get(querier: zenoh.Querier, parameters: str) -> list[InspectionResult]:
    results: list[InspectionResult] = []
    for reply in querier.get(parameters=parameters):
        if reply.ok is None:
            raise HistoryError(reply.err.payload.to_string() if reply.err else "query failed")
        results.append(InspectionResult.model_validate_json(reply.ok.payload.to_bytes()))
    return results
