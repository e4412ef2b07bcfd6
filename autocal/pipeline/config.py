"""The settings of one calibration (:class:`CalibrationConfig`) and their checks.

One validated, frozen configuration is shared by the CLI, the Python API, the job service
and the workers; :class:`PipelineError` is what the calibration stage raises for a run
that cannot be configured or carried out.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from autocal.errors import AutocalError
from autocal.fit.defaults import DEFAULT_INFLATE_ERRORS, DEFAULT_PASSES, Passes

ProductName = Literal["calh5", "calfits", "hdf5", "png"]
Progress = Callable[[float, str], None]

#: Default 1-sigma (K) of a receiver prior given as a number or a table without sigma_k.
DEFAULT_PRIOR_SIGMA_K = 10.0


class PipelineError(AutocalError):
    """The calibration could not be configured or run."""


class CalibrationConfig(BaseModel):
    """Everything that defines one calibration (shared by the CLI, the API and workers).

    Frequencies in MHz, LSTs in hours, temperatures in kelvin.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    inputs: list[str] = Field(..., min_length=1, description="UVH5 files or Miriad folders")
    input_format: Literal["auto", "uvh5", "miriad", "edges"] = "auto"
    edges_r: Literal["q", "p0"] = Field(
        "q", description="EDGES: fit Q = (p0 - p1)/(p2 - p1) or the raw antenna power p0"
    )
    edges_bin: int = Field(64, ge=1, description="EDGES: native channels averaged per bin")
    sky: str = Field("gsm2008", description="sky model (autocal.sky.models.get_sky spec)")
    beam: str = Field("hera", description="beam (autocal.sky.beam_names.get_beam spec)")
    tgnd_k: float = Field(300.0, ge=0.0, description="ground temperature")
    nside: int = Field(64, ge=2, le=8192, description="HEALPix resolution of Tsky (a power of two)")
    model: Literal["constant", "legendre"] = "constant"
    order: int = Field(1, ge=0, le=10, description="Legendre order (model=legendre)")
    weights: Literal["radiometer", "identity"] = "radiometer"
    passes: Passes = Field(
        DEFAULT_PASSES,
        description="radiometer weighting passes (auto: 2 only when data weights bias G)",
    )
    antennas: list[int] | None = Field(None, min_length=1, description="None: every antenna")
    pols: list[str] | None = Field(None, min_length=1, description="None: the same-feed ones")
    freq_range_mhz: tuple[float, float] | None = None
    lst_range_h: tuple[float, float] | None = None
    products: list[ProductName] = Field(default_factory=lambda: ["calh5", "hdf5", "png"])
    reference: list[str] | None = Field(
        None, description="reference gains (calfits/calh5) to compare |g| with"
    )
    inflate_errors: bool = Field(
        DEFAULT_INFLATE_ERRORS,
        description="radiometer weights: scale each channel's covariance by chi2/dof when it "
        "exceeds 1, so errors cover unmodelled structure (identity weights always scale)",
    )
    trxr_prior: float | str | None = Field(
        None,
        description="receiver-temperature prior: a number (K), a CSV table "
        "freq_mhz,trxr_k[,sigma_k] or a previous solution.h5 of the same antennas/pols",
    )
    rfi_flagging: bool = Field(
        True,
        description="flag band edges and RFI from the autos before the fit (robust median "
        "filters in frequency and time, as hera_qm's xrfi); false: the data's own flags only",
    )
    trxr_prior_sigma_k: float = Field(
        DEFAULT_PRIOR_SIGMA_K,
        gt=0.0,
        description="1-sigma (K) of a number prior and of a table without sigma_k",
    )

    @model_validator(mode="after")
    def _check(self) -> CalibrationConfig:
        check_ranges(self.freq_range_mhz, self.lst_range_h)
        check_prior_spec(self.trxr_prior, self.trxr_prior_sigma_k)
        if self.nside & (self.nside - 1):
            raise ValueError(f"nside must be a power of two (got {self.nside})")
        return self


def check_prior_spec(spec: float | str | None, sigma_k: float) -> None:
    """Raise ``ValueError`` for a receiver prior that is not a finite number or a path."""
    if isinstance(spec, bool):
        raise ValueError("trxr_prior must be a number (K) or a path, not a boolean")
    if isinstance(spec, float) and not np.isfinite(spec):
        raise ValueError("trxr_prior must be a finite temperature in K")
    if isinstance(spec, str) and not spec.strip():
        raise ValueError("trxr_prior is empty: give a number in K or a .csv/.h5 path")
    if not np.isfinite(sigma_k):
        raise ValueError("trxr_prior_sigma_k must be finite")


def check_ranges(
    freq_range_mhz: tuple[float, float] | None, lst_range_h: tuple[float, float] | None
) -> None:
    """Raise ``ValueError`` unless the frequency (MHz) and LST (h) selections make sense."""
    if freq_range_mhz is not None:
        lo, hi = freq_range_mhz
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
            raise ValueError("freq_range_mhz must be (low, high) MHz with 0 < low < high")
        if hi > 1e5:
            raise ValueError("freq_range_mhz is in MHz, not Hz")
    if lst_range_h is not None and not all(0 <= v <= 24 for v in lst_range_h):
        raise ValueError("lst_range_h values must be hours within [0, 24]")


def read_selection(config: CalibrationConfig) -> dict[str, Any]:
    """Return the readers' selection of a configuration.

    Keys ``antennas``, ``pols``, ``freq_range`` (Hz) and ``lst_range`` (hours): the keyword
    arguments of :func:`autocal.io.uvh5.read_uvh5` and the other readers.
    """
    return {
        "antennas": config.antennas,
        "pols": config.pols,
        "freq_range": None
        if config.freq_range_mhz is None
        else (config.freq_range_mhz[0] * 1e6, config.freq_range_mhz[1] * 1e6),
        "lst_range": config.lst_range_h,
    }
