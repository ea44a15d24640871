"""Bounded disk: the oldest results and deviation files go beyond their budgets."""

from __future__ import annotations

import os
import time

import numpy as np
from test_store import T0, res

from service.config import RetentionSection
from service.models import Alarm
from service.retention import Janitor
from service.store import DeviationArchive, ResultStore


def test_the_oldest_rows_go_beyond_the_size_budget(store_target):
    with ResultStore(store_target) as store:
        for seq in range(50):
            store.put(res(seq))
        body = len(store.get(res(0).id).model_dump_json())
        removed = store.enforce(max_bytes=20 * body + body // 2, max_age_s=None)
        assert removed == 30
        kept = sorted(r.seq for r in store.iter_all())
        assert kept == list(range(30, 50))  # the newest, by trigger time
        assert store.enforce(max_bytes=20 * body + body // 2, max_age_s=None) == 0


def test_rows_older_than_the_age_limit_go(store_target):
    now = time.time_ns()
    with ResultStore(store_target) as store:
        store.put(res(1, t=now - 3 * 86400 * 10**9))
        store.put(res(2, t=now - 3600 * 10**9))
        assert store.enforce(max_bytes=None, max_age_s=86400) == 1
        assert [r.seq for r in store.iter_all()] == [2]


def test_acknowledged_alarms_older_than_the_kept_results_go_with_them(store_target):
    def alarm(at_seq: int, acked: bool) -> Alarm:
        t = res(at_seq).triggered_ns
        a = Alarm(kind="spc_rule", message=f"at {at_seq}", triggered_ns=t, line="l",
                  station="s", raised_ns=t + 1)  # fmt: skip
        return (
            a.model_copy(update={"acknowledged_by": "ann", "acknowledged_ns": t + 2})
            if acked
            else a
        )

    with ResultStore(store_target) as store:
        for seq in range(10):
            store.put(res(seq))
        alarms = [alarm(2, True), alarm(3, False), alarm(8, True), alarm(9, False)]
        for a in alarms:
            store.put_alarm(a)
        assert store.enforce(max_bytes=None, max_age_s=None) == 0
        assert len(store.alarms()) == 4  # nothing went: the alarms stay too
        body = len(store.get(res(0).id).model_dump_json())
        assert store.enforce(max_bytes=5 * body + body // 2, max_age_s=None) == 5
        # Results 0-4 went: the acknowledged alarm of part 2 with them; the open one of
        # part 3 waits for a person, and those of kept parts stay.
        assert sorted(a.message for a in store.alarms()) == ["at 3", "at 8", "at 9"]


def test_the_archive_keeps_within_its_budget_newest_first(tmp_path):
    arc = DeviationArchive(tmp_path / "dev")
    rng = np.random.default_rng(0)
    for i in range(10):
        p = arc.save(f"r{i}", rng.normal(size=(500, 3)), rng.normal(size=500))
        os.utime(p, (T0 / 1e9 + i, T0 / 1e9 + i))  # written one second apart
    size = (tmp_path / "dev" / "r0.npz").stat().st_size
    assert arc.enforce(max_bytes=int(4.5 * size), max_age_s=None) == 6
    assert sorted(p.stem for p in (tmp_path / "dev").glob("*.npz")) == [
        f"r{i}" for i in range(6, 10)
    ]
    assert arc.enforce(max_bytes=None, max_age_s=1.0) == 4  # all older than a second


def test_the_janitor_applies_the_config(tmp_path, store_target):
    store = ResultStore(store_target)
    arc = DeviationArchive(tmp_path / "dev")
    for seq in range(5):
        store.put(res(seq))
        arc.save(res(seq).id, np.zeros((100, 3)), np.zeros(100))
    policy = RetentionSection(results_max_mb=1e-6, deviations_max_mb=1e-6)
    try:
        # Its thread sweeps as it starts; closing joins it, so the sweep is over.
        Janitor(store, arc, policy, period_s=3600).close()
        assert store.count() == 0 and not list(arc.directory.glob("*.npz"))
    finally:
        store.close()


def test_the_archive_holds_its_budget_as_it_writes(tmp_path):
    """With a size budget the archive never passes it, whatever the sweeps' period."""
    rng = np.random.default_rng(1)
    probe = DeviationArchive(tmp_path / "probe").save("p", rng.normal(size=(500, 3)),
                                                      rng.normal(size=500))  # fmt: skip
    size = probe.stat().st_size
    arc = DeviationArchive(tmp_path / "dev", max_bytes=int(3.5 * size))
    for i in range(12):
        arc.save(f"r{i:02d}", rng.normal(size=(500, 3)), rng.normal(size=500))
        used = sum(p.stat().st_size for p in (tmp_path / "dev").glob("*.npz"))
        assert used <= 3.5 * size
    assert sorted(p.stem for p in (tmp_path / "dev").glob("*.npz"))[-1] == "r11"
