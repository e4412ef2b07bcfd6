"""An EDGES-like day simulated through a real receiver solution into raw files.

:func:`simulate_edges_day` computes the beam-weighted sky for the EDGES site over one
sidereal day, passes it through a receiver solution
(:func:`~autocal.edges.noise_waves.decalibrate`) into the three switch powers with
radiometer noise, and writes them as raw ACQ (or autocal HDF5) files;
:func:`autocal.edges.day_fit.fit_edges_day` calibrates them back with the
auto-correlation fit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from autocal.core.coords import night_epoch
from autocal.core.sites import EDGES
from autocal.edges.noise_waves import (
    RAW_SCALE_DEFAULT,
    T_OFFSET_DEFAULT,
    AutoModelExpectation,
    decalibrate,
    expected_auto_model,
    gamma_at,
)
from autocal.edges.solutions import ReceiverCalError, ReceiverSolution, resolve_solution
from autocal.io.edges_acq import write_acq
from autocal.io.edges_hdf5 import write_edges_hdf5
from autocal.io.edges_spectra import (
    MIN_OBS_FREQ_HZ,
    NATIVE_DF_HZ,
    EdgesSpectra,
    channel_bins,
    native_freqs,
)
from autocal.io.edges_time import acq_time_to_jd, jd_to_acq_time, lsts_for_jds
from autocal.simulate.mock import SIDEREAL_DAY
from autocal.tsky.compute import compute_tsky

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class EdgesDay:
    """A simulated EDGES-like day written as raw files.

    Attributes
    ----------
    paths
        The written files (time order).
    freqs
        ``(Nfreq,)`` Hz: the binned channels :func:`autocal.io.edges_read.read_edges` returns
        for ``freq_range`` and ``bin_factor``.
    jds, lsts
        ``(Ntime,)`` UTC Julian dates (whole seconds) and LSTs (hours) of the cycles.
    t_ant
        ``(Ntime, Nfreq)`` true antenna temperature (= the beam-weighted sky, K).
    solution
        The receiver solution at ``freqs``.
    gamma_ant
        ``(Nfreq,)`` antenna reflection coefficient used.
    expected
        ``{"q": ..., "p0": ...}`` :class:`AutoModelExpectation`.
    config
        Everything needed to recompute the sky model and to read the files.
    """

    paths: list[Path]
    freqs: np.ndarray
    jds: np.ndarray
    lsts: np.ndarray
    t_ant: np.ndarray
    solution: ReceiverSolution
    gamma_ant: np.ndarray
    expected: dict[str, AutoModelExpectation]
    config: dict[str, Any]


def simulate_edges_day(
    out_dir: str | Path,
    *,
    solution: ReceiverSolution | str = "edges2-lowband-2015",
    freq_range: tuple[float, float] = (50e6, 100e6),
    bin_factor: int = 64,
    n_times: int = 72,
    jd_start: float = 2458000.5,
    sky: str = "powerlaw:gsm2008@408:-2.55",
    beam: str = "edges-low",
    tgnd: float = 300.0,
    nside: int = 64,
    gamma_ant: Any = 0.0,
    raw_scale: float | np.ndarray = RAW_SCALE_DEFAULT,
    t_offset: float | np.ndarray = T_OFFSET_DEFAULT,
    integration_time: float = 6.71,
    noise: bool = True,
    seed: int | None = 0,
    n_files: int = 4,
    file_format: Literal["acq", "hdf5"] = "acq",
) -> EdgesDay:
    """Simulate one sidereal day of raw EDGES spectra through a receiver solution.

    The antenna temperature is the beam-weighted sky (:func:`autocal.tsky.compute.compute_tsky`
    with ``sky``, ``beam``, the EDGES site, ``tgnd``; CMB included once) at the binned
    channel centres, sampled ``n_times`` times over one sidereal day. It passes through
    the receiver (:func:`decalibrate`) into ``p0, p1, p2``, constant within each bin of
    ``bin_factor`` native channels (so that binning on reading is exact), with radiometer
    noise ``p / sqrt(dnu dt)`` per native channel (``dnu`` = 6.1 kHz, ``dt`` =
    ``integration_time``), and is written as ``n_files`` native-grid files (ACQ by
    default, else autocal HDF5).

    Returns
    -------
    EdgesDay
        Files, truth and the expected ``G``, ``Trxr`` for ``R = Q`` and ``R = p0``.
    """
    if n_times < 3:
        raise ReceiverCalError("simulate at least 3 cycles")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    native = native_freqs()
    index, freqs = channel_bins(native, freq_range, bin_factor, min_freq=MIN_OBS_FREQ_HZ)
    sol = resolve_solution(solution).at(freqs)
    gamma = gamma_at(gamma_ant, freqs)
    jds = _cycle_jds(jd_start, n_times)
    lsts = lsts_for_jds(jds, EDGES)
    t_ant = compute_tsky(
        sky,
        beam,
        EDGES,
        freqs,
        lsts,
        tgnd=tgnd,
        nside=nside,
        epoch=night_epoch(jds, EDGES.lon_deg),
    ).tsky
    powers = decalibrate(t_ant, sol, gamma, raw_scale=raw_scale, t_offset=t_offset)
    fine = _native_powers(powers, bin_factor, integration_time, noise, seed)
    paths = _write_files(
        out, fine, native, index.ravel(), jds, integration_time, n_files, file_format
    )
    expected = {
        r: expected_auto_model(sol, gamma, r, raw_scale=raw_scale, t_offset=t_offset)
        for r in ("q", "p0")
    }
    config = {
        "solution": sol.describe(),
        "freq_range_Hz": list(freq_range),
        "bin_factor": int(bin_factor),
        "n_times": int(n_times),
        "sky": sky,
        "beam": beam,
        "tgnd_K": float(tgnd),
        "nside": int(nside),
        "raw_scale": raw_scale,
        "t_offset_K": t_offset,
        "integration_time_s": float(integration_time),
        "noise": bool(noise),
        "seed": seed,
        "file_format": file_format,
    }
    logger.info("simulated an EDGES-like day: %d cycles in %d file(s)", n_times, len(paths))
    return EdgesDay(paths, freqs, jds, lsts, t_ant, sol, gamma, expected, config)


def _cycle_jds(jd_start: float, n_times: int) -> np.ndarray:
    """UTC Julian dates of ``n_times`` cycles over one sidereal day, in whole seconds."""
    jds = jd_start + np.arange(n_times) * SIDEREAL_DAY / n_times
    return acq_time_to_jd(jd_to_acq_time(jds))  # whole seconds, as an ACQ file stores them


def _native_powers(
    powers: tuple[np.ndarray, np.ndarray, np.ndarray],
    bin_factor: int,
    integration_time: float,
    noise: bool,
    seed: int | None,
) -> list[np.ndarray]:
    """Spread ``p0, p1, p2`` over ``bin_factor`` native channels a bin, with radiometer noise."""
    rng = np.random.default_rng(seed)
    sigma_rel = 1.0 / np.sqrt(NATIVE_DF_HZ * integration_time)
    fine = []
    for p in powers:
        full = np.repeat(p, bin_factor, axis=1)
        if noise:
            full = full * (1.0 + sigma_rel * rng.standard_normal(full.shape))
        fine.append(full)
    return fine


def _write_files(
    out: Path,
    fine: list[np.ndarray],
    native: np.ndarray,
    chans: np.ndarray,
    jds: np.ndarray,
    integration_time: float,
    n_files: int,
    file_format: str,
) -> list[Path]:
    """Write the native-grid powers ``fine`` (channels ``native[chans]``) as ``n_files`` files."""
    n_times = jds.size
    paths = []
    for k, part in enumerate(np.array_split(np.arange(n_times), max(1, min(n_files, n_times)))):
        spec = EdgesSpectra(
            p0=fine[0][part],
            p1=fine[1][part],
            p2=fine[2][part],
            freqs=native[chans],
            jds=jds[part],
            channel_width=NATIVE_DF_HZ,
            integration_time=integration_time,
            meta={"history": "simulated by autocal.edges.simulated_day.simulate_edges_day"},
        )
        stamp = jd_to_acq_time(jds[part][:1])[0].replace(":", "_")
        if file_format == "acq":
            paths.append(
                write_acq(
                    out / f"edges_sim_{k:02d}_{stamp}.acq",
                    spec,
                    header={"site": "edges-sim", "instrument": "autocal-sim"},
                )
            )
        elif file_format == "hdf5":
            paths.append(write_edges_hdf5(out / f"edges_sim_{k:02d}_{stamp}.h5", spec))
        else:
            raise ReceiverCalError(f"unknown file_format {file_format!r}: use 'acq' or 'hdf5'")
    return paths
