"""The FastAPI application of the job service.

Run with ``uvicorn autocal.service.app:create_app --factory`` (settings from
``AUTOCAL_*``; see :mod:`autocal.service.settings`). Interactive documentation is served
at ``/docs`` and ``/redoc`` (their files served from an installed package, offline:
:mod:`.routers.docs`), the schema at ``/openapi.json``.

Errors always answer JSON ``{"detail": "<what is wrong and what to do>"}``: request
validation failures are 422 with ``errors`` naming each bad field and why; unexpected
failures are 500 with a reference to the server log, never a stack trace.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from autocal import __version__
from autocal.service.body_limit import BodyLimitMiddleware
from autocal.service.routers import (
    MAX_ERRORS,
    describe_problem,
    docs,
    health,
    job_results,
    jobs,
    monitoring,
    nightly,
    problems_message,
    ui,
    uploads,
)
from autocal.service.schemas import ApiError
from autocal.service.settings import Settings, get_settings
from autocal.service.store import JobStore
from autocal.service.tokens import FailedAuthLimiter, checked_tokens

logger = logging.getLogger(__name__)

DESCRIPTION = """
Calibrate radio-telescope auto-correlations as jobs: submit an observation (files under
the data roots or uploads), follow its progress, fetch the solution (G, |g|, Trxr with
uncertainties per antenna, polarisation and channel) and download the products.
Write endpoints need `Authorization: Bearer <token>` (one of the named tokens the operator
configured); reads too when the service runs with `AUTOCAL_READ_AUTH=1`. Anonymous reads
show jobs without server paths, worker names or logs.
"""


class CatchAllMiddleware:
    """Answer unexpected exceptions with a generic 500 JSON body and log them.

    Sits inside Starlette's server-error middleware, so the client never sees a stack
    trace and the exception is logged once, here, with a reference the client can quote.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Run the wrapped application, turning an escaping exception into a 500."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, tracked)
        except Exception:
            reference = uuid.uuid4().hex[:12]
            logger.exception(
                "unhandled error (reference %s) in %s %s",
                reference,
                scope.get("method"),
                scope.get("path"),
            )
            if started:  # too late for an error answer; the connection is closed
                return
            response = JSONResponse(
                {
                    "detail": f"internal server error (reference {reference}); the operator "
                    "can find the details in the server log"
                },
                status_code=500,
            )
            await response(scope, receive, send)


async def single_valued_query(request: Request) -> None:
    """Refuse a query parameter given more than once (every parameter here takes one value).

    Without this, ``?night=1&night=2`` silently used the last value.
    """
    counts: dict[str, int] = {}
    for key, _ in request.query_params.multi_items():
        counts[key] = counts.get(key, 0) + 1
    repeated = sorted(k for k, n in counts.items() if n > 1)
    if repeated:
        raise ApiError(
            422,
            f"query parameter {repeated[0]!r} given {counts[repeated[0]]} times; give it once",
            errors=[
                {"field": f"query.{k}", "message": f"given {counts[k]} times", "type": "repeated"}
                for k in repeated
            ],
        )


#: What FastAPI says of a body that ``json.loads`` cannot take (invalid UTF-8, nested too
#: deep): replaced by :data:`_UNPARSEABLE`.
_PARSE_FAILURE = "There was an error parsing the body"
_UNPARSEABLE = (
    "the body could not be read as JSON (it must be UTF-8 text holding one JSON object, "
    "nested a few levels at most): send the object the API's schema shows (/openapi.json)"
)


def _json_media(request: Request) -> bool:
    """Whether the request says its body is JSON (``application/json`` or ``+json``)."""
    media = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    return media == "application/json" or media.endswith("+json")


async def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = exc.errors()
    if not _json_media(request) and any(tuple(e.get("loc", ()))[:1] == ("body",) for e in errors):
        # a form, text or multipart body where JSON was expected: say so, not "not a dict"
        media = request.headers.get("content-type") or "none"
        detail = f"send the body as JSON with Content-Type: application/json (got {media})"
        problem = {"field": "header.content-type", "message": detail, "type": "media_type"}
        return JSONResponse({"detail": detail, "errors": [problem]}, status_code=415)
    problems = [describe_problem(dict(e)) for e in errors][:MAX_ERRORS]
    return JSONResponse(
        {"detail": problems_message("invalid request", problems), "errors": problems},
        status_code=422,
    )


async def _http_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    body: dict[str, Any] = {
        "detail": exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    }
    errors = getattr(exc, "errors", None)
    if errors:
        body["errors"] = errors
    if exc.status_code == 400 and exc.detail == _PARSE_FAILURE:
        body = {
            "detail": _UNPARSEABLE,
            "errors": [{"field": "body", "message": _UNPARSEABLE, "type": "json_invalid"}],
        }
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        headers["Allow"] = _allowed_methods(request)
        body["detail"] = f"method {request.method} not allowed here; use {headers['Allow']}"
    return JSONResponse(body, status_code=exc.status_code, headers=headers)


def _allowed_methods(request: Request) -> str:
    """Return every method of the routes at the request's path, for a 405's ``Allow``.

    Starlette lists only the first route's methods, but ``/jobs`` is two routes (``GET``
    and ``POST``); RFC 9110 asks for all of them.
    """
    methods: set[str] = set()
    for route in request.app.state.api_routes:
        match, _ = route.matches(request.scope)
        if match != Match.NONE:
            methods |= set(getattr(route, "methods", None) or ())
    return ", ".join(sorted(methods))


def create_app(settings: Settings | None = None, store: JobStore | None = None) -> FastAPI:
    """Build the application.

    Parameters
    ----------
    settings
        Service settings (default: :func:`get_settings`, from ``AUTOCAL_*``).
    store
        Job store (default: one on ``settings.resolved_database_url()``, disposed of at
        shutdown).

    Returns
    -------
    fastapi.FastAPI
        The application; ``app.state.settings`` and ``app.state.store`` hold the above.
    """
    settings = settings if settings is not None else get_settings()
    tokens = checked_tokens(settings)  # TokenConfigError: refuse to start
    owns_store = store is None
    store = store if store is not None else JobStore(settings.resolved_database_url())
    if not tokens:
        logger.warning("no API token is configured: write endpoints refuse every request")

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        yield
        if owns_store:
            store.engine.dispose()

    app = FastAPI(
        title="autocal job service",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        dependencies=[Depends(single_valued_query)],
        docs_url=None,  # /docs and /redoc: routers.docs, their files from fastapi-offline
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.store = store
    app.state.tokens = tokens
    app.state.auth_limiter = FailedAuthLimiter(settings.auth_failures, settings.auth_window_s)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_middleware(CatchAllMiddleware)
    # outermost: an oversized body is refused before it is read, before authentication
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_body_bytes)
    # ui: the monitoring web page (HTML, left out of the schema)
    modules = (jobs, job_results, uploads, nightly, health, monitoring, ui, docs)
    for module in modules:
        app.include_router(module.router)
    app.state.api_routes = [route for module in modules for route in module.router.routes]
    return app
