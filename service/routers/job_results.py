"""Results and product downloads of a job.

========================================  ==================================================
``GET /jobs/{id}/results``                calibrate: G, ``|g|``, Trxr... per antenna and pol;
                                          diagnose: accepted effects, steps, gaps
``GET /jobs/{id}/products``               the product files: name, size, media type, URL
``GET /jobs/{id}/products/{name}``        download one product file
========================================  ==================================================

Both answer 409 for a job that has not succeeded (as ``/results`` does): a queued,
running, failed or cancelled job has no products to serve.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query
from fastapi import Path as PathParam
from fastapi.responses import FileResponse

from autocal.fit.separation import separation_summary
from autocal.service.paths import job_products_dir
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
    AntennaPolResult,
    ApiError,
    DiagnosisResults,
    DiagnosisStep,
    ErrorBody,
    JobResults,
    ProductEntry,
    ProductList,
    json_safe,
)
from autocal.service.settings import Settings

logger = logging.getLogger(__name__)

router = APIRouter(prefix="/jobs", tags=["jobs"])

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


def _succeeded(job: dict[str, Any], what: str) -> None:
    """Refuse (409) a job that has not succeeded: it has no ``what`` to serve."""
    if job["state"] != "succeeded":
        raise ApiError(
            409, f"job {job['id']} is {job['state']}; {what} exist only once it has succeeded"
        )


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


def _anonymised(
    results: JobResults | DiagnosisResults, reader: str | None, settings: Settings
) -> JobResults | DiagnosisResults:
    """Return ``results`` with server paths made relative for an anonymous reader."""
    redactor = redactor_for(reader, settings)
    if redactor is None:
        return results
    return type(results).model_validate(redactor.value(results.model_dump(mode="json")))


def _values(arr: np.ndarray) -> list[float | None]:
    values = np.asarray(arr, dtype=np.float64)
    return [float(v) if np.isfinite(v) else None for v in values]


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
            absorbed=list(doc.get("absorbed") or []),
            below_model_accuracy=list(doc.get("below_model_accuracy") or []),
            indistinguishable=doc.get("indistinguishable"),
            not_tested=dict(doc.get("not_tested") or {}),
            rfi_flagging=doc.get("rfi_flagging"),
            summary=json_safe(job.get("result")),
        )
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        # ValueError covers malformed JSON and pydantic's ValidationError
        logger.exception("job %s: unreadable diagnosis product %s", job["id"], path)
        raise ApiError(
            500, "the job's diagnosis product is unreadable; see the server log"
        ) from None


@router.get(
    "/{job_id}/results",
    response_model=JobResults | DiagnosisResults,
    responses={
        **api_errors(401, 404, 409, 429),
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
    reader: ReaderDep,
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

    job = job_or_404(store, job_id)
    _succeeded(job, "results")
    if job["kind"] == "diagnose":
        if antenna is not None or pol is not None:
            raise ApiError(
                422,
                "the antenna and pol filters apply to calibrate jobs; a diagnosis covers the "
                "whole selection (per-feed values are in each step's details)",
            )
        return _anonymised(_diagnosis_results(settings, job), reader, settings)
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
    results = JobResults(
        job_id=job_id,
        freqs_mhz=[float(f) / 1e6 for f in sol.freqs],
        antennas=antennas,
        pols=pols,
        model=json_safe(sol.model.describe()),
        units=UNITS,
        solutions=solutions,
        summary=json_safe(result.get("solution")),
        comparison=json_safe(result.get("comparison")),
        quality=json_safe(result.get("quality")),
        rfi_flagging=json_safe(result.get("rfi_flagging")),
    )
    return _anonymised(results, reader, settings)


@router.get(
    "/{job_id}/products",
    response_model=ProductList,
    responses=api_errors(401, 404, 409, 422, 429),
)
def job_products(
    job_id: JobId, store: StoreDep, settings: SettingsDep, _reader: ReaderDep
) -> ProductList:
    """List a succeeded job's product files, each with its download URL.

    The names are those ``GET /jobs/{id}/products/{name}`` takes; a product no longer on
    disk (removed by the janitor) is left out.
    """
    job = job_or_404(store, job_id)
    _succeeded(job, "products")
    entries = []
    for name in sorted(job.get("products") or {}):
        try:
            path = _product_path(settings, job, name)
            size = path.stat().st_size
        except (ApiError, OSError):  # gone (the janitor), or going while listed
            continue
        entries.append(
            ProductEntry(
                name=name,
                file=path.name,
                media_type=MEDIA_TYPES.get(path.suffix.lower(), "application/octet-stream"),
                size_bytes=size,
                url=f"/jobs/{job['id']}/products/{name}",
            )
        )
    return ProductList(job_id=job["id"], products=entries)


@router.get(
    "/{job_id}/products/{name}",
    response_class=FileResponse,
    responses={
        200: {"content": {"application/octet-stream": {}}, "description": "the product file"},
        **api_errors(401, 404, 409, 422, 429),
    },
)
def job_product(
    job_id: JobId,
    name: Annotated[str, PathParam(min_length=1, max_length=64)],
    store: StoreDep,
    settings: SettingsDep,
    _reader: ReaderDep,
) -> FileResponse:
    """Download a product by name (``GET /jobs/{id}/products`` lists them).

    ``calibrate``: calh5, calfits, hdf5, png, residuals_png, summary, compare_json...
    ``diagnose``: diagnosis (diagnosis.json), summary_txt (summary.txt), summary
    (summary.json), residuals_step1_png... (before/after each accepted step) or
    residuals_png (nothing accepted).
    """
    job = job_or_404(store, job_id)
    _succeeded(job, "products")
    path = _product_path(settings, job, name)
    media = MEDIA_TYPES.get(path.suffix.lower(), "application/octet-stream")
    return FileResponse(path, media_type=media, filename=path.name)
