"""Mock auto-correlations: ``R = G(t) (Tsky + Trxr) + noise``.

The defaults are the paper's reference setup (Gehlot et al. 2021, DESIGN.md section 1):
110-190 MHz in 250 kHz channels, one integration every 5 sidereal minutes over 24 h of
LST, constant ``G = 1``, ``Trxr = 150 K``, radiometer noise ``sigma = R / sqrt(dnu dt)``
with ``dnu = 5 kHz`` and ``dt = 1 s``. Gain drifts (t = LST in hours):

- ``a``: ``G0 - A (t/12 - 1)`` (linear), ``b``: ``G0 + A sin(2 pi t / 24)``,
- ``c``: ``G0 + A sin(2 pi - 2 pi t / 24)`` (the sine shifted by half a period),

with ``A = 0.1``. The truth can use a different sky or beam from the one a later fit
assumes (model-incompleteness scenarios), including the beam error model
(:class:`autocal.sky.analytic_beams.PerturbedBeam`).

The noise the data carry is recorded honestly in the written UVH5 file: the file's
``channel_width`` and ``integration_time`` describe the sampling grid, and
``nsample_array = dnu_noise dt_noise / (channel_width integration_time)`` so that the
radiometer equation applied to the file gives the simulated noise level.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from autocal.core.coords import night_epoch
from autocal.core.observation import Observation
from autocal.core.sites import get_site
from autocal.errors import AutocalError
from autocal.fit.model import unwrap_lsts
from autocal.io.datasets import data_file
from autocal.sky.analytic_beams import PerturbedBeam, s1_airy, s1_dipole
from autocal.sky.beam_base import Beam
from autocal.sky.beam_names import get_beam
from autocal.tsky.compute import compute_tsky

logger = logging.getLogger(__name__)

#: Names of the gain profiles.
GAIN_PROFILES = ("constant", "a", "b", "c")
#: Solar days per sidereal day.
SIDEREAL_DAY = 0.9972695663


class SimulationError(AutocalError):
    """Invalid simulation settings."""


def gain_profile(
    name: str, lsts: np.ndarray, g0: float | np.ndarray = 1.0, amplitude: float = 0.1
) -> np.ndarray:
    """Return the gain ``G(t)`` of a named profile.

    Parameters
    ----------
    name
        ``constant``, ``a`` (linear), ``b`` (sine) or ``c`` (shifted sine).
    lsts
        ``(Ntime,)`` LST in hours.
    g0
        Mean gain (scalar or ``(Nfreq,)``).
    amplitude
        Drift amplitude ``A`` (relative to 1, added to ``G0``).

    Returns
    -------
    numpy.ndarray
        ``(Ntime,)`` for scalar ``g0``, else ``(Ntime, Nfreq)``.
    """
    t = np.asarray(lsts, dtype=np.float64)
    if name == "constant":
        drift = np.zeros_like(t)
    elif name == "a":
        drift = -amplitude * (t / 12.0 - 1.0)
    elif name == "b":
        drift = amplitude * np.sin(2 * np.pi * t / 24.0)
    elif name == "c":
        drift = amplitude * np.sin(2 * np.pi - 2 * np.pi * t / 24.0)
    else:
        raise SimulationError(f"unknown gain profile {name!r}: use one of {GAIN_PROFILES}")
    g0 = np.asarray(g0, dtype=np.float64)
    if g0.ndim == 0:
        return float(g0) + drift
    return g0[None, :] + drift[:, None]


def hera_h1c_bandpass(freqs: np.ndarray) -> np.ndarray:
    """Relative gain ``G(nu)`` of the H1C bandpass polynomial (hera_sim), 1 at 150 MHz.

    The polynomial (``hera/instrument/HERA_H1C_BANDPASS.npy``, frequency in GHz) gives
    the voltage-gain amplitude; ``G`` is its square.
    """
    coeffs = np.load(data_file("hera/instrument/HERA_H1C_BANDPASS.npy"))
    amp = np.polyval(coeffs, np.asarray(freqs) / 1e9)
    ref = np.polyval(coeffs, 0.15)
    if np.any(amp <= 0):
        raise SimulationError(
            "the H1C bandpass polynomial is not positive over the requested band; "
            "keep the band within about 105-195 MHz or use bandpass='flat'"
        )
    return (amp / ref) ** 2


def lsts_to_jds(lsts: np.ndarray, site: Any, jd_start: float) -> np.ndarray:
    """Julian dates at which the site sees the given LSTs, from ``jd_start`` onwards.

    Parameters
    ----------
    lsts
        ``(Ntime,)`` LSTs in hours, in time order (may pass through 24 h).
    site
        :class:`autocal.core.sites.Site` or name.
    jd_start
        The first JD is the first time at or after ``jd_start`` with LST ``lsts[0]``.

    Returns
    -------
    numpy.ndarray
        JDs whose apparent LST (as pyuvdata computes it) equals ``lsts`` to < 1 ms.
    """
    from pyuvdata.utils import get_lst_for_time

    site = get_site(site)

    def lst_of(jd: np.ndarray) -> np.ndarray:
        rad = get_lst_for_time(
            np.atleast_1d(jd), latitude=site.lat_deg, longitude=site.lon_deg, altitude=site.alt_m
        )
        return np.asarray(rad) * 12.0 / np.pi

    un = unwrap_lsts(lsts)
    lst0 = lst_of(np.array([jd_start]))[0]
    first = jd_start + ((un[0] - lst0) % 24.0) / 24.0 * SIDEREAL_DAY
    jds = first + (un - un[0]) / 24.0 * SIDEREAL_DAY
    for _ in range(3):
        err = (np.asarray(lsts) - lst_of(jds) + 12.0) % 24.0 - 12.0
        jds = jds + err / 24.0 * SIDEREAL_DAY
    return jds


#: Largest simulated observation (values, ~8 bytes each plus the model's copies): ~2.4 GB.
MAX_SIMULATED_VALUES = 300_000_000
#: Largest HEALPix resolution of a simulation's Tsky (as ``autocal diagnose`` allows).
MAX_NSIDE = 8192


class SimulationConfig(BaseModel):
    """Settings of a mock observation (shared by the CLI, the pipeline and the API).

    Frequencies are in MHz, times in hours or seconds as named; defaults are the paper's
    reference setup.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    sky: str = Field("gsm2008", description="true sky model (autocal.sky.models.get_sky spec)")
    beam: str = Field("hera", description="true beam (autocal.sky.beam_names.get_beam spec)")
    beam_error: bool = Field(False, description="apply the paper's beam error model to the beam")
    beam_error_kind: Literal["auto", "airy", "dipole"] = Field(
        "auto", description="s1 of the beam error model: airy (dishes) or dipole"
    )
    site: str = "hera"
    telescope: str = "HERA"
    antennas: list[int] = Field(default_factory=lambda: [0])
    pols: list[str] = Field(default_factory=lambda: ["ee"])
    freq_start_mhz: float = 110.0
    freq_stop_mhz: float = 190.0
    channel_width_khz: float = Field(250.0, gt=0.0, description="channel spacing, kHz")
    lst_start_h: float = Field(0.0, ge=0.0, lt=24.0)
    duration_h: float = Field(24.0, gt=0.0, le=48.0, description="LST hours covered")
    cadence_s: float = Field(300.0, gt=0.0, description="sidereal seconds between samples")
    jd_start: float = Field(2458098.0, description="the observation starts at or after this JD")
    gain: Literal["constant", "a", "b", "c"] = "constant"
    gain_amplitude: float = 0.1
    g0: float = Field(1.0, gt=0.0)
    bandpass: Literal["flat", "hera-h1c"] = "flat"
    trxr_k: float = Field(150.0, ge=0.0)
    tgnd_k: float = Field(300.0, ge=0.0)
    noise: bool = True
    noise_dnu_hz: float = Field(5e3, gt=0.0)
    noise_dt_s: float = Field(1.0, gt=0.0)
    seed: int | None = Field(0, ge=0, description="noise seed (None: a fresh one)")
    nside: int = Field(64, ge=1, le=MAX_NSIDE, description="HEALPix resolution of Tsky")

    @model_validator(mode="after")
    def _check(self) -> SimulationConfig:
        if self.freq_stop_mhz <= self.freq_start_mhz:
            raise ValueError("freq_stop_mhz must exceed freq_start_mhz")
        if not self.antennas:
            raise ValueError("give at least one antenna")
        if not self.pols:
            raise ValueError("give at least one polarisation")
        if len(set(self.antennas)) != len(self.antennas):
            raise ValueError("antenna numbers must be unique")
        if self.nside & (self.nside - 1):
            raise ValueError(f"nside must be a power of two (got {self.nside})")
        nfreq, ntime = self.nfreq(), self.ntime()
        values = nfreq * ntime * len(self.antennas) * len(self.pols)
        if values > MAX_SIMULATED_VALUES:
            raise ValueError(
                f"{nfreq} channels x {ntime} integrations x {len(self.antennas)} antenna(s) x "
                f"{len(self.pols)} pol(s) = {values:.3g} values, more than the "
                f"{MAX_SIMULATED_VALUES:.0e} a simulation holds in memory: widen the "
                "channels or the cadence, or shorten the span"
            )
        return self

    def nfreq(self) -> int:
        """Return the number of channels (start to stop inclusive in channel-width steps)."""
        width = self.channel_width_khz * 1e3
        return int(np.floor((self.freq_stop_mhz - self.freq_start_mhz) * 1e6 / width + 1e-9)) + 1

    def ntime(self) -> int:
        """Return the number of integrations."""
        return max(round(self.duration_h * 3600.0 / self.cadence_s), 1)

    def freqs(self) -> np.ndarray:
        """Channel centres in Hz (start to stop inclusive in channel-width steps)."""
        return self.freq_start_mhz * 1e6 + self.channel_width_khz * 1e3 * np.arange(self.nfreq())

    def lsts(self) -> np.ndarray:
        """LSTs in hours (time order, wrapped to [0, 24))."""
        return (self.lst_start_h + np.arange(self.ntime()) * self.cadence_s / 3600.0) % 24.0


def true_beam(config: SimulationConfig, pol: str) -> Beam:
    """Return the true beam of one polarisation (with the error model if asked)."""
    beam = get_beam(config.beam, pol)
    if not config.beam_error:
        return beam
    return perturbed(beam, config.beam_error_kind)


def perturbed(beam: Beam, kind: str = "auto") -> PerturbedBeam:
    """Wrap a beam in the paper's error model, choosing ``s1`` for dishes or dipoles."""
    if kind == "auto":
        kind = "dipole" if beam.describe().get("beam") == "gaussian-dipole" else "airy"
    if kind == "airy":
        return PerturbedBeam(base=beam, s1=s1_airy, s1_kind="airy")
    return PerturbedBeam(base=beam, s1=s1_dipole, s1_kind="dipole")


@dataclass(frozen=True)
class Truth:
    """What generated a mock observation.

    Attributes
    ----------
    gain
        ``(Ntime, Nfreq)`` true ``G(t, nu)``.
    trxr
        ``(Nfreq,)`` true receiver temperature (K).
    tsky
        ``(Npol, Ntime, Nfreq)`` true beam-weighted sky (K).
    config
        The simulation settings.
    """

    gain: np.ndarray
    trxr: np.ndarray
    tsky: np.ndarray
    config: dict[str, Any]

    @property
    def mean_gain(self) -> np.ndarray:
        """``(Nfreq,)`` time-averaged true gain."""
        return self.gain.mean(axis=0)


def mock_autos(
    tsky: np.ndarray,
    gain: np.ndarray,
    trxr: np.ndarray | float,
    *,
    nant: int = 1,
    bandwidth_time: float | None = 5e3,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Return ``(Nant, Npol, Ntime, Nfreq)`` mock autos ``G (Tsky + Trxr) + noise``.

    Parameters
    ----------
    tsky
        ``(Npol, Ntime, Nfreq)`` true Tsky in kelvin.
    gain
        ``(Ntime,)`` or ``(Ntime, Nfreq)`` gain.
    trxr
        Receiver temperature in kelvin (scalar or ``(Nfreq,)``).
    nant
        Number of antennas (independent noise, same gain and Tsky).
    bandwidth_time
        ``dnu dt`` of the radiometer noise; ``None`` for noiseless data.
    rng
        Random generator.
    """
    tsky = np.asarray(tsky, dtype=np.float64)
    g = np.asarray(gain, dtype=np.float64)
    if g.ndim == 1:
        g = g[:, None]
    clean = g[None] * (tsky + np.asarray(trxr, dtype=np.float64))  # (P, T, F)
    out = np.broadcast_to(clean[None], (nant, *clean.shape)).copy()
    if bandwidth_time is not None:
        rng = rng or np.random.default_rng()
        out *= 1.0 + rng.standard_normal(out.shape) / np.sqrt(bandwidth_time)
    return out


def true_tsky(
    config: SimulationConfig, jds: np.ndarray, progress: bool | None = None
) -> np.ndarray:
    """``(Npol, Ntime, Nfreq)`` true Tsky of a simulation."""
    freqs, lsts = config.freqs(), config.lsts()
    epoch = night_epoch(jds, get_site(config.site).lon_deg)
    return np.stack(
        [
            compute_tsky(
                config.sky,
                true_beam(config, pol),
                config.site,
                freqs,
                lsts,
                tgnd=config.tgnd_k,
                nside=config.nside,
                epoch=epoch,
                pol=pol,
                progress=progress,
            ).tsky
            for pol in config.pols
        ]
    )


def simulate(
    config: SimulationConfig | None = None, progress: bool | None = None
) -> tuple[Observation, Truth]:
    """Simulate one mock observation.

    Parameters
    ----------
    config
        Settings (default: the paper's reference setup for one HERA antenna, pol ee).
    progress
        Progress bars for the Tsky computation.

    Returns
    -------
    (Observation, Truth)
        The mock data (with the file metadata a UVH5 writer needs) and what made it.
    """
    config = config or SimulationConfig()
    site = get_site(config.site)
    freqs, lsts = config.freqs(), config.lsts()
    jds = lsts_to_jds(lsts, site, config.jd_start)
    tsky = true_tsky(config, jds, progress)
    g0 = hera_h1c_bandpass(freqs) * config.g0 if config.bandpass == "hera-h1c" else config.g0
    gain = np.broadcast_to(
        np.atleast_2d(gain_profile(config.gain, lsts, g0, config.gain_amplitude).T).T,
        (lsts.size, freqs.size),
    ).copy()
    rng = np.random.default_rng(config.seed)
    bt = config.noise_dnu_hz * config.noise_dt_s if config.noise else None
    data = mock_autos(
        tsky, gain, config.trxr_k, nant=len(config.antennas), bandwidth_time=bt, rng=rng
    )
    width = config.channel_width_khz * 1e3
    tint = config.cadence_s * SIDEREAL_DAY
    nsamples = config.noise_dnu_hz * config.noise_dt_s / (width * tint)
    obs = Observation(
        data=data,
        freqs=freqs,
        lsts=lsts,
        jds=jds,
        antennas=np.asarray(config.antennas),
        pols=tuple(config.pols),
        site=site,
        channel_width=width,
        integration_time=tint,
        nsamples=np.full(data.shape, nsamples),
        antenna_names=tuple(f"HH{a}" for a in config.antennas)
        if config.telescope.upper() == "HERA"
        else (),
        telescope_name=config.telescope,
        meta={
            "source": "autocal simulate",
            "simulation": config.model_dump(),
        },
    )
    truth = Truth(
        gain=gain, trxr=np.full(freqs.size, config.trxr_k), tsky=tsky, config=config.model_dump()
    )
    logger.info(
        "simulated %d antennas x %d pols x %d times x %d channels (gain %s, noise %s)",
        *data.shape,
        config.gain,
        "on" if config.noise else "off",
    )
    return obs, truth
