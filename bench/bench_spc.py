"""Control charts: how often a stable process raises an alarm, by baseline size and chart kind.

A chart's limits come from a baseline of the part's first ``baseline_parts``
results (``[spc]``): a short baseline misjudges the within sigma, and every
chart whose sigma came out small alarms on a stable process far more often
than the 0.27 % the 3-sigma rule promises. Printed, for individuals charts
(limits ``mean +- 3 MR-bar / d2``, the line's): the false-alarm probability
per point of an in-control normal process, averaged over baselines, and its
10th and 90th percentiles across them (one line's charts against another's),
by baseline size; then the same per part for a part with eight charts (seven
comparison points and the fit's RMS, the demo panel's). The exact tail
probability of each baseline's limits is used, so the figures carry no
sampling noise of the later points.

For a count of rare defects (Poisson, one dented part in ten): the
probability that a stable part raises an alarm on an individuals chart, on
a c chart with 3-sigma limits (``c-bar + 3 sqrt(c-bar)``) and on the c
chart with Poisson probability limits the line uses (``inspection.spc.c_limits``).

No peer: these are the charts' own figures, the ground for the defaults.
``BENCH_SPC_BASELINES`` (default 20000) baselines per size. Run:
``make bench BENCH=spc``.
"""

from __future__ import annotations

import os
import time

import numpy as np
from scipy import stats

from inspection import spc

SIZES = (20, 30, 50, 100, 200)
CHARTS_PER_PART = 8
DEFECT_RATE = 0.1


def individuals_false_alarms(m: int, baselines: int, rng: np.random.Generator) -> np.ndarray:
    """Per baseline of ``m`` N(0, 1) values: the probability a later value falls outside."""
    x = rng.standard_normal((baselines, m))
    center = x.mean(axis=1)
    sigma = np.abs(np.diff(x, axis=1)).mean(axis=1) / spc.D2[2]
    return stats.norm.cdf(center - 3 * sigma) + stats.norm.sf(center + 3 * sigma)


def count_false_alarms(
    m: int, baselines: int, rng: np.random.Generator
) -> tuple[float, float, float]:
    """Mean probability that a part's defect count alarms: individuals, 3-sigma c, line's c."""
    x = rng.poisson(DEFECT_RATE, (baselines, m)).astype(np.float64)
    center = x.mean(axis=1)
    ind_ucl = center + 3 * np.abs(np.diff(x, axis=1)).mean(axis=1) / spc.D2[2]
    sigma3_ucl = center + 3 * np.sqrt(center)
    keep = center > 0  # a defect-free baseline gives no c limits (and no alarms)
    ours = np.array(
        [spc.c_limits(row).ucl if k else np.inf for row, k in zip(x, keep, strict=True)]
    )
    # P(count > ucl) for a Poisson count: sf at floor(ucl).
    ind = stats.poisson.sf(np.floor(ind_ucl), DEFECT_RATE)
    sigma3 = np.where(keep, stats.poisson.sf(np.floor(sigma3_ucl), DEFECT_RATE), 0.0)
    line = np.where(keep, stats.poisson.sf(np.floor(np.minimum(ours, 1e9)), DEFECT_RATE), 0.0)
    return float(ind.mean()), float(sigma3.mean()), float(line.mean())


def main() -> int:
    baselines = int(os.environ.get("BENCH_SPC_BASELINES", "20000"))
    rng = np.random.default_rng(7)
    nominal = 2 * stats.norm.sf(3.0)
    print(f"individuals charts of a stable normal process, {baselines} baselines per size")
    print(f"nominal per point: {100 * nominal:.2f} %; per part of {CHARTS_PER_PART} charts: "
          f"{100 * (1 - (1 - nominal) ** CHARTS_PER_PART):.1f} %")  # fmt: skip
    print(f"{'baseline':>9} {'per point':>10} {'p10':>7} {'p90':>7} {'per part':>9} "
          f"{'parts per alarm':>16} {'wall s':>7} {'cpu s':>6}")  # fmt: skip
    for m in SIZES:
        w0, c0 = time.perf_counter(), time.process_time()
        p = individuals_false_alarms(m, baselines, rng)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        # Each chart of a part has its own baseline: draw the part's eight from the same set.
        part = 1 - np.prod(1 - rng.choice(p, (baselines, CHARTS_PER_PART)), axis=1)
        print(f"{m:>9} {100 * p.mean():>9.2f}% {100 * np.quantile(p, 0.1):>6.2f}% "
              f"{100 * np.quantile(p, 0.9):>6.2f}% {100 * part.mean():>8.1f}% "
              f"{1 / part.mean():>16.0f} {wall:>7.2f} {cpu:>6.2f}")  # fmt: skip
    print(f"\ndefect count per part, Poisson at {DEFECT_RATE} (one dented part in ten), "
          f"{baselines // 10} baselines per size")  # fmt: skip
    print(f"{'baseline':>9} {'individuals':>12} {'c 3-sigma':>10} {'c (line)':>9}")
    for m in SIZES:
        ind, sigma3, line = count_false_alarms(m, baselines // 10, rng)
        print(f"{m:>9} {100 * ind:>11.2f}% {100 * sigma3:>9.2f}% {100 * line:>8.3f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
