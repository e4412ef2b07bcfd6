"""Jobs: submit, list, inspect, cancel, results and product downloads.

========================================  ==================================================
``POST /jobs``                            queue a calibration or a diagnosis (token; 202,
                                          idempotent)
``GET /jobs``                             list, filtered by state, night, antenna, kind
``GET /jobs/{id}``                        state, progress, timings, log tail, config...
``POST /jobs/{id}/cancel``                cancel (token; 202; 409 when already final)
``GET /jobs/{id}/results``                calibrate: G, ``|g|``, Trxr... per antenna and pol;
                                          diagnose: accepted effects, steps, gaps
``GET /jobs/{id}/products/{name}``        download one product file
========================================  ==================================================

Job kinds: ``calibrate`` (default; :func:`autocal.pipeline.calibrate.run_calibration`) and
``diagnose`` (:func:`autocal.diagnosis.run.run_diagnosis`). Both are validated before they
are queued (options against the kind's configuration, paths under the allowed roots) and
deduplicated on kind, resolved inputs and options.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Query, Response
from fastapi import Path as PathParam
from fastapi.responses import FileResponse
from pydantic import ValidationError

from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.run import DiagnoseConfig
from autocal.fit.priors import PriorError
from autocal.fit.separation import separation_summary
from autocal.pipeline.config import PipelineError
from autocal.service.auth import app_settings, require_token
from autocal.service.input_check import fingerprint_config
from autocal.service.nightly import (
    NightlyError,
    checked_options,
    job_key,
    night_of,
    submit_calibration,
)
from autocal.service.paths import InputPathError, job_products_dir, resolve_input
from autocal.service.routers import (
    MAX_ERRORS,
    app_store,
    as_api_error,
    describe_problem,
    problems_message,
)
from autocal.service.schemas import (
    CALIBRATE_ONLY,
    DIAGNOSE_ONLY,
    AntennaPolResult,
    ApiError,
    DiagnosisResults,
    DiagnosisStep,
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
from autocal.sky.models import SkyModelError

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
    ".txt": "text/plain; charset=utf-8",
}
UNITS = {
    "freqs_mhz": "MHz",
    "G": "raw/K",
    "sigma_G": "raw/K",
    "abs_g": "sqrt(raw/K)",
    "sigma_abs_g": "sqrt(raw/K)",
    "Trxr": "K",
    "sigma_Trxr": "K",
    "sigma_G_stat": "raw/K",
    "sigma_abs_g_stat": "sqrt(raw/K)",
    "sigma_Trxr_stat": "K",
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


# diagnose jobs --------------------------------------------------------------------------


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


def _diagnose_api_error(err: Exception) -> ApiError:
    """Translate a submission error of a diagnose job into an HTTP error."""
    if not isinstance(err, ValidationError):
        return as_api_error(err)
    problems = []
    for error in err.errors()[:MAX_ERRORS]:
        problem = describe_problem(error, ("body",))
        loc = error.get("loc") or ()
        if error.get("type") == "extra_forbidden" and loc and str(loc[-1]) in CALIBRATE_ONLY:
            problem["message"] = (
                f"{loc[-1]!r} is an option of kind 'calibrate', not of kind 'diagnose'"
            )
        if not loc:  # a model-level check: name the field it talks about
            named = [f for f in DiagnoseConfig.model_fields if f in problem["message"]]
            problem["field"] = f"body.{named[0]}" if named else "body"
        problems.append(problem)
    return ApiError(422, problems_message("invalid diagnose settings", problems), errors=problems)


def build_diagnose_config(
    settings: Settings, inputs: Sequence[str], options: Mapping[str, Any] | None = None
) -> DiagnoseConfig:
    """Validate diagnose options and resolve every path they name.

    Parameters
    ----------
    settings
        The service settings (allowed roots).
    inputs
        UVH5 files (absolute, relative to a data root) or upload ids.
    options
        Further :class:`DiagnoseConfig` fields (``sky``, ``beam``, ``trxr_prior``...).

    Returns
    -------
    DiagnoseConfig
        With resolved absolute inputs and beam file.

    Raises
    ------
    pydantic.ValidationError
        For invalid or unknown options.
    InputPathError
        For paths outside the allowed roots (403) or missing (400).
    autocal.diagnosis.errors.DiagnoseError
        For an input that is a folder rather than a UVH5 file.
    autocal.sky.models.SkyModelError
        For an unknown sky model.
    """
    opts = checked_options(DiagnoseConfig, settings, inputs, options)
    resolved = [resolve_input(str(p), settings) for p in inputs]
    folders = [str(p) for p in resolved if p.is_dir()]
    if folders:
        raise DiagnoseError(
            f"diagnose reads UVH5 files, not folders ({', '.join(folders)}); "
            "convert Miriad data to UVH5 first"
        )
    return DiagnoseConfig(inputs=[str(p) for p in resolved], **opts)


def submit_diagnosis(
    store: JobStore,
    settings: Settings,
    inputs: Sequence[str],
    options: Mapping[str, Any] | None = None,
    *,
    force: bool = False,
) -> tuple[dict[str, Any], bool]:
    """Queue a diagnosis of one observation, idempotently.

    The deduplication key is that of a calibration (:func:`job_key`): kind ``diagnose``,
    the sorted resolved inputs and the rest of the configuration.

    Parameters
    ----------
    store
        The job store.
    settings
        The service settings.
    inputs
        UVH5 files or upload ids.
    options
        Further :class:`DiagnoseConfig` fields.
    force
        Queue a new job even if an identical one is queued, running or succeeded.

    Returns
    -------
    (dict, bool)
        The job record and whether it was created (``False``: an identical job exists).
    """
    config = build_diagnose_config(settings, inputs, options)
    job, created = store.submit(
        config.model_dump(mode="json"),
        kind="diagnose",
        night=night_of(config.inputs),
        antennas=config.antennas,
        dedupe_key=job_key("diagnose", config),  # type: ignore[arg-type]  # any config model
        force=force,
        max_attempts=settings.max_attempts,
        input_fingerprints=fingerprint_config(config.model_dump(mode="json"), settings),
    )
    logger.info(
        "%s diagnose job %s (%d input(s))",
        "queued" if created else "existing",
        job["id"],
        len(config.inputs),
    )
    return job, created


def _diagnosis_results(settings: Settings, job: dict[str, Any]) -> DiagnosisResults:
    """Build the results of a succeeded diagnose job from its ``diagnosis.json``."""
    path = _product_path(settings, job, "diagnosis")
    try:
        doc = json_safe(json.loads(path.read_text()))  # NaN -> null
        steps = []
        for index, step in enumerate(doc.get("steps") or [], 1):
            known = {"name", "parameters", "statistic", "delta", "p_value"}
            known |= {"gap_before", "gap_after", "candidates"}
            steps.append(
                DiagnosisStep(
                    step=index,
                    name=step["name"],
                    parameters=step.get("parameters") or {},
                    statistic=step.get("statistic"),
                    delta=step.get("delta"),
                    p_value=step.get("p_value"),
                    gap_before=step.get("gap_before") or {},
                    gap_after=step.get("gap_after") or {},
                    candidates=step.get("candidates") or {},
                    details={k: v for k, v in step.items() if k not in known},
                )
            )
        return DiagnosisResults(
            job_id=job["id"],
            effects=list(doc.get("effects") or []),
            steps=steps,
            initial_gap=doc.get("initial_gap") or {},
            final_gap=doc.get("final_gap") or {},
            identifiability=doc.get("identifiability") or {},
            config=doc.get("config") or {},
            product_change=doc.get("product_change") or {},
            unexplained=doc.get("unexplained"),
            negligible=list(doc.get("negligible") or []),
            summary=json_safe(job.get("result")),
        )
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        # ValueError covers malformed JSON and pydantic's ValidationError
        logger.exception("job %s: unreadable diagnosis product %s", job["id"], path)
        raise ApiError(
            500, "the job's diagnosis product is unreadable; see the server log"
        ) from None


# endpoints ------------------------------------------------------------------------------


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
    dependencies=[Depends(require_token)],
    responses={202: {"links": _JOB_LINKS}, **_errors(400, 401, 403, 422, 503)},
)
def create_job(
    body: JobCreate, response: Response, store: StoreDep, settings: SettingsDep
) -> JobAccepted:
    """Queue a calibration (``kind: "calibrate"``, the default) or a diagnosis of one observation.

    Inputs are paths under the data roots (absolute, or relative to a data root) or upload
    ids; a diagnosis reads UVH5 files. Options are validated against the kind's
    configuration: an option of the other kind, an unknown field or a bad value is a 422
    naming the field; a path outside the data roots is a 403. An identical job (same kind,
    inputs and settings) that is queued, running or succeeded is returned instead of a
    new one (``created: false``) unless ``force``.

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
    )
    try:
        if body.kind == "diagnose":
            job, created = submit_diagnosis(
                store, settings, body.inputs, body.given(), force=body.force
            )
        else:
            job, created = submit_calibration(
                store, settings, body.inputs, body.options(), kind=body.kind, force=body.force
            )
    except errors as err:
        raise (_diagnose_api_error(err) if body.kind == "diagnose" else as_api_error(err)) from None
    response.headers["Location"] = f"/jobs/{job['id']}"
    return JobAccepted(id=job["id"], state=job["state"], created=created, links=_links(job["id"]))


@router.get("", response_model=JobList, responses=_errors(422))
def list_jobs(
    store: StoreDep,
    state: Annotated[JobStateName | None, Query(description="only jobs in this state")] = None,
    night: Annotated[int | None, Query(ge=0, le=10**8, description="integer JD")] = None,
    antenna: Annotated[int | None, Query(ge=0, le=10**6)] = None,
    kind: Annotated[
        str | None, Query(max_length=32, description="only jobs of this kind: calibrate, diagnose")
    ] = None,
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
    responses=_errors(401, 404, 409, 422, 503),
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


@router.get(
    "/{job_id}/results",
    response_model=JobResults | DiagnosisResults,
    responses={
        **_errors(404, 409),
        422: {
            "model": ErrorBody,
            "description": "a bad filter value, or an antenna/pol filter on a diagnose job "
            "(a diagnosis covers its whole selection)",
        },
    },
)
def job_results(
    job_id: JobId,
    store: StoreDep,
    settings: SettingsDep,
    antenna: Annotated[
        int | None, Query(ge=0, le=10**6, description="only this antenna (calibrate)")
    ] = None,
    pol: Annotated[
        str | None, Query(max_length=4, description="only this polarisation (calibrate)")
    ] = None,
) -> JobResults | DiagnosisResults:
    """Return the results of a succeeded job (NaN as null).

    ``calibrate``: the solution per antenna and polarisation and the comparison.
    ``diagnose``: the accepted ``effects`` in order and one entry per step: the effect
    ``name``, its ``parameters`` (``value``, ``sigma``), the ``statistic`` (Delta BIC) and
    ``delta`` (Delta chi^2), ``gap_before`` and ``gap_after`` (chi2/dof, rms normalised
    residual...); the initial and final gap and the identifiability of each effect.
    """
    # the API process imports the product reader (h5py, the fit records) on first use only
    from autocal.io.products import ProductFormatError, read_solution

    job = _job_or_404(store, job_id)
    if job["state"] != "succeeded":
        raise ApiError(
            409, f"job {job_id} is {job['state']}; results exist only once it has succeeded"
        )
    if job["kind"] == "diagnose":
        if antenna is not None or pol is not None:
            raise ApiError(
                422,
                "the antenna and pol filters apply to calibrate jobs; a diagnosis covers the "
                "whole selection (per-feed values are in each step's details)",
            )
        return _diagnosis_results(settings, job)
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
        "sigma_G_stat": sol.sigma_G_stat,
        "sigma_abs_g_stat": sol.sigma_abs_g_stat,
        "sigma_Trxr_stat": sol.sigma_Trxr_stat,
        "reduced_chi2": sol.reduced_chi2,
    }
    flags = sol.flags
    separation = {(e["antenna"], e["pol"]): e for e in separation_summary(sol)}
    solutions = [
        AntennaPolResult(
            antenna=ant,
            pol=p,
            flags=[bool(f) for f in flags[ia, ip]],
            separation=json_safe(separation.get((ant, p))),
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
    """Download a product by name (``GET /jobs/{id}`` lists a job's products).

    ``calibrate``: calh5, calfits, hdf5, png, residuals_png, summary, compare_json...
    ``diagnose``: diagnosis (diagnosis.json), summary_txt (summary.txt), summary
    (summary.json), residuals_step1_png... (before/after each accepted step) or
    residuals_png (nothing accepted).
    """
    path = _product_path(settings, _job_or_404(store, job_id), name)
    media = MEDIA_TYPES.get(path.suffix.lower(), "application/octet-stream")
    return FileResponse(path, media_type=media, filename=path.name)
