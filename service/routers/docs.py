"""The interactive API documentation, served without the internet.

========================================  ==================================================
``GET /docs``                             Swagger UI on the service's ``/openapi.json``
``GET /redoc``                            ReDoc on the same schema
``GET /docs/static/{name}``               their scripts, style sheet and icon
========================================  ==================================================

FastAPI's own pages load Swagger UI and ReDoc from a CDN, so they were blank on an
observatory's offline network. Here the files come from the ``fastapi-offline`` package
(Swagger UI 5, which renders the OpenAPI 3.1 schema FastAPI writes, and ReDoc 2), installed
with the service; the pages' URLs carry the ASGI ``root_path`` (``autocal serve
--root-path``), as FastAPI's own do.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse

from autocal.service.schemas import ApiError

router = APIRouter(include_in_schema=False)

#: The only files served from the package, with their media types.
ASSETS = {
    "swagger-ui-bundle.js": "text/javascript; charset=utf-8",
    "swagger-ui.css": "text/css; charset=utf-8",
    "redoc.standalone.js": "text/javascript; charset=utf-8",
    "favicon.png": "image/png",
}


def assets_dir() -> Path:
    """Return the folder of Swagger UI's and ReDoc's files (the ``fastapi-offline`` package)."""
    import fastapi_offline

    return Path(fastapi_offline.__file__).resolve().parent / "static"


def _urls(request: Request) -> tuple[str, str]:
    """Return the schema's URL and the assets' folder URL, under the ASGI ``root_path``."""
    root = str(request.scope.get("root_path", "")).rstrip("/")
    return f"{root}{request.app.openapi_url or '/openapi.json'}", f"{root}/docs/static"


@router.get("/docs", response_class=HTMLResponse)
def swagger_ui(request: Request) -> HTMLResponse:
    """Return Swagger UI on the service's schema, its files served by this service."""
    schema, static = _urls(request)
    return get_swagger_ui_html(
        openapi_url=schema,
        title=f"{request.app.title} - API documentation",
        swagger_js_url=f"{static}/swagger-ui-bundle.js",
        swagger_css_url=f"{static}/swagger-ui.css",
        swagger_favicon_url=f"{static}/favicon.png",
    )


@router.get("/redoc", response_class=HTMLResponse)
def redoc(request: Request) -> HTMLResponse:
    """Return ReDoc on the service's schema, its script served by this service."""
    schema, static = _urls(request)
    return get_redoc_html(
        openapi_url=schema,
        title=f"{request.app.title} - API reference",
        redoc_js_url=f"{static}/redoc.standalone.js",
        redoc_favicon_url=f"{static}/favicon.png",
        with_google_fonts=False,
    )


@router.get("/docs/static/{name}")
def docs_asset(name: str) -> FileResponse:
    """Return one of the documentation pages' files (404 for any other name)."""
    media = ASSETS.get(name)
    if media is None:
        raise ApiError(404, f"no documentation file {name!r}")
    return FileResponse(assets_dir() / name, media_type=media)
