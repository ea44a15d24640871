"""Statistical process control: control limits, run rules and capability of a measured feature.

Individuals and moving-range charts (subgroups of one, the usual case on a
line that measures every part) and X-bar/R charts (subgroups of ``n``) take
their limits from a *baseline*: the values of a period the process was
judged stable in. Limits use the *within* sigma (the short-term spread, from
the average moving range or the average range over ``d2``), never the
overall standard deviation, so that a drift widens nothing and stands out.

A count of nonconformities per part (surface defects) is charted on a *c
chart* (ISO 7870-3): counts of rare events follow Poisson. An individuals
chart on them puts its upper limit below one and flags every part with a
single defect; even the c chart's ``c-bar + 3 sqrt(c-bar)`` does at a small
c-bar (0.72 at 0.05), so its limits are Poisson *probability limits*: the
counts beyond which a stable process falls no more often than a normal one
beyond 3 sigma (0.135 % a side). The zone rules assume a symmetric spread,
which a count of rare events is not (nine defect-free parts in a row sit
"below the centre line" most of the time), so a c chart is checked by the
beyond-limits rule alone.

Run rules follow ISO 7870-2 / Western Electric / Nelson. Each rule has a
stable name; ISO 7870-2 recommends the 3-sigma rule alone for routine use
(every further rule adds false alarms), which is :data:`DEFAULT_RULES`.

Capability follows ISO 22514: ``Cp``/``Cpk`` with the within sigma (what the
process could do), ``Pp``/``Ppk`` with the overall sigma (what it did), each
with its sample size and a confidence interval; below a minimum sample size
none is given, and the reason says why.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy import stats

from .errors import InvalidInput

# Control chart constants for subgroups of n (ASTM STP 15D / ISO 7870-2, Table 2).
D2: dict[int, float] = {
    2: 1.128, 3: 1.693, 4: 2.059, 5: 2.326, 6: 2.534, 7: 2.704, 8: 2.847, 9: 2.970, 10: 3.078,
}  # fmt: skip
D3: dict[int, float] = {
    2: 0.0, 3: 0.0, 4: 0.0, 5: 0.0, 6: 0.0, 7: 0.076, 8: 0.136, 9: 0.184, 10: 0.223,
}  # fmt: skip
D4: dict[int, float] = {
    2: 3.267, 3: 2.574, 4: 2.282, 5: 2.114, 6: 2.004, 7: 1.924, 8: 1.864, 9: 1.816, 10: 1.777,
}  # fmt: skip

MAX_SUBGROUP = 10
"""Largest subgroup of an X-bar/R chart (beyond it the range wastes the data)."""

MIN_BASELINE = 2
"""Fewest baseline values (individuals) or subgroups that give a within sigma."""

RULES: dict[str, str] = {
    "nelson1": "one point beyond the control limits (3 sigma)",
    "nelson2": "nine points in a row on one side of the centre line",
    "nelson3": "six points in a row steadily increasing or decreasing",
    "nelson4": "fourteen points in a row alternating up and down",
    "nelson5": "two of three points in a row beyond 2 sigma on one side",
    "nelson6": "four of five points in a row beyond 1 sigma on one side",
    "nelson7": "fifteen points in a row within 1 sigma",
    "nelson8": "eight points in a row beyond 1 sigma on either side",
    "we4": "eight points in a row on one side of the centre line",
}
"""Every run rule by its name. Western Electric's rules 1-3 are Nelson's 1, 5 and 6."""

RULE_SETS: dict[str, tuple[str, ...]] = {
    "iso7870": ("nelson1",),
    "western_electric": ("nelson1", "nelson5", "nelson6", "we4"),
    "nelson": tuple(f"nelson{i}" for i in range(1, 9)),
}
"""Named sets of rules; a config may list rules or sets."""

DEFAULT_RULES: tuple[str, ...] = RULE_SETS["iso7870"]

TAIL = float(stats.norm.sf(3.0))
"""Probability of a stable normal value beyond 3 sigma on one side (0.135 %)."""

C_CHART_RULES: tuple[str, ...] = ("nelson1",)
"""The rules a c chart is checked by (see the module's note)."""

MIN_CAPABILITY_N = 25
"""Fewest values that give a capability figure by default: below it the
confidence interval of Cpk spans more than +-0.4 at Cpk = 1.33."""


def resolve_rules(names: Sequence[str]) -> tuple[str, ...]:
    """Rule names and set names (``western_electric``, ...) as distinct rule names, in order."""
    out: list[str] = []
    for name in names:
        members = RULE_SETS.get(name, (name,))
        for m in members:
            if m not in RULES:
                known = ", ".join([*RULES, *RULE_SETS])
                raise InvalidInput(f"unknown run rule {name!r}; known: {known}")
            if m not in out:
                out.append(m)
    return tuple(out)


ChartKind = Literal["individuals", "xbar_r", "c"]


@dataclass(frozen=True)
class Limits:
    """Control limits of a chart, in the measured unit (mm for deviations).

    Attributes
    ----------
    center : float
        Centre line (the baseline's mean, or mean of subgroup means).
    sigma : float
        Within sigma of one value (individuals) or of one subgroup's mean.
    lcl, ucl : float
        ``center -+ 3 sigma``.
    spread_center, spread_ucl, spread_lcl : float or None
        The moving-range (or range) chart's centre and limits; None on a c chart.
    subgroup : int
        1 for individuals (and c), else the X-bar/R subgroup size.
    n : int
        Baseline values (individuals, c) or subgroups used.
    kind : str
        ``"individuals"``, ``"xbar_r"`` or ``"c"``.
    """

    center: float
    sigma: float
    lcl: float
    ucl: float
    spread_center: float | None
    spread_lcl: float | None
    spread_ucl: float | None
    subgroup: int
    n: int
    kind: ChartKind = "individuals"

    @property
    def rules_apply(self) -> tuple[str, ...] | None:
        """The rules this kind of chart admits (None: all of them)."""
        return C_CHART_RULES if self.kind == "c" else None


def within_sigma(x: npt.ArrayLike) -> float:
    """Short-term sigma from the average moving range of two, ``MR-bar / d2``.

    Parameters
    ----------
    x : (n,) float, n >= 2, in time order
    """
    a = _values(x, at_least=2)
    return float(np.mean(np.abs(np.diff(a)))) / D2[2]


def individuals_limits(baseline: npt.ArrayLike) -> Limits:
    """Limits of an individuals and moving-range chart from baseline values in time order.

    Parameters
    ----------
    baseline : (n,) float, n >= :data:`MIN_BASELINE`
    """
    a = _values(baseline, at_least=MIN_BASELINE)
    mr_bar = float(np.mean(np.abs(np.diff(a))))
    sigma = mr_bar / D2[2]
    center = float(a.mean())
    return Limits(
        center=center, sigma=sigma, lcl=center - 3 * sigma, ucl=center + 3 * sigma,
        spread_center=mr_bar, spread_lcl=0.0, spread_ucl=D4[2] * mr_bar, subgroup=1, n=len(a),
    )  # fmt: skip


def subgroups(x: npt.ArrayLike, size: int) -> npt.NDArray[np.float64]:
    """Consecutive values as whole subgroups, ``(len(x) // size, size)``; a partial tail is left."""
    if not 2 <= size <= MAX_SUBGROUP:
        raise InvalidInput(f"a subgroup holds 2..{MAX_SUBGROUP} values, got {size}")
    a = _values(x, at_least=0)
    k = len(a) // size
    return a[: k * size].reshape(k, size)


def xbar_r_limits(groups: npt.ArrayLike) -> Limits:
    """Limits of an X-bar and R chart from baseline subgroups.

    Parameters
    ----------
    groups : (k, n) float, k >= :data:`MIN_BASELINE` subgroups of n in 2..10 values
    """
    g = np.asarray(groups, dtype=np.float64)
    if g.ndim != 2 or not 2 <= g.shape[1] <= MAX_SUBGROUP or g.shape[0] < MIN_BASELINE:
        raise InvalidInput(
            f"need (k >= {MIN_BASELINE}, 2..{MAX_SUBGROUP}) subgroups, got shape {g.shape}"
        )
    if not np.isfinite(g).all():
        raise InvalidInput("subgroup values must be finite")
    n = g.shape[1]
    r_bar = float(np.mean(g.max(axis=1) - g.min(axis=1)))
    center = float(g.mean())
    sigma = r_bar / D2[n] / math.sqrt(n)  # sigma of a subgroup's mean
    return Limits(
        center=center, sigma=sigma, lcl=center - 3 * sigma, ucl=center + 3 * sigma,
        spread_center=r_bar, spread_lcl=D3[n] * r_bar, spread_ucl=D4[n] * r_bar, subgroup=n,
        n=g.shape[0], kind="xbar_r",
    )  # fmt: skip


def c_limits(baseline: npt.ArrayLike) -> Limits:
    """Limits of a c chart from baseline counts of nonconformities per part.

    The centre is c-bar, sigma ``sqrt(c-bar)``; ``ucl`` is the largest count
    a Poisson process of mean c-bar exceeds with probability at most
    :data:`TAIL`, ``lcl`` the smallest it falls below as rarely (0 when no
    count can): a count above ``ucl`` or below ``lcl`` is beyond the limits.

    Parameters
    ----------
    baseline : (n,) float, whole numbers >= 0, n >= :data:`MIN_BASELINE`

    Raises
    ------
    InvalidInput
        Counts that are negative or fractional, or a baseline without a single
        nonconformity: its limits would be zero and every later one an alarm.
    """
    a = _values(baseline, at_least=MIN_BASELINE)
    if (a < 0).any() or (a != np.round(a)).any():
        raise InvalidInput("a c chart counts: its values must be whole numbers >= 0")
    center = float(a.mean())
    if center == 0:
        raise InvalidInput(
            f"none in the {len(a)} baseline parts: a count chart needs a baseline that has some"
        )
    ucl = float(stats.poisson.ppf(1 - TAIL, center))
    lcl = float(stats.poisson.ppf(TAIL, center))
    return Limits(
        center=center, sigma=math.sqrt(center), lcl=lcl, ucl=ucl, spread_center=None,
        spread_lcl=None, spread_ucl=None, subgroup=1, n=len(a), kind="c",
    )  # fmt: skip


@dataclass(frozen=True)
class RuleHit:
    """A run rule that holds at ``index`` (the last point of the run that makes it hold)."""

    rule: str
    index: int
    description: str


def run_rules(
    x: npt.ArrayLike, limits: Limits, rules: Sequence[str] = DEFAULT_RULES
) -> list[RuleHit]:
    """Every point at which one of ``rules`` holds, in index order, then rule order.

    Parameters
    ----------
    x : (n,) float
        The plotted values in time order (individuals, or subgroup means).
    limits : Limits
        ``center`` and ``sigma`` define the zones.
    rules : sequence of str
        Names of :data:`RULES` (or of :data:`RULE_SETS`); of them, a chart
        checks those its kind admits (:attr:`Limits.rules_apply`).
    """
    a = _values(x, at_least=0)
    names = resolve_rules(rules)
    admitted = limits.rules_apply
    if admitted is not None:
        names = tuple(n for n in names if n in admitted)
    if limits.sigma <= 0:
        # A baseline without spread (every value alike) has no zones: only a
        # value off the centre line can be flagged, and it is by rule 1.
        z = np.zeros_like(a)
        z[a > limits.center] = np.inf
        z[a < limits.center] = -np.inf
    else:
        z = (a - limits.center) / limits.sigma
    # Beyond the limits themselves: the same as |z| > 3 where they are 3 sigma, and
    # right for a c chart's probability limits too.
    beyond = (a > limits.ucl) | (a < limits.lcl)
    hits = []
    for i in range(len(a)):
        for name in names:
            if beyond[i] if name == "nelson1" else _holds(name, z, i):
                hits.append(RuleHit(name, i, RULES[name]))
    return hits


def _holds(rule: str, z: npt.NDArray[np.float64], i: int) -> bool:
    def last(k: int) -> npt.NDArray[np.float64] | None:
        return z[i - k + 1 : i + 1] if i + 1 >= k else None

    if rule in ("nelson2", "we4"):
        w = last(9 if rule == "nelson2" else 8)
        return w is not None and bool((w > 0).all() or (w < 0).all())
    if rule == "nelson3":
        w = last(6)
        if w is None:
            return False
        d = np.diff(w)
        return bool((d > 0).all() or (d < 0).all())
    if rule == "nelson4":
        w = last(14)
        if w is None:
            return False
        d = np.sign(np.diff(w))
        return bool((d != 0).all() and (d[1:] * d[:-1] < 0).all())
    if rule in ("nelson5", "nelson6"):
        k, m, zone = (3, 2, 2.0) if rule == "nelson5" else (5, 4, 1.0)
        w = last(k)
        if w is None:
            return False
        # The run must end on a point in the zone, or the hit is the earlier one's.
        side = np.sign(z[i])
        return bool(abs(z[i]) > zone and np.sum(w * side > zone) >= m)
    if rule == "nelson7":
        w = last(15)
        return w is not None and bool((np.abs(w) < 1).all())
    if rule == "nelson8":
        w = last(8)
        return w is not None and bool((np.abs(w) > 1).all() and (w > 0).any() and (w < 0).any())
    raise InvalidInput(f"unknown run rule {rule!r}")


@dataclass(frozen=True)
class Interval:
    """A two-sided confidence interval at ``level`` (0.95: 95 %)."""

    low: float
    high: float
    level: float


@dataclass(frozen=True)
class Capability:
    """Capability of a feature against its tolerance ``[lower, upper]``.

    ``cp``/``cpk`` use the within sigma (average moving range over d2): the
    potential of the process as it runs part to part. ``pp``/``ppk`` use the
    overall sample standard deviation: what it delivered over the window,
    drift included. Every figure is None when ``reason`` says why there is none.
    """

    n: int
    mean: float | None
    sigma_within: float | None
    sigma_overall: float | None
    cp: float | None
    cpk: float | None
    pp: float | None
    ppk: float | None
    cp_ci: Interval | None
    cpk_ci: Interval | None
    pp_ci: Interval | None
    ppk_ci: Interval | None
    reason: str | None


def capability(
    x: npt.ArrayLike,
    lower: float,
    upper: float,
    *,
    min_n: int = MIN_CAPABILITY_N,
    level: float = 0.95,
) -> Capability:
    """Cp, Cpk, Pp and Ppk of values in time order, with confidence intervals.

    ``C = (upper - lower) / (6 sigma)``, ``Ck = min(upper - mean, mean - lower)
    / (3 sigma)``. Intervals: Cp and Pp from the chi-square distribution of
    the variance with n - 1 degrees of freedom; Cpk and Ppk by Bissell's
    normal approximation, ``Ck +- z sqrt(1 / (9 n) + Ck^2 / (2 (n - 1)))``.

    Parameters
    ----------
    x : (n,) float
        Measured values in time order (NaN: not measured, left out).
    lower, upper : float
        Tolerance limits, ``lower < upper``.
    min_n : int
        Fewest values that give a figure (at least 2).
    level : float
        Confidence of the intervals, in (0, 1).
    """
    if not lower < upper:
        raise InvalidInput(f"the tolerance needs lower < upper, got [{lower}, {upper}]")
    if min_n < 2:
        raise InvalidInput(f"min_n must be at least 2, got {min_n}")
    if not 0 < level < 1:
        raise InvalidInput(f"level must lie in (0, 1), got {level}")
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    a = a[np.isfinite(a)]
    n = len(a)
    mean = float(a.mean()) if n else None
    none = dict(cp=None, cpk=None, pp=None, ppk=None, cp_ci=None, cpk_ci=None, pp_ci=None,
                ppk_ci=None)  # fmt: skip
    if n < min_n:
        return Capability(
            n=n, mean=mean, sigma_within=None, sigma_overall=None, **none,
            reason=f"{n} values, fewer than the {min_n} a capability figure needs: "
            "with so few, its confidence interval is too wide to say anything",
        )  # fmt: skip
    assert mean is not None
    s_within = within_sigma(a)
    s_overall = float(a.std(ddof=1))
    if s_within <= 0 or s_overall <= 0:
        return Capability(
            n=n, mean=mean, sigma_within=s_within, sigma_overall=s_overall, **none,
            reason="the values do not vary (the gauge's resolution is too coarse for them)",
        )  # fmt: skip
    width = upper - lower
    near = min(upper - mean, mean - lower)
    cp, cpk = width / (6 * s_within), near / (3 * s_within)
    pp, ppk = width / (6 * s_overall), near / (3 * s_overall)
    return Capability(
        n=n, mean=mean, sigma_within=s_within, sigma_overall=s_overall,
        cp=cp, cpk=cpk, pp=pp, ppk=ppk,
        cp_ci=_ratio_interval(cp, n, level), cpk_ci=_k_interval(cpk, n, level),
        pp_ci=_ratio_interval(pp, n, level), ppk_ci=_k_interval(ppk, n, level),
        reason=None,
    )  # fmt: skip


def _ratio_interval(c: float, n: int, level: float) -> Interval:
    alpha = 1 - level
    lo = c * math.sqrt(stats.chi2.ppf(alpha / 2, n - 1) / (n - 1))
    hi = c * math.sqrt(stats.chi2.ppf(1 - alpha / 2, n - 1) / (n - 1))
    return Interval(float(lo), float(hi), level)


def _k_interval(ck: float, n: int, level: float) -> Interval:
    z = float(stats.norm.ppf(1 - (1 - level) / 2))
    half = z * math.sqrt(1 / (9 * n) + ck * ck / (2 * (n - 1)))
    return Interval(ck - half, ck + half, level)


def _values(x: npt.ArrayLike, *, at_least: int) -> npt.NDArray[np.float64]:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise InvalidInput(f"values must be one-dimensional, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InvalidInput("values must be finite")
    if len(a) < at_least:
        raise InvalidInput(f"need at least {at_least} values, got {len(a)}")
    return a
