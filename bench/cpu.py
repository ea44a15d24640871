"""CPU time of calls that run OpenMP threads (numba's ``parallel=True`` kernels).

``time.process_time()`` sums every thread of the process, but Linux brings
another thread's sum up to date only when that thread is descheduled or at a
timer tick. OpenMP's threads keep spinning after a parallel region and are put
to sleep only later: read around one call of a few milliseconds, the clock
misses much of what the other threads did and all of their spinning. (A
50,000-point grid query on two threads: 1.4 ms wall, 1.6 ms of CPU read around
each call, 3.1 ms per call over 200 calls back to back, and after the last
call the other thread spins for about 20 ms more.)

:func:`cpu_per_call` reads the clock around a batch of calls and once more
after a pause long enough for the threads to fall asleep, so that the batch
is charged with its threads' work and their spinning: what the calls cost a
process that makes them.
"""

from __future__ import annotations

import time
from collections.abc import Callable

# Longer than OpenMP's threads spin before they sleep (about 20 ms, measured
# with libgomp's defaults).
SETTLE_S = 0.05


def cpu_per_call(fn: Callable[[], object], calls: int = 1) -> float:
    """Run ``fn`` ``calls`` times; the CPU seconds per call, threads and their
    spinning included."""
    cpu = time.process_time()
    for _ in range(calls):
        fn()
    time.sleep(SETTLE_S)
    return (time.process_time() - cpu) / calls
