"""Submission of diagnose jobs: options checked against the diagnosis configuration.

``POST /jobs`` with ``kind: "diagnose"`` lands here (:func:`submit_diagnosis`); the options
are validated and every path resolved under the allowed roots before the job is queued, and
errors are turned into 4xx answers naming the field (:func:`diagnose_api_error`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

from pydantic import ValidationError

from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.run import DiagnoseConfig
from autocal.pipeline.option_rules import diagnosis_refusals
from autocal.service.input_check import fingerprint_config
from autocal.service.nightly import checked_options, job_key, night_of
from autocal.service.paths import resolve_input
from autocal.service.routers import MAX_ERRORS, as_api_error, describe_problem, problems_message
from autocal.service.schemas import CALIBRATE_ONLY, ApiError
from autocal.service.settings import Settings
from autocal.service.store import JobStore
from autocal.service.submission_checks import (
    SubmissionError,
    check_distinct,
    check_sky_varies,
    check_uvh5_inputs,
)

logger = logging.getLogger(__name__)


def diagnose_api_error(err: Exception) -> ApiError:
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
    for field, why in diagnosis_refusals(dict(options or {})):
        raise SubmissionError(field, why)
    opts = checked_options(DiagnoseConfig, settings, inputs, options)
    resolved = [resolve_input(str(p), settings) for p in inputs]
    folders = [str(p) for p in resolved if p.is_dir()]
    if folders:
        raise DiagnoseError(
            f"diagnose reads UVH5 files, not folders ({', '.join(folders)}); "
            "convert Miriad data to UVH5 first"
        )
    check_distinct(resolved, "inputs")
    check_uvh5_inputs(resolved, opts)
    # the diagnosis fits G and Trxr too: a sky constant in time leaves them inseparable
    check_sky_varies(opts.get("sky"), opts.get("trxr_prior"))
    return DiagnoseConfig(inputs=[str(p) for p in resolved], **opts)


def submit_diagnosis(
    store: JobStore,
    settings: Settings,
    inputs: Sequence[str],
    options: Mapping[str, Any] | None = None,
    *,
    force: bool = False,
    submitted_by: str | None = None,
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
    submitted_by
        The name of the API token that asked for it.

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
        submitted_by=submitted_by,
        input_fingerprints=fingerprint_config(config.model_dump(mode="json"), settings),
    )
    logger.info(
        "%s diagnose job %s (%d input(s))",
        "queued" if created else "existing",
        job["id"],
        len(config.inputs),
    )
    return job, created
