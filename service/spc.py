"""Control charts, capability and their alarms over the stored results of a part.

A part's charted *features* are its comparison points (the deviation, mm),
its fit's RMS (``fit_rms``, mm) and its count of surface defects
(``defects``, on a c chart). Limits come from the part's frozen baseline when a person
froze one (``POST /v1/parts/{name}/baseline``), else from the part's first
``baseline_parts`` results: until there are that many, a chart has no limits
and says so. The arithmetic is :mod:`inspection.spc`'s.

:class:`SpcMonitor` is a result sink: after each measured part it charts the
part's features and raises an ``spc_rule`` alarm when a run rule holds at
the newest point and did not at the one before (a new excursion, not one
alarm per part of the same run).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from inspection import spc
from inspection.deviations import Verdict
from inspection.errors import InvalidInput

from .config import SpcSection
from .models import (
    Alarm,
    AlarmKind,
    Baseline,
    ChartLimits,
    ChartPoint,
    ConfidenceInterval,
    ControlChart,
    InspectionResult,
    Trend,
    TrendPoint,
    finite_or_none,
)
from .pipeline import Outcome
from .protocol import FrameSet
from .store import ResultStore

log = logging.getLogger(__name__)

FIT_RMS = "fit_rms"
DEFECTS = "defects"
PART_FEATURES = (FIT_RMS, DEFECTS)
"""Features of every measured part, besides its comparison points."""

AlarmSink = Callable[[Alarm], object]


@dataclass(frozen=True)
class SpcSettings:
    """The ``[spc]`` section as the charts take it."""

    rules: tuple[str, ...] = spc.DEFAULT_RULES
    baseline_parts: int = 100
    window: int = 100
    min_capability_n: int = spc.MIN_CAPABILITY_N
    alarms: bool = True

    @classmethod
    def from_config(cls, section: SpcSection) -> SpcSettings:
        return cls(
            rules=spc.resolve_rules(section.rules),
            baseline_parts=section.baseline_parts,
            window=section.window,
            min_capability_n=section.min_capability_n,
            alarms=section.alarms,
        )


def features(results: Sequence[InspectionResult]) -> list[str]:
    """The comparison points of the results (in the newest result's order), then the part's."""
    names: list[str] = []
    for r in reversed(results):
        for c in r.comparison:
            if c.name not in names:
                names.append(c.name)
    return [*names, *PART_FEATURES]


def feature_values(results: Sequence[InspectionResult], feature: str) -> np.ndarray:
    """``(len(results),)`` float: the feature of each result; NaN where it was not measured."""
    out = np.full(len(results), np.nan)
    for i, r in enumerate(results):
        if feature == FIT_RMS:
            v = r.rms_mm
        elif feature == DEFECTS:
            v = None if r.defects is None else float(len(r.defects))
        else:
            c = next((c for c in r.comparison if c.name == feature), None)
            v = None if c is None or c.verdict == Verdict.NOT_MEASURABLE else c.deviation_mm
        if v is not None:
            out[i] = v
    return out


def tolerance(results: Sequence[InspectionResult], feature: str) -> tuple[float, float] | None:
    """The newest limits of a comparison point in ``results`` (None for part features)."""
    for r in reversed(results):
        for c in r.comparison:
            if c.name == feature:
                return c.lower_mm, c.upper_mm
    return None


def chart_subgroup(feature: str, subgroup: int) -> int:
    """The subgroup a feature is charted in: a count is charted per part."""
    return 1 if feature == DEFECTS else subgroup


def limits_from(values: np.ndarray, subgroup: int, feature: str = "") -> spc.Limits:
    """Limits from baseline values (NaN left out); raises InvalidInput when too few.

    The defect count gets a c chart; any other feature an individuals chart
    (``subgroup`` 1) or an X-bar/R chart.
    """
    finite = values[np.isfinite(values)]
    if feature == DEFECTS:
        return spc.c_limits(finite)
    if subgroup == 1:
        return spc.individuals_limits(finite)
    return spc.xbar_r_limits(spc.subgroups(finite, subgroup))


def _public_limits(lim: spc.Limits, *, frozen: bool, by: str | None = None,
                   at: int | None = None) -> ChartLimits:  # fmt: skip
    return ChartLimits(
        center=lim.center, sigma=lim.sigma, lcl=lim.lcl, ucl=lim.ucl,
        spread_center=lim.spread_center, spread_lcl=lim.spread_lcl, spread_ucl=lim.spread_ucl,
        subgroup=lim.subgroup, n=lim.n, kind=lim.kind, frozen=frozen, frozen_by=by, frozen_ns=at,
    )  # fmt: skip


def _inner_limits(c: ChartLimits) -> spc.Limits:
    return spc.Limits(
        center=c.center, sigma=c.sigma, lcl=c.lcl, ucl=c.ucl, spread_center=c.spread_center,
        spread_lcl=c.spread_lcl, spread_ucl=c.spread_ucl, subgroup=c.subgroup, n=c.n, kind=c.kind,
    )  # fmt: skip


def chart(
    part: str,
    feature: str,
    results: Sequence[InspectionResult],
    *,
    first: Sequence[InspectionResult],
    baseline: Baseline | None,
    settings: SpcSettings,
    subgroup: int = 1,
) -> ControlChart:
    """The control chart of one feature over ``results`` (oldest first).

    Parameters
    ----------
    first : sequence of InspectionResult
        The part's first ``settings.baseline_parts`` results: the provisional
        baseline while none is frozen.
    baseline : Baseline, optional
        The part's frozen baseline; its limits win where it has the feature.
    subgroup : int
        The part spec's subgroup size (1: individuals).
    """
    subgroup = chart_subgroup(feature, subgroup)
    limits: ChartLimits | None = None
    note = None
    if baseline is not None and feature in baseline.limits:
        limits = baseline.limits[feature]
    else:
        base = feature_values(first, feature)
        need = max(settings.baseline_parts, 2 * subgroup)
        have = int(np.isfinite(base).sum())
        if have < need:
            note = f"collecting a baseline: {have} of the {need} measured parts it needs"
        else:
            try:
                limits = _public_limits(limits_from(base, subgroup, feature), frozen=False)
            except InvalidInput as exc:
                note = f"no limits: {exc}"
    values = feature_values(results, feature)
    points = _points(results, values, subgroup, counts=feature == DEFECTS)
    if limits is not None and points:
        plotted = np.array([p.value for p in points], dtype=np.float64)
        for hit in spc.run_rules(plotted, _inner_limits(limits), settings.rules):
            points[hit.index].rules.append(hit.rule)
    tol = tolerance(results, feature)
    capability = None
    if tol is not None and tol[0] < tol[1]:
        capability = trend_point(feature, values, tol, results, settings.min_capability_n)
    return ControlChart(
        part=part,
        feature=feature,
        unit="count" if feature == DEFECTS else "mm",
        rules=list(settings.rules),
        limits=limits,
        limits_note=note,
        lower_mm=tol[0] if tol else None,
        upper_mm=tol[1] if tol else None,
        points=points,
        capability=capability,
    )


def _points(
    results: Sequence[InspectionResult], values: np.ndarray, subgroup: int, *, counts: bool = False
) -> list[ChartPoint]:
    """Plotted points: one per measured value (individuals, counts) or per whole subgroup."""
    keep = [i for i in range(len(results)) if np.isfinite(values[i])]
    out: list[ChartPoint] = []
    if subgroup == 1:
        prev: float | None = None
        for i in keep:
            v = float(values[i])
            r = results[i]
            spread = None if prev is None or counts else abs(v - prev)
            out.append(ChartPoint(result_id=r.id, serial=r.serial, triggered_ns=r.triggered_ns,
                                  value=v, spread=spread))  # fmt: skip
            prev = v
        return out
    for k in range(len(keep) // subgroup):
        idx = keep[k * subgroup : (k + 1) * subgroup]
        g = values[idx]
        r = results[idx[-1]]
        out.append(ChartPoint(result_id=r.id, serial=r.serial, triggered_ns=r.triggered_ns,
                              value=float(g.mean()), spread=float(g.max() - g.min())))  # fmt: skip
    return out


def trend_point(
    name: str,
    values: np.ndarray,
    tol: tuple[float, float],
    results: Sequence[InspectionResult],
    min_n: int,
) -> TrendPoint:
    """Capability of one comparison point (values oldest first, NaN: not measured)."""
    lower, upper = tol
    cap = spc.capability(values, lower, upper, min_n=min_n)
    fails = sum(
        1 for r in results for c in r.comparison if c.name == name and c.verdict == Verdict.FAIL
    )

    def ci(i: spc.Interval | None) -> ConfidenceInterval | None:
        if i is None or not (np.isfinite(i.low) and np.isfinite(i.high)):
            return None
        return ConfidenceInterval(low=i.low, high=i.high, level=i.level)

    return TrendPoint(
        name=name, n=cap.n, mean_mm=finite_or_none(cap.mean),
        sigma_within_mm=finite_or_none(cap.sigma_within),
        sigma_overall_mm=finite_or_none(cap.sigma_overall), lower_mm=lower, upper_mm=upper,
        cp=finite_or_none(cap.cp), cpk=finite_or_none(cap.cpk), pp=finite_or_none(cap.pp),
        ppk=finite_or_none(cap.ppk), cp_ci=ci(cap.cp_ci), cpk_ci=ci(cap.cpk_ci),
        pp_ci=ci(cap.pp_ci), ppk_ci=ci(cap.ppk_ci), capability_note=cap.reason, fails=fails,
    )  # fmt: skip


def trend(store: ResultStore, part: str, window: int, settings: SpcSettings) -> Trend:
    """Capability per comparison point of a part over its last ``window`` measured parts."""
    results = store.measured(part, limit=window)
    points = []
    for name in features(results):
        tol = tolerance(results, name)
        if tol is None or not tol[0] < tol[1]:
            continue
        values = feature_values(results, name)
        points.append(trend_point(name, values, tol, results, settings.min_capability_n))
    return Trend(
        part=part,
        window=window,
        parts=len(results),
        since_ns=results[0].triggered_ns if results else None,
        until_ns=results[-1].triggered_ns if results else None,
        points=points,
    )


def part_chart(
    store: ResultStore, part: str, feature: str, settings: SpcSettings, subgroup: int = 1
) -> ControlChart:
    """The chart of ``feature`` over the part's last ``settings.window`` measured parts."""
    results = store.measured(part, limit=settings.window)
    first = store.measured(part, limit=max(settings.baseline_parts, 2 * subgroup), oldest=True)
    return chart(part, feature, results, first=first, baseline=store.baseline(part),
                 settings=settings, subgroup=subgroup)  # fmt: skip


def freeze_baseline(
    store: ResultStore,
    part: str,
    *,
    since_ns: int | None,
    until_ns: int | None,
    by: str,
    subgroup: int = 1,
    limit: int = 10_000,
) -> Baseline:
    """Limits of every feature from the part's results in a period, kept as its baseline.

    Raises
    ------
    inspection.errors.InvalidInput
        Fewer results in the period than a feature's limits need.
    """
    results = store.measured(
        part, limit=limit, oldest=True, since_ns=since_ns or 0, until_ns=until_ns or 2**63 - 1
    )
    now = time.time_ns()
    limits: dict[str, ChartLimits] = {}
    for feature in features(results):
        values = feature_values(results, feature)
        try:
            lim = limits_from(values, chart_subgroup(feature, subgroup), feature)
        except InvalidInput:
            continue  # a point measured too rarely in the period: it keeps provisional limits
        limits[feature] = _public_limits(lim, frozen=True, by=by, at=now)
    if not limits:
        raise InvalidInput(
            f"{len(results)} measured parts of {part!r} in that period: too few for any limits"
        )
    baseline = Baseline(part=part, since_ns=since_ns, until_ns=until_ns, frozen_ns=now,
                        frozen_by=by, results=len(results), limits=limits)  # fmt: skip
    store.put_baseline(baseline)
    return baseline


class SpcMonitor:
    """A result sink that charts each measured part and raises alarms for run rules.

    Parameters
    ----------
    store : ResultStore
        Holds the result already (the monitor runs after the store's sink).
    settings : SpcSettings
    subgroups : mapping of part name to subgroup size
        Read at each result (a station's parts change as it takes new ones); 1 for a
        part it lacks.
    alarms : iterable of callable(Alarm)
        Where alarms go (zenoh, the store, the streams, the recording).
    """

    def __init__(
        self,
        store: ResultStore,
        settings: SpcSettings,
        *,
        subgroups: Mapping[str, int] | None = None,
        alarms: Iterable[AlarmSink] = (),
    ) -> None:
        self.store = store
        self.settings = settings
        self.subgroups: Mapping[str, int] = subgroups if subgroups is not None else {}
        self.alarms = list(alarms)

    def __call__(self, outcome: Outcome, fs: FrameSet | None) -> None:
        r = outcome.result
        if not self.settings.alarms or r.status.value not in ("pass", "fail"):
            return
        for alarm in self.check(r):
            for sink in self.alarms:
                try:
                    sink(alarm)
                except Exception:
                    log.exception("alarm sink %r failed", sink)

    def check(self, r: InspectionResult) -> list[Alarm]:
        """The alarms the newest result ``r`` raises."""
        subgroup = self.subgroups.get(r.part, 1)
        # The longest rule looks back 15 points: that many subgroups suffice.
        recent = self.store.measured(r.part, limit=16 * subgroup)
        if not recent or recent[-1].id != r.id:
            return []  # a result stored out of order (a replay): its chart moved on
        first = self.store.measured(
            r.part, limit=max(self.settings.baseline_parts, 2 * subgroup), oldest=True
        )
        baseline = self.store.baseline(r.part)
        out = []
        for feature in features([r]):
            ch = chart(r.part, feature, recent, first=first, baseline=baseline,
                       settings=self.settings, subgroup=subgroup)  # fmt: skip
            if not ch.points or ch.points[-1].result_id != r.id:
                continue  # not measured in this part, or a subgroup still filling
            last = ch.points[-1]
            before = set(ch.points[-2].rules) if len(ch.points) > 1 else set()
            for rule in last.rules:
                if rule in before:
                    continue
                assert ch.limits is not None
                out.append(Alarm(
                    kind=AlarmKind.spc_rule,
                    message=(
                        f"{r.part} {feature}: {spc.RULES[rule]} ({rule}) at {r.serial}: "
                        f"{last.value:+.4f} {ch.unit}, limits {ch.limits.lcl:+.4f} .. "
                        f"{ch.limits.ucl:+.4f}"
                    ),
                    triggered_ns=r.triggered_ns, line=r.line, station=r.station, seq=r.seq,
                    raised_ns=time.time_ns(), part=r.part, feature=feature, rule=rule,
                    value=last.value, result_id=r.id, serial=r.serial,
                ))  # fmt: skip
        for a in out:
            log.warning("alarm %s: %s", a.kind.value, a.message)
        return out
