"""Validated configuration: the line (``configs/line.toml``) and part specs (``configs/parts/``).

Every model rejects unknown keys (``extra="forbid"``) so a typo fails at
start-up instead of being ignored, and every quantity carries its unit in its
name (``trigger_period_s``, ``radius_mm``). Nothing is read at import time:
``main`` calls :func:`load_line_config` and :func:`load_part_spec` and passes
the results on.

Paths in a line file that describe the installation (the rig calibration, the
parts directory) are relative to the file's own directory; storage paths are
deployment values, relative to the working directory, and may be overridden by
environment variables (see :data:`ENV_OVERRIDES`).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_serializer,
    field_validator,
    model_validator,
)

from inspection.surface import NODE_MM as SURFACE_NODE_MM
from inspection.surface import SurfaceParams

from .names import KEY_PREFIX_PATTERN, NAME_MAX_LEN, NAME_PATTERN
from .store_url import check_postgres_url, redact_url

Name = Annotated[str, Field(pattern=NAME_PATTERN, min_length=1, max_length=NAME_MAX_LEN)]
"""A line, station, part or serial name: see :mod:`service.names` for the rule."""

GENERATED_PANEL = "generated:panel"
"""The ``cad`` value that selects the project's own procedural sheet-metal panel."""
GENERATED_STEPPED_PLATE = "generated:stepped-plate"
"""The ``cad`` value that selects the holographic head's test part: a 24 mm plate with a
step deeper than one phase interval (``inspection.holography.stepped_plate``)."""
GENERATED = (GENERATED_PANEL, GENERATED_STEPPED_PLATE)


class ConfigError(ValueError):
    """A configuration file is missing, is not TOML, or does not validate."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# --------------------------------------------------------------------------- parts


class PointKind(StrEnum):
    """What a comparison point measures: the surface along its normal, or a feature (of the
    outline, measured in the images after the fit; a character line, in the cloud), one
    entry per characteristic."""

    surface = "surface"
    hole = "hole"
    trim_edge = "trim_edge"
    gap_flush = "gap_flush"
    character_line = "character_line"


Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class ComparisonPointSpec(_Strict):
    """A named point on the CAD surface whose deviation along ``normal`` is toleranced.

    The signed deviation (positive on the outer side of the surface) must lie
    within ``[lower_mm, upper_mm]``; measured points within ``radius_mm`` of
    ``position_mm`` are pooled, and at least ``min_support`` of them are needed
    for a verdict (fewer: not measurable).
    """

    name: Name
    position_mm: Vec3 = Field(description="Nominal position on the CAD surface, CAD frame, mm.")
    normal: Vec3 = Field(description="Outward surface normal, CAD frame; normalised on load.")
    lower_mm: float = Field(description="Lower signed limit of the deviation, mm.")
    upper_mm: float = Field(description="Upper signed limit of the deviation, mm.")
    radius_mm: float = Field(gt=0, le=100, description="Support radius, mm.")
    min_support: int = Field(
        default=10, ge=1, le=100_000, description="Points needed for a verdict."
    )
    kind: PointKind = PointKind.surface
    diameter_mm: float | None = Field(
        default=None, gt=0, le=1000, description="A hole's nominal diameter, mm (holes only)."
    )
    length_mm: float = Field(
        default=0.0, ge=0, le=2000, description="A slot's nominal overall length, mm (0: round)."
    )
    axis: Vec3 | None = Field(
        default=None,
        description="A hole's in-plane x (a slot's long axis), CAD frame; unset: the CAD's x.",
    )
    mate_mm: Vec3 | None = Field(
        default=None,
        description="gap_flush: the mating part's nominal edge point, this part's CAD frame, mm.",
    )
    tolerances: dict[str, Annotated[list[float], Field(min_length=2, max_length=2)]] = Field(
        default_factory=dict,
        description="Limits [lower_mm, upper_mm] of single characteristics (d, len, trim, "
        "trim_max, gap, flush, line, line_max, x, y); the others take lower_mm and upper_mm.",
    )

    @field_validator("normal")
    @classmethod
    def _unit_normal(cls, v: list[float]) -> list[float]:
        n = math.sqrt(sum(c * c for c in v))
        if not n > 1e-9:
            raise ValueError("normal must be a non-zero vector")
        return [c / n for c in v]

    @model_validator(mode="after")
    def _ordered_limits(self) -> ComparisonPointSpec:
        if not self.lower_mm < self.upper_mm:
            raise ValueError(f"lower_mm ({self.lower_mm}) must be below upper_mm ({self.upper_mm})")
        return self

    @model_validator(mode="after")
    def _a_whole_feature(self) -> ComparisonPointSpec:
        # The measuring side's own rules (a hole's diameter, a gap's mate, tolerances of
        # the kind's characteristics), checked when the spec loads.
        from inspection.deviations import ComparisonPoint

        ComparisonPoint(
            self.name, tuple(self.position_mm), tuple(self.normal),  # type: ignore[arg-type]
            self.lower_mm, self.upper_mm, self.radius_mm, kind=self.kind.value,
            diameter_mm=self.diameter_mm, length_mm=self.length_mm,
            axis=None if self.axis is None else tuple(self.axis),  # type: ignore[arg-type]
            mate=None if self.mate_mm is None else tuple(self.mate_mm),  # type: ignore[arg-type]
            tolerances=tuple((k, lo, hi) for k, (lo, hi) in self.tolerances.items()),
        )  # fmt: skip
        return self


class Loss(StrEnum):
    """Robust loss of the fine registration (IRLS weight function)."""

    l2 = "l2"
    huber = "huber"
    cauchy = "cauchy"
    tukey = "tukey"


class RegistrationSettings(_Strict):
    """How a cloud is fitted to the CAD model; mapped onto ``inspection.align``/``register``."""

    loss: Loss = Loss.tukey
    max_iterations: int = Field(default=50, ge=1, le=1000)
    max_correspondence_mm: float = Field(
        default=10.0,
        gt=0,
        le=1000,
        description="Points farther than this from the CAD are outliers.",
    )
    min_inlier_fraction: float = Field(
        default=0.5, ge=0, le=1, description="Below this the fit is reported as an error."
    )
    max_rms_mm: float = Field(
        default=1.0, gt=0, le=100, description="Above this the fit is an error."
    )
    ambiguous_is_error: bool = Field(
        default=False,
        description="A pose the global alignment calls ambiguous makes the result an error "
        "(else it is measured and the reason says so).",
    )
    max_points: int = Field(
        default=150_000,
        ge=100,
        le=10_000_000,
        description="Clouds are subsampled to this size to fit.",
    )
    seen_from_above: bool | None = Field(
        default=None,
        description="The rig looks down on the part (+z of the rig frame): a point can only "
        "have been measured on a CAD face turned up towards it, so one whose closest face is "
        "turned away counts as an outlier. Keeps a thin part modelled as a solid (sheet metal "
        "with its underside) from being fitted half onto that underside. Needs loss 'tukey'; "
        "unset: on with 'tukey', off with the others. Applies to clouds in the rig frame.",
    )

    @model_validator(mode="after")
    def _view_needs_plateau(self) -> RegistrationSettings:
        if self.seen_from_above and self.loss != Loss.tukey:
            raise ValueError(
                f"seen_from_above needs loss 'tukey' (a loss whose outliers do not pull), "
                f"got {self.loss.value!r}"
            )
        return self

    def view_direction(self) -> tuple[float, float, float] | None:
        """Direction towards the sensor in the rig frame, or None when not used."""
        on = self.loss == Loss.tukey if self.seen_from_above is None else self.seen_from_above
        return (0.0, 0.0, 1.0) if on else None


_SURFACE = SurfaceParams()


class AlignmentMethod(StrEnum):
    """How a part is aligned to its CAD (``inspection.alignment.rps.ALIGNMENTS``)."""

    best_fit = "best_fit"
    rps = "rps"
    best_fit_rps = "best_fit_rps"


class DatumSpec(_Strict):
    """One datum of the part's reference point system (RPS)."""

    point: Name = Field(description="The hole or surface comparison point that measures it.")
    fixes: list[Annotated[str, Field(pattern="^[xyz]$")] | Vec3] = Field(
        min_length=1,
        max_length=3,
        description='Directions it fixes, CAD frame: "x", "y", "z" or a vector.',
    )
    weight: float = Field(default=1.0, gt=0, le=1e6, description="Relative weight.")


class AlignmentSettings(_Strict):
    """The part's alignment: the best fit, its RPS alone, or the best fit with the RPS held."""

    method: AlignmentMethod = AlignmentMethod.best_fit
    datums: list[DatumSpec] = Field(default_factory=list, max_length=32)

    def scheme(self, positions: dict[str, list[float]]) -> Any:
        """The ``inspection.alignment.rps.RpsScheme`` of these datums at the points'
        ``positions`` (None for a best fit); raises InvalidInput for a free direction."""
        if self.method is AlignmentMethod.best_fit:
            return None
        from inspection.alignment.rps import Datum, RpsScheme

        datums = tuple(
            Datum(d.point, tuple(positions[d.point]), tuple(d.fixes), d.weight)  # type: ignore[arg-type]
            for d in self.datums
        )
        return RpsScheme(datums, self.method.value)

    @model_validator(mode="after")
    def _datums_with_rps(self) -> AlignmentSettings:
        if self.method is not AlignmentMethod.best_fit and not self.datums:
            raise ValueError(f"alignment method {self.method.value!r} needs datums")
        if self.method is AlignmentMethod.best_fit and self.datums:
            raise ValueError("datums are given but the alignment method is 'best_fit'")
        return self


class SurfaceSettings(_Strict):
    """How the surface between the comparison points is judged; ``inspection.SurfaceParams``.

    A region of the surface whose deviation (smoothed over three nodes, 6 mm
    at the default ``node_mm``) leaves ``[lower_mm, upper_mm]`` over at least
    ``min_area_mm2`` is a surface defect (a dent or a bump).
    """

    lower_mm: float = Field(
        default=_SURFACE.lower_mm, lt=0, ge=-100, description="Signed lower limit, mm (a dent)."
    )
    upper_mm: float = Field(
        default=_SURFACE.upper_mm, gt=0, le=100, description="Signed upper limit, mm (a bump)."
    )
    min_area_mm2: float = Field(
        default=_SURFACE.min_area_mm2,
        ge=0,
        le=1e6,
        description="Smaller regions out of the band are not reported, mm^2.",
    )
    fails_part: bool = Field(
        default=_SURFACE.fails_part, strict=True, description="A surface defect fails the part."
    )
    node_mm: float = Field(
        default=SURFACE_NODE_MM,
        gt=0,
        le=50,
        description="Cell of the defect search's grid on the CAD, mm; the support (3x) and "
        "the distance that makes a point an edge point (2x) scale with it. The default suits "
        "a stereo cloud of a part of 100-1000 mm; a sensor of a small field takes a finer one.",
    )

    def params(self) -> SurfaceParams:
        return SurfaceParams(**self.model_dump(exclude={"node_mm"}))


class TreeSettings(_Strict):
    """Build parameters of the closest-point grid (``GridTree.build``); ``None``: its defaults."""

    spacing_mm: float | None = Field(default=None, gt=0, le=100)
    band_mm: float | None = Field(default=None, gt=0, le=1000)
    nurbs_cell_mm: float = Field(
        default=2.0,
        gt=0,
        le=100,
        description="Grid cell of the NURBS faces' sampling the tree is built on (a STEP "
        "CAD of B-spline faces only): the pose is fitted to it, deviations are refined on "
        "the exact faces.",
    )

    def build_kwargs(self) -> dict[str, float]:
        """Keyword arguments for ``GridTree.build`` (only those set)."""
        return {
            k: v for k, v in self.model_dump(exclude={"nurbs_cell_mm"}).items() if v is not None
        }


class PartSpecBase(_Strict):
    """A part type without its CAD source: what a client sends with a CAD upload."""

    name: Name
    version: str = Field(default="1", min_length=1, max_length=64, pattern=NAME_PATTERN)
    scale: float = Field(
        default=1.0, gt=0, le=1e6, description="Multiplies CAD coordinates to give mm."
    )
    description: str = Field(default="", max_length=1000)
    points: list[ComparisonPointSpec] = Field(default_factory=list, max_length=1000)
    registration: RegistrationSettings = Field(default_factory=RegistrationSettings)
    surface: SurfaceSettings = Field(default_factory=SurfaceSettings)
    tree: TreeSettings = Field(default_factory=TreeSettings)
    alignment: AlignmentSettings = Field(default_factory=AlignmentSettings)
    subgroup_size: int = Field(
        default=1,
        ge=1,
        le=10,
        description="Parts per subgroup of its control charts: 1 gives individuals and "
        "moving-range charts, 2..10 X-bar/R charts.",
    )

    @field_validator("points")
    @classmethod
    def _unique_point_names(cls, v: list[ComparisonPointSpec]) -> list[ComparisonPointSpec]:
        seen: set[str] = set()
        for p in v:
            if p.name in seen:
                raise ValueError(f"comparison point name {p.name!r} is used twice")
            seen.add(p.name)
        return v

    @model_validator(mode="after")
    def _datums_name_points(self) -> PartSpecBase:
        kinds = {p.name: p.kind for p in self.points}
        for d in self.alignment.datums:
            if kinds.get(d.point) not in (PointKind.surface, PointKind.hole):
                raise ValueError(f"datum {d.point!r} must name a surface or hole point")
        # Refused here, not when the part loads: a free direction is a spec error
        # (InvalidInput is a ValueError, reported with the spec's other errors).
        self.alignment.scheme({p.name: p.position_mm for p in self.points})
        return self


class PartSpec(PartSpecBase):
    """A part type: its CAD source, comparison points, registration and tree settings.

    ``cad`` is a mesh path (relative to the spec file's directory unless
    absolute), :data:`GENERATED_PANEL`, the project's own sheet-metal panel,
    whose parameters are given in ``panel`` (keyword arguments of
    ``inspection.panel.PanelSpec``), or :data:`GENERATED_STEPPED_PLATE`.
    """

    cad: str = Field(min_length=1, max_length=4096)
    panel: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _panel_only_when_generated(self) -> PartSpec:
        if self.panel and self.cad != GENERATED_PANEL:
            raise ValueError(f"'panel' parameters are only allowed with cad = {GENERATED_PANEL!r}")
        if self.cad.startswith("generated:") and self.cad not in GENERATED:
            raise ValueError(
                f"unknown generated CAD {self.cad!r}; there are {', '.join(map(repr, GENERATED))}"
            )
        return self

    @property
    def is_generated(self) -> bool:
        return self.cad in GENERATED

    def cad_path(self, base_dir: Path) -> Path:
        """The CAD file's path, resolved against ``base_dir`` (the spec's directory)."""
        if self.is_generated:
            raise ValueError(f"part {self.name!r} has a generated CAD, not a file")
        p = Path(self.cad)
        return p if p.is_absolute() else base_dir / p


# --------------------------------------------------------------------------- line


class LineSection(_Strict):
    name: Name = "line1"
    conveyor_speed_mm_s: float = Field(
        default=1000.0,
        gt=0,
        le=10_000,
        description="Belt speed along +x; the simulated frames smear by it times the flash.",
    )
    trigger_period_s: float = Field(
        default=2.0, ge=0.05, le=3600, description="Time between triggers."
    )


class ExecutorKind(StrEnum):
    """Where a station's measurements run."""

    in_process = "in-process"
    dask = "dask"


DASK_LOCAL_MAX_WORKERS = 64
"""Worker processes ``local:N`` may start on this host at most."""

DASK_ADDRESS_RULE = (
    "tcp://HOST:PORT (a Dask scheduler's address) or local:N "
    f"(N single-threaded worker processes on this host, 1 to {DASK_LOCAL_MAX_WORKERS})"
)


@dataclass(frozen=True)
class DaskAddress:
    """A Dask cluster to measure on: a running scheduler, or one started here.

    Attributes
    ----------
    scheduler : str or None
        ``tcp://HOST:PORT`` of a running scheduler.
    local_workers : int or None
        Start a cluster of this many single-threaded worker processes on this host.
    """

    scheduler: str | None = None
    local_workers: int | None = None

    def __str__(self) -> str:
        return self.scheduler if self.scheduler is not None else f"local:{self.local_workers}"


_TCP_ADDRESS = re.compile(
    r"tcp://(?P<host>[A-Za-z0-9.-]{1,253}|\[[0-9A-Fa-f:.]{2,45}\]):(?P<port>\d{1,5})"
)


def parse_dask_address(text: object) -> DaskAddress:
    """``tcp://HOST:PORT`` or ``local:N`` as a :class:`DaskAddress`.

    Raises
    ------
    ValueError
        Anything else, with the rule in the message.
    """
    if not isinstance(text, str):
        raise ValueError(f"a Dask address must be a string: {DASK_ADDRESS_RULE}")
    shown = text if len(text) <= 80 else text[:80] + "..."
    if text.startswith("local:"):
        n = text.removeprefix("local:")
        if n.isascii() and n.isdigit() and 1 <= int(n) <= DASK_LOCAL_MAX_WORKERS:
            return DaskAddress(local_workers=int(n))
        raise ValueError(f"{shown!r} is not a Dask address: {DASK_ADDRESS_RULE}")
    m = _TCP_ADDRESS.fullmatch(text)
    if m is None or not 1 <= int(m["port"]) <= 65535:
        raise ValueError(f"{shown!r} is not a Dask address: {DASK_ADDRESS_RULE}")
    return DaskAddress(scheduler=text)


class Sensor(StrEnum):
    """What a station measures with (the FrameSet's ``sensor``)."""

    flash = "flash"
    holography = "holography"


class StationSection(_Strict):
    name: Name = "st1"
    sensor: Sensor = Field(
        default=Sensor.flash,
        description="`flash`: the four-camera rig with its projected pattern; `holography`: "
        "the small-field dual-wavelength holographic head of the [holography] section.",
    )
    rig_calibration: str | None = Field(
        default=None,
        description="Calibrated rig (TOML written by `inspection calibrate`), relative to the "
        "line file; unset: Rig.default(), the rig shipped with the package.",
    )
    parts_dir: str = Field(default="parts", description="Part specs, relative to the line file.")
    guided_matching: bool = Field(
        default=True,
        description=(
            "Match every trigger a second time with the part's CAD at the first fit's pose "
            "shaping the matching windows, and the ring pairs too: ~0.7 s more per part; on "
            "the demo panel the part's corners come out 0.07 mm off (median) instead of 0.15."
        ),
    )
    path: Literal["cloud", "comparison_points"] = Field(
        default="cloud",
        description=(
            "What the station measures: the whole reconstructed cloud (`cloud`), or each "
            "comparison point by local photogrammetry around it alone (`comparison_points`: "
            "faster, but the surface between the points is not checked, so a part whose "
            "[surface] fails parts needs `cloud`)."
        ),
    )
    parts: list[Name] = Field(default_factory=lambda: ["demo-panel"], min_length=1)
    queue_size: int = Field(
        default=4, ge=1, le=1000, description="Frame sets waiting for the worker."
    )
    part_wait_s: float = Field(
        default=120.0,
        ge=1.0,
        le=3600.0,
        description=(
            "How long a FrameSet naming a part the worker does not hold yet (one created "
            "over the API) waits while the part is taken from the store and loaded (its tree "
            "built, on its first use with a tree cache); then it is answered `error`, naming "
            "the part and what its load was doing. The load goes on for the FrameSets after it."
        ),
    )
    metrics_port: int | None = Field(
        default=9464,
        ge=0,
        le=65535,
        description="A worker running on its own serves Prometheus metrics here, on the "
        "HTTP host (0: any free port; unset: none). With the API in the same process they "
        "are on the API's /metrics.",
    )
    max_seq_jump: int = Field(
        default=300,
        ge=1,
        le=1_000_000,
        description=(
            "Triggers a FrameSet's seq may skip: those skipped are answered `missed`; a "
            "longer jump is refused with an error result and an alarm (a forged or corrupt "
            "seq), and so is a seq answered already."
        ),
    )

    executor: ExecutorKind = Field(
        default=ExecutorKind.in_process,
        description=(
            "Where the station's parts are measured: `in-process` (in the worker itself), or "
            "`dask` (on the Dask cluster of `dask_scheduler`; the worker still accounts for "
            "every trigger)."
        ),
    )
    dask_scheduler: str | None = Field(
        default=None,
        description=f'With `executor = "dask"`: {DASK_ADDRESS_RULE}.',
    )

    @field_validator("parts")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("station parts must be unique")
        return v

    @field_validator("dask_scheduler")
    @classmethod
    def _dask_address(cls, v: str | None) -> str | None:
        if v is not None:
            parse_dask_address(v)
        return v

    @model_validator(mode="after")
    def _executor_has_its_address(self) -> StationSection:
        if self.executor is ExecutorKind.dask and self.dask_scheduler is None:
            raise ValueError(f'executor = "dask" needs dask_scheduler: {DASK_ADDRESS_RULE}')
        if self.executor is ExecutorKind.in_process and self.dask_scheduler is not None:
            raise ValueError(
                'dask_scheduler is set but executor is "in-process": set executor = "dask" '
                "or remove dask_scheduler"
            )
        return self

    def dask_address(self) -> DaskAddress | None:
        """The Dask cluster to measure on (None: in-process)."""
        if self.executor is ExecutorKind.in_process or self.dask_scheduler is None:
            return None
        return parse_dask_address(self.dask_scheduler)


class HolographySection(_Strict):
    """The holographic head of a ``sensor = "holography"`` station, and how its simulated
    parts lie in their fixture."""

    pixels: int = Field(default=256, ge=64, le=4096, description="Sensor pixels per side (even).")
    field_mm: float = Field(default=18.0, gt=1, le=200, description="Field of view per side.")
    synthetic_mm: float = Field(
        default=1.1, ge=0.05, le=100, description="Synthetic wavelength of the two lasers."
    )
    calibration: str | None = Field(
        default=None,
        description="The head's calibration (TOML of inspection.holography.HoloCalibration), "
        "relative to the line file; unset: calibrated at start-up from a simulated flat plate "
        "under the simulated head.",
    )
    fixture_height_mm: float = Field(
        default=0.0,
        ge=-50,
        le=50,
        description="Height of the part's frame in the head's frame: where the fixture holds it.",
    )
    height_range_mm: float = Field(
        default=0.05,
        ge=0,
        le=0.5,
        description="Half-range of the simulated part's height about the fixture's, mm; the "
        "measurement needs it well within a quarter of the synthetic wavelength.",
    )
    tilt_range_mrad: float = Field(
        default=2.0, ge=0, le=20, description="Half-range of its tilts about x and y, mrad."
    )
    dent_depth_mm: tuple[float, float] = Field(
        default=(0.03, 0.15), description="Range of a simulated dent's depth, mm."
    )
    dent_radius_mm: tuple[float, float] = Field(
        default=(2.5, 4.0), description="Range of where a dent blends back into the surface, mm."
    )
    coarse_pose: bool = Field(
        default=True,
        description="Align the part's tilts to the gradient field of the speckle displacements "
        "before the phase-based pose: a part tilted more than about two degrees off the "
        "fixture is measured only so. Changes nothing for a part the fixture holds well and "
        "costs CPU time (README: the holographic sensor); off saves it where the fixture is "
        "known to hold the tilts.",
    )

    @field_validator("pixels")
    @classmethod
    def _even(cls, v: int) -> int:
        if v % 2:
            raise ValueError(f"pixels must be even, got {v}")
        return v

    @field_validator("dent_depth_mm", "dent_radius_mm", mode="before")
    @classmethod
    def _one_number_is_a_range(cls, v: object) -> object:
        return (v, v) if isinstance(v, int | float) and not isinstance(v, bool) else v

    @field_validator("dent_depth_mm", "dent_radius_mm")
    @classmethod
    def _range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not 0 < v[0] <= v[1] <= 20:
            raise ValueError(f"a range 0 < lo <= hi <= 20 mm is needed, got {list(v)}")
        return v


class ProjectorSection(_Strict):
    """The flash: how long it lasts and which speckle slide it projects (simulated line)."""

    flash_us: float = Field(
        default=50.0,
        gt=0,
        le=10_000,
        description="Flash (exposure) duration, microseconds: a flash rig's tens of µs "
        "(at 1 m/s, 50 µs moves the part 0.05 mm, under a tenth of a pixel; 2 ms, 2 mm).",
    )
    pattern_seed: int = Field(
        default=7,
        ge=0,
        le=2**32 - 1,
        description="Seed of the projected speckle slide (7: the slide of Rig.nominal()).",
    )


class ZenohMode(StrEnum):
    peer = "peer"
    client = "client"
    router = "router"


CommonName = Annotated[str, Field(pattern=r"^[^\x00-\x1f\x7f]+$", min_length=1, max_length=64)]
"""A certificate's subject common name (X.509 bounds it to 64 characters)."""


class AccessControlSection(_Strict):
    """Who may do what on the line's keys, by certificate common name (``bus.AccessControl``).

    Enforced by the session that listens (the router, or the peer of
    ``inspection run``); everything not listed is denied, so a certificate of
    the line's CA issued to a name in no list connects and can do nothing.
    """

    ingest: list[CommonName] = Field(default_factory=list, description="May publish FrameSets.")
    worker: list[CommonName] = Field(
        default_factory=list,
        description="May publish results, status and alarms, answer history queries and "
        "hold worker liveliness tokens.",
    )
    subscriber: list[CommonName] = Field(
        default_factory=list,
        description="May only subscribe, query and watch tokens (as every role may).",
    )


class ZenohSection(_Strict):
    """The bus: mode, endpoints, and optionally TLS and access control.

    The ``tls_*`` paths are relative to the line file (installation paths);
    with ``tls_ca_certificate`` set, every endpoint must be ``tls/``.
    """

    prefix: str = Field(default="insp/v1", pattern=KEY_PREFIX_PATTERN)
    mode: ZenohMode = ZenohMode.peer
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    tls_ca_certificate: str | None = Field(
        default=None,
        min_length=1,
        description="PEM certificate of the CA that signs the line's certificates; set: TLS "
        "on every endpoint, peers checked against this CA alone.",
    )
    tls_certificate: str | None = Field(
        default=None, min_length=1, description="This process's PEM certificate."
    )
    tls_private_key: str | None = Field(
        default=None, min_length=1, description="This process's PEM private key."
    )
    tls_mutual: bool = Field(
        default=True,
        description="Mutual TLS: present the certificate and require one from whoever "
        "connects (without it anyone who trusts the CA may connect).",
    )
    tls_verify_name: bool = Field(
        default=True,
        description="The certificate of the endpoint connected to must name its host.",
    )
    access_control: AccessControlSection | None = Field(
        default=None, description="Unset: whoever may connect may do anything."
    )

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for e in v:
            if not re.fullmatch(r"[a-z0-9]+/\S+", e):
                raise ValueError(f"not a zenoh endpoint (like tcp/127.0.0.1:7447): {e!r}")
        return v

    @model_validator(mode="after")
    def _tls_consistent(self) -> ZenohSection:
        tls = self.tls_ca_certificate is not None
        if (self.tls_certificate is None) != (self.tls_private_key is None):
            raise ValueError("tls_certificate and tls_private_key are set together")
        if self.tls_certificate is not None and not tls:
            raise ValueError("tls_certificate needs tls_ca_certificate")
        for key in ("listen", "connect"):
            for e in getattr(self, key):
                if tls and not e.startswith("tls/"):
                    raise ValueError(
                        f"{key}: {e!r} is not a tls/ endpoint; with tls_ca_certificate set "
                        "a plain one would let anyone in"
                    )
                if not tls and e.startswith("tls/"):
                    raise ValueError(f"{key}: {e!r} needs tls_ca_certificate")
        if tls and self.tls_certificate is None and (self.tls_mutual or self.listen):
            raise ValueError(
                "tls_certificate and tls_private_key are needed "
                + ("to listen" if self.listen else "with tls_mutual")
            )
        if self.access_control is not None and not (tls and self.tls_mutual):
            raise ValueError(
                "access_control needs tls_ca_certificate and tls_mutual = true: "
                "it goes by the common names of client certificates"
            )
        return self


McapCompression = Literal["none", "lz4", "zstd"]
McapImageEncoding = Literal["raw", "png"]


class StorageSection(_Strict):
    """Where the line keeps what it produces.

    The results go to the SQLite file ``data_dir/database`` unless ``url`` names
    a PostgreSQL database (``postgresql://user@host:5432/db``): one store for
    several stations and an API on other hosts. The URL is shown without its
    password wherever the configuration is logged or recorded; libpq also takes
    the password from ``PGPASSWORD`` or ``~/.pgpass``, which keeps it out of the
    file. Recordings, trees and per-point deviations stay in ``data_dir``.
    """

    data_dir: str = Field(default="runs", description="Relative to the working directory.")
    database: str = Field(
        default="results.sqlite", description="SQLite file, relative to data_dir."
    )
    url: str | None = Field(
        default=None,
        description="A postgresql:// URL: the results go to that database instead of "
        "the SQLite file.",
    )
    mcap_dir: str = Field(default="mcap", description="Relative to data_dir.")
    mcap_rotate_mb: float = Field(default=512.0, gt=0, le=1_000_000)
    mcap_rotate_min: float = Field(
        default=10.0,
        gt=0,
        le=100_000,
        description="A recording is finished after this long too, so at most this much "
        "of it is in a file the indexed reader cannot read yet.",
    )
    mcap_compression: McapCompression = Field(
        default="zstd",
        description="Chunk compression of the recordings: none, lz4 or zstd "
        "(bytes and CPU per part of each: make bench BENCH=line).",
    )
    mcap_image_encoding: McapImageEncoding = Field(
        default="raw",
        description="Images in the recordings: raw (foxglove.RawImage) or png (lossless "
        "foxglove.CompressedImage).",
    )
    trees_dir: str = Field(default="trees", description="Tree cache, relative to data_dir.")
    deviations_dir: str = Field(
        default="deviations", description="Per-inspection arrays, rel. to data_dir."
    )
    state_dir: str = Field(
        default="state",
        description="The worker's journal and the ingest's seq, relative to data_dir.",
    )

    @field_validator("url", mode="before")
    @classmethod
    def _empty_url_is_none(cls, v: object) -> object:
        return None if v == "" else v  # INSPECTION_STORAGE_URL= turns the URL off

    @field_validator("url")
    @classmethod
    def _postgres_url(cls, v: str | None) -> str | None:
        return None if v is None else check_postgres_url(v)

    @field_serializer("url")
    def _url_without_password(self, v: str | None) -> str | None:
        return None if v is None else redact_url(v)

    def data_path(self) -> Path:
        return Path(self.data_dir)

    def database_path(self) -> Path:
        return self.data_path() / self.database

    def store_target(self) -> str | Path:
        """What :class:`service.store.ResultStore` opens: the URL, else the SQLite file."""
        return self.url if self.url is not None else self.database_path()

    def mcap_path(self) -> Path:
        return self.data_path() / self.mcap_dir

    def trees_path(self) -> Path:
        return self.data_path() / self.trees_dir

    def deviations_path(self) -> Path:
        return self.data_path() / self.deviations_dir

    def journal_path(self, line: str, station: str) -> Path:
        """The worker's journal of FrameSets accepted and not yet answered."""
        return self.data_path() / self.state_dir / line / station / "journal"

    def ingest_seq_path(self, line: str, station: str) -> Path:
        """The ingest's next seq: kept across its restarts so no seq is used twice."""
        return self.data_path() / self.state_dir / line / station / "ingest-seq"

    def station_parts_path(self, line: str, station: str) -> Path:
        """A station worker's copies of the parts it took from the store (its own, apart
        from the uploads folder an API of the same data directory keeps)."""
        return self.data_path() / self.state_dir / line / station / "parts"


class RecordPolicy(StrEnum):
    all = "all"
    failures = "failures"
    every_nth = "every_nth"


class RetentionSection(_Strict):
    """What the MCAP recorder keeps, and the disk budget it keeps within.

    ``record``: every part, only parts that did not pass, or every n-th part
    (failures are always kept). The oldest files are deleted when the MCAP
    directory exceeds ``max_total_mb`` or a file is older than ``max_age_h``
    (either may be ``None``: no such limit).
    """

    record: RecordPolicy = RecordPolicy.all
    every_nth: int = Field(default=10, ge=1, le=1_000_000)
    max_total_mb: float | None = Field(default=10_000.0, gt=0)
    max_age_h: float | None = Field(default=None, gt=0)
    deviations_max_mb: float | None = Field(
        default=5_000.0,
        gt=0,
        description="The per-point deviations behind the colour maps: the oldest go beyond this.",
    )
    deviations_max_age_h: float | None = Field(default=None, gt=0)
    results_max_mb: float | None = Field(
        default=2_000.0,
        gt=0,
        description="The results in the store (their JSON): the oldest rows go beyond this.",
    )
    results_max_age_d: float | None = Field(default=None, gt=0)


class SimulatorSection(_Strict):
    """The ingest's simulated rig: how parts arrive and which defects they carry.

    The bounds keep a part inside the rig's measuring volume (800 x 500 mm at
    the belt) and a dent within what the rig resolves and the surface holds.
    """

    defect_rate: float = Field(
        default=0.1, ge=0, le=1, description="Fraction of parts given a defect."
    )
    dent_depth_mm: tuple[float, float] = Field(
        default=(0.2, 2.0),
        description="Range of an injected dent's depth, mm (a number: that depth).",
    )
    dent_radius_mm: tuple[float, float] = Field(
        default=(12.0, 20.0),
        description="Range of an injected dent's radius, mm (a number: that radius).",
    )
    dent_flat_mm: float = Field(
        default=7.0,
        ge=0,
        le=200,
        description="Radius of the dent's flat bottom, mm (0: a smooth bowl); below the radius.",
    )
    dent_bump_fraction: float = Field(
        default=0.5, ge=0, le=1, description="Share of the injected dents that are bumps."
    )
    position_range_x_mm: float = Field(
        default=60.0, ge=0, le=400, description="Half-range of the part's x on the belt, mm."
    )
    position_range_y_mm: float = Field(
        default=10.0, ge=0, le=250, description="Half-range of the part's y on the belt, mm."
    )
    yaw_range_deg: float = Field(
        default=180.0, ge=0, le=180, description="Half-range of the in-plane rotation, degrees."
    )
    flip: bool = Field(default=False, description="Half of the parts arrive turned by 180 deg.")
    hole_shift_mm: float = Field(
        default=0.0,
        ge=0,
        le=2,
        description="A generated part's holes lie off their drawn place by up to this in x and "
        "y, mm (drawn per part; the truth goes into the FrameSet).",
    )
    hole_radius_mm: float = Field(
        default=0.0, ge=0, le=1, description="... and their radius differs by up to this, mm."
    )
    seed: int = Field(default=0, ge=0)
    parts: list[Name] = Field(
        default_factory=list,
        max_length=100,
        description="The parts the simulated ingest sends, one drawn at random per trigger "
        "(default: the station's parts). A name that is not a part of the station is a part "
        "created over the API, read from the result store when the ingest starts.",
    )
    drift_point: Name | None = Field(
        default=None,
        description="A comparison point of the station's first part where a dent grows part "
        "by part (a process drifting, for trying the control charts).",
    )
    drift_after_seq: int = Field(default=0, ge=0, description="The drift starts after this seq.")
    drift_mm_per_part: float = Field(
        default=0.02, gt=0, le=1, description="How much deeper the dent is at each part, mm."
    )

    @field_validator("dent_depth_mm", "dent_radius_mm", mode="before")
    @classmethod
    def _one_number_is_a_range(cls, v: object) -> object:
        return (v, v) if isinstance(v, int | float) and not isinstance(v, bool) else v

    @field_validator("dent_depth_mm")
    @classmethod
    def _depth_range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not 0 < v[0] <= v[1] <= 20:
            raise ValueError(f"a depth range 0 < lo <= hi <= 20 mm is needed, got {list(v)}")
        return v

    @field_validator("dent_radius_mm")
    @classmethod
    def _radius_range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not 1 <= v[0] <= v[1] <= 200:
            raise ValueError(f"a radius range 1 <= lo <= hi <= 200 mm is needed, got {list(v)}")
        return v

    @model_validator(mode="after")
    def _flat_within_the_dent(self) -> SimulatorSection:
        if not self.dent_flat_mm < self.dent_radius_mm[0]:
            raise ValueError(
                f"dent_flat_mm ({self.dent_flat_mm}) must be below dent_radius_mm "
                f"({self.dent_radius_mm})"
            )
        return self


class AuthScope(StrEnum):
    none = "none"
    writes = "writes"
    all = "all"


class HttpSection(_Strict):
    """The REST API: where it listens, who may call it, what it takes.

    API keys never live in this file (its contents go into every recording's
    metadata): they come from ``$INSPECTION_API_KEYS`` or ``api_keys_file``.
    """

    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535, description="0: any free port.")
    max_upload_mb: float = Field(default=100.0, gt=0, le=10_000)
    trend_window: int = Field(default=50, ge=2, le=100_000, description="Parts in a trend.")
    auth: AuthScope = Field(
        default=AuthScope.writes,
        description="What needs an API key: writes (the default), all requests, or none.",
    )
    api_keys_file: str | None = Field(
        default=None,
        description="API keys, one per line, relative to the line file (besides "
        "$INSPECTION_API_KEYS). Without any key, writes are open only on a loopback host.",
    )
    allowed_origins: list[str] = Field(
        default_factory=list,
        max_length=100,
        description="Web origins (scheme://host[:port]) allowed to write and to read "
        "cross-origin; the API's own origin always is.",
    )
    max_measurements: int = Field(
        default=1, ge=1, le=64, description="Uploaded clouds measured at once."
    )
    max_waiting_measurements: int = Field(
        default=2, ge=0, le=1000, description="Uploads waiting for a turn; more get 503."
    )
    max_point_offset_mm: float = Field(
        default=1.0,
        gt=0,
        le=100,
        description="A part created over the API is refused when one of its comparison "
        "points lies farther than this from its CAD surface.",
    )

    @field_validator("allowed_origins")
    @classmethod
    def _origins(cls, v: list[str]) -> list[str]:
        for o in v:
            if not re.fullmatch(r"https?://[A-Za-z0-9.-]+(:\d{1,5})?/?", o):
                raise ValueError(f"not a web origin (like https://host:8443): {o!r}")
        return v


ZENOH_TLS_FILES = ("tls_ca_certificate", "tls_certificate", "tls_private_key")
"""The keys of ``[zenoh]`` that name files (relative to the line file)."""


class SpcSection(_Strict):
    """Control charts and their alarms (see :mod:`inspection.spc`)."""

    rules: list[str] = Field(
        default_factory=lambda: ["nelson1"],
        max_length=20,
        description="Run rules (nelson1..nelson8, we4) or sets (iso7870, western_electric, "
        "nelson); ISO 7870-2 suggests the 3-sigma rule alone (nelson1) for routine use.",
    )
    baseline_parts: int = Field(
        default=100,
        ge=2,
        le=10_000,
        description="Until a person freezes a baseline, limits come from a part's first "
        "this many results (fewer misjudge the within sigma, and a stable process alarms "
        "more often than the rules promise).",
    )
    window: int = Field(default=100, ge=2, le=100_000, description="Parts on a chart.")
    min_capability_n: int = Field(
        default=25, ge=2, le=10_000, description="Fewest values a capability figure needs."
    )
    alarms: bool = Field(default=True, description="A rule that fires raises an alarm.")

    @field_validator("rules")
    @classmethod
    def _known_rules(cls, v: list[str]) -> list[str]:
        # Imported here: the rules module loads scipy.stats, which reading a config does not need.
        from inspection.errors import InvalidInput
        from inspection.spc import resolve_rules

        try:
            resolve_rules(v)
        except InvalidInput as exc:
            raise ValueError(str(exc)) from exc
        return v


class LineConfig(_Strict):
    """The whole line: ``configs/line.toml``.

    ``base_dir`` is the line file's directory (set by :func:`load_line_config`);
    installation paths (rig calibration, parts) are resolved against it.
    """

    line: LineSection = Field(default_factory=LineSection)
    station: StationSection = Field(default_factory=StationSection)
    projector: ProjectorSection = Field(default_factory=ProjectorSection)
    zenoh: ZenohSection = Field(default_factory=ZenohSection)
    storage: StorageSection = Field(default_factory=StorageSection)
    retention: RetentionSection = Field(default_factory=RetentionSection)
    simulator: SimulatorSection = Field(default_factory=SimulatorSection)
    holography: HolographySection | None = None
    """The head of a ``sensor = "holography"`` station (its defaults when absent)."""
    spc: SpcSection = Field(default_factory=SpcSection)
    http: HttpSection = Field(default_factory=HttpSection)
    base_dir: str = Field(default=".", exclude=True)

    @model_validator(mode="after")
    def _holography_for_its_sensor(self) -> LineConfig:
        if self.holography is not None and self.station.sensor is not Sensor.holography:
            raise ValueError('a [holography] section is for a station with sensor = "holography"')
        path = self.holo_calibration_path()
        if path is not None:
            # Read here, not when the stages are built: a bad file stops the start-up with
            # the key and the file named.
            from inspection.errors import InspectionError
            from inspection.holography import HoloCalibration

            if not path.is_file():
                raise ValueError(f"[holography] calibration: no such file {str(path)!r}")
            try:
                head = HoloCalibration.load(path).head
            except (OSError, InspectionError) as exc:
                raise ValueError(f"[holography] calibration: {exc}") from None
            h = self.head()
            if (head.pixels, head.field_mm, head.synthetic_mm) != (
                h.pixels,
                h.field_mm,
                h.synthetic_mm,
            ):
                raise ValueError(
                    f"[holography] calibration {path.name} is for {head.pixels} px over "
                    f"{head.field_mm:g} mm with a {head.synthetic_mm:g} mm synthetic wavelength; "
                    f"the section says {h.pixels} px, {h.field_mm:g} mm, {h.synthetic_mm:g} mm"
                )
        return self

    def head(self) -> HolographySection:
        """The station's holographic head (the section's defaults when it is absent)."""
        return self.holography if self.holography is not None else HolographySection()

    def holo_calibration_path(self) -> Path | None:
        value = self.head().calibration
        if value is None:
            return None
        p = Path(value)
        return p if p.is_absolute() else Path(self.base_dir) / p

    def rig_calibration_path(self) -> Path | None:
        if self.station.rig_calibration is None:
            return None
        p = Path(self.station.rig_calibration)
        return p if p.is_absolute() else Path(self.base_dir) / p

    def deviations_max_bytes(self) -> int | None:
        """The deviation archive's budget, bytes (None: no size limit)."""
        mb = self.retention.deviations_max_mb
        return None if mb is None else int(mb * 1e6)

    def api_keys_path(self) -> Path | None:
        if self.http.api_keys_file is None:
            return None
        p = Path(self.http.api_keys_file)
        return p if p.is_absolute() else Path(self.base_dir) / p

    def parts_path(self) -> Path:
        p = Path(self.station.parts_dir)
        return p if p.is_absolute() else Path(self.base_dir) / p

    def zenoh_tls_path(self, key: str) -> Path | None:
        """A ``zenoh.tls_*`` file (``tls_ca_certificate``, ...) resolved against the line file."""
        value = getattr(self.zenoh, key)
        if value is None:
            return None
        p = Path(value)
        return p if p.is_absolute() else Path(self.base_dir) / p

    @model_validator(mode="after")
    def _zenoh_tls_files(self) -> LineConfig:
        # Checked here, not left to zenoh: its error names neither the key nor the file.
        for key in ZENOH_TLS_FILES:
            p = self.zenoh_tls_path(key)
            if p is None:
                continue
            if not p.is_file():
                raise ValueError(f"zenoh.{key}: no such file {str(p)!r}")
            try:
                head = p.read_bytes()[:1_000_000]
            except OSError as exc:
                raise ValueError(f"zenoh.{key}: {p.name}: {exc.strerror}") from None
            want = b"PRIVATE KEY-----" if key == "tls_private_key" else b"BEGIN CERTIFICATE-----"
            if want not in head:
                what = "a PEM private key" if key == "tls_private_key" else "a PEM certificate"
                raise ValueError(f"zenoh.{key}: {p.name} is not {what}")
        return self

    def part_spec_paths(self) -> list[Path]:
        """The spec file of every part of the station (``<parts_dir>/<name>.toml``)."""
        return [self.parts_path() / f"{name}.toml" for name in self.station.parts]

    def key(self, *parts: str) -> str:
        """A zenoh key under the prefix, line and station: ``key("frames")``."""
        return "/".join([self.zenoh.prefix, self.line.name, self.station.name, *parts])

    def effective(self) -> dict[str, Any]:
        """The configuration as plain JSON data (what is logged and recorded)."""
        return self.model_dump(mode="json")

    def hash(self) -> str:
        """SHA-256 (hex) of the canonical JSON of :meth:`effective`."""
        return canonical_hash(self.effective())


def canonical_hash(data: Any) -> str:
    """SHA-256 (hex) of ``data`` as JSON with sorted keys and no spaces."""
    blob = json.dumps(data, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(blob.encode()).hexdigest()


ENV_OVERRIDES: dict[str, tuple[str, str]] = {
    "INSPECTION_DATA_DIR": ("storage", "data_dir"),
    "INSPECTION_STORAGE_URL": ("storage", "url"),
    "INSPECTION_HTTP_HOST": ("http", "host"),
    "INSPECTION_HTTP_PORT": ("http", "port"),
    "INSPECTION_ZENOH_MODE": ("zenoh", "mode"),
    "INSPECTION_ZENOH_LISTEN": ("zenoh", "listen"),
    "INSPECTION_ZENOH_CONNECT": ("zenoh", "connect"),
    "INSPECTION_ZENOH_TLS_CA_CERTIFICATE": ("zenoh", "tls_ca_certificate"),
    "INSPECTION_ZENOH_TLS_CERTIFICATE": ("zenoh", "tls_certificate"),
    "INSPECTION_ZENOH_TLS_PRIVATE_KEY": ("zenoh", "tls_private_key"),
    "INSPECTION_TRIGGER_PERIOD_S": ("line", "trigger_period_s"),
    "INSPECTION_DEFECT_RATE": ("simulator", "defect_rate"),
}
"""Environment variables that override deployment values: variable -> (section, key).

List values (zenoh endpoints) are comma-separated; an empty value means an
empty list. Each process of a line gives its own certificate and key this way
(one line file, one certificate per process); relative paths are still
resolved against the line file.
"""

_LIST_KEYS = {("zenoh", "listen"), ("zenoh", "connect")}


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: no such file") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc


def _format_validation(path: Path | str, exc: ValidationError) -> str:
    lines = [f"{path}: invalid configuration"]
    for err in exc.errors():
        where = ".".join(str(x) for x in err["loc"]) or "(top level)"
        lines.append(f"  {where}: {err['msg']}")
    return "\n".join(lines)


def apply_overrides(
    data: dict[str, Any],
    env: Mapping[str, str] | None = None,
    overrides: Mapping[tuple[str, str], Any] | None = None,
) -> dict[str, Any]:
    """Return ``data`` (raw TOML) with environment variables, then explicit overrides, applied.

    ``overrides`` maps (section, key) to a value (e.g. from command-line
    flags); a value of ``None`` is skipped. Values are validated afterwards
    with the rest.
    """
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    for var, (section, key) in ENV_OVERRIDES.items():
        if env is None or var not in env:
            continue
        raw = env[var]
        value: Any = (
            [e.strip() for e in raw.split(",") if e.strip()]
            if (section, key) in _LIST_KEYS
            else raw
        )
        out.setdefault(section, {})[key] = value
    for (section, key), value in (overrides or {}).items():
        if value is not None:
            out.setdefault(section, {})[key] = value
    return out


def load_line_config(
    path: str | Path,
    *,
    env: Mapping[str, str] | None = None,
    overrides: Mapping[tuple[str, str], Any] | None = None,
) -> LineConfig:
    """Read, override and validate a line file.

    Parameters
    ----------
    path : str or Path
        The TOML file.
    env : mapping, optional
        Environment to take :data:`ENV_OVERRIDES` from; pass ``os.environ`` in
        ``main``. ``None``: no environment overrides (tests stay hermetic).
    overrides : mapping of (section, key) to value, optional
        Applied after the environment (command-line flags win).

    Raises
    ------
    ConfigError
        Missing file, bad TOML, unknown keys, values out of bounds.
    """
    p = Path(path)
    data = apply_overrides(_read_toml(p), env, overrides)
    if "base_dir" in data:
        raise ConfigError(f"{p}: 'base_dir' is not a configuration key")
    data["base_dir"] = str(p.parent)
    try:
        cfg = LineConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation(p, exc)) from exc
    if cfg.station.path != "cloud":
        for spec_path in cfg.part_spec_paths():
            check_path(load_part_spec(spec_path), cfg.station.path, where=f"{p}: ")
    return cfg


def path_refusal(spec: PartSpecBase, path: str) -> str | None:
    """Why a station measuring on ``path`` cannot measure ``spec`` (None: it can)."""
    if path == "comparison_points" and spec.surface.fails_part:
        return (
            f"part {spec.name!r}: station path 'comparison_points' does not check the surface "
            "between the comparison points, so its [surface] cannot fail parts: set the "
            "station's path to 'cloud', or the part's [surface] fails_part to false"
        )
    return None


def check_path(spec: PartSpecBase, path: str, *, where: str = "") -> None:
    """Refuse a part spec that a station measuring on ``path`` cannot measure.

    Raises
    ------
    ConfigError
    """
    refusal = path_refusal(spec, path)
    if refusal is not None:
        raise ConfigError(where + refusal)


def line_config_from_env(path: str | Path, **kwargs: Any) -> LineConfig:
    """:func:`load_line_config` with the process environment (for ``main``)."""
    return load_line_config(path, env=os.environ, **kwargs)


def load_part_spec(path: str | Path) -> PartSpec:
    """Read and validate a part spec; the file's stem must equal its ``name``.

    Raises
    ------
    ConfigError
    """
    p = Path(path)
    data = _read_toml(p)
    try:
        spec = PartSpec.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation(p, exc)) from exc
    if spec.name != p.stem:
        raise ConfigError(
            f"{p}: the part's name {spec.name!r} differs from the file name {p.stem!r}"
        )
    return spec
