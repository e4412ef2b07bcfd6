"""``POST /nightly``: one calibration job per observation of a night or a folder."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends
from pydantic import ValidationError

from autocal.pipeline.config import PipelineError
from autocal.service.auth import app_settings, require_token
from autocal.service.nightly import NightlyError, submit_nightly
from autocal.service.paths import InputPathError
from autocal.service.routers import app_store, as_api_error
from autocal.service.schemas import ErrorBody, NightlyAccepted, NightlyCreate
from autocal.service.settings import Settings
from autocal.service.store import JobStore
from autocal.service.submission_checks import SubmissionError
from autocal.sky.models import SkyModelError

router = APIRouter(tags=["nightly"])


@router.post(
    "/nightly",
    status_code=202,
    response_model=NightlyAccepted,
    responses={
        code: {"model": ErrorBody, "description": text}
        for code, text in {
            400: "a malformed path",
            401: "missing or wrong API token",
            429: "too many failed authentications; see Retry-After",
            403: "folder or option path outside the allowed folders",
            404: "no zen.<JD>.*uvh5* files found",
            422: "neither night nor folder, or invalid options; each bad field is named",
            503: "writes disabled: no API token configured",
        }.items()
    },
)
def create_nightly(
    body: NightlyCreate,
    store: Annotated[JobStore, Depends(app_store)],
    settings: Annotated[Settings, Depends(app_settings)],
    caller: Annotated[str, Depends(require_token)],
) -> NightlyAccepted:
    """Find the night's UVH5 files, group them into observations, submit one job each.

    Files ``zen.<JD>.<fraction>.*uvh5*`` of the same folder, JD and name suffix whose start
    times follow each other (no gap above 2.5 typical spacings) form one observation.
    Observations that already have a queued, running or succeeded job with the same
    settings are not resubmitted unless ``force``.
    """
    try:
        report = submit_nightly(
            store,
            settings,
            night=body.night,
            folder=body.folder,
            force=body.force,
            options=body.options(),
            submitted_by=caller,
        )
    except (
        ValidationError,
        InputPathError,
        NightlyError,
        SkyModelError,
        PipelineError,
        SubmissionError,
    ) as err:
        raise as_api_error(err) from None
    return NightlyAccepted(**report)
