"""Jobs: submit, list, inspect, cancel, results and product downloads.

========================================  ==================================================
``POST /jobs``                            queue a calibration (token; 202, idempotent)
``GET /jobs``                             list, filtered by state, night, antenna, kind
``GET /jobs/{id}``                        state, progress, timings, log tail, config...
``POST /jobs/{id}/cancel``                cancel (token; 202; 409 when already final)
``GET /jobs/{id}/results``                G, |g|, Trxr... per antenna and pol (succeeded)
``GET /jobs/{id}/products/{name}``        download one product file
========================================  ==================================================
"""

from __future__ import annotations

import logging
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Query, Response
from fastapi import Path as PathParam
from fastapi.responses import FileResponse
from pydantic import ValidationError

from autocal.pipeline import PipelineError
from autocal.service.auth import app_settings, require_token
from autocal.service.nightly import NightlyError, submit_calibration
from autocal.service.paths import InputPathError, job_products_dir
from autocal.service.routers import app_store, as_api_error
from autocal.service.schemas import (
    AntennaPolResult,
    ApiError,
    ErrorBody,
    JobAccepted,
    JobCreate,
    JobDetail,
    JobLinks,
    JobList,
    JobResults,
    JobStateName,
    JobSummary,
    JobTimings,
    json_safe,
)
from autocal.service.settings import Settings
from autocal.service.store import FINAL_STATES, JobStore, StoreError
from autocal.sky import SkyModelError

logger = logging.getLogger(__name__)

router = APIRouter(prefix="/jobs", tags=["jobs"])

JobId = Annotated[str, PathParam(min_length=1, max_length=64, description="the job id")]
StoreDep = Annotated[JobStore, Depends(app_store)]
SettingsDep = Annotated[Settings, Depends(app_settings)]

_ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorBody, "description": "malformed input path"},
    401: {"model": ErrorBody, "description": "missing or wrong API token"},
    403: {"model": ErrorBody, "description": "path outside the allowed folders"},
    404: {"model": ErrorBody, "description": "unknown job"},
    409: {"model": ErrorBody, "description": "the job is not in a state that allows this"},
    422: {"model": ErrorBody, "description": "invalid request; each bad field is named"},
    503: {"model": ErrorBody, "description": "writes disabled: no API token configured"},
}
#: Media types of product files by suffix.
MEDIA_TYPES = {
    ".png": "image/png",
    ".json": "application/json",
    ".h5": "application/x-hdf5",
    ".calh5": "application/x-hdf5",
    ".calfits": "application/fits",
    ".fits": "application/fits",
}
UNITS = {
    "freqs_mhz": "MHz",
    "G": "raw/K",
    "sigma_G": "raw/K",
    "abs_g": "sqrt(raw/K)",
    "sigma_abs_g": "sqrt(raw/K)",
    "Trxr": "K",
    "sigma_Trxr": "K",
    "reduced_chi2": "",
}


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: _ERRORS[code] for code in codes}


# record -> response ---------------------------------------------------------------------


def _links(job_id: str) -> JobLinks:
    base = f"/jobs/{job_id}"
    return JobLinks(
        self=base, cancel=f"{base}/cancel", results=f"{base}/results", products=f"{base}/products"
    )


def _timings(job: dict[str, Any]) -> JobTimings:
    started, finished = job.get("started_at"), job.get("finished_at")
    duration = None
    if started and finished:
        duration = (
            datetime.fromisoformat(finished) - datetime.fromisoformat(started)
        ).total_seconds()
    return JobTimings(
        created=job.get("created_at"),
        started=started,
        finished=finished,
        heartbeat=job.get("heartbeat_at"),
        duration_s=duration,
    )


def _summary_fields(job: dict[str, Any]) -> dict[str, Any]:
    return {
        "id": job["id"],
        "kind": job["kind"],
        "state": job["state"],
        "progress": float(job.get("progress") or 0.0),
        "message": job.get("message") or "",
        "night": job.get("night"),
        "antennas": job.get("antennas"),
        "attempts": int(job.get("attempts") or 0),
        "timings": _timings(job),
        "links": _links(job["id"]),
    }


def job_summary(job: dict[str, Any]) -> JobSummary:
    """Return the listing view of a job record."""
    return JobSummary(**_summary_fields(job))


def job_detail(job: dict[str, Any], log_lines: int = 50) -> JobDetail:
    """Return the full view of a job record (log tail of ``log_lines`` lines)."""
    log = (job.get("log") or "").splitlines()
    products = job.get("products") or {}
    return JobDetail(
        **_summary_fields(job),
        max_attempts=int(job.get("max_attempts") or 0),
        worker=job.get("worker"),
        cancel_requested=bool(job.get("cancel_requested")),
        error=job.get("error"),
        log_tail=log[-log_lines:] if log_lines else [],
        config=json_safe(job.get("config") or {}),
        provenance=json_safe(job.get("provenance")),
        result=json_safe(job.get("result")),
        products={name: f"/jobs/{job['id']}/products/{name}" for name in sorted(products)},
    )


def _job_or_404(store: JobStore, job_id: str) -> dict[str, Any]:
    job = store.get(job_id)
    if job is None:
        raise ApiError(404, f"no job {job_id!r}: list jobs with GET /jobs")
    return job


def _product_path(settings: Settings, job: dict[str, Any], name: str) -> Path:
    """Return a product file of a job, refusing anything outside the job's folder."""
    products = job.get("products") or {}
    if name not in products:
        available = ", ".join(sorted(products)) or "none"
        raise ApiError(404, f"job {job['id']} has no product {name!r} (available: {available})")
    folder = job_products_dir(settings, job["id"])
    try:
        path = Path(products[name]).resolve(strict=True)
    except (OSError, RuntimeError):
        raise ApiError(404, f"product {name!r} of job {job['id']} is no longer on disk") from None
    if not path.is_relative_to(folder) or not path.is_file():
        logger.warning("job %s: product %s at %s is outside %s", job["id"], name, path, folder)
        raise ApiError(404, f"product {name!r} of job {job['id']} is not available")
    return path


def _values(arr: np.ndarray) -> list[float | None]:
    values = np.asarray(arr, dtype=np.float64)
    return [float(v) if np.isfinite(v) else None for v in values]


# endpoints ------------------------------------------------------------------------------


@router.post(
    "",
    status_code=202,
    response_model=JobAccepted,
    dependencies=[Depends(require_token)],
    responses=_errors(400, 401, 403, 422, 503),
)
def create_job(
    body: JobCreate, response: Response, store: StoreDep, settings: SettingsDep
) -> JobAccepted:
    """Queue a calibration of one observation.

    Inputs are paths under the data roots (absolute, or relative to a data root) or upload
    ids. An identical job (same kind, inputs and settings) that is queued, running or
    succeeded is returned instead of a new one (``created: false``) unless ``force``.
    """
    try:
        job, created = submit_calibration(
            store, settings, body.inputs, body.options(), kind=body.kind, force=body.force
        )
    except (ValidationError, InputPathError, NightlyError, SkyModelError, PipelineError) as err:
        raise as_api_error(err) from None
    response.headers["Location"] = f"/jobs/{job['id']}"
    return JobAccepted(id=job["id"], state=job["state"], created=created, links=_links(job["id"]))


@router.get("", response_model=JobList, responses=_errors(422))
def list_jobs(
    store: StoreDep,
    state: Annotated[JobStateName | None, Query(description="only jobs in this state")] = None,
    night: Annotated[int | None, Query(ge=0, le=10**8, description="integer JD")] = None,
    antenna: Annotated[int | None, Query(ge=0, le=10**6)] = None,
    kind: Annotated[str | None, Query(max_length=32)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=10**7)] = 0,
) -> JobList:
    """List jobs, newest first."""
    jobs = store.list(
        state=state, night=night, antenna=antenna, kind=kind, limit=limit, offset=offset
    )
    return JobList(
        items=[job_summary(j) for j in jobs], count=len(jobs), limit=limit, offset=offset
    )


@router.get("/{job_id}", response_model=JobDetail, responses=_errors(404, 422))
def get_job(
    job_id: JobId,
    store: StoreDep,
    log_lines: Annotated[int, Query(ge=0, le=200, description="log lines returned")] = 50,
) -> JobDetail:
    """Return a job: state, progress, timings, attempts, error, log tail, config, provenance."""
    return job_detail(_job_or_404(store, job_id), log_lines)


@router.post(
    "/{job_id}/cancel",
    status_code=202,
    response_model=JobDetail,
    dependencies=[Depends(require_token)],
    responses=_errors(401, 404, 409, 503),
)
def cancel_job(job_id: JobId, store: StoreDep) -> JobDetail:
    """Cancel a queued job at once, or ask the worker of a running job to stop."""
    job = _job_or_404(store, job_id)
    if job["state"] in FINAL_STATES:
        raise ApiError(409, f"job {job_id} is already {job['state']}; nothing to cancel")
    try:
        job = store.request_cancel(job_id)
    except StoreError as err:
        raise ApiError(409, str(err)) from None
    return job_detail(job)


@router.get("/{job_id}/results", response_model=JobResults, responses=_errors(404, 409, 422))
def job_results(
    job_id: JobId,
    store: StoreDep,
    settings: SettingsDep,
    antenna: Annotated[int | None, Query(ge=0, le=10**6, description="only this antenna")] = None,
    pol: Annotated[str | None, Query(max_length=4, description="only this polarisation")] = None,
) -> JobResults:
    """Return the solution per antenna and polarisation (NaN as null) and the comparison."""
    from autocal.io.products import ProductFormatError, read_solution

    job = _job_or_404(store, job_id)
    if job["state"] != "succeeded":
        raise ApiError(
            409, f"job {job_id} is {job['state']}; results exist only once it has succeeded"
        )
    path = _product_path(settings, job, "hdf5")
    try:
        sol = read_solution(path)
    except ProductFormatError:
        logger.exception("job %s: unreadable solution product %s", job_id, path)
        raise ApiError(
            500, "the job's solution product is unreadable; see the server log"
        ) from None
    antennas = [int(a) for a in sol.antennas]
    pols = [str(p) for p in sol.pols]
    if antenna is not None and antenna not in antennas:
        raise ApiError(404, f"antenna {antenna} is not in the solution (antennas: {antennas})")
    if pol is not None and pol.lower() not in pols:
        raise ApiError(404, f"polarisation {pol!r} is not in the solution (pols: {pols})")
    arrays = {
        "G": sol.G,
        "sigma_G": sol.sigma_G,
        "abs_g": sol.abs_g,
        "sigma_abs_g": sol.sigma_abs_g,
        "Trxr": sol.Trxr,
        "sigma_Trxr": sol.sigma_Trxr,
        "reduced_chi2": sol.reduced_chi2,
    }
    flags = sol.flags
    solutions = [
        AntennaPolResult(
            antenna=ant,
            pol=p,
            flags=[bool(f) for f in flags[ia, ip]],
            **{name: _values(arr[ia, ip]) for name, arr in arrays.items()},
        )
        for ia, ant in enumerate(antennas)
        if antenna is None or ant == antenna
        for ip, p in enumerate(pols)
        if pol is None or p == pol.lower()
    ]
    result = job.get("result") or {}
    return JobResults(
        job_id=job_id,
        freqs_mhz=[float(f) / 1e6 for f in sol.freqs],
        antennas=antennas,
        pols=pols,
        model=json_safe(sol.model.describe()),
        units=UNITS,
        solutions=solutions,
        summary=json_safe(result.get("solution")),
        comparison=json_safe(result.get("comparison")),
    )


@router.get(
    "/{job_id}/products/{name}",
    response_class=FileResponse,
    responses={
        200: {"content": {"application/octet-stream": {}}, "description": "the product file"},
        **_errors(404, 422),
    },
)
def job_product(
    job_id: JobId,
    name: Annotated[str, PathParam(min_length=1, max_length=64)],
    store: StoreDep,
    settings: SettingsDep,
) -> FileResponse:
    """Download a product by name: calh5, calfits, hdf5, png, residuals_png, summary..."""
    path = _product_path(settings, _job_or_404(store, job_id), name)
    media = MEDIA_TYPES.get(path.suffix.lower(), "application/octet-stream")
    return FileResponse(path, media_type=media, filename=path.name)
