"""What the job routers share: the path parameter, dependencies and documented errors."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends
from fastapi import Path as PathParam

from autocal.service.auth import app_settings, read_access
from autocal.service.job_views import Redactor
from autocal.service.routers import app_store
from autocal.service.schemas import ApiError, ErrorBody
from autocal.service.settings import Settings
from autocal.service.store import JobStore

JobId = Annotated[str, PathParam(min_length=1, max_length=64, description="the job id")]
StoreDep = Annotated[JobStore, Depends(app_store)]
SettingsDep = Annotated[Settings, Depends(app_settings)]
#: The reader's token name, ``None`` when anonymous (401/429 on a wrong token).
ReaderDep = Annotated[str | None, Depends(read_access)]

ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorBody, "description": "malformed input path"},
    401: {"model": ErrorBody, "description": "missing or wrong API token"},
    429: {"model": ErrorBody, "description": "too many failed authentications; see Retry-After"},
    403: {"model": ErrorBody, "description": "path outside the allowed folders"},
    404: {"model": ErrorBody, "description": "unknown job"},
    409: {"model": ErrorBody, "description": "the job is not in a state that allows this"},
    422: {"model": ErrorBody, "description": "invalid request; each bad field is named"},
    503: {"model": ErrorBody, "description": "writes disabled: no API token configured"},
}


def api_errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """Return the OpenAPI ``responses`` entries of the given error codes."""
    return {code: ERRORS[code] for code in codes}


def job_or_404(store: JobStore, job_id: str) -> dict[str, Any]:
    """Return a job record or raise a 404 naming the job."""
    job = store.get(job_id)
    if job is None:
        raise ApiError(404, f"no job {job_id!r}: list jobs with GET /jobs")
    return job


def redactor_for(reader: str | None, settings: Settings) -> Redactor | None:
    """Return the redactor of an anonymous reader, ``None`` for a token holder."""
    return None if reader is not None else Redactor(settings)
