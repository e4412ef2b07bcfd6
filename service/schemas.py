"""Request and response bodies of the job service (one schema per direction).

Requests (``*Create``) forbid unknown fields, so a misspelt option is a 422 naming it
rather than a silently ignored setting. Responses carry JSON-safe values only: NaN and
infinities from the solutions become ``null`` (:func:`json_safe`).

Two job kinds share ``POST /jobs`` (:class:`JobCreate`): ``calibrate`` (the default;
options of :class:`~autocal.pipeline.config.CalibrationConfig`) and ``diagnose`` (options of
:class:`~autocal.diagnosis.run.DiagnoseConfig`). The body is one flat object; the options
that only one kind accepts (:data:`CALIBRATE_ONLY`, :data:`DIAGNOSE_ONLY`) are refused
with a 422 naming them when sent with the other kind. ``GET /jobs/{id}/results`` answers
:class:`JobResults` for a calibration and :class:`DiagnosisResults` for a diagnosis.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import HTTPException
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    StrictBool,
    StringConstraints,
    field_validator,
    model_validator,
)

PathText = Annotated[str, StringConstraints(min_length=1, max_length=4096)]


def _json_integer(value: Any) -> Any:
    if isinstance(value, bool | str):
        raise ValueError("must be a JSON integer, not a boolean or a string")
    return value


def _not_boolean(value: Any) -> Any:
    if isinstance(value, bool):
        raise ValueError("must not be a boolean")
    return value


#: Numbers and integers as the schema states them: pydantic's lax mode would read ``false``
#: as 0 and ``"300"`` as 300; an integral number such as 2.0 stays a valid integer. (The
#: integer's limits come before the check so that the schema keeps them.)
Number = Annotated[float, Strict()]
_INTEGER = BeforeValidator(_json_integer)
AntennaNumber = Annotated[int, Field(ge=0, le=1_000_000), _INTEGER]
Order = Annotated[int, Field(ge=0, le=10), _INTEGER]
EdgesBin = Annotated[int, Field(ge=1, le=65536), _INTEGER]
MaxSteps = Annotated[int, Field(ge=0, le=50), _INTEGER]
NightJD = Annotated[int, Field(ge=2_000_000, le=3_000_000), _INTEGER]

#: The job kinds the API accepts.
JobKind = Literal["calibrate", "diagnose"]
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


#: HEALPix resolutions of Tsky the service takes; the schema lists them as an ``enum`` (so
#: forms and generated clients offer them) while the validator names a wrong one.
NSIDES = tuple(2**k for k in range(1, 11))
Nside = Annotated[int, Field(ge=2, le=1024, json_schema_extra={"enum": list(NSIDES)}), _INTEGER]


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
    order: Order | None = Field(None, description="Legendre order")
    weights: Literal["radiometer", "identity"] | None = None
    antennas: list[AntennaNumber] | None = Field(
        None, min_length=1, max_length=10_000, description="antenna numbers; omit for all"
    )
    pols: list[Literal["ee", "nn", "xx", "yy"]] | None = Field(
        None, min_length=1, max_length=4, description="polarisations; omit for all"
    )
    freq_range_mhz: tuple[Number, Number] | None = Field(None, description="(low, high) MHz")
    lst_range_h: tuple[Number, Number] | None = Field(None, description="(start, stop) hours")
    products: list[Literal["calh5", "calfits", "hdf5", "png"]] | None = Field(
        None, max_length=4, description="the HDF5 product is always written (results need it)"
    )
    reference: list[PathText] | None = Field(
        None, max_length=1000, description="reference gains (calfits/calh5) to compare with"
    )
    tgnd_k: Number | None = Field(None, ge=0.0, le=10_000.0, description="ground temperature K")
    nside: Nside | None = Field(None, description="HEALPix nside, a power of two")
    input_format: Literal["auto", "uvh5", "miriad", "edges"] | None = None
    edges_r: Literal["q", "p0"] | None = Field(
        None, description="EDGES: fit Q = (p0 - p1)/(p2 - p1) or the raw antenna power p0"
    )
    edges_bin: EdgesBin | None = Field(None, description="EDGES: native channels averaged per bin")
    passes: Annotated[Literal["auto", 1, 2], BeforeValidator(_not_boolean)] | None = Field(
        None, description="radiometer weighting passes (auto: 2 only when data weights bias G)"
    )
    inflate_errors: StrictBool | None = Field(
        None, description="radiometer weights: scale each channel's covariance by chi2/dof > 1"
    )
    rfi_flagging: StrictBool | None = Field(
        None,
        description="flag band edges and RFI from the autos before the fit (default true; "
        "calibrate and diagnose alike); the counts per reason are in the results and the "
        "summary under rfi_flagging",
    )
    trxr_prior: Annotated[Number, Field(ge=-100_000.0, le=100_000.0)] | PathText | None = Field(
        None,
        description="receiver-temperature prior: a number (K), or a CSV table "
        "freq_mhz,trxr_k[,sigma_k] or a previous solution.h5 under the data roots; calibrate: "
        "G's errors include it; diagnose: makes effects constant in time (sky_offset, "
        "ground_temperature, missing_cmb) and sky scalings identifiable",
    )
    trxr_prior_sigma_k: Number | None = Field(
        None,
        gt=0.0,
        le=100_000.0,
        description="1-sigma K of a number prior or a table without sigma_k "
        "(calibrate 10, diagnose 1)",
    )

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


class DiagnoseOptions(BaseModel):
    """Settings only the ``diagnose`` kind accepts (defaults: :class:`DiagnoseConfig`)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    bic_threshold: Number | None = Field(
        None, ge=0.0, le=1e12, description="diagnose: Delta BIC an effect must exceed (10)"
    )
    alpha: Number | None = Field(
        None,
        gt=0.0,
        le=1.0,
        description="diagnose: largest chi^2 probability of an accepted effect (1e-4)",
    )
    max_steps: MaxSteps | None = Field(None, description="diagnose: most effects (5)")


#: Options of the request body that only ``kind: "calibrate"`` accepts (every calibration
#: option that :class:`autocal.diagnosis.run.DiagnoseConfig` does not have; a test checks).
CALIBRATE_ONLY = frozenset(
    {
        "model",
        "order",
        "weights",
        "passes",
        "inflate_errors",
        "products",
        "reference",
        "input_format",
        "edges_r",
        "edges_bin",
    }
)
#: Options of the request body that only ``kind: "diagnose"`` accepts.
DIAGNOSE_ONLY = frozenset(DiagnoseOptions.model_fields)


class JobCreate(DiagnoseOptions, CalibrationOptions):
    """``POST /jobs``: calibrate or diagnose one observation.

    ``kind: "calibrate"`` (default) takes the calibration options; ``kind: "diagnose"``
    takes ``sky``, ``beam``, ``tgnd_k``, ``nside``, ``antennas``, ``pols``,
    ``freq_range_mhz``, ``lst_range_h``, ``rfi_flagging``, ``trxr_prior``,
    ``trxr_prior_sigma_k`` and the ``diagnose:`` options. An option of the other kind is a
    422 naming it.
    """

    model_config = ConfigDict(
        json_schema_extra={
            # what misplaced() refuses, in the schema: the other kind's options only as null
            "if": {"properties": {"kind": {"const": "diagnose"}}, "required": ["kind"]},
            "then": {"properties": {name: {"type": "null"} for name in sorted(CALIBRATE_ONLY)}},
            "else": {"properties": {name: {"type": "null"} for name in sorted(DIAGNOSE_ONLY)}},
            "examples": [
                {
                    "inputs": [
                        "hera/autos/zen.2458116.30448.HH.uvh5",
                        "hera/autos/zen.2458116.31193.HH.uvh5",
                    ],
                    "beam": "hera",
                    "antennas": [23],
                    "freq_range_mhz": [110, 190],
                },
                {
                    "kind": "diagnose",
                    "inputs": ["hera/autos/zen.2458116.30448.HH.uvh5"],
                    "beam": "hera",
                    "antennas": [23],
                    "freq_range_mhz": [110, 190],
                    "trxr_prior": 150,
                    "trxr_prior_sigma_k": 10,
                },
            ],
        }
    )

    kind: JobKind = Field(
        "calibrate", description="calibrate (solve G, Trxr) or diagnose (name missing effects)"
    )
    inputs: list[PathText] = Field(
        ...,
        min_length=1,
        max_length=10_000,
        description="under the data roots, or upload ids: UVH5 files / Miriad folders "
        "(calibrate), UVH5 files (diagnose)",
    )
    force: StrictBool = Field(False, description="submit even if an identical job exists")

    @field_validator("inputs")
    @classmethod
    def _each_input_once(cls, inputs: list[str]) -> list[str]:
        """Refuse an input listed more than once (it would be read, and counted, twice)."""
        seen: dict[str, int] = {}
        for item in inputs:
            seen[item] = seen.get(item, 0) + 1
        repeated = {k: n for k, n in seen.items() if n > 1}
        if repeated:
            name, count = next(iter(repeated.items()))
            raise ValueError(
                f"{name!r} is listed {count} times ({len(repeated)} inputs repeated); "
                "list each file once"
            )
        return inputs

    def given(self) -> dict[str, Any]:
        """Return every option that was given (``None`` = default), of either kind."""
        names = set(CalibrationOptions.model_fields) | DIAGNOSE_ONLY
        return {k: v for k, v in self.model_dump().items() if k in names and v is not None}

    def misplaced(self) -> list[str]:
        """Return the given options that the job's kind does not accept."""
        other = DIAGNOSE_ONLY if self.kind == "calibrate" else CALIBRATE_ONLY
        return sorted(set(self.given()) & other)


class NightlyCreate(CalibrationOptions):
    """``POST /nightly``: one job per observation of a night or a folder."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"night": 2458116, "beam": "hera", "antennas": [23]}],
            # a night, a folder or both: the schema says so, as the validator below does
            "anyOf": [{"required": ["night"]}, {"required": ["folder"]}],
        }
    )

    night: NightJD | None = Field(None, description="integer Julian date of the night")
    folder: PathText | None = Field(None, description="folder under the data roots to scan")
    force: StrictBool = Field(False, description="resubmit observations that already have a job")

    @model_validator(mode="after")
    def _night_or_folder(self) -> NightlyCreate:
        """Require a night, a folder or both."""
        if self.night is None and self.folder is None:
            raise ValueError("give a night (integer JD) or a folder (or both)")
        return self


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
    worker: str | None = Field(
        ..., description="host:pid:tag of the worker running it (null for anonymous readers)"
    )
    submitted_by: str | None = Field(
        None, description="name of the API token that submitted it (null for anonymous readers)"
    )
    cancel_requested: bool
    error: str | None
    log_tail: list[str]
    log_hidden: bool = Field(
        False, description="true when the log tail is withheld: send the API token to see it"
    )
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
    next_cursor: str | None = Field(
        None,
        description="opaque cursor of the next page (pass it as ?cursor=); null on the last page",
    )
    next: str | None = Field(
        None, description="URL of the next page (the same filters and the cursor); null at the end"
    )


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
    sigma_G_stat: list[float | None] = Field(  # noqa: N815 - the physics symbol
        ..., description="statistical part of sigma_G (sigma_G is the total 1-sigma)"
    )
    sigma_abs_g_stat: list[float | None]
    sigma_Trxr_stat: list[float | None]  # noqa: N815 - the physics symbol
    reduced_chi2: list[float | None]
    flags: list[bool]
    separation: dict[str, Any] | None = Field(
        None,
        description="how well G and n separate over the span and the error budget (medians "
        "over channels): sky_contrast, corr_G_n, drift_sensitivity, separation (weak or "
        "adequate), G_if_trxr_K (G if Trxr were known), jackknife_factor, drift_weight, "
        "G_halves, message",
    )


class JobResults(BaseModel):
    """``GET /jobs/{id}/results`` of a calibration."""

    job_id: str
    kind: Literal["calibrate"] = "calibrate"
    freqs_mhz: list[float]
    antennas: list[int]
    pols: list[str]
    model: dict[str, Any]
    units: dict[str, str]
    solutions: list[AntennaPolResult]
    summary: dict[str, Any] | None
    comparison: dict[str, Any] | None
    quality: dict[str, Any] | None = Field(
        None,
        description="how much of the solution is flagged and why: status ok, mostly_flagged "
        "or fully_flagged, counts per reason, message (summary.json's quality block)",
    )
    rfi_flagging: dict[str, Any] | None = Field(
        None,
        description="band edges and RFI flagged before the fit: samples per reason "
        "(band_edge, rfi_frequency, rfi_time), channels, integrations, method",
    )


class DiagnosisParameter(BaseModel):
    """A fitted parameter of an accepted effect (null where undefined)."""

    model_config = ConfigDict(extra="allow")

    value: float | None
    sigma: float | None = Field(..., description="1-sigma uncertainty (0 for fixed values)")


class DiagnosisStep(BaseModel):
    """One accepted effect of a diagnosis."""

    step: int = Field(..., ge=1, description="1 for the first effect accepted")
    name: str = Field(..., description="the effect, e.g. gain_drift, cable_reflection")
    parameters: dict[str, DiagnosisParameter]
    statistic: float | None = Field(..., description="Delta BIC of the effect")
    delta: float | None = Field(..., description="Delta chi^2 (drop of the fit's chi^2)")
    p_value: float | None = Field(None, description="chi^2 survival probability of delta")
    gap_before: dict[str, Any] = Field(..., description="gap metrics before the step")
    gap_after: dict[str, Any] = Field(..., description="gap metrics after the step")
    candidates: dict[str, float | None] = Field(
        default_factory=dict, description="Delta BIC of every candidate at this step"
    )
    details: dict[str, Any] = Field(
        default_factory=dict, description="the rest: k, overdispersion, per-feed values..."
    )


class DiagnosisResults(BaseModel):
    """``GET /jobs/{id}/results`` of a diagnosis (from its ``diagnosis.json``)."""

    job_id: str
    kind: Literal["diagnose"] = "diagnose"
    effects: list[str] = Field(..., description="the accepted effects, in order")
    steps: list[DiagnosisStep]
    initial_gap: dict[str, Any] = Field(..., description="chi2/dof, rms residual... at start")
    final_gap: dict[str, Any] = Field(..., description="the same for the final model")
    identifiability: dict[str, float | None] = Field(
        ..., description="per effect: Fisher fraction left after the (G, n) projection"
    )
    config: dict[str, Any] = Field(..., description="statistic, thresholds, prior, candidates")
    negligible: list[str] = Field(
        default_factory=list,
        description="effects detected but negligible for G and Trxr (kept in the fit, not "
        "named among the effects); their steps carry details.negligible = true",
    )
    absorbed: list[str] = Field(
        default_factory=list,
        description="effects fitted but reported as part of the unexplained remainder "
        "(negligible for G and Trxr, each explaining < 10 % of the remainder's excess chi2; "
        "shares under unexplained.absorbed): not evidence of the effect",
    )
    below_model_accuracy: list[str] = Field(
        default_factory=list,
        description="effects fitted but below the forward model's accuracy (a signal under "
        "the model beam's floor of the data rms, in config.forward_model_accuracy: 1e-4 for "
        "an analytic beam, 7e-4 for a HEALPix beam file; the signal in the step's "
        "details.signal_rms): not attributed, whatever it would change in G and Trxr "
        "(the step's product_impact)",
    )
    indistinguishable: dict[str, Any] | None = Field(
        None,
        description="null, or the step at which the search stopped because an entry of the "
        "receiver and one of the forward model explain a residual within "
        "config.decisive_margin of each other (Delta BIC), or within config.lead_sigmas "
        "sigma of the noise of the lead (lead_sigma per rival): candidates {name: Delta "
        "BIC}, each one's product_impact and a message; none of them is named",
    )
    unexplained: dict[str, Any] | None = Field(
        None,
        description="null when the final model fits within the noise; else the remaining "
        "gap's size and structure (time, frequency, antennas) that no catalogue entry explains",
    )
    product_change: dict[str, Any] = Field(
        default_factory=dict,
        description="how G and Trxr change from the starting model to the diagnosed one, in "
        "units of the total 1-sigma (median and worst channel); each step's own change is "
        "in its details.product_impact",
    )
    not_tested: dict[str, str] = Field(
        default_factory=dict,
        description="catalogue entries the search did not test, each with the reason (e.g. "
        "per-antenna entries above the feed limit)",
    )
    rfi_flagging: dict[str, Any] | None = Field(
        None,
        description="band edges and RFI flagged from the autos before the fits, as a "
        "calibration flags them: samples per reason (band_edge, rfi_frequency, rfi_time), "
        "channels, integrations, method; or applied false and why (the outliers of the "
        "residual rounds are in config.outlier_flagging)",
    )
    summary: dict[str, Any] | None = Field(
        None, description="the job's summary: observation, config, timings"
    )


class ProductEntry(BaseModel):
    """One product file of a job."""

    name: str = Field(..., description="the name to download it by")
    file: str = Field(..., description="its file name")
    media_type: str
    size_bytes: int
    url: str = Field(..., description="GET it to download the file")


class ProductList(BaseModel):
    """Answer to ``GET /jobs/{id}/products``: the product files of a succeeded job."""

    job_id: str
    products: list[ProductEntry]


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
    job_id: str | None = Field(..., description="null when the observation was refused")
    state: str = Field(..., description="the job's state, or refused (see error)")
    created: bool
    error: str | None = Field(
        None, description="why the observation's files were refused (no job was queued)"
    )


class NightlyAccepted(BaseModel):
    """``POST /nightly``."""

    night: int | None
    observations: list[NightlyObservation]
    created: int
    existing: int
    refused: int = Field(0, description="observations refused by the submission checks")


class Health(BaseModel):
    """``GET /health``."""

    status: Literal["ok", "degraded"]
    version: str
    database: Literal["ok", "error"]
    queued: int | None
    running: int | None
