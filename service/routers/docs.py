"""The interactive API documentation, served without the internet.

========================================  ==================================================
``GET /docs``                             Swagger UI on the service's ``/openapi.json``
``GET /docs/static/{name}``               its script and style sheet
========================================  ==================================================

FastAPI's own ``/docs`` page loads Swagger UI's script and style sheet from a CDN, so it was
blank on an observatory's offline network. Here they come from the ``swagger-ui-bundle``
package (Swagger UI 4, the files only), installed with the service; ReDoc, which has no such
package, is not served.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse

from autocal.service.schemas import ApiError

router = APIRouter(include_in_schema=False)

#: The only files served from the bundle, with their media types.
ASSETS = {
    "swagger-ui-bundle.js": "text/javascript; charset=utf-8",
    "swagger-ui.css": "text/css; charset=utf-8",
}


def assets_dir() -> Path:
    """Return the folder of Swagger UI's files (the ``swagger-ui-bundle`` package)."""
    from swagger_ui_bundle import swagger_ui_path

    return Path(swagger_ui_path)


@router.get("/docs", response_class=HTMLResponse)
def swagger_ui(request: Request) -> HTMLResponse:
    """Return Swagger UI on ``/openapi.json``, its files served by this service."""
    return get_swagger_ui_html(
        openapi_url=request.app.openapi_url or "/openapi.json",
        title=f"{request.app.title} - API documentation",
        swagger_js_url="/docs/static/swagger-ui-bundle.js",
        swagger_css_url="/docs/static/swagger-ui.css",
        swagger_favicon_url="data:,",  # none: the default one is fetched from the internet
    )


@router.get("/docs/static/{name}")
def swagger_asset(name: str) -> FileResponse:
    """Return one of Swagger UI's files (404 for any other name)."""
    media = ASSETS.get(name)
    if media is None:
        raise ApiError(404, f"no documentation file {name!r}")
    return FileResponse(assets_dir() / name, media_type=media)
