"""Errors of the API: every 4xx/5xx answer is ``{"error": {"code": ..., "message": ...}}``.

Codes are stable (clients switch on them); messages are for people.

::

    ApiError(status, code, message)      raised by routes
    RequestValidationError -> 422        validation_error
    HTTPException          -> its status  not_found, method_not_allowed, http_<status>
    InvalidInput           -> 422        invalid_input (inspection's own validation)
    UnknownPart            -> 404        unknown_part
    PartNotReady           -> 409        part_not_ready
    PartConflict           -> 409        part_conflict
    CadLoadError           -> 422        invalid_cad
    PointOffSurface        -> 422        point_off_surface (with each point's distance)
    PathConflict           -> 422        path_conflict (a check the station's path does not make)
    unknown query param    -> 422        unknown_parameter
    StoreError             -> 503        store_unavailable (the database cannot be reached)
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from inspection.errors import CadLoadError, InvalidInput

from ..models import ErrorBody, ErrorDetail
from ..parts import PartConflict, PartNotReady, PathConflict, PointOffSurface, UnknownPart
from ..store import StoreError

log = logging.getLogger(__name__)


class ApiError(Exception):
    """An answer other than success, with a stable ``code``."""

    def __init__(
        self, status: int, code: str, message: str, headers: dict[str, str] | None = None
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.headers = headers


def error_response(
    status: int, code: str, message: str, headers: dict[str, str] | None = None
) -> JSONResponse:
    body = ErrorBody(error=ErrorDetail(code=code, message=message))
    return JSONResponse(body.model_dump(), status_code=status, headers=headers)


_HTTP_CODES = {
    400: "bad_request",
    404: "not_found",
    405: "method_not_allowed",
    413: "payload_too_large",
    503: "unavailable",
    415: "unsupported_media_type",
}

# Responses documented in OpenAPI for every route.
ERROR_RESPONSES: dict[int | str, dict[str, object]] = {
    422: {"model": ErrorBody, "description": "Invalid request"},
}


def install_error_handlers(app: FastAPI) -> None:
    """Translate every error into the one error body."""

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return error_response(exc.status, exc.code, exc.message, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        parts = []
        for err in exc.errors():
            where = ".".join(str(x) for x in err.get("loc", ()))
            parts.append(f"{where}: {err.get('msg', 'invalid')}")
        return error_response(422, "validation_error", "; ".join(parts) or "invalid request")

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _HTTP_CODES.get(exc.status_code, f"http_{exc.status_code}")
        return error_response(
            exc.status_code, code, str(exc.detail), headers=getattr(exc, "headers", None)
        )

    @app.exception_handler(UnknownPart)
    async def _unknown_part(request: Request, exc: UnknownPart) -> JSONResponse:
        return error_response(404, "unknown_part", str(exc))

    @app.exception_handler(PartNotReady)
    async def _not_ready(request: Request, exc: PartNotReady) -> JSONResponse:
        return error_response(409, "part_not_ready", str(exc))

    @app.exception_handler(PartConflict)
    async def _conflict(request: Request, exc: PartConflict) -> JSONResponse:
        return error_response(409, "part_conflict", str(exc))

    @app.exception_handler(PointOffSurface)
    async def _off_surface(request: Request, exc: PointOffSurface) -> JSONResponse:
        return error_response(422, "point_off_surface", str(exc))

    @app.exception_handler(PathConflict)
    async def _path_conflict(request: Request, exc: PathConflict) -> JSONResponse:
        return error_response(422, "path_conflict", str(exc))

    @app.exception_handler(InvalidInput)
    async def _invalid(request: Request, exc: InvalidInput) -> JSONResponse:
        return error_response(422, "invalid_input", str(exc))

    @app.exception_handler(CadLoadError)
    async def _cad(request: Request, exc: CadLoadError) -> JSONResponse:
        return error_response(422, "invalid_cad", str(exc))

    @app.exception_handler(StoreError)
    async def _store(request: Request, exc: StoreError) -> JSONResponse:
        # A database server on another host can be down while the API is up: the
        # client may retry, as after any 503. Where the database is stays in the log.
        log.error("result store: %s", exc)
        return error_response(
            503, "store_unavailable", "the result store cannot be reached; retry shortly"
        )

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, "internal_error", f"{type(exc).__name__}: internal error")
