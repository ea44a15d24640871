"""Bounded disk for what the line keeps beside its recordings: results and deviations.

A :class:`Janitor` thread applies ``[retention]`` every ``period_s``: the
oldest per-point deviation files go beyond ``deviations_max_mb`` or
``deviations_max_age_h``, the oldest result rows beyond ``results_max_mb``
of result JSON or ``results_max_age_d``, and the acknowledged alarms raised
before the oldest result kept. (The recordings keep their own
budget, enforced by the recorder after every trigger.) A colour map whose
deviations were deleted is drawn from the result alone.
"""

from __future__ import annotations

import logging
import threading

from .config import RetentionSection
from .store import DeviationArchive, ResultStore

log = logging.getLogger(__name__)


class Janitor:
    """Keeps ``store`` and ``archive`` within the retention policy, from a thread.

    Parameters
    ----------
    store : ResultStore or None
    archive : DeviationArchive or None
    policy : RetentionSection
    period_s : float
        Between sweeps: a directory may pass its budget by what the line
        writes in this time (the deviations, ~0.7 MB a part).
    """

    def __init__(
        self,
        store: ResultStore | None,
        archive: DeviationArchive | None,
        policy: RetentionSection,
        *,
        period_s: float = 10.0,
    ) -> None:
        self.store = store
        self.archive = archive
        self.policy = policy
        self.period_s = period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="janitor", daemon=True)
        self._thread.start()

    def sweep(self) -> tuple[int, int]:
        """Apply the policy once; returns (result rows, deviation files) deleted."""
        p = self.policy
        rows = files = 0
        if self.store is not None:
            rows = self.store.enforce(
                _bytes(p.results_max_mb), _seconds(p.results_max_age_d, 86400)
            )
        if self.archive is not None:
            files = self.archive.enforce(
                _bytes(p.deviations_max_mb), _seconds(p.deviations_max_age_h, 3600)
            )
        if rows or files:
            log.info("retention: %d result(s) and %d deviation file(s) deleted", rows, files)
        return rows, files

    def _run(self) -> None:
        while True:
            try:
                self.sweep()
            except Exception:  # the next sweep may do better; measuring goes on regardless
                log.exception("retention sweep failed")
            if self._stop.wait(self.period_s):
                return

    def close(self) -> None:
        self._stop.set()
        self._thread.join(10.0)


def _bytes(mb: float | None) -> int | None:
    return None if mb is None else int(mb * 1e6)


def _seconds(value: float | None, unit_s: float) -> float | None:
    return None if value is None else value * unit_s
