"""The reference gains on the solution's channels: time selection, averaging, interpolation.

:func:`prepare_reference` runs steps 1-6 of the procedure in
:mod:`autocal.compare.comparison`: it selects the reference times matching the solution
(:func:`select_reference_times`), measures the reference's drift
(:func:`~autocal.compare.drift.fractional_end_change`), optionally smooths each time along
frequency (:func:`smooth_frequency`), averages over time with the scatter as the error
(:func:`time_average`) and interpolates onto the solution's channels
(:func:`interpolate_frequency`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from autocal.compare.axes import MatchedAxes
from autocal.compare.drift import fractional_end_change
from autocal.compare.errors import CompareError

if TYPE_CHECKING:
    from autocal.io.calsol_read import ReferenceGains

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class PreparedReference:
    """The reference averaged over the selected times and interpolated (before conversion).

    Arrays are ``(Nant, Npol, ...)`` over the compared antennas and polarisations.

    Attributes
    ----------
    times
        Indices of the selected reference times.
    time_info
        How they were selected (:func:`select_reference_times`).
    band
        ``(Nref,)`` reference channels inside the solution's band.
    drifts
        ``[ant][pol]`` :func:`~autocal.compare.drift.fractional_end_change` of
        ``|g_ref|^2`` over the selected times, on ``band``.
    amplitude, sigma
        ``(Nant, Npol, Nfreq)`` time-averaged ``|g_ref|`` and its scatter over time on the
        solution's channels (NaN outside the reference's range and in flagged gaps).
    common_rel
        ``(Nant, Npol)`` the band-averaged scatter over time, relative (zero in relative
        mode).
    """

    times: np.ndarray
    time_info: dict[str, Any]
    band: np.ndarray
    drifts: list[list[dict[str, Any]]]
    amplitude: np.ndarray
    sigma: np.ndarray
    common_rel: np.ndarray


def select_reference_times(
    ref_jds: np.ndarray, jds: np.ndarray
) -> tuple[np.ndarray, dict[str, Any]]:
    """Pick the reference solution times matching a solution's JD span.

    Parameters
    ----------
    ref_jds
        ``(Ntime_ref,)`` reference JDs (increasing).
    jds
        The solution's fitted JDs.

    Returns
    -------
    indices, info
        Indices into ``ref_jds`` and a description (``match`` = ``"overlap"`` or
        ``"nearest"``, counts, JD ranges, the reference's integration step, the fraction
        of the solution's span the selected reference times cover, offset in days for
        ``"nearest"``).

    Notes
    -----
    The selected times are averaged (:func:`time_average`) and their scatter is the
    reference's uncertainty; a single ``"nearest"`` time has no scatter, so the
    reference's uncertainty is then unknown (and the drift not measurable).
    """
    ref_jds = np.asarray(ref_jds, dtype=np.float64)
    jds = np.asarray(jds, dtype=np.float64)
    lo, hi = float(jds.min()), float(jds.max())
    step = float(np.median(np.diff(ref_jds))) if ref_jds.size > 1 else 0.0
    tol = max(step / 2.0, 1.0 / 86400.0)
    inside = np.flatnonzero((ref_jds >= lo - tol) & (ref_jds <= hi + tol))
    info: dict[str, Any] = {
        "solution_jd_range": [lo, hi],
        "reference_jd_range": [float(ref_jds.min()), float(ref_jds.max())],
        "reference_step_s": step * 86400.0,
        "ntimes_reference": int(ref_jds.size),
    }
    if inside.size:
        span = hi - lo
        covered = float(np.ptp(ref_jds[inside]) + step)
        info.update(
            match="overlap",
            ntimes=int(inside.size),
            span_coverage=float(min(1.0, covered / (span + step))) if span + step > 0 else 1.0,
        )
        return inside, info
    mid = 0.5 * (lo + hi)
    best = int(np.argmin(np.abs(ref_jds - mid)))
    offset = float(ref_jds[best] - mid)
    logger.warning(
        "no reference time overlaps the solution's JDs %.5f-%.5f; using the nearest "
        "reference time %.5f (%.3f days away)",
        lo,
        hi,
        ref_jds[best],
        offset,
    )
    info.update(match="nearest", ntimes=1, offset_days=offset, span_coverage=0.0)
    return np.array([best]), info


def time_average(
    amp: np.ndarray, *, error: str = "scatter"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average ``|g|`` over the time axis (-2) ignoring NaN.

    Parameters
    ----------
    amp
        ``(..., Ntime, Nfreq)`` amplitudes, NaN where flagged.
    error
        ``"scatter"`` (default): the per-channel uncertainty is the standard deviation
        over time, ``std_t(|g|, ddof=1)``, the error of a single-time reference (a
        calibration that varies over a span in which the gain should be constant does
        not become more accurate by averaging). ``"sem"``: the standard error of the
        mean, ``std / sqrt(N)``, only right for independent noise in time.

    Returns
    -------
    average, sigma, count
        ``sqrt(mean |g|^2)``, the uncertainty (NaN where fewer than two samples) and
        the sample counts, each ``(..., Nfreq)``.
    """
    if error not in ("scatter", "sem"):
        raise CompareError(f"error must be 'scatter' or 'sem', got {error!r}")
    finite = np.isfinite(amp)
    count = finite.sum(axis=-2)
    filled = np.where(finite, amp, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_sq = (filled**2).sum(axis=-2) / count
        mean = filled.sum(axis=-2) / count
        var = (np.where(finite, (amp - mean[..., None, :]) ** 2, 0.0)).sum(axis=-2) / (count - 1)
        if error == "sem":
            var = var / count
        sigma = np.where(count >= 2, np.sqrt(var), np.nan)
        avg = np.where(count > 0, np.sqrt(mean_sq), np.nan)
    return avg, sigma, count


def smooth_frequency(
    freqs: np.ndarray, values: np.ndarray, sigma: np.ndarray, fwhm_mhz: float
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth along frequency with a Gaussian kernel of FWHM ``fwhm_mhz`` (normalised).

    Only finite values contribute; non-finite channels stay NaN. The uncertainty is
    ``sqrt(sum w^2 sigma^2) / sum w`` (independent channels; NaN sigmas count as 0).

    Parameters
    ----------
    freqs
        ``(Nfreq,)`` Hz.
    values, sigma
        ``(..., Nfreq)``.
    fwhm_mhz
        Kernel FWHM in MHz (> 0).

    Returns
    -------
    smoothed, smoothed_sigma
        Like ``values``.
    """
    if not (np.isfinite(fwhm_mhz) and fwhm_mhz > 0):
        raise CompareError(f"the smoothing width must be a positive number of MHz, got {fwhm_mhz}")
    f = np.asarray(freqs, dtype=np.float64) / 1e6
    s = fwhm_mhz / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    kernel = np.exp(-0.5 * ((f[:, None] - f[None, :]) / s) ** 2)  # (out, in)
    ok = np.isfinite(values)
    v = np.where(ok, values, 0.0)
    e = np.where(ok & np.isfinite(sigma), sigma, 0.0)
    w = ok.astype(np.float64)
    wsum = w @ kernel.T
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (v * w) @ kernel.T / wsum
        err = np.sqrt((e**2 * w) @ (kernel**2).T) / wsum
    return np.where(ok, out, np.nan), np.where(ok & np.isfinite(sigma), err, np.nan)


def interpolate_frequency(
    ref_freqs: np.ndarray, values: np.ndarray, freqs: np.ndarray
) -> np.ndarray:
    """Linearly interpolate ``(..., Nref)`` values onto ``freqs``.

    A target channel is NaN outside the reference range or where a bracketing reference
    channel is NaN (flagged gaps are never bridged).
    """
    ref_freqs = np.asarray(ref_freqs, dtype=np.float64)
    freqs = np.asarray(freqs, dtype=np.float64)
    flat = values.reshape(-1, ref_freqs.size)
    out = np.full((flat.shape[0], freqs.size), np.nan)
    inside = (freqs >= ref_freqs[0] - 1.0) & (freqs <= ref_freqs[-1] + 1.0)
    target = np.clip(freqs, ref_freqs[0], ref_freqs[-1])
    for i, row in enumerate(flat):
        ok = np.isfinite(row)
        if ref_freqs.size == 1:
            out[i] = np.where(inside & ok[0], row[0], np.nan)
            continue
        val = np.interp(target, ref_freqs, np.where(ok, row, 0.0))
        good = np.interp(target, ref_freqs, ok.astype(np.float64))
        out[i] = np.where(inside & (good > 1.0 - 1e-6), val, np.nan)
    return out.reshape((*values.shape[:-1], freqs.size))


def _nanmean(x: np.ndarray, axis: int, keepdims: bool = False) -> np.ndarray:
    """NaN-ignoring mean without warnings (NaN where nothing is finite)."""
    ok = np.isfinite(x)
    n = ok.sum(axis=axis, keepdims=keepdims)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.where(ok, x, 0.0).sum(axis=axis, keepdims=keepdims) / n, np.nan)


def _nanstd(x: np.ndarray, axis: int) -> np.ndarray:
    """NaN-ignoring standard deviation (``ddof=1``), NaN with fewer than two values."""
    ok = np.isfinite(x)
    n = ok.sum(axis=axis)
    mean = _nanmean(x, axis, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        var = np.where(ok, (x - mean) ** 2, 0.0).sum(axis=axis) / (n - 1)
        return np.where(n >= 2, np.sqrt(var), np.nan)


def prepare_reference(
    reference: ReferenceGains,
    axes: MatchedAxes,
    solution_jds: np.ndarray,
    mode: str,
    smooth_mhz: float | None,
) -> PreparedReference:
    """Select, average and interpolate the reference (procedure steps 1-6).

    Parameters
    ----------
    reference
        The reference gains.
    axes
        The matched axes (:func:`~autocal.compare.axes.index_axes`).
    solution_jds
        The solution's fitted JDs.
    mode
        ``"absolute"`` or ``"relative"`` (relative: each time is divided by its mean over
        the band first, and the band-averaged scatter is not an error).
    smooth_mhz
        FWHM (MHz) of the Gaussian smoothing along frequency, or ``None``/0 for none.

    Returns
    -------
    PreparedReference
        The reference on the solution's channels, in the reference's units.
    """
    freqs, ref_freqs = axes.freqs, axes.ref_freqs
    tsel, time_info = select_reference_times(reference.jds, solution_jds)
    amp = reference.abs_g[np.ix_(axes.ref_antennas, axes.ref_pols, tsel, np.arange(ref_freqs.size))]
    band = (ref_freqs >= freqs.min() - 1.0) & (ref_freqs <= freqs.max() + 1.0)
    drifts = [
        [fractional_end_change(amp[ia, ip][:, band] ** 2) for ip in range(len(axes.pols))]
        for ia in range(len(axes.antennas))
    ]
    amp_t = amp
    if mode == "relative":
        # redcal's overall amplitude per time is degenerate: it must not count as scatter
        amp_t = amp / _nanmean(np.where(band, amp, np.nan), axis=-1, keepdims=True)
    if smooth_mhz:
        amp_t, _ = smooth_frequency(ref_freqs, amp_t, np.zeros_like(amp_t), float(smooth_mhz))
    ref_avg, ref_sig, _ = time_average(amp_t, error="scatter")
    with np.errstate(invalid="ignore", divide="ignore"):
        band_level = _nanmean(amp_t[..., band] / ref_avg[..., None, band], axis=-1)  # (A, P, T)
    ref_common_rel = _nanstd(band_level, axis=-1)  # (A, P): the band-averaged scatter
    if mode == "relative":
        ref_common_rel = np.zeros_like(ref_common_rel)
    ref_i = interpolate_frequency(ref_freqs, ref_avg, freqs)
    sig_i = interpolate_frequency(ref_freqs, np.where(np.isfinite(ref_avg), ref_sig, np.nan), freqs)
    sig_i = np.where(np.isfinite(ref_i), sig_i, np.nan)
    return PreparedReference(
        times=tsel,
        time_info=time_info,
        band=band,
        drifts=drifts,
        amplitude=ref_i,
        sigma=sig_i,
        common_rel=ref_common_rel,
    )
