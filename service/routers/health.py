"""``GET /health``: liveness, database and queue (no token needed)."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse

from autocal import __version__
from autocal.service.routers import app_store
from autocal.service.schemas import Health
from autocal.service.store import JobStore

logger = logging.getLogger(__name__)

router = APIRouter(tags=["health"])


@router.get(
    "/health",
    response_model=Health,
    responses={503: {"model": Health, "description": "the database does not answer"}},
)
def health(store: JobStore = Depends(app_store)) -> Health | JSONResponse:  # noqa: B008
    """Report the service version, whether the database answers and the queue length."""
    try:
        store.ping()
        queued, running = store.count("queued"), store.count("running")
    except Exception:
        logger.exception("health check: the job database does not answer")
        body = Health(
            status="degraded", version=__version__, database="error", queued=None, running=None
        )
        return JSONResponse(body.model_dump(), status_code=503)
    return Health(status="ok", version=__version__, database="ok", queued=queued, running=running)
