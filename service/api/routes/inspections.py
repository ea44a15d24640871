"""Inspections: measure an uploaded cloud, list and show results, draw their colour maps."""

from __future__ import annotations

import itertools
import re
import time
from datetime import UTC, datetime
from typing import Any, cast

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse, Response
from starlette.requests import ClientDisconnect

from inspection.measure import Frame, validate_cloud

from ...models import ErrorBody, InspectionResult, Page, Recording, Status, new_upload_id
from ...names import NAME_MAX_LEN, NAME_PATTERN, NAME_RULE, is_valid_name
from ...parts import UnknownPart
from ...recordings import locate
from ...report import PdfUnavailable, ReportContext, report_html, report_pdf
from ...results import upload_trigger
from ...spc import PART_FEATURES, SpcSettings, part_chart
from ...store import Filters, InvalidCursor
from ..clouds import UnsupportedCloudFormat, parse_cloud
from ..colormap import Marker, PointMark, render_top_view
from ..deps import NameQuery, PartQuery, Services, ServicesDep
from ..errors import ApiError
from ..forms import file_field, only_fields, read_multipart, text_field
from ..gate import Busy
from ..measurer import MeasurerDied
from ..params import known_parameters
from ..tables import CSV_COLUMNS, results_csv, wants_csv

router = APIRouter(tags=["inspections"], dependencies=[Depends(known_parameters)])

UPLOAD_STATION = "api"
"""The station recorded for clouds measured through the API (not from a trigger)."""

_counter = itertools.count(1)

FRAMES = ("rig", "data", "cad")

MAX_NS = 2**63 - 1
"""The latest time the store can hold, ns since the epoch (SQLite's int64)."""

UPLOAD_FIELDS = ("file", "part", "frame", "serial")

_POST_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file", "part"],
                    "additionalProperties": False,
                    "properties": {
                        "file": {
                            "type": "string",
                            "format": "binary",
                            "minLength": 1,
                            "description": "The cloud: .npy (N, 3) float or PLY, mm "
                            "(recognised by its first bytes); at most the server's "
                            "max_upload_mb with the rest of the body (else 413)",
                        },
                        "part": {
                            "type": "string",
                            "pattern": NAME_PATTERN,
                            "maxLength": NAME_MAX_LEN,
                            "description": f"Part name: {NAME_RULE}",
                        },
                        "frame": {
                            "type": "string",
                            "enum": list(FRAMES),
                            "default": "rig",
                            "description": "rig: seen from above, anywhere on the belt; "
                            "data: any frame, anywhere; cad: near the CAD frame",
                        },
                        "serial": {
                            "type": "string",
                            "pattern": NAME_PATTERN,
                            "maxLength": NAME_MAX_LEN,
                            "description": f"{NAME_RULE}; default: upload-<n>",
                        },
                    },
                }
            }
        },
    }
}

CURSOR_PATTERN = r"^[A-Za-z0-9_-]+$"
"""The alphabet of the cursors the store hands out (unpadded URL-safe base64)."""

_READ_ERRORS: dict[int | str, dict[str, object]] = {
    404: {"model": ErrorBody, "description": "Unknown result"},
    422: {"model": ErrorBody, "description": "Invalid request"},
}

_POST_ERRORS: dict[int | str, dict[str, object]] = {
    400: {"model": ErrorBody, "description": "Malformed multipart body"},
    404: {"model": ErrorBody, "description": "Unknown part"},
    409: {"model": ErrorBody, "description": "The part's tree is not ready"},
    413: {"model": ErrorBody, "description": "Body above the server's max_upload_mb"},
    415: {"model": ErrorBody, "description": "Not multipart, or a cloud neither NPY nor PLY"},
    422: {"model": ErrorBody, "description": "Invalid field or cloud"},
}


SINCE_SCHEMA: dict[str, Any] = {
    "anyOf": [
        {"type": "integer", "minimum": 0, "maximum": MAX_NS},
        {"type": "string", "format": "date-time"},
        {"type": "string", "format": "date"},
        {"type": "null"},
    ]
}
"""What ``since`` accepts (:func:`parse_since` also takes a date-time without its offset)."""


def parse_since(value: str | None, what: str = "since") -> int | None:
    """A time bound as ns since the epoch: an integer (ns) or an ISO 8601 time (naive = UTC).

    The store keeps times as 64-bit integers: an integer outside them is refused;
    a calendar time before the epoch or beyond 2262 is clamped to their range
    (everything, or nothing), which is what it asks for.
    """
    if value is None:
        return None
    if value.lstrip("-").isdigit():
        if len(value) > 20 or not 0 <= int(value) <= MAX_NS:
            raise ApiError(
                422, "validation_error", f"{what} must be ns since the epoch in [0, {MAX_NS}]"
            )
        return int(value)
    try:
        dt = datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError as exc:
        raise ApiError(
            422, "validation_error", f"{what} must be ns since the epoch or ISO 8601, got {value!r}"
        ) from exc
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return min(max(int(round(dt.timestamp() * 1e9)), 0), MAX_NS)


@router.post(
    "/v1/inspections",
    response_model=InspectionResult,
    responses=_POST_ERRORS,
    openapi_extra=_POST_BODY,
    summary="Inspect an uploaded point cloud of a part; answers with the result",
)
async def create_inspection(svc: ServicesDep, request: Request) -> InspectionResult:
    # A place is taken before the body is parsed: a busy API refuses at once. The
    # body is still read and dropped, so that the client gets the answer.
    try:
        svc.gate.admit()
    except Busy as exc:
        try:
            async for _ in request.stream():
                pass
        except ClientDisconnect:
            pass
        raise ApiError(
            503, "busy", "the API is measuring as many uploads as it may; retry shortly",
            headers={"Retry-After": str(exc.retry_after_s)},
        ) from None  # fmt: skip
    try:
        return await _inspect_upload(svc, request)
    finally:
        svc.gate.leave()


async def _inspect_upload(svc: Services, request: Request) -> InspectionResult:
    form = await read_multipart(request)
    try:
        only_fields(form, UPLOAD_FIELDS)
        part_name = text_field(form, "part")
        if part_name is None:
            raise ApiError(422, "validation_error", "the form needs a 'part' field")
        frame = text_field(form, "frame", "rig")
        if frame not in FRAMES:
            raise ApiError(
                422, "validation_error", f"frame must be one of {', '.join(FRAMES)}, got {frame!r}"
            )
        serial = text_field(form, "serial", f"upload-{next(_counter)}")
        if serial is None or not is_valid_name(serial):
            raise ApiError(422, "validation_error", f"serial {serial!r} is not a name: {NAME_RULE}")
        part = svc.parts.get(part_name)  # 404 unknown / 409 not ready, before reading the cloud
        data, _ = await file_field(form, "file")
    finally:
        await form.close()
    trigger = upload_trigger(
        part,
        id=new_upload_id(),
        line=svc.settings.line.name,
        station=UPLOAD_STATION,
        serial=serial,
        triggered_ns=time.time_ns(),
    )
    # InvalidInput (NaN, too few points, truncated file) goes to the 422 handler:
    # nothing is stored for a cloud that cannot be measured at all. A large cloud
    # costs CPU the line needs: it is parsed where it is measured, at a lower priority.
    try:
        if svc.measurer is not None:
            kept = svc.archive.max_points if svc.archive is not None else 0
            done = await svc.measurer.measure(
                part, data, trigger, frame=cast(Frame, frame), trees_dir=svc.parts.trees_dir,
                keep_points=kept,
            )  # fmt: skip
            result, points_cad, distances = done.result, done.points_cad, done.distances
        else:
            points = await svc.gate.run(lambda: validate_cloud(parse_cloud(data)))
            outcome = await svc.gate.run(svc.pipeline, part, points, trigger, frame=frame)
            result, points_cad, distances = (
                outcome.result, outcome.points_cad(), outcome.distances
            )  # fmt: skip
    except UnsupportedCloudFormat as exc:
        raise ApiError(415, "unsupported_cloud_format", str(exc)) from exc
    except MeasurerDied as exc:
        raise ApiError(
            503, "measurer_died", f"{exc}; retry shortly", headers={"Retry-After": "5"}
        ) from exc
    await svc.gate.run(lambda: svc.record(result, points_cad, distances))
    return result


@router.get(
    "/v1/inspections",
    response_model=Page[InspectionResult],
    responses={
        **_READ_ERRORS,
        200: {
            "content": {"text/csv": {"schema": {"type": "string"}}},
            "description": "A page of results; with `Accept: text/csv` as CSV, one row per "
            "result and comparison point (columns: " + ", ".join(CSV_COLUMNS) + "); the "
            "next page's cursor is then in the X-Next-Cursor header",
        },
    },
    summary="Results, newest first; pass `next` as `cursor` for the following page",
)
def list_inspections(
    svc: ServicesDep,
    request: Request,
    part: PartQuery = None,
    status: Status | None = None,
    serial: NameQuery = None,
    station: NameQuery = None,
    since: str | None = Query(
        None,
        description="From this trigger time: ns since the epoch, or an ISO 8601 date or "
        "time (naive: UTC)",
        json_schema_extra=SINCE_SCHEMA,
    ),
    until: str | None = Query(
        None,
        description="Up to this trigger time (included), as `since`",
        json_schema_extra=SINCE_SCHEMA,
    ),
    limit: int = Query(50, ge=1, le=1000),
    cursor: str | None = Query(
        None,
        max_length=512,
        description="`next` of the previous page",
        # Stated, and checked below: a cursor of other characters is an invalid_cursor too.
        json_schema_extra={"pattern": CURSOR_PATTERN},
    ),
) -> Any:
    filters = Filters(
        part=part, status=status, serial=serial, station=station,
        since_ns=parse_since(since, "since"), until_ns=parse_since(until, "until"),
    )  # fmt: skip
    if cursor is not None and not re.fullmatch(CURSOR_PATTERN, cursor):
        raise ApiError(422, "invalid_cursor", f"not a valid cursor: {cursor!r}")
    try:
        items, nxt = svc.store.list(filters, limit=limit, cursor=cursor)
    except InvalidCursor as exc:
        raise ApiError(422, "invalid_cursor", str(exc)) from exc
    if wants_csv(request):
        headers = {"Content-Disposition": 'attachment; filename="inspections.csv"'}
        if nxt is not None:
            headers["X-Next-Cursor"] = nxt
        return Response(results_csv(items), media_type="text/csv; charset=utf-8", headers=headers)
    return Page[InspectionResult](items=items, next=nxt)


def _result(svc: Services, id_: str) -> InspectionResult:
    result = svc.store.get(id_)
    if result is None:
        raise ApiError(404, "unknown_inspection", f"no inspection with id {id_!r}")
    return result


@router.get("/v1/inspections/{id}", response_model=InspectionResult, responses=_READ_ERRORS)
def get_inspection(svc: ServicesDep, id: str) -> InspectionResult:
    return _result(svc, id)


@router.get(
    "/v1/inspections/{id}/colormap.png",
    response_class=Response,
    responses={**_READ_ERRORS, 200: {"content": {"image/png": {}}}},
    summary="Top view of the part coloured by deviation (CAD frame, seen from +z)",
)
def colormap(
    svc: ServicesDep,
    id: str,
    limit_mm: float | None = Query(None, gt=0, le=1000, description="Colour saturation, mm"),
    size_px: int = Query(800, ge=100, le=4000),
    annotated: bool = Query(
        False, description="Mark and name the comparison points; draw mm axes (CAD frame)"
    ),
) -> Response:
    result = _result(svc, id)
    png = colormap_png(svc, result, limit_mm=limit_mm, size_px=size_px, annotated=annotated)
    return Response(png, media_type="image/png", headers={"Cache-Control": "max-age=3600"})


def colormap_png(
    svc: Services,
    result: InspectionResult,
    *,
    limit_mm: float | None = None,
    size_px: int = 800,
    annotated: bool = True,
) -> bytes:
    """The result's top-view deviation map (404 ``no_deviations`` when none were kept)."""
    arrays = None
    if svc.archive is not None:
        try:
            arrays = svc.archive.load(result.id)
        except ValueError:
            arrays = None
    if arrays is None:
        raise ApiError(404, "no_deviations", f"no per-point deviations were kept for {result.id!r}")
    points, distances = arrays
    if limit_mm is None:
        tol = [max(abs(c.lower_mm), abs(c.upper_mm)) for c in result.comparison]
        limit_mm = max(tol) if tol else 1.0
    markers = [
        Marker(tuple(f.center_mm), f.area_mm2, f"{f.kind} {f.peak_mm:+.2f} mm")  # type: ignore[arg-type]
        for f in result.defects or ()
    ]
    marks: list[PointMark] = []
    if annotated:
        verdicts = {c.name: c.verdict.value for c in result.comparison}
        try:
            specs = svc.parts.public(result.part).points
        except UnknownPart:
            specs = []  # a part deleted since: its points are not known any more
        marks = [
            PointMark(tuple(p.position_mm), p.name, verdicts.get(p.name) == "fail")  # type: ignore[arg-type]
            for p in specs
        ]
    return render_top_view(
        points,
        distances,
        limit_mm=limit_mm,
        size_px=size_px,
        title=f"{result.part} {result.serial} {result.status.value}",
        markers=markers,
        points_marked=marks,
        axes=annotated,
    )


@router.get(
    "/v1/inspections/{id}/recording",
    response_model=Recording,
    responses={**_READ_ERRORS, 404: {"model": ErrorBody, "description": "Not recorded"}},
    summary="The MCAP file and log times that hold the inspection's frames, cloud and result",
)
def recording(svc: ServicesDep, id: str) -> Recording:
    result = _result(svc, id)
    found = locate(svc.settings.storage.mcap_path(), result.id, result.triggered_ns)
    if found is None:
        raise ApiError(
            404, "not_recorded",
            f"no recording holds {id!r} (an upload, or its file went by the retention)",
        )  # fmt: skip
    return Recording(file=found.file, start_ns=found.start_ns, end_ns=found.end_ns,
                     topics=found.topics, finished=found.finished)  # fmt: skip


def _report_page(svc: Services, id: str) -> str:
    result = _result(svc, id)
    try:
        png: bytes | None = colormap_png(svc, result, size_px=900)
    except ApiError:
        png = None  # no deviations kept: the report says so
    settings = SpcSettings.from_config(svc.settings.spc)
    try:
        subgroup = svc.parts.public(result.part).subgroup_size
    except UnknownPart:
        subgroup = 1
    charts = []
    if result.status.value in ("pass", "fail"):
        names = [c.name for c in result.comparison] + list(PART_FEATURES)
        charts = [part_chart(svc.store, result.part, n, settings, subgroup) for n in names]
    found = locate(svc.settings.storage.mcap_path(), result.id, result.triggered_ns)
    where = None if found is None else f"{found.file} at {found.start_ns} ns"
    return report_html(result, ReportContext(png, charts, where))


@router.get(
    "/v1/inspections/{id}/report.html",
    # A plain Response: with HTMLResponse the errors would be documented as HTML too.
    response_class=Response,
    responses={**_READ_ERRORS, 200: {"content": {"text/html": {}}}},
    summary="The part's report: colour map, comparison table, defects, fit, traceability, trends",
)
def report_page(svc: ServicesDep, id: str) -> Response:
    return HTMLResponse(_report_page(svc, id))


@router.get(
    "/v1/inspections/{id}/report.pdf",
    response_class=Response,
    responses={
        **_READ_ERRORS,
        200: {"content": {"application/pdf": {}}},
        503: {"model": ErrorBody, "description": "The PDF renderer is not installed"},
    },
    summary="The part's report as PDF",
)
def report_document(svc: ServicesDep, id: str) -> Response:
    page = _report_page(svc, id)
    try:
        pdf = report_pdf(page)
    except PdfUnavailable as exc:
        raise ApiError(503, "pdf_unavailable", str(exc)) from exc
    name = re.sub(r"[^A-Za-z0-9._-]", "_", _result(svc, id).serial)
    disposition = f'inline; filename="report-{name}.pdf"'
    return Response(pdf, media_type="application/pdf", headers={"Content-Disposition": disposition})
