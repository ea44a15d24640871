"""Results as CSV in long format: one row per result and comparison point.

Parts of different specs share one file this way (a wide table would need a
column per point of every spec); a result without comparison points (an
error, a missed part) is one row with the point's columns empty.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable
from datetime import UTC, datetime

from starlette.requests import Request

from ..models import InspectionResult

CSV_COLUMNS = (
    "id", "line", "station", "part", "serial", "seq", "triggered_ns", "triggered_utc", "status",
    "reason", "rms_mm", "inlier_fraction", "defects", "point", "deviation_mm", "lower_mm",
    "upper_mm", "support", "point_verdict", "spec_version", "software_version",
)  # fmt: skip


def wants_csv(request: Request) -> bool:
    """The client asks for CSV (and not for JSON first)."""
    accept = request.headers.get("accept", "").lower()
    return "text/csv" in accept and not accept.lstrip().startswith("application/json")


def _utc(ns: int) -> str:
    try:
        return datetime.fromtimestamp(ns / 1e9, UTC).isoformat(timespec="milliseconds")
    except (OverflowError, ValueError, OSError):
        return ""


def _cell(v: object) -> object:
    # A spreadsheet runs a cell starting with = + - @ as a formula: reasons and names
    # come from outside, so such text is quoted as text.
    if isinstance(v, str) and v[:1] in ("=", "+", "-", "@", "\t", "\r"):
        return "'" + v
    return "" if v is None else v


def results_csv(results: Iterable[InspectionResult]) -> str:
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\r\n")
    w.writerow(CSV_COLUMNS)
    for r in results:
        head = [
            r.id, r.line, r.station, r.part, r.serial, r.seq, r.triggered_ns,
            _utc(r.triggered_ns), r.status.value, r.reason, r.rms_mm, r.inlier_fraction,
            None if r.defects is None else len(r.defects),
        ]  # fmt: skip
        tail = [r.spec_version, r.software_version]
        if not r.comparison:
            w.writerow([_cell(v) for v in [*head, None, None, None, None, None, None, *tail]])
        for c in r.comparison:
            row = [*head, c.name, c.deviation_mm, c.lower_mm, c.upper_mm, c.support,
                   c.verdict.value, *tail]  # fmt: skip
            w.writerow([_cell(v) for v in row])
    return out.getvalue()
