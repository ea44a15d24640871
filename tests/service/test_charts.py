"""Control charts over stored results, and the monitor that turns run rules into alarms."""

from __future__ import annotations

import numpy as np
import pytest

from service.models import (
    InspectionResult,
    PointResult,
    Status,
    SurfaceDefectResult,
    make_result_id,
    software_version,
)
from service.pipeline import Outcome
from service.spc import SpcMonitor, SpcSettings, freeze_baseline, part_chart
from service.store import ResultStore

T0 = 1_800_000_000_000_000_000


def dent(i: int) -> SurfaceDefectResult:
    return SurfaceDefectResult(kind="dent", center_mm=[10.0 * i, 0.0, 0.0], area_mm2=80.0,
                               peak_mm=-0.6, mean_mm=-0.4, points=50)  # fmt: skip


def res(seq: int, dev: float, status: Status = Status.passed, dents: int = 0) -> InspectionResult:
    t = T0 + seq * 10**9
    return InspectionResult(
        defects=[dent(i) for i in range(dents)],
        id=make_result_id("l", "s", seq, t), line="l", station="s", part="p", serial=f"S{seq}",
        seq=seq, triggered_ns=t, status=status, rms_mm=0.02, software_version=software_version(),
        comparison=[PointResult(name="c", deviation_mm=dev, lower_mm=-0.5, upper_mm=0.5,
                                support=30, verdict="pass")],
    )  # fmt: skip


@pytest.fixture
def store():
    s = ResultStore(":memory:")
    yield s
    s.close()


def run(store, monitor, devs, start=0):
    raised = []
    monitor.alarms = [raised.append]
    for i, d in enumerate(devs, start=start):
        r = res(i, d)
        store.put(r)
        monitor(Outcome(r), None)
    return raised


def test_no_alarm_while_the_baseline_fills_then_one_per_excursion(store):
    rng = np.random.default_rng(0)
    monitor = SpcMonitor(store, SpcSettings(baseline_parts=10))
    assert run(store, monitor, [5.0] + list(rng.normal(0, 0.01, 9))) == []  # no limits yet
    # The first part (5.0) sits in the baseline and widens it: freeze a clean one instead.
    store.put_baseline(freeze_baseline(store, "p", since_ns=T0 + 1, until_ns=None, by="t"))
    drift = [0.0, 0.3, 0.35, 0.4, 0.0, 0.45]
    raised = run(store, monitor, drift, start=10)
    assert [(a.feature, a.rule, a.seq) for a in raised] == [
        ("c", "nelson1", 11),
        ("c", "nelson1", 15),
    ]
    assert raised[0].result_id == res(11, 0).id and raised[0].value == pytest.approx(0.3)


def test_results_without_a_measurement_raise_nothing(store):
    monitor = SpcMonitor(store, SpcSettings(baseline_parts=3))
    run(store, monitor, [0.0, 0.01, -0.01, 0.0])
    r = res(9, 9.0, Status.error)
    store.put(r)
    got = []
    monitor.alarms = [got.append]
    monitor(Outcome(r), None)
    assert got == []


def test_xbar_r_chart_from_the_spec_subgroup(store):
    devs = np.random.default_rng(1).normal(0, 0.02, 31)
    for i, d in enumerate(devs):
        store.put(res(i, float(d)))
    ch = part_chart(store, "p", "c", SpcSettings(baseline_parts=12), subgroup=3)
    assert ch.limits.subgroup == 3 and ch.limits.n == 4  # twelve parts: four subgroups
    assert len(ch.points) == 10  # 31 parts: ten whole subgroups, the last part waits
    groups = devs[:30].reshape(10, 3)
    assert [p.value for p in ch.points] == pytest.approx(groups.mean(axis=1))
    assert [p.spread for p in ch.points] == pytest.approx(np.ptp(groups, axis=1))
    assert ch.points[0].serial == "S2"  # a subgroup is plotted at its last part
    assert ch.limits.ucl - ch.limits.center == pytest.approx(3 * ch.limits.sigma)


def test_part_features_are_charted_with_their_units(store):
    for i in range(25):
        store.put(res(i, 0.01 * (i % 2)))
    rms = part_chart(store, "p", "fit_rms", SpcSettings())
    defects = part_chart(store, "p", "defects", SpcSettings())
    assert rms.unit == "mm" and defects.unit == "count" and rms.capability is None
    assert len(rms.points) == len(defects.points) == 25


def test_defect_counts_get_a_c_chart_where_one_dent_is_no_excursion(store):
    # One dented part in ten through the baseline: c-bar 0.1, upper limit 2 dents.
    monitor = SpcMonitor(store, SpcSettings(baseline_parts=20))
    raised = []
    monitor.alarms = [raised.append]
    for i in range(40):
        r = res(i, 0.0, dents={5: 1, 15: 1, 24: 1, 28: 2, 31: 3}.get(i, 0))
        store.put(r)
        monitor(Outcome(r), None)
    ch = part_chart(store, "p", "defects", SpcSettings(baseline_parts=20))
    assert ch.limits.kind == "c" and ch.limits.center == pytest.approx(0.1)
    assert ch.limits.ucl == 2.0
    assert all(p.spread is None for p in ch.points)
    assert [(a.feature, a.seq) for a in raised if a.feature == "defects"] == [("defects", 31)]
    # Frozen, the count keeps its c chart.
    frozen = freeze_baseline(store, "p", since_ns=None, until_ns=None, by="qe")
    assert frozen.limits["defects"].kind == "c" and frozen.limits["c"].kind == "individuals"


def test_a_defect_free_baseline_gives_no_count_limits_and_says_why(store):
    for i in range(25):
        store.put(res(i, 0.0, dents=1 if i == 22 else 0))
    ch = part_chart(store, "p", "defects", SpcSettings(baseline_parts=20))
    assert ch.limits is None and "none in the 20 baseline parts" in ch.limits_note
    assert [p.value for p in ch.points][22] == 1.0 and all(not p.rules for p in ch.points)


def test_a_part_whose_surface_was_not_checked_has_no_defect_count(store):
    from service.spc import feature_values

    checked = [res(i, 0.0, dents=i % 2) for i in range(4)]
    unchecked = [r.model_copy(update={"defects": None, "path": "comparison_points"})
                 for r in (res(i, 0.0) for i in range(4, 8))]  # fmt: skip
    values = feature_values([*checked, *unchecked], "defects")
    assert values[:4].tolist() == [0.0, 1.0, 0.0, 1.0]
    assert np.isnan(values[4:]).all()  # not measured, not zero
    for r in [*checked, *unchecked]:
        store.put(r)
    chart = part_chart(store, "p", "defects", SpcSettings())
    assert len(chart.points) == 4
