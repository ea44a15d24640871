"""Control limits, run rules and capability against hand-worked values and seeded processes."""

import numpy as np
import pytest
from scipy import stats

from inspection.errors import InvalidInput
from inspection.spc import (
    D2,
    DEFAULT_RULES,
    RULES,
    TAIL,
    c_limits,
    capability,
    individuals_limits,
    resolve_rules,
    run_rules,
    subgroups,
    within_sigma,
    xbar_r_limits,
)


def test_individuals_limits_by_hand():
    x = [10.0, 12.0, 11.0, 13.0, 12.0]
    lim = individuals_limits(x)
    mr_bar = (2 + 1 + 2 + 1) / 4
    assert lim.center == pytest.approx(11.6)
    assert lim.sigma == pytest.approx(mr_bar / 1.128)
    assert lim.ucl == pytest.approx(11.6 + 3 * mr_bar / 1.128)
    assert lim.spread_ucl == pytest.approx(3.267 * mr_bar)
    assert (lim.subgroup, lim.n) == (1, 5)


def test_xbar_r_limits_by_hand():
    g = np.array([[1.0, 2.0, 3.0], [2.0, 2.0, 5.0]])
    lim = xbar_r_limits(g)
    r_bar = (2 + 3) / 2
    assert lim.center == pytest.approx(g.mean())
    assert lim.sigma == pytest.approx(r_bar / D2[3] / np.sqrt(3))
    assert lim.spread_ucl == pytest.approx(2.574 * r_bar)
    assert subgroups(np.arange(7.0), 3).shape == (2, 3)


def test_within_sigma_recovers_a_stable_process():
    x = np.random.default_rng(1).normal(0.0, 0.02, 5000)
    assert within_sigma(x) == pytest.approx(0.02, rel=0.03)


def test_a_drift_widens_the_overall_sigma_not_the_within():
    rng = np.random.default_rng(2)
    x = rng.normal(0.0, 0.01, 200) + np.linspace(0, 0.1, 200)
    cap = capability(x, -0.2, 0.2)
    assert cap.sigma_within == pytest.approx(0.01, rel=0.15)
    assert cap.sigma_overall == pytest.approx(np.std(x, ddof=1))
    assert cap.cp > cap.pp and cap.cpk > cap.ppk


def test_capability_by_hand_and_its_interval_covers_the_truth():
    rng = np.random.default_rng(3)
    x = rng.normal(0.05, 0.05, 400)
    cap = capability(x, -0.3, 0.3)
    s = np.std(x, ddof=1)
    assert cap.pp == pytest.approx(0.6 / (6 * s))
    assert cap.ppk == pytest.approx(min(0.3 - x.mean(), x.mean() + 0.3) / (3 * s))
    assert cap.pp_ci.low < 2.0 < cap.pp_ci.high  # true Pp = 0.6 / 0.3
    assert cap.ppk_ci.low < 0.25 / 0.15 < cap.ppk_ci.high
    assert cap.n == 400 and cap.reason is None


def test_no_capability_below_the_minimum_sample_and_it_says_why():
    cap = capability([0.01, 0.02, 0.0], -0.1, 0.1, min_n=25)
    assert cap.n == 3
    assert cap.cp is None and cap.cpk is None and cap.pp is None and cap.ppk is None
    assert "3 values" in cap.reason and "25" in cap.reason


def test_capability_leaves_out_values_not_measured():
    x = np.r_[np.random.default_rng(4).normal(0, 0.01, 30), np.nan]
    assert capability(x, -0.1, 0.1).n == 30


@pytest.mark.parametrize(
    ("bad", "kwargs"),
    [
        ([0.0] * 30, {"lower": 1.0, "upper": 0.0}),
        ([0.0] * 30, {"lower": 0, "upper": 1, "min_n": 1}),
    ],
)
def test_capability_refuses_bad_input(bad, kwargs):
    with pytest.raises(InvalidInput):
        capability(bad, **kwargs)


STABLE = individuals_limits(np.random.default_rng(5).normal(0.0, 1.0, 2000))


def _fired(x, rules):
    return {(h.rule, h.index) for h in run_rules(x, STABLE, rules)}


def test_the_default_is_the_three_sigma_rule_alone():
    assert DEFAULT_RULES == ("nelson1",)
    run = [0.5] * 12  # nine in a row on one side: not a default alarm
    assert _fired(run, DEFAULT_RULES) == set()
    assert ("nelson1", 3) in _fired([0, 0, 0, 3.5, 0], DEFAULT_RULES)


@pytest.mark.parametrize(
    ("rule", "x", "first"),
    [
        ("nelson1", [0, 0, -3.4], 2),
        ("nelson2", [0.3] * 9, 8),
        ("we4", [-0.3] * 8, 7),
        ("nelson3", [0.0, 0.1, 0.2, 0.3, 0.4, 0.5], 5),
        ("nelson4", [0.5, -0.5] * 7, 13),
        ("nelson5", [2.5, 0.0, 2.5], 2),
        ("nelson6", [1.5, 1.5, 0.0, 1.5, 1.5], 4),
        ("nelson7", [0.1, -0.1] * 8, 14),
        ("nelson8", [1.5, -1.5] * 4, 7),
    ],
)
def test_each_rule_fires_first_where_its_run_completes(rule, x, first):
    hits = [h.index for h in run_rules(x, STABLE, [rule])]
    assert hits and hits[0] == first
    assert not [h for h in run_rules(np.asarray(x)[:first], STABLE, [rule])]


def test_a_stable_process_rarely_fires_the_default_rule():
    x = np.random.default_rng(6).normal(0.0, 1.0, 1000)
    hits = run_rules(x, STABLE, DEFAULT_RULES)
    assert len(hits) < 10  # 0.27 % expected: about 3


def test_rule_sets_expand_and_unknown_rules_are_refused():
    assert resolve_rules(["western_electric"]) == ("nelson1", "nelson5", "nelson6", "we4")
    assert set(resolve_rules(["nelson"])) <= set(RULES)
    with pytest.raises(InvalidInput, match="unknown run rule"):
        resolve_rules(["nelson9"])


def test_limits_refuse_too_few_or_non_finite_values():
    with pytest.raises(InvalidInput):
        individuals_limits([1.0])
    with pytest.raises(InvalidInput):
        individuals_limits([1.0, np.nan, 2.0])
    with pytest.raises(InvalidInput):
        xbar_r_limits(np.zeros((1, 3)))


def test_a_baseline_without_spread_flags_any_other_value_by_the_first_rule():
    flat = individuals_limits([0.0, 0.0, 0.0])
    hits = run_rules([0.0, 0.0, 1.0], flat, ["nelson1", "nelson2"])
    assert [(h.rule, h.index) for h in hits] == [("nelson1", 2)]


def test_c_chart_has_poisson_probability_limits_and_a_single_rare_defect_stays_inside():
    counts = [0] * 18 + [1, 1]  # one defect in ten parts
    lim = c_limits(counts)
    assert lim.kind == "c" and lim.n == 20 and lim.spread_center is None
    assert lim.center == pytest.approx(0.1) and lim.sigma == pytest.approx(0.1**0.5)
    # P(X > 2 | 0.1) = 1.5e-4 <= 0.135 % < P(X > 1 | 0.1) = 4.7e-3.
    assert (lim.lcl, lim.ucl) == (0.0, 2.0)
    # An individuals chart on the same counts puts its upper limit below one.
    assert individuals_limits(counts).ucl < 1.0
    later = [0, 1, 0, 2, 3, 0]
    assert [(h.rule, h.index) for h in run_rules(later, lim)] == [("nelson1", 4)]
    # The zone rules assume a symmetric spread: a long defect-free run is no signal.
    assert run_rules([0] * 12, lim, ["nelson1", "nelson2", "we4", "nelson7"]) == []


@pytest.mark.parametrize("c_bar", [0.05, 0.1, 0.5, 2.0, 16.0])
def test_c_chart_limits_hold_the_normal_tail_probability(c_bar):
    n = 40
    lim = c_limits([c_bar * n] + [0.0] * (n - 1))
    assert lim.center == pytest.approx(c_bar)
    # ucl: the least count exceeded no more often than 3 sigma of a normal value is.
    assert stats.poisson.sf(lim.ucl, c_bar) <= TAIL < stats.poisson.sf(lim.ucl - 1, c_bar)
    below = stats.poisson.cdf(lim.lcl - 1, c_bar)
    assert below <= TAIL and (lim.lcl == 0 or stats.poisson.cdf(lim.lcl, c_bar) > TAIL)
    assert (lim.lcl > 0) == (c_bar == 16.0)


def test_c_chart_refuses_what_is_not_a_count_or_a_baseline_without_any():
    with pytest.raises(InvalidInput, match="whole numbers"):
        c_limits([0.0, 1.5, 2.0])
    with pytest.raises(InvalidInput, match="whole numbers"):
        c_limits([0.0, -1.0, 2.0])
    with pytest.raises(InvalidInput, match="none in the 5 baseline parts"):
        c_limits([0, 0, 0, 0, 0])
