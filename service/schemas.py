"""Request and response bodies of the job service (one schema per direction).

Requests (``*Create``) forbid unknown fields, so a misspelt option is a 422 naming it
rather than a silently ignored setting. Responses carry JSON-safe values only: NaN and
infinities from the solutions become ``null`` (:func:`json_safe`).
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import HTTPException
from pydantic import BaseModel, ConfigDict, Field, StringConstraints, field_validator

PathText = Annotated[str, StringConstraints(min_length=1, max_length=4096)]

#: The job kinds the API accepts (``diagnose`` arrives with the diagnosis workflow).
JobKind = Literal["calibrate"]
JobStateName = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class ApiError(HTTPException):
    """An HTTP error with a message for the client (and optionally per-field errors).

    Parameters
    ----------
    status_code
        HTTP status.
    detail
        What is wrong and what to do.
    errors
        Per-field problems (``field``, ``message``, ``type``).
    headers
        Extra response headers.
    """

    def __init__(
        self,
        status_code: int,
        detail: str,
        *,
        errors: list[dict[str, Any]] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(status_code=status_code, detail=detail, headers=headers)
        self.errors = errors


def json_safe(value: Any) -> Any:
    """Return ``value`` with non-finite floats replaced by ``None`` (recursively).

    Parameters
    ----------
    value
        Dicts, lists, tuples, scalars (numpy scalars included).

    Returns
    -------
    object
        The same structure, JSON-encodable without NaN or infinities.
    """
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "item") and callable(value.item) and not isinstance(value, (str, bytes)):
        try:
            value = value.item()
        except (TypeError, ValueError):
            return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# errors ---------------------------------------------------------------------------------


class FieldProblem(BaseModel):
    """One invalid field of a request."""

    field: str = Field(..., description="where: body.<field>, query.<name>, path.<name>")
    message: str
    type: str


class ErrorBody(BaseModel):
    """Every 4xx/5xx answer: a message saying what is wrong and what to do."""

    detail: str
    errors: list[FieldProblem] | None = None


# requests -------------------------------------------------------------------------------


class CalibrationOptions(BaseModel):
    """Calibration settings; omitted ones take the :class:`CalibrationConfig` defaults."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    sky: Annotated[str, StringConstraints(min_length=1, max_length=200)] | None = Field(
        None, description="sky model: gsm2008, gsm2016, lfsm, haslam, uniform:T0, powerlaw:..."
    )
    beam: PathText | None = Field(
        None,
        description="dipole, airy, hera, edges-low, edges-low-45deg, edges-mid, edges-high, "
        "or a beam file under the data roots",
    )
    model: Literal["constant", "legendre"] | None = None
    order: int | None = Field(None, ge=0, le=10, description="Legendre order")
    weights: Literal["radiometer", "identity"] | None = None
    antennas: list[Annotated[int, Field(ge=0, le=1_000_000)]] | None = Field(
        None, max_length=10_000
    )
    pols: list[Literal["ee", "nn", "xx", "yy"]] | None = Field(None, max_length=4)
    freq_range_mhz: tuple[float, float] | None = Field(None, description="(low, high) MHz")
    lst_range_h: tuple[float, float] | None = Field(None, description="(start, stop) hours")
    products: list[Literal["calh5", "calfits", "hdf5", "png"]] | None = Field(
        None, max_length=4, description="the HDF5 product is always written (results need it)"
    )
    reference: list[PathText] | None = Field(
        None, max_length=1000, description="reference gains (calfits/calh5) to compare with"
    )
    tgnd_k: float | None = Field(None, ge=0.0, le=10_000.0, description="ground temperature K")
    nside: int | None = Field(None, ge=2, le=1024, description="HEALPix nside, power of two")
    input_format: Literal["auto", "uvh5", "miriad", "edges"] | None = None
    inflate_errors: bool | None = None

    @field_validator("nside")
    @classmethod
    def _power_of_two(cls, value: int | None) -> int | None:
        if value is not None and value & (value - 1):
            raise ValueError(f"nside must be a power of two (got {value})")
        return value

    def options(self) -> dict[str, Any]:
        """Return the calibration options that were given (``None`` = default)."""
        names = set(CalibrationOptions.model_fields)
        return {k: v for k, v in self.model_dump().items() if k in names and v is not None}


class JobCreate(CalibrationOptions):
    """``POST /jobs``: calibrate one observation."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "inputs": [
                        "hera/autos/zen.2458116.30448.HH.uvh5",
                        "hera/autos/zen.2458116.31193.HH.uvh5",
                    ],
                    "beam": "hera",
                    "antennas": [23],
                    "freq_range_mhz": [110, 190],
                }
            ]
        }
    )

    kind: JobKind = "calibrate"
    inputs: list[PathText] = Field(
        ...,
        min_length=1,
        max_length=10_000,
        description="UVH5 files / Miriad folders under the data roots, or upload ids",
    )
    force: bool = Field(False, description="submit even if an identical job exists")


class NightlyCreate(CalibrationOptions):
    """``POST /nightly``: one job per observation of a night or a folder."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"night": 2458116, "beam": "hera", "antennas": [23]}]}
    )

    night: int | None = Field(
        None, ge=2_000_000, le=3_000_000, description="integer Julian date of the night"
    )
    folder: PathText | None = Field(None, description="folder under the data roots to scan")
    force: bool = Field(False, description="resubmit observations that already have a job")


# responses ------------------------------------------------------------------------------


class JobLinks(BaseModel):
    """Where to find a job's resources."""

    self: str
    cancel: str
    results: str
    products: str


class JobAccepted(BaseModel):
    """Answer to ``POST /jobs``."""

    id: str
    state: JobStateName
    created: bool = Field(..., description="false when an identical job already existed")
    links: JobLinks


class JobTimings(BaseModel):
    """When a job was created, started and finished (UTC)."""

    created: datetime | None
    started: datetime | None
    finished: datetime | None
    heartbeat: datetime | None
    duration_s: float | None


class JobSummary(BaseModel):
    """A job in a listing."""

    id: str
    kind: str
    state: JobStateName
    progress: float
    message: str
    night: int | None
    antennas: list[int] | None
    attempts: int
    timings: JobTimings
    links: JobLinks


class JobDetail(JobSummary):
    """Everything about one job."""

    max_attempts: int
    worker: str | None
    cancel_requested: bool
    error: str | None
    log_tail: list[str]
    config: dict[str, Any]
    provenance: dict[str, Any] | None
    result: dict[str, Any] | None
    products: dict[str, str] = Field(..., description="product name -> download URL")


class JobList(BaseModel):
    """``GET /jobs``."""

    items: list[JobSummary]
    count: int
    limit: int
    offset: int


class AntennaPolResult(BaseModel):
    """The solution of one antenna and polarisation (per channel; null where undefined)."""

    antenna: int
    pol: str
    G: list[float | None]
    sigma_G: list[float | None]  # noqa: N815 - the physics symbol
    abs_g: list[float | None]
    sigma_abs_g: list[float | None]
    Trxr: list[float | None]
    sigma_Trxr: list[float | None]  # noqa: N815 - the physics symbol
    reduced_chi2: list[float | None]
    flags: list[bool]


class JobResults(BaseModel):
    """``GET /jobs/{id}/results``."""

    job_id: str
    freqs_mhz: list[float]
    antennas: list[int]
    pols: list[str]
    model: dict[str, Any]
    units: dict[str, str]
    solutions: list[AntennaPolResult]
    summary: dict[str, Any] | None
    comparison: dict[str, Any] | None


class UploadCreated(BaseModel):
    """``POST /uploads``."""

    upload_id: str = Field(..., description="use as an input: the id or upload:<id>")
    path: str
    filename: str
    bytes: int
    sha256: str


class NightlyObservation(BaseModel):
    """One observation of a nightly submission."""

    night: int
    kind: str
    files: list[str]
    job_id: str
    state: str
    created: bool


class NightlyAccepted(BaseModel):
    """``POST /nightly``."""

    night: int | None
    observations: list[NightlyObservation]
    created: int
    existing: int


class Health(BaseModel):
    """``GET /health``."""

    status: Literal["ok", "degraded"]
    version: str
    database: Literal["ok", "error"]
    queued: int | None
    running: int | None
