"""Part types: list, show, create from a CAD upload (tree built as a job), delete; jobs."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import ValidationError

from ...models import ErrorBody, Job, Page, PartCreate, PartPublic
from ...names import NAME_MAX_LEN, NAME_PATTERN
from ...parts import UPLOAD_SUFFIXES
from ..deps import PartPath, ServicesDep
from ..errors import ApiError
from ..forms import file_field, json_part_schema, only_fields, read_multipart, text_field
from ..params import known_parameters

router = APIRouter(tags=["parts"], dependencies=[Depends(known_parameters)])


_ERRORS: dict[int | str, dict[str, object]] = {
    404: {"model": ErrorBody, "description": "Unknown part or job"},
    409: {"model": ErrorBody, "description": "Conflicts with the part's state"},
    422: {"model": ErrorBody, "description": "Invalid request"},
}

CREATE_FIELDS = ("cad", "spec")

_CREATE_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["cad", "spec"],
                    "additionalProperties": False,
                    "properties": {
                        "cad": {
                            "type": "string",
                            "format": "binary",
                            "minLength": 1,
                            "description": "The mesh; its file name ends in "
                            f"{', '.join(UPLOAD_SUFFIXES)} (else 415); at most the server's "
                            "max_upload_mb with the rest of the body (else 413)",
                        },
                        "spec": {
                            **json_part_schema(PartCreate),
                            "description": "PartCreate as JSON",
                        },
                    },
                },
                "encoding": {"spec": {"contentType": "application/json"}},
            }
        },
    }
}


@router.get(
    "/v1/parts",
    response_model=Page[PartPublic],
    responses={422: _ERRORS[422]},
    summary="Part types, by name",
)
def list_parts(
    svc: ServicesDep,
    limit: int = Query(100, ge=1, le=1000),
    cursor: str | None = Query(
        None,
        pattern=NAME_PATTERN,
        max_length=NAME_MAX_LEN,
        description="`next` of the previous page",
    ),
) -> Page[PartPublic]:
    names = [n for n in svc.parts.names() if cursor is None or n > cursor]
    page = names[:limit]
    items = []
    for n in page:
        try:
            items.append(svc.parts.public(n))
        except KeyError:  # deleted meanwhile
            continue
    return Page[PartPublic](items=items, next=page[-1] if len(names) > limit else None)


@router.get("/v1/parts/{name}", response_model=PartPublic, responses=_ERRORS)
def get_part(svc: ServicesDep, name: PartPath) -> PartPublic:
    return svc.parts.public(name)


@router.post(
    "/v1/parts",
    response_model=PartPublic,
    status_code=202,
    responses={
        **_ERRORS,
        400: {"model": ErrorBody, "description": "Malformed multipart body"},
        413: {"model": ErrorBody, "description": "Body above the server's max_upload_mb"},
        415: {"model": ErrorBody, "description": "Not multipart, or not a CAD file name"},
        422: {"model": ErrorBody, "description": "Invalid spec or CAD file"},
    },
    openapi_extra=_CREATE_BODY,
    summary="Create a part from a CAD file and a spec; its tree is built in the background",
)
async def create_part(svc: ServicesDep, request: Request, response: Response) -> PartPublic:
    form = await read_multipart(request)
    try:
        only_fields(form, CREATE_FIELDS)
        raw_spec = text_field(form, "spec")
        if raw_spec is None:
            raise ApiError(
                422, "validation_error", "the form needs a 'spec' field (PartCreate as JSON)"
            )
        try:
            spec = PartCreate.model_validate_json(raw_spec)
        except ValidationError as exc:
            where = "; ".join(
                f"{'.'.join(str(x) for x in e['loc']) or 'spec'}: {e['msg']}" for e in exc.errors()
            )
            raise ApiError(422, "invalid_spec", f"invalid part spec: {where}") from exc
        data, filename = await file_field(form, "cad")
        suffix = Path(filename).suffix.lower()
        if suffix not in UPLOAD_SUFFIXES:
            raise ApiError(
                415,
                "unsupported_cad_format",
                f"the CAD file must end in one of {', '.join(UPLOAD_SUFFIXES)}, got {filename!r}",
            )
    finally:
        await form.close()
    job = await run_in_threadpool(
        svc.parts.create, spec, data, filename,
        max_point_offset_mm=svc.settings.http.max_point_offset_mm,
    )  # fmt: skip
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    return svc.parts.public(spec.name)


@router.delete(
    "/v1/parts/{name}", status_code=204, responses=_ERRORS, summary="Delete an uploaded part"
)
def delete_part(svc: ServicesDep, name: PartPath) -> Response:
    svc.parts.delete(name)
    return Response(status_code=204)


@router.get(
    "/v1/jobs/{job_id}", response_model=Job, responses=_ERRORS, summary="A tree build's progress"
)
def get_job(svc: ServicesDep, job_id: str) -> Job:
    try:
        return svc.parts.job(job_id)
    except KeyError as exc:
        raise ApiError(404, "unknown_job", f"no job {job_id!r}") from exc
