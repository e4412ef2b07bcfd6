"""Jobs: submit, list, inspect and cancel (results and products: :mod:`.job_results`).

========================================  ==================================================
``POST /jobs``                            queue a calibration or a diagnosis (token; 202,
                                          idempotent)
``GET /jobs``                             list, newest first, filtered by state, night,
                                          antenna, kind; pages follow ``next_cursor``
``GET /jobs/{id}``                        state, progress, timings, log tail, config...
``POST /jobs/{id}/cancel``                cancel (token; 202; 409 when already final)
========================================  ==================================================

Job kinds: ``calibrate`` (default; :func:`autocal.pipeline.calibrate.run_calibration`) and
``diagnose`` (:func:`autocal.diagnosis.run.run_diagnosis`). Both are validated before they
are queued (options against the kind's configuration, paths under the allowed roots) and
deduplicated on kind, resolved inputs and options.
"""

from __future__ import annotations

import logging
from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Query, Request, Response
from pydantic import ValidationError

from autocal.diagnosis.errors import DiagnoseError
from autocal.fit.priors import PriorError
from autocal.pipeline.config import PipelineError
from autocal.service.auth import require_token
from autocal.service.diagnose_jobs import diagnose_api_error, submit_diagnosis
from autocal.service.job_index import CursorError, decode_cursor, encode_cursor
from autocal.service.job_views import job_detail, job_links, job_summary
from autocal.service.nightly import NightlyError, submit_calibration
from autocal.service.paths import InputPathError
from autocal.service.routers import as_api_error, problems_message
from autocal.service.routers.job_common import (
    JobId,
    ReaderDep,
    SettingsDep,
    StoreDep,
    api_errors,
    job_or_404,
    redactor_for,
)
from autocal.service.schemas import (
    DIAGNOSE_ONLY,
    ApiError,
    JobAccepted,
    JobCreate,
    JobDetail,
    JobKind,
    JobList,
    JobStateName,
)
from autocal.service.store import FINAL_STATES, StoreError
from autocal.service.submission_checks import SubmissionError
from autocal.sky.models import SkyModelError

logger = logging.getLogger(__name__)

router = APIRouter(prefix="/jobs", tags=["jobs"])


def _misplaced_error(body: JobCreate) -> ApiError:
    """422 naming the options the body's kind does not accept."""
    problems = []
    for name in body.misplaced():
        owner = "diagnose" if name in DIAGNOSE_ONLY else "calibrate"
        problems.append(
            {
                "field": f"body.{name}",
                "message": f"{name!r} is an option of kind {owner!r}, not of kind "
                f"{body.kind!r}: remove it or set kind to {owner!r}",
                "type": "kind_mismatch",
            }
        )
    return ApiError(
        422, problems_message(f"invalid {body.kind} settings", problems), errors=problems
    )


#: OpenAPI links of a queued job (``POST /jobs`` -> the operations on its ``id``): Swagger UI
#: shows them and schemathesis follows them in its stateful tests.
_JOB_LINKS = {
    name: {
        "operationRef": f"#/paths/~1jobs~1{{job_id}}{suffix}",
        "parameters": {"job_id": "$response.body#/id"},
        "description": text,
    }
    for name, suffix, text in (
        ("GetJob", "/get", "the job's state, progress and products"),
        ("CancelJob", "~1cancel/post", "cancel the job"),
        ("JobResults", "~1results/get", "the job's results once it succeeded"),
    )
}


@router.post(
    "",
    status_code=202,
    response_model=JobAccepted,
    responses={202: {"links": _JOB_LINKS}, **api_errors(400, 401, 403, 422, 429, 503)},
)
def create_job(
    body: JobCreate,
    response: Response,
    store: StoreDep,
    settings: SettingsDep,
    caller: Annotated[str, Depends(require_token)],
) -> JobAccepted:
    """Queue a calibration (``kind: "calibrate"``, the default) or a diagnosis of one observation.

    Inputs are paths under the data roots (absolute, or relative to a data root) or upload
    ids; a diagnosis reads UVH5 files. Options are validated against the kind's
    configuration: an option of the other kind, an unknown field or a bad value is a 422
    naming the field; a path outside the data roots is a 403. An identical job (same kind,
    inputs and settings) that is queued, running or succeeded is returned instead of a
    new one (``created: false``) unless ``force``. The job records the name of the token
    that submitted it (``submitted_by``).

    A diagnosis fits the current model to the autos, measures the gap, tests the
    catalogue of candidate effects (gain_drift, noise_drift, sky_scale, sky_offset,
    sky_spectral_index, ground_temperature, beam_width, missing_cmb, cable_reflection),
    accepts the best by Delta BIC while significant and repeats; its results name the
    accepted effects with their parameters.
    """
    if body.misplaced():
        raise _misplaced_error(body)
    errors = (
        ValidationError,
        InputPathError,
        NightlyError,
        SkyModelError,
        PipelineError,
        DiagnoseError,
        PriorError,
        SubmissionError,
    )
    try:
        if body.kind == "diagnose":
            job, created = submit_diagnosis(
                store, settings, body.inputs, body.given(), force=body.force, submitted_by=caller
            )
        else:
            job, created = submit_calibration(
                store,
                settings,
                body.inputs,
                body.options(),
                kind=body.kind,
                force=body.force,
                submitted_by=caller,
            )
    except errors as err:
        raise (diagnose_api_error(err) if body.kind == "diagnose" else as_api_error(err)) from None
    response.headers["Location"] = f"/jobs/{job['id']}"
    return JobAccepted(
        id=job["id"], state=job["state"], created=created, links=job_links(job["id"])
    )


@router.get("", response_model=JobList, responses=api_errors(401, 422, 429))
def list_jobs(
    request: Request,
    store: StoreDep,
    settings: SettingsDep,
    reader: ReaderDep,
    state: Annotated[JobStateName | None, Query(description="only jobs in this state")] = None,
    night: Annotated[int | None, Query(ge=0, le=10**8, description="integer JD")] = None,
    antenna: Annotated[
        int | None,
        Query(ge=0, le=10**6, description="only jobs naming this antenna or every antenna"),
    ] = None,
    kind: Annotated[JobKind | None, Query(description="only jobs of this kind")] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="jobs per page")] = 100,
    cursor: Annotated[
        str | None,
        Query(max_length=200, description="the next_cursor of the previous page"),
    ] = None,
    offset: Annotated[
        int,
        Query(
            ge=0,
            le=10**7,
            deprecated=True,
            description="jobs to skip; its cost grows with it: follow next_cursor instead",
        ),
    ] = 0,
) -> JobList:
    """List jobs, newest first, one page at a time.

    A page costs the same whatever the number of jobs (keyset pagination on the creation
    time and id, filters on indexes). ``next_cursor`` (and the ready-made URL ``next``)
    gives the following page with the same filters; it is null on the last page.
    """
    if cursor is not None and offset:
        raise ApiError(
            422,
            "give either cursor or offset, not both (cursor is the one to use)",
            errors=[{"field": "query.offset", "message": "not with cursor", "type": "conflict"}],
        )
    try:
        after = decode_cursor(cursor) if cursor is not None else None
    except CursorError as err:
        raise ApiError(
            422, str(err), errors=[{"field": "query.cursor", "message": str(err), "type": "cursor"}]
        ) from None
    filters = {"state": state, "night": night, "antenna": antenna, "kind": kind}
    jobs, key = store.page(limit=limit, after=after, offset=offset, **filters)
    next_cursor = encode_cursor(*key) if key is not None else None
    next_url = None
    if next_cursor is not None:
        query = {k: v for k, v in filters.items() if v is not None}
        next_url = (
            f"{request.url.path}?{urlencode({**query, 'limit': limit, 'cursor': next_cursor})}"
        )
    redactor = redactor_for(reader, settings)
    return JobList(
        items=[job_summary(j, redactor) for j in jobs],
        count=len(jobs),
        limit=limit,
        offset=offset,
        next_cursor=next_cursor,
        next=next_url,
    )


@router.get("/{job_id}", response_model=JobDetail, responses=api_errors(401, 404, 422, 429))
def get_job(
    job_id: JobId,
    store: StoreDep,
    settings: SettingsDep,
    reader: ReaderDep,
    log_lines: Annotated[int, Query(ge=0, le=200, description="log lines returned")] = 50,
) -> JobDetail:
    """Return a job: state, progress, timings, attempts, error, log tail, config, provenance.

    An anonymous reader gets paths relative to the data roots, no worker and no log tail
    (``log_hidden: true``); send a token to see them.
    """
    return job_detail(job_or_404(store, job_id), log_lines, redactor_for(reader, settings))


@router.post(
    "/{job_id}/cancel",
    status_code=202,
    response_model=JobDetail,
    dependencies=[Depends(require_token)],
    responses=api_errors(401, 404, 409, 422, 429, 503),
)
def cancel_job(job_id: JobId, store: StoreDep) -> JobDetail:
    """Cancel a queued job at once, or ask the worker of a running job to stop."""
    job = job_or_404(store, job_id)
    if job["state"] in FINAL_STATES:
        raise ApiError(409, f"job {job_id} is already {job['state']}; nothing to cancel")
    try:
        job = store.request_cancel(job_id)
    except StoreError as err:
        raise ApiError(409, str(err)) from None
    return job_detail(job)
