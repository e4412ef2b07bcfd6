"""Response models of the monitoring endpoints (``/antennas``, ``/nights``)."""

from __future__ import annotations

from pydantic import BaseModel, Field


class BandValues(BaseModel):
    """Medians over one 25 MHz band's solved channels, with the median total 1-sigma."""

    band: str = Field(description="'lo-hi' in MHz")
    lo_mhz: float
    hi_mhz: float
    n_channels: int = Field(description="solved channels in the band")
    G: float | None = None
    sigma_G: float | None = None  # noqa: N815 - the physics symbol
    abs_g: float | None = None
    sigma_abs_g: float | None = None
    Trxr: float | None = None
    sigma_Trxr: float | None = None  # noqa: N815 - the physics symbol


class AntennaNightValues(BaseModel):
    """One antenna-pol on one night (one configuration): medians with total sigmas.

    Units: ``G`` raw/K, ``abs_g`` sqrt(raw/K), ``Trxr`` K. Several observations of a
    night are combined by the median (sigmas too).
    """

    antenna: int
    pol: str
    night: int = Field(description="integer JD")
    config_hash: str = Field(description="hash of the calibration settings without inputs")
    job_id: str = Field(description="the latest job of the night for this antenna-pol")
    jobs: list[str]
    observations: list[str]
    G: float | None = None
    sigma_G: float | None = None  # noqa: N815 - the physics symbol
    abs_g: float | None = None
    sigma_abs_g: float | None = None
    Trxr: float | None = None
    sigma_Trxr: float | None = None  # noqa: N815 - the physics symbol
    reduced_chi2: float | None = None
    flagged_fraction: float | None = None
    ratio: float | None = Field(None, description="comparison: median autocal/reference")
    sigma_ratio: float | None = None
    effects: list[str] | None = Field(None, description="effects named by a diagnosis")
    bands: list[BandValues]


class AntennaState(AntennaNightValues):
    """An antenna-pol's latest night, with the reasons it is an outlier that night."""

    outliers: list[str]


class AntennaList(BaseModel):
    """``GET /antennas``."""

    items: list[AntennaState]
    count: int


class AntennaHistory(BaseModel):
    """``GET /antennas/{antenna}/history``: the antenna's values night by night."""

    antenna: int
    pol: str | None
    night_from: int | None
    night_to: int | None
    items: list[AntennaNightValues]
    count: int


class Outlier(BaseModel):
    """An antenna-pol flagged on a night, by one test, with the numbers behind it."""

    antenna: int
    pol: str
    night: int
    job_id: str | None
    quantity: str = Field(description="G, Trxr or reduced_chi2")
    test: str = Field(description="array, history or chi2_jump")
    value: float
    sigma: float | None
    reference: float
    spread: float | None
    z: float | None = Field(description="departure in units of the combined sigma")
    reason: str


class NightSummary(BaseModel):
    """A line of ``GET /nights``."""

    night: int
    antennas: int = Field(description="antennas with recorded values")
    observations: int
    jobs: dict[str, int] = Field(description="jobs of the night by state")


class NightList(BaseModel):
    """``GET /nights``: newest first."""

    items: list[NightSummary]
    count: int


class FailedJob(BaseModel):
    """A failed job of a night and why it failed."""

    job_id: str
    kind: str
    error: str
    inputs: list[str]
    finished: str | None


class NightDetail(BaseModel):
    """``GET /nights/{night}``."""

    night: int
    antennas: list[AntennaNightValues]
    outliers: list[Outlier]
    failed_jobs: list[FailedJob]
    jobs: dict[str, int]
