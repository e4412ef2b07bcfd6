"""Monitoring across nights: antennas' latest state and history, nights, outliers.

========================================  ==================================================
``GET /antennas``                         each antenna-pol's values on its latest night,
                                          with the reasons it is an outlier then
``GET /antennas/{antenna}/history``       its values night by night (``pol``, ``from``,
                                          ``to``), with sigmas and per-band values
``GET /nights``                           every night: antennas, observations, jobs
``GET /nights/{night}``                   a night: antennas, outliers, failed jobs
========================================  ==================================================

Reads need no token. An unknown antenna or night is a 404 listing the ones that exist. As
for ``GET /jobs/{id}``, an anonymous reader gets a night's failed jobs with their inputs
relative to the data roots and no server path in their errors.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query
from fastapi import Path as PathParam

from autocal.service.auth import read_access
from autocal.service.monitoring import (
    MonitoringError,
    antenna_history,
    latest_state,
    night_detail,
    nights_overview,
)
from autocal.service.monitoring_schemas import (
    AntennaHistory,
    AntennaList,
    NightDetail,
    NightList,
)
from autocal.service.routers import app_store
from autocal.service.routers.job_common import ReaderDep, SettingsDep, redactor_for
from autocal.service.schemas import ApiError, ErrorBody, json_safe
from autocal.service.store import JobStore

# reads follow AUTOCAL_READ_AUTH like the job reads (autocal.service.auth.read_access)
router = APIRouter(tags=["monitoring"], dependencies=[Depends(read_access)])

StoreDep = Annotated[JobStore, Depends(app_store)]
Night = Annotated[int, Query(ge=0, le=10**8, description="integer JD")]
_ERRORS: dict[int | str, dict[str, Any]] = {
    404: {
        "model": ErrorBody,
        "description": "unknown antenna, pol or night (the message lists them)",
    },
    422: {"model": ErrorBody, "description": "invalid request; each bad field is named"},
}


def _not_found(err: MonitoringError) -> ApiError:
    return ApiError(404, str(err))


@router.get("/antennas", response_model=AntennaList, responses={422: _ERRORS[422]})
def list_antennas(store: StoreDep) -> AntennaList:
    """Each antenna-pol's values on the latest night it was calibrated, with its outliers."""
    items = json_safe(latest_state(store))
    return AntennaList(items=items, count=len(items))


@router.get("/antennas/{antenna}/history", response_model=AntennaHistory, responses=_ERRORS)
def get_antenna_history(
    store: StoreDep,
    antenna: Annotated[int, PathParam(ge=0, le=10**6, description="antenna number")],
    pol: Annotated[
        str | None, Query(min_length=1, max_length=4, description="only this pol")
    ] = None,
    night_from: Annotated[
        int | None, Query(alias="from", ge=0, le=10**8, description="first night (JD)")
    ] = None,
    night_to: Annotated[
        int | None, Query(alias="to", ge=0, le=10**8, description="last night (JD)")
    ] = None,
) -> AntennaHistory:
    """Return an antenna's values night by night: G, ``|g|``, Trxr with sigmas, chi2/dof, bands."""
    if night_from is not None and night_to is not None and night_from > night_to:
        raise ApiError(
            422,
            f"from ({night_from}) is after to ({night_to})",
            errors=[{"field": "query.from", "message": "after 'to'", "type": "value_error"}],
        )
    try:
        items = antenna_history(
            store, antenna, pol=pol.lower() if pol else None, nights=(night_from, night_to)
        )
    except MonitoringError as err:
        raise _not_found(err) from None
    return AntennaHistory(
        antenna=antenna,
        pol=pol,
        night_from=night_from,
        night_to=night_to,
        items=json_safe(items),
        count=len(items),
    )


@router.get("/nights", response_model=NightList, responses={422: _ERRORS[422]})
def list_nights(store: StoreDep) -> NightList:
    """Every night with a job or recorded values, newest first."""
    items = nights_overview(store)
    return NightList(items=items, count=len(items))


@router.get("/nights/{night}", response_model=NightDetail, responses=_ERRORS)
def get_night(
    store: StoreDep,
    settings: SettingsDep,
    reader: ReaderDep,
    night: Annotated[int, PathParam(ge=0, le=10**8, description="integer JD of the night")],
) -> NightDetail:
    """Return a night: antennas calibrated, outliers and failed jobs, with reasons.

    An anonymous reader gets the failed jobs' inputs relative to the data roots and their
    errors without server paths; send a token to see them whole.
    """
    try:
        detail = night_detail(store, night)
    except MonitoringError as err:
        raise _not_found(err) from None
    redactor = redactor_for(reader, settings)
    if redactor is not None:
        detail["failed_jobs"] = redactor.value(detail["failed_jobs"])
    return NightDetail(**json_safe(detail))
