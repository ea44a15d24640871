"""The station's stored results on zenoh: what a subscriber missed, fetched by seq or time."""

from __future__ import annotations

import pytest
from linekit import LINE, STATION, client, free_port, peer
from test_store import T0, res

from service import bus
from service.history import HistoryError, HistoryQuery, HistoryQueryable, fetch_results
from service.protocol import Keys
from service.store import ResultStore

KEYS = Keys(LINE)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A store of 25 results (seq 0..24, seq 7 twice: a refused repeat) served on a peer,
    and a client session that asks it."""
    path = tmp_path_factory.mktemp("history") / "results.sqlite"
    port = free_port()
    with (
        ResultStore(path) as store,
        bus.open_session(peer(port)) as server,
        bus.open_session(client(port)) as asker,
    ):
        for seq in range(25):
            store.put(res(seq))
        store.put(res(7, status="error", t=T0 + 7_500_000_000))
        queryable = HistoryQueryable(server, KEYS, STATION, store)
        try:
            yield store, asker
        finally:
            queryable.close()


def test_every_stored_result_comes_back_once_in_seq_order(served):
    store, asker = served
    got = fetch_results(asker, KEYS, STATION)
    assert [r.seq for r in got] == sorted([*range(25), 7])
    assert {r.id for r in got} == {r.id for r in store.iter_all()}


def test_a_seq_range_is_fetched_a_page_at_a_time(served):
    _, asker = served
    got = fetch_results(asker, KEYS, STATION, HistoryQuery(first_seq=5, last_seq=12, limit=3))
    assert [r.seq for r in got] == [5, 6, 7, 7, 8, 9, 10, 11, 12]
    assert len({r.id for r in got}) == 9


def test_a_time_range_selects_by_trigger_time(served):
    _, asker = served
    q = HistoryQuery(since_ns=T0 + 20 * 10**9, until_ns=T0 + 22 * 10**9)
    assert [r.seq for r in fetch_results(asker, KEYS, STATION, q)] == [20, 21, 22]


@pytest.mark.parametrize(
    "params, message",
    [("seq=x..3", "seq must be an integer"), ("limit=0", "limit must be within"),
     ("since=99999999999999999999", "within 0..2**63-1")],
)  # fmt: skip
def test_a_bad_selector_is_answered_with_an_error(served, params, message):
    _, asker = served
    replies = list(asker.get(f"{KEYS.history(STATION)}?{params}", timeout=10))
    assert len(replies) == 1 and replies[0].ok is None
    assert message in replies[0].err.payload.to_string()
    assert "bad_selector" in replies[0].err.payload.to_string()


def test_no_queryable_is_an_error_not_an_empty_answer():
    port = free_port()
    with bus.open_session(peer(port)) as lone:
        with pytest.raises(HistoryError, match="no queryable"):
            fetch_results(lone, KEYS, STATION, timeout_s=0.5)
