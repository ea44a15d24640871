"""The quality desk: control charts, frozen baselines and alarms (acknowledged by a person)."""

from __future__ import annotations

import hashlib
import re
import time

from fastapi import APIRouter, Depends, Query, Request

from inspection.errors import InvalidInput

from ...models import (
    Alarm,
    AlarmAck,
    Baseline,
    BaselineCreate,
    ControlChart,
    ErrorBody,
    Trend,
)
from ...spc import SpcSettings, part_chart, trend
from ...spc import freeze_baseline as freeze
from ..access import presented_key
from ..deps import PartPath, ServicesDep
from ..errors import ApiError
from ..params import known_parameters

router = APIRouter(tags=["quality"], dependencies=[Depends(known_parameters)])

_ERRORS: dict[int | str, dict[str, object]] = {
    404: {"model": ErrorBody, "description": "Unknown part, feature or alarm"},
    422: {"model": ErrorBody, "description": "Invalid request"},
}

_WRITE_ERRORS: dict[int | str, dict[str, object]] = {
    **_ERRORS,
    400: {"model": ErrorBody, "description": "A body that is not JSON"},
}

FEATURE_PATTERN = r"^[A-Za-z0-9._-]{1,128}$"


def _settings(svc: ServicesDep) -> SpcSettings:
    return SpcSettings.from_config(svc.settings.spc)


def _subgroup(svc: ServicesDep, part: str) -> int:
    return svc.parts.public(part).subgroup_size


def who(request: Request, by: str) -> str:
    """Who writes: the name they give and which key they hold (its hash's first digits).

    The key itself is never kept; its digest tells keys apart in the record.
    """
    key = presented_key({k.lower(): v for k, v in request.headers.items()})
    name = by.strip() or "anonymous"
    if key is None:
        return f"{name} (no key)"
    return f"{name} (key {hashlib.sha256(key).hexdigest()[:8]})"


@router.get(
    "/v1/parts/{name}/trends",
    response_model=Trend,
    responses=_ERRORS,
    summary="Capability per comparison point over the last parts: Cp, Cpk (within sigma), "
    "Pp, Ppk (overall sigma), each with n and a 95 % interval",
)
def trends(
    svc: ServicesDep,
    name: PartPath,
    window: int | None = Query(None, ge=2, le=100_000, description="Parts (default: the config's)"),
) -> Trend:
    svc.parts.public(name)  # 404 for unknown parts
    return trend(svc.store, name, window or svc.settings.http.trend_window, _settings(svc))


@router.get(
    "/v1/parts/{name}/charts/{feature}",
    response_model=ControlChart,
    responses=_ERRORS,
    summary="Control chart of a comparison point, `fit_rms` or `defects`: values, limits, "
    "run rules that hold, capability",
)
def chart(
    svc: ServicesDep,
    name: PartPath,
    feature: str,
) -> ControlChart:
    svc.parts.public(name)
    if not re.fullmatch(FEATURE_PATTERN, feature):
        raise ApiError(422, "validation_error", f"not a feature name: {feature[:64]!r}")
    ch = part_chart(svc.store, name, feature, _settings(svc), _subgroup(svc, name))
    known = {p.name for p in svc.parts.public(name).points} | {"fit_rms", "defects"}
    if feature not in known and not ch.points:
        raise ApiError(404, "unknown_feature", f"{name!r} has no feature {feature!r}")
    return ch


@router.get(
    "/v1/parts/{name}/baseline",
    response_model=Baseline,
    responses=_ERRORS,
    summary="The part's frozen baseline (404: limits come from its first results)",
)
def get_baseline(svc: ServicesDep, name: PartPath) -> Baseline:
    svc.parts.public(name)
    b = svc.store.baseline(name)
    if b is None:
        raise ApiError(404, "no_baseline", f"no baseline is frozen for {name!r}")
    return b


@router.post(
    "/v1/parts/{name}/baseline",
    response_model=Baseline,
    status_code=201,
    responses=_WRITE_ERRORS,
    summary="Freeze the control limits from the results of a period judged stable",
)
def post_baseline(
    svc: ServicesDep, request: Request, name: PartPath, body: BaselineCreate
) -> Baseline:
    svc.parts.public(name)
    if body.since_ns is not None and body.until_ns is not None and body.since_ns > body.until_ns:
        raise ApiError(422, "validation_error", "since_ns must not be after until_ns")
    try:
        return freeze(svc.store, name, since_ns=body.since_ns, until_ns=body.until_ns,
                      by=who(request, body.by), subgroup=_subgroup(svc, name))  # fmt: skip
    except InvalidInput as exc:
        raise ApiError(422, "too_few_results", str(exc)) from exc


@router.delete(
    "/v1/parts/{name}/baseline",
    status_code=204,
    responses=_ERRORS,
    summary="Thaw the baseline: limits come from the part's first results again",
)
def delete_baseline(svc: ServicesDep, name: PartPath) -> None:
    svc.parts.public(name)
    if not svc.store.delete_baseline(name):
        raise ApiError(404, "no_baseline", f"no baseline is frozen for {name!r}")


@router.get(
    "/v1/alarms", response_model=list[Alarm], responses=_ERRORS, summary="Alarms, newest first"
)
def list_alarms(
    svc: ServicesDep,
    open: bool = Query(False, description="Only those nobody acknowledged"),
    limit: int = Query(50, ge=1, le=1000),
) -> list[Alarm]:
    return svc.store.alarms(open_only=open, limit=limit)


@router.get("/v1/alarms/{id}", response_model=Alarm, responses=_ERRORS)
def get_alarm(svc: ServicesDep, id: str) -> Alarm:
    a = svc.store.alarm(id)
    if a is None:
        raise ApiError(404, "unknown_alarm", f"no alarm {id[:100]!r}")
    return a


@router.post(
    "/v1/alarms/{id}/ack",
    response_model=Alarm,
    responses=_WRITE_ERRORS,
    summary="Acknowledge an alarm: records who (a name and which key) and when",
)
def ack_alarm(svc: ServicesDep, request: Request, id: str, body: AlarmAck) -> Alarm:
    a = get_alarm(svc, id)
    if a.acknowledged_ns is not None:
        return a  # the first acknowledgement stands
    acked = a.model_copy(update={"acknowledged_by": who(request, body.by),
                                 "acknowledged_ns": time.time_ns()})  # fmt: skip
    svc.store.put_alarm(acked)
    return acked
