"""The quality desk in a browser: the dashboard's pages, their assets and the API's docs.

Everything a page loads is served from the package itself (the vendored
libraries are under ``static/vendor``, see its README), so the dashboard,
``/docs`` and ``/redoc`` work on a plant network without internet. The pages
hold no data: they read the REST API from the browser, with the API key a
person enters once (kept for the browser tab's session) on writes.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

STATIC = Path(__file__).parent / "static"
VENDOR = "/static/vendor"

POLICY = (
    "default-src 'self'; img-src 'self' data: blob:; style-src 'self' 'unsafe-inline'; "
    "script-src 'self' 'unsafe-inline' blob:; worker-src 'self' blob:; connect-src 'self'; "
    "font-src 'self' data:; frame-ancestors 'self'; form-action 'self'"
)
"""What the pages may load: from the service alone. A vendored library that reaches for
a CDN (ReDoc's footer logo does) is stopped by the browser before any request leaves."""

HEADERS = {"Cache-Control": "no-cache", "Content-Security-Policy": POLICY}

router = APIRouter(include_in_schema=False)


def _page(name: str) -> FileResponse:
    return FileResponse(STATIC / name, media_type="text/html", headers=HEADERS)


@router.get("/")
def board() -> FileResponse:
    return _page("board.html")


@router.get("/ui/inspections/{id}")
def inspection(id: str) -> FileResponse:
    return _page("inspection.html")


@router.get("/ui/trends")
def trends() -> FileResponse:
    return _page("trends.html")


@router.get("/ui/search")
def search() -> FileResponse:
    return _page("search.html")


@router.get("/docs")
def docs() -> HTMLResponse:
    page = get_swagger_ui_html(
        openapi_url="/openapi.json",
        title="Inspection API",
        swagger_js_url=f"{VENDOR}/swagger-ui/swagger-ui-bundle.js",
        swagger_css_url=f"{VENDOR}/swagger-ui/swagger-ui.css",
        swagger_favicon_url="/static/favicon.svg",
        # Swagger UI would send the schema to validator.swagger.io for its badge.
        swagger_ui_parameters={"validatorUrl": None},
    )
    page.headers.update(HEADERS)
    return page


@router.get("/redoc")
def redoc() -> HTMLResponse:
    page = get_redoc_html(
        openapi_url="/openapi.json",
        title="Inspection API",
        redoc_js_url=f"{VENDOR}/redoc/redoc.standalone.js",
        redoc_favicon_url="/static/favicon.svg",
        with_google_fonts=False,
    )
    page.headers.update(HEADERS)
    return page


def install(app: FastAPI) -> None:
    """Add the pages, the docs and the static assets to ``app`` (made with no docs of its own)."""
    app.include_router(router)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
