"""The data the service exchanges: one pydantic model per record, shared by REST, zenoh and MCAP.

:class:`InspectionResult` is the contract of ../DESIGN section 5: the same
model is published on zenoh (JSON), returned and listed by the REST API, stored
in SQLite and recorded in MCAP with its JSON Schema
(``InspectionResult.model_json_schema()``). Its ``schema_version`` changes
whenever a field is added, removed or changes meaning.

Request and response models of the API are kept apart (``PartCreate`` /
``PartPublic``). Non-finite numbers are rejected everywhere: JSON has no NaN,
so a missing value is ``null``.
"""

from __future__ import annotations

import math
import os
import time
from enum import StrEnum
from typing import Annotated, Generic, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, field_validator

from inspection.deviations import Verdict
from inspection.spc import ChartKind

from .config import ComparisonPointSpec, Name, PartSpecBase, Vec3
from .names import ID_PATTERN, ID_SEPARATOR, NAME_MAX_LEN

SCHEMA_VERSION = 5
"""Version of :class:`InspectionResult`'s JSON."""

MAX_ID_LEN = 2 * NAME_MAX_LEN + 2 * 19 + 3
"""The longest result id: a trigger's line and station names at their limit,
its sequence number and time (each below 2**63: 19 digits), and three separators."""

T = TypeVar("T")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# --------------------------------------------------------------------------- results


class Status(StrEnum):
    """The status of one inspected (or missed) part."""

    passed = "pass"
    fail = "fail"
    not_measurable = "not_measurable"
    error = "error"
    missed = "missed"


class PointResult(_Model):
    """The deviation at one named comparison point."""

    name: str
    deviation_mm: float | None = Field(
        description="Robust signed deviation along the CAD normal, mm; null if not measurable."
    )
    lower_mm: float
    upper_mm: float
    support: int = Field(ge=0, description="Measured points pooled within the support radius.")
    verdict: Verdict
    reason: str | None = Field(default=None, description="Why the point is not measurable.")
    kind: str = Field(
        default="surface",
        description="The comparison point's kind; a feature's entries (hole, trim_edge, "
        "gap_flush, character_line) are named <point>.<characteristic>.",
    )
    at_mm: Vec3 | None = Field(
        default=None,
        description="Where the largest deviation along a fitted curve lies (the _max entries "
        "of trim edges and character lines): on the nominal, CAD frame, mm.",
    )


class FieldStats(_Model):
    """Summary of the signed deviations over the surface (CAD frame, mm).

    Only the points the surface measured count; the others are counted apart
    (``edge``, ``outliers``, ``far``). The statistics are ``null`` when no
    point counts.
    """

    points: int = Field(ge=0, description="Points measured.")
    inliers: int = Field(ge=0, description="Points counted below.")
    edge: int = Field(
        default=0,
        ge=0,
        description="Points off the CAD's edge or near its outline, holes, sharp bends or "
        "occlusion edges (within 4 mm).",
    )
    outliers: int = Field(default=0, ge=0, description="Points the fit rejects.")
    far: int = Field(
        default=0, ge=0, description="Points beyond the correspondence distance (background)."
    )
    mean_mm: float | None = None
    std_mm: float | None = None
    rms_mm: float | None = None
    min_mm: float | None = None
    max_mm: float | None = None
    median_mm: float | None = None
    p001_mm: float | None = Field(default=None, description="0.1th percentile.")
    p05_mm: float | None = None
    p95_mm: float | None = None
    p999_mm: float | None = Field(default=None, description="99.9th percentile.")


class SurfaceDefectResult(_Model):
    """A region of the surface whose deviation leaves the spec's surface band."""

    kind: Literal["dent", "bump"] = Field(description="dent: into the material; bump: outward.")
    center_mm: list[float] = Field(
        min_length=3, max_length=3, description="Centre of the region, CAD frame, mm."
    )
    area_mm2: float = Field(ge=0, description="Area of the CAD surface it covers, mm^2.")
    peak_mm: float = Field(
        description="Extreme of the field smoothed over the defect search's support, signed, mm."
    )
    mean_mm: float = Field(description="Mean of the smoothed field over the region, signed, mm.")
    nearest_point: str | None = Field(
        default=None, description="The comparison point nearest to the centre."
    )
    points: int = Field(default=0, ge=0, description="Measured points in the region.")


Matrix4 = Annotated[
    list[Annotated[list[float], Field(min_length=4, max_length=4)]],
    Field(min_length=4, max_length=4),
]


class InspectionResult(_Model):
    """The result of one triggered part (DESIGN section 5).

    ``transform`` is T_cad_rig, which maps rig-frame points into the CAD frame,
    as a nested 4x4 list, rows first; ``null`` when no fit was made.
    ``timings_ms`` holds one entry per pipeline stage that ran (e.g.
    ``reconstruct``, ``guide``, ``align``, ``deviations``, ``total``).
    """

    schema_version: int = SCHEMA_VERSION
    id: str = Field(
        min_length=1,
        max_length=MAX_ID_LEN,
        pattern=ID_PATTERN,
        description="Unique per inspection.",
    )
    line: Name
    station: Name
    part: Name
    serial: Name
    seq: int = Field(ge=0, description="Per-station trigger sequence number.")
    triggered_ns: int = Field(
        ge=0, description="Trigger time, ns since the Unix epoch (ingest clock)."
    )
    status: Status
    reason: str | None = Field(default=None, description="Why the status is error, missed, ...")
    transform: Matrix4 | None = None
    rms_mm: float | None = Field(default=None, ge=0)
    inlier_fraction: float | None = Field(default=None, ge=0, le=1)
    converged: bool | None = Field(default=None, description="The final fit converged.")
    stop_reason: str | None = Field(
        default=None, description="Why the fit stopped: converged, max_iterations, no_progress."
    )
    iterations: int | None = Field(default=None, ge=0, description="Iterations of the final fit.")
    observability: float | None = Field(
        default=None,
        ge=0,
        description="Smallest over largest eigenvalue of the fit's normal matrix "
        "(1: constrained alike in every direction; 0: a direction left free).",
    )
    weak_directions: list[str] = Field(
        default_factory=list,
        description="Directions the measured surface leaves free, CAD frame "
        "(e.g. 'translation along x', 'rotation about z').",
    )
    ambiguous: bool | None = Field(
        default=None,
        description="The global search found another pose fitting almost as well "
        "(null: no global search ran).",
    )
    runner_up_score: float | None = Field(
        default=None,
        ge=0,
        description="The best other pose's score over the chosen one's (1: fits as well).",
    )
    path: Literal["cloud", "comparison_points"] | None = Field(
        default=None,
        description="What measured the part: the whole reconstructed cloud (cloud) or local "
        "photogrammetry at each comparison point alone (comparison_points); null: not measured.",
    )
    comparison: list[PointResult] = Field(default_factory=list)
    defects: list[SurfaceDefectResult] | None = Field(
        default=None,
        description="Surface defects, largest first; null: the surface was not checked (the "
        "comparison-point path, or no measurement), which is not the same as none found.",
    )
    field: FieldStats | None = None
    timings_ms: dict[str, float] = Field(default_factory=dict)
    spec_version: str | None = None
    cad_hash: str | None = None
    tree_hash: str | None = None
    calibration_id: str | None = None
    software_version: str

    @field_validator("transform")
    @classmethod
    def _rigid_bottom_row(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None and any(
            abs(a - b) > 1e-9 for a, b in zip(v[3], (0.0, 0.0, 0.0, 1.0), strict=True)
        ):
            raise ValueError("the last row of a homogeneous transform must be [0, 0, 0, 1]")
        return v


class AlarmKind(StrEnum):
    seq_jump = "seq_jump"
    seq_repeat = "seq_repeat"
    seq_rebased = "seq_rebased"
    bad_frameset = "bad_frameset"
    queue_overflow = "queue_overflow"
    spc_rule = "spc_rule"


def new_alarm_id() -> str:
    """A fresh alarm id, ordered by time like the results' ids."""
    return f"alarm.{time.time_ns()}.{os.urandom(4).hex()}"


class Alarm(_Model):
    """What a person should look at, published on ``<prefix>/<line>/<station>/alarm``.

    Alarms come with a result where there is one (the ``error`` result of a
    FrameSet whose seq was refused, say); they say what the result cannot:
    that the trigger source misbehaves, or (``spc_rule``) that a control
    chart's run rule holds at the newest part. An alarm stays open until a
    person acknowledges it through the API, which records who and when.
    """

    id: str = Field(default_factory=new_alarm_id, pattern=ID_PATTERN, max_length=64)
    kind: AlarmKind
    message: str = Field(max_length=2000)
    triggered_ns: int = Field(description="The trigger it is about (or when it was raised), ns.")
    line: Name
    station: Name
    seq: int | None = Field(default=None, description="The seq it is about, when there is one.")
    raised_ns: int = Field(description="When the worker raised it, ns since the epoch.")
    part: Name | None = Field(default=None, description="spc_rule: the part type.")
    feature: str | None = Field(
        default=None,
        max_length=128,
        description="spc_rule: the charted feature: a comparison point's name, "
        "'fit_rms' or 'defects'.",
    )
    rule: str | None = Field(default=None, max_length=32, description="spc_rule: e.g. nelson1.")
    value: float | None = Field(default=None, description="spc_rule: the value that fired it.")
    result_id: str | None = Field(
        default=None, max_length=MAX_ID_LEN, description="The result it is about, if any."
    )
    serial: Name | None = None
    acknowledged_by: str | None = Field(default=None, max_length=200)
    acknowledged_ns: int | None = None


def make_result_id(line: str, station: str, seq: int, triggered_ns: int) -> str:
    """The id of the result of one trigger: ``<line>~<station>~<seq>~<triggered_ns>``.

    Deterministic, so a replay of a recorded trigger gets the same id and a
    trigger delivered twice is stored once. Names cannot hold the separator,
    so no two triggers share an id whatever dots their names contain.
    """
    return ID_SEPARATOR.join((line, station, str(seq), str(triggered_ns)))


def new_upload_id() -> str:
    """A fresh id for an inspection that did not come from a trigger (an API upload)."""
    return f"upload.{time.time_ns()}.{os.urandom(4).hex()}"


def missed_serial(seq: int) -> str:
    """The serial published for a missed part whose serial never arrived."""
    return f"unknown-{seq}"


def software_version() -> str:
    """The installed package's version (``0+unknown`` when not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("inspection")
    except PackageNotFoundError:
        return "0+unknown"


# --------------------------------------------------------------------------- API


class ErrorDetail(_Model):
    code: str = Field(description="Stable, machine-readable, e.g. 'unknown_part'.")
    message: str


class ErrorBody(_Model):
    """Every 4xx/5xx answer of the API: ``{"error": {"code": ..., "message": ...}}``."""

    error: ErrorDetail


class Page(_Model, Generic[T]):
    """One page of a list; pass ``next`` as ``cursor`` to get the following page (null: the end)."""

    items: list[T]
    next: str | None = None


class PartCreate(PartSpecBase):
    """The spec JSON sent with a CAD upload to create a part (the CAD comes as the file)."""


class PartState(StrEnum):
    building = "building"
    ready = "ready"
    failed = "failed"


class PartPublic(_Model):
    """A part type as the API shows it."""

    name: str
    version: str
    description: str = ""
    cad: str = Field(
        description="Where the CAD came from: a file name, an upload, or generated:panel."
    )
    scale: float
    cad_hash: str | None = None
    tree_hash: str | None = None
    state: PartState
    job: str | None = Field(
        default=None, description="The tree build job, while building or if failed."
    )
    points: list[ComparisonPointSpec]
    subgroup_size: int = Field(default=1, description="Parts per subgroup of its charts.")
    faces: int | None = None
    extents_mm: list[float] | None = None
    cad_kind: Literal["mesh", "nurbs"] | None = Field(
        default=None,
        description="What deviations are measured to, once loaded: 'nurbs', the exact "
        "B-spline faces of a STEP CAD; 'mesh', the triangles.",
    )
    nurbs_faces: int | None = Field(default=None, description="B-spline faces, for 'nurbs'.")


class JobState(StrEnum):
    queued = "queued"
    running = "running"
    done = "done"
    failed = "failed"


class Job(_Model):
    """A background job (a tree build) and its progress."""

    id: str
    kind: str = "tree_build"
    part: str
    state: JobState
    progress: float = Field(ge=0, le=1, description="Fraction done, 0..1.")
    message: str = ""
    created_ns: int
    finished_ns: int | None = None


class ConfidenceInterval(_Model):
    low: float
    high: float
    level: float = Field(gt=0, lt=1, description="0.95: a 95 % interval.")


class TrendPoint(_Model):
    """Statistics and capability of one charted feature over the last parts.

    ``cp``/``cpk`` use the within sigma (average moving range / 1.128): what the
    process can do from part to part. ``pp``/``ppk`` use the overall sample
    standard deviation: what it delivered in the window, drifts included.
    ``C = (upper - lower) / (6 sigma)``, ``Ck = min(upper - mean, mean - lower)
    / (3 sigma)``. None below the minimum sample size: ``capability_note`` says why.
    """

    name: str
    n: int = Field(ge=0, description="Measurements used (not-measurable ones are left out).")
    mean_mm: float | None = None
    sigma_within_mm: float | None = Field(default=None, description="Moving range / d2.")
    sigma_overall_mm: float | None = Field(default=None, description="Sample std (n - 1).")
    lower_mm: float | None = None
    upper_mm: float | None = None
    cp: float | None = None
    cpk: float | None = None
    pp: float | None = None
    ppk: float | None = None
    cp_ci: ConfidenceInterval | None = None
    cpk_ci: ConfidenceInterval | None = None
    pp_ci: ConfidenceInterval | None = None
    ppk_ci: ConfidenceInterval | None = None
    capability_note: str | None = Field(
        default=None, description="Why there is no capability figure."
    )
    fails: int = Field(default=0, ge=0)


class Trend(_Model):
    """Trends of a part over its last ``window`` results (status pass or fail)."""

    part: str
    window: int
    parts: int = Field(description="Results used (at most window).")
    since_ns: int | None = None
    until_ns: int | None = None
    points: list[TrendPoint]


class ChartLimits(_Model):
    """A control chart's limits (within sigma), and where they come from."""

    center: float
    sigma: float
    lcl: float
    ucl: float
    spread_center: float | None = Field(
        description="Moving range (or range) chart's centre line; null on a c chart."
    )
    spread_lcl: float | None
    spread_ucl: float | None
    subgroup: int = Field(ge=1, description="1: individuals and moving range; else X-bar/R.")
    n: int = Field(ge=0, description="Baseline values (or subgroups).")
    kind: ChartKind = Field(
        default="individuals",
        description="individuals and moving range, X-bar and R, or c (a count per part: "
        "Poisson limits, checked by the beyond-limits rule alone).",
    )
    frozen: bool = Field(description="Frozen by a person; else the part's first results.")
    frozen_by: str | None = None
    frozen_ns: int | None = None


class ChartPoint(_Model):
    """One plotted value: a part (or a subgroup, its last part's identity)."""

    result_id: str
    serial: str
    triggered_ns: int
    value: float | None = Field(description="The deviation (or subgroup mean); null: unmeasured.")
    spread: float | None = Field(description="Moving range (or subgroup range).")
    rules: list[str] = Field(default_factory=list, description="Run rules holding here.")


class ControlChart(_Model):
    """A control chart of one feature of a part: a comparison point, ``fit_rms`` or ``defects``."""

    part: str
    feature: str
    unit: str = "mm"
    rules: list[str] = Field(description="The run rules checked.")
    limits: ChartLimits | None = None
    limits_note: str | None = Field(default=None, description="Why there are no limits yet.")
    lower_mm: float | None = Field(default=None, description="Tolerance, for a comparison point.")
    upper_mm: float | None = None
    points: list[ChartPoint]
    capability: TrendPoint | None = None


class BaselineCreate(_Model):
    """Freeze a part's control limits from the results of a period judged stable."""

    since_ns: int | None = Field(default=None, ge=0, description="From (default: the first).")
    until_ns: int | None = Field(default=None, ge=0, description="To (default: now).")
    by: str = Field(default="", max_length=100, description="Who freezes it (a name).")


class Baseline(_Model):
    """A part's frozen baseline: the limits per charted feature and who froze them."""

    part: str
    since_ns: int | None
    until_ns: int | None
    frozen_ns: int
    frozen_by: str
    results: int = Field(ge=0)
    limits: dict[str, ChartLimits]


class AlarmAck(_Model):
    """Acknowledge an alarm."""

    by: str = Field(default="", max_length=100, description="Who acknowledges it (a name).")


class Recording(_Model):
    """Where one inspection is recorded: open ``file`` in the recordings folder (Foxglove,
    the MCAP library) at the log times ``start_ns`` .. ``end_ns``."""

    file: str
    start_ns: int
    end_ns: int
    topics: list[str]
    finished: bool = Field(description="Complete and indexed; else still being written.")


class Health(_Model):
    """Liveness (the process answers) and readiness (every check passes)."""

    alive: bool = True
    ready: bool
    checks: dict[str, bool]
    version: str


def finite_or_none(x: float | None) -> float | None:
    """``x`` as a float, or None when it is missing or not finite (JSON has no NaN)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None
