"""Statistics of the gain ratio ``r = |g_auto| / |g_ref|`` over the compared channels.

:func:`ratio_statistics` (mean, scatter, pulls), :func:`broadband_offset` (``mean(r) - 1``
with an error that allows for errors correlated in frequency, step 8 of the procedure in
:mod:`autocal.compare.comparison`, via :func:`block_bootstrap_error`) and the delay
spectrum of the ratio (:func:`ratio_delay_spectra`, :func:`delay_peak`).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from autocal.compare.delay import DelayError, delay_spectrum

logger = logging.getLogger(__name__)

#: Block length (MHz) of the block bootstrap of the mean ratio over channels.
BOOTSTRAP_BLOCK_MHZ = 5.0
#: Number of bootstrap resamples.
BOOTSTRAP_RESAMPLES = 1000
#: Seed of the bootstrap's random generator (results are reproducible).
BOOTSTRAP_SEED = 2458116
#: The block length is capped so that the band holds at least this many blocks.
BOOTSTRAP_MIN_BLOCKS = 4
#: Delay beyond which the largest delay-spectrum amplitude is reported (ns).
DELAY_REPORT_NS = 200.0


def _cbb_variance(x: np.ndarray, block: int, resamples: int, seed: int) -> float:
    """Circular block bootstrap variance of the mean of ``x`` (blocks of ``block``)."""
    n = x.size
    nblock = -(-n // block)
    rest = n - (nblock - 1) * block
    ext = np.concatenate([x, x[:block]])
    csum = np.concatenate([[0.0], np.cumsum(ext)])
    starts = np.random.default_rng(seed).integers(0, n, size=(resamples, nblock))
    lengths = np.full(nblock, block)
    lengths[-1] = rest
    sums = csum[starts + lengths] - csum[starts]
    return float(np.var(sums.sum(axis=1) / n, ddof=1))


def block_bootstrap_error(
    values: np.ndarray,
    freqs: np.ndarray,
    *,
    block_mhz: float = BOOTSTRAP_BLOCK_MHZ,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> tuple[float, dict[str, Any]]:
    """Error of the mean over channels of values correlated in frequency.

    A circular block bootstrap over the channels (in frequency order, flagged channels
    dropped) with blocks of ``block_mhz`` (at most a quarter of the channels, at least
    one). Its variance is biased low by the correlation beyond a block (``~ c / L``) and
    by the subtracted sample mean (``~ L / N``); both are corrected: Richardson
    extrapolation from blocks of ``L`` and ``L / 2``, ``V = max(V_L, 2 V_L - V_{L/2})``,
    then division by ``1 - 1.5 L / N`` (``1 - 1 / N`` for ``L = 1``, the plain
    bootstrap).

    Parameters
    ----------
    values
        ``(N,)`` finite values.
    freqs
        ``(N,)`` their frequencies in Hz, increasing.
    block_mhz
        Block length in MHz.
    resamples
        Number of bootstrap resamples.
    seed
        Seed of the random generator.

    Returns
    -------
    error, info
        The 1-sigma error of ``mean(values)`` (NaN for fewer than two values) and the
        block length used (channels and MHz), the resamples and the seed.
    """
    x = np.asarray(values, dtype=np.float64)
    f = np.asarray(freqs, dtype=np.float64)
    n = x.size
    info: dict[str, Any] = {"resamples": int(resamples), "seed": int(seed)}
    if n < 2:
        return float("nan"), {**info, "block_channels": None, "block_MHz": None}
    width = float(np.median(np.abs(np.diff(f)))) if n > 1 else 0.0
    block = round(block_mhz * 1e6 / width) if width > 0 else 1
    block = int(np.clip(block, 1, max(1, n // BOOTSTRAP_MIN_BLOCKS)))
    var = _cbb_variance(x, block, resamples, seed)
    if block >= 2:
        half = _cbb_variance(x, block // 2, resamples, seed)
        var = max(var, 2.0 * var - half)
        var /= max(1.0 - 1.5 * block / n, 0.25)
    else:
        var /= 1.0 - 1.0 / n
    info.update(block_channels=block, block_MHz=block * width / 1e6)
    return float(np.sqrt(var)), info


def ratio_statistics(
    ratio: np.ndarray,
    sigma: np.ndarray,
    valid: np.ndarray,
    nvalid_auto: int,
    nfreq: int,
) -> dict[str, Any]:
    """Return the ratio's statistics over the valid channels of one antenna/polarisation.

    Parameters
    ----------
    ratio, sigma
        ``(Nfreq,)`` ratio and its 1-sigma error.
    valid
        ``(Nfreq,)`` channels compared.
    nvalid_auto
        Number of channels valid in the solution.
    nfreq
        Number of the solution's channels.

    Returns
    -------
    dict
        Channel counts and, when a channel is compared, the ratio's mean, median, rms
        (about its mean and about 1), range, median error, the error of the mean from
        independent channels, pulls ``(r - 1) / sigma`` and shape pulls
        ``(r - mean) / sigma``.
    """
    r = ratio[valid]
    s = sigma[valid]
    n = int(r.size)
    out: dict[str, Any] = {
        "n_channels": nfreq,
        "n_compared": n,
        "n_auto_valid": nvalid_auto,
    }
    if n == 0:
        return out
    mean = float(np.mean(r))
    pulls = (r - 1.0) / s
    shape_pulls = (r - mean) / s
    finite = np.isfinite(pulls)
    sigma_mean = float(np.sqrt(np.sum(s**2)) / n)
    out.update(
        ratio_mean=mean,
        ratio_median=float(np.median(r)),
        ratio_rms=float(np.sqrt(np.mean((r - mean) ** 2))),
        ratio_rms_about_one=float(np.sqrt(np.mean((r - 1.0) ** 2))),
        ratio_min=float(r.min()),
        ratio_max=float(r.max()),
        sigma_ratio_median=float(np.median(s)),
        sigma_of_ratio_mean=sigma_mean,
        offset_sigma=float((mean - 1.0) / sigma_mean) if sigma_mean > 0 else None,
        pull_rms=float(np.sqrt(np.mean(pulls[finite] ** 2))) if finite.any() else None,
        shape_pull_rms=float(np.sqrt(np.mean(shape_pulls[finite] ** 2))) if finite.any() else None,
        chi2_per_channel=float(np.mean(pulls[finite] ** 2)) if finite.any() else None,
        fraction_within_2sigma=float(np.mean(np.abs(pulls[finite]) <= 2.0))
        if finite.any()
        else None,
    )
    return out


def broadband_offset(
    ratio: np.ndarray,
    sigma: np.ndarray,
    valid: np.ndarray,
    freqs: np.ndarray,
    ref_common_rel: float,
    auto_sys_rel: np.ndarray | None,
    sigma_no_sys: np.ndarray | None = None,
) -> dict[str, Any]:
    """Return the broadband offset ``mean(r) - 1`` and its error (procedure step 8).

    Parameters
    ----------
    ratio, sigma
        ``(Nfreq,)`` ratio and its 1-sigma error.
    valid
        ``(Nfreq,)`` channels compared.
    freqs
        ``(Nfreq,)`` Hz.
    ref_common_rel
        The reference's band-averaged scatter over time, relative (common to all
        channels).
    auto_sys_rel
        ``(Nfreq,)`` the auto's systematic ``|g|`` error, relative, taken as fully
        correlated across channels, or ``None``.
    sigma_no_sys
        The per-channel ratio error with the auto's statistical error only (for the
        ``*_without_auto_systematic`` entries), or ``None``.

    Returns
    -------
    dict
        ``offset``, ``offset_error``, ``offset_sigma`` and the error's parts.
    """
    r = ratio[valid]
    n = r.size
    if n == 0:
        return {"offset": None, "offset_error": None}
    s = sigma[valid]
    mean = float(np.mean(r))
    boot, info = block_bootstrap_error(r, freqs[valid])
    indep = float(np.sqrt(np.nansum(s**2)) / n)
    channel = float(np.nanmax([boot, indep]))
    ref_common = mean * ref_common_rel if np.isfinite(ref_common_rel) else 0.0
    auto_sys = 0.0
    if auto_sys_rel is not None:
        a = auto_sys_rel[valid]
        if np.isfinite(a).any():
            auto_sys = float(np.mean(r[np.isfinite(a)] * a[np.isfinite(a)]))
    err = float(np.sqrt(channel**2 + ref_common**2 + auto_sys**2))
    offset = mean - 1.0
    err_stat = None
    if sigma_no_sys is not None and auto_sys_rel is not None:
        indep_stat = float(np.sqrt(np.nansum(sigma_no_sys[valid] ** 2)) / n)
        err_stat = float(np.sqrt(np.nanmax([boot, indep_stat]) ** 2 + ref_common**2))
    return {
        "offset": offset,
        "offset_error": err,
        "offset_sigma": offset / err if err > 0 else None,
        "offset_error_bootstrap": boot,
        "offset_error_independent": indep,
        "offset_sigma_independent": offset / indep if indep > 0 else None,
        "offset_error_reference_common": ref_common,
        "offset_error_auto_systematic": auto_sys,
        "offset_error_without_auto_systematic": err_stat,
        "offset_sigma_without_auto_systematic": offset / err_stat if err_stat else None,
        "bootstrap": info,
    }


def ratio_delay_spectra(
    ratio: np.ndarray, valid: np.ndarray, freqs: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Return the delay spectra of the mean-subtracted ratio of every antenna/polarisation.

    Parameters
    ----------
    ratio
        ``(Nant, Npol, Nfreq)``.
    valid
        Like ``ratio``: channels compared.
    freqs
        ``(Nfreq,)`` Hz.

    Returns
    -------
    delays, amplitude
        ``(Ndelay,)`` seconds and ``(Nant, Npol, Ndelay)`` normalised amplitudes (NaN
        for rows with fewer than 4 valid channels), or ``None, None`` for fewer than 4
        or non-uniform channels.
    """
    if freqs.size < 4:
        return None, None
    steps = np.diff(freqs)
    if not np.allclose(steps, steps[0], rtol=1e-6, atol=0.0):
        logger.warning("channels are not uniformly spaced: no delay spectrum of the ratio")
        return None, None
    nant, npol, _ = ratio.shape
    amps = None
    delays = None
    for ia in range(nant):
        for ip in range(npol):
            if valid[ia, ip].sum() < 4:
                continue
            try:
                spec = delay_spectrum(
                    ratio[ia, ip], freqs, flags=~valid[ia, ip], subtract_mean=True
                )
            except DelayError as err:  # pragma: no cover - guarded above
                logger.warning("no delay spectrum for antenna index %d: %s", ia, err)
                continue
            if amps is None:
                delays = spec.delays
                amps = np.full((nant, npol, delays.size), np.nan)
            amps[ia, ip] = spec.amplitude
    return delays, amps


def delay_peak(delays: np.ndarray | None, amplitude: np.ndarray | None) -> dict[str, Any]:
    """Return the largest delay-spectrum amplitude beyond :data:`DELAY_REPORT_NS`.

    Parameters
    ----------
    delays
        ``(Ndelay,)`` seconds, or ``None``.
    amplitude
        ``(Ndelay,)`` one antenna/polarisation's delay spectrum, or ``None``.

    Returns
    -------
    dict
        ``delay_max_beyond_ns``, ``delay_max_amplitude`` and ``delay_of_max_ns``, or
        empty when there is no finite amplitude beyond the limit.
    """
    out: dict[str, Any] = {}
    if amplitude is not None and delays is not None:
        beyond = delays * 1e9 > DELAY_REPORT_NS
        row = amplitude
        if beyond.any() and np.isfinite(row[beyond]).any():
            k = int(np.nanargmax(np.where(beyond, row, np.nan)))
            out["delay_max_beyond_ns"] = DELAY_REPORT_NS
            out["delay_max_amplitude"] = float(row[k])
            out["delay_of_max_ns"] = float(delays[k] * 1e9)
    return out
