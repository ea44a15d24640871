"""Multipart parsing shared by the upload routes: content type (415), size and shape checks."""

from __future__ import annotations

from typing import Any

from fastapi import Request
from pydantic import BaseModel
from starlette.datastructures import FormData, UploadFile
from starlette.formparsers import MultiPartException
from starlette.requests import ClientDisconnect

from .errors import ApiError


async def read_multipart(request: Request, *, max_files: int = 1, max_fields: int = 16) -> FormData:
    """The request's multipart form; 415 for another content type, 400 when malformed."""
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        raise ApiError(
            415,
            "unsupported_media_type",
            f"send multipart/form-data (a file and form fields), not {ctype or 'no content type'}",
        )
    try:
        return await request.form(max_files=max_files, max_fields=max_fields)
    except MultiPartException as exc:
        raise ApiError(400, "malformed_multipart", f"malformed multipart body: {exc}") from exc
    except ClientDisconnect as exc:
        raise ApiError(
            400, "incomplete_body", "the client closed the connection mid-upload"
        ) from exc


async def file_field(form: FormData, name: str) -> tuple[bytes, str]:
    """The bytes and file name of upload ``name``; 422 when it is missing or not a file."""
    item: Any = form.get(name)
    if item is None:
        raise ApiError(422, "validation_error", f"the form needs a file part named {name!r}")
    if not isinstance(item, UploadFile):
        raise ApiError(422, "validation_error", f"{name!r} must be a file, not a text field")
    data = await item.read()
    if not data:
        raise ApiError(422, "empty_file", f"the uploaded {name!r} file is empty")
    return data, item.filename or ""


def only_fields(form: FormData, names: tuple[str, ...]) -> None:
    """422 for a field the form does not define: a misspelt ``serail`` must not pass unseen."""
    unknown = sorted(set(form.keys()) - set(names))
    if unknown:
        raise ApiError(
            422,
            "validation_error",
            f"unknown form fields {', '.join(map(repr, unknown))}; the form has {', '.join(names)}",
        )


def text_field(form: FormData, name: str, default: str | None = None) -> str | None:
    item = form.get(name)
    if item is None:
        return default
    if not isinstance(item, str):
        raise ApiError(422, "validation_error", f"{name!r} must be a text field, not a file")
    return item


def json_part_schema(model: type[BaseModel]) -> dict[str, Any]:
    """``model``'s JSON Schema with its definitions inlined, for a JSON part of a multipart body.

    A body schema given through ``openapi_extra`` cannot add to the document's
    components, and its ``$ref`` resolve against the document's root; inlined,
    the schema stands alone. (The models sent this way are not recursive.)
    """
    schema = model.model_json_schema()
    defs = schema.pop("$defs", {})

    def inline(node: Any) -> Any:
        if isinstance(node, dict):
            ref = node.get("$ref")
            if isinstance(ref, str) and ref.startswith("#/$defs/"):
                rest = {k: v for k, v in node.items() if k != "$ref"}
                return {**inline(defs[ref.removeprefix("#/$defs/")]), **inline(rest)}
            return {k: inline(v) for k, v in node.items()}
        if isinstance(node, list):
            return [inline(v) for v in node]
        return node

    inlined: dict[str, Any] = inline(schema)
    return inlined
