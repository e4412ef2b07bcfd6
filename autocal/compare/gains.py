r"""Compare gains from auto-correlations with gains from cross-correlation calibration.

autocal fits ``R = G (Tsky + Trxr)`` per antenna, polarisation and channel, so its gain
amplitude ``|g_auto| = sqrt(G)`` is in ``sqrt(raw / K)``: ``R / |g_auto|^2`` is an
antenna temperature in kelvin. Cross-correlation calibration (hera_cal) provides complex
gains ``g_ref`` in the *divide* convention, ``V_cal = V_raw / (g_i g_j^*)``, so for an
auto-correlation ``R / |g_ref|^2`` is the calibrated power.

Absolute references (abscal, Jy-referenced)
-------------------------------------------
abscal's ``R / |g_ref|^2`` is in Jy. For a peak-normalised power beam ``A`` (``A = 1`` at
its peak, the normalisation that makes a point source of flux ``S`` at the peak read
``S`` Jy), an auto-correlation in Jy is the beam-weighted specific intensity,
``V_Jy = 1e26 * \oint A(n) I(n) d\Omega``. In the Rayleigh-Jeans limit
``I = 2 k_B T / lambda^2``, so for the beam-weighted temperature autocal models,
``Tsky = \oint A T d\Omega / \oint A d\Omega`` (ground below the horizon included),

    V_Jy = 2 k_B Tsky Omega_A / lambda^2 * 1e26,   Omega_A = \oint A / A_peak d\Omega,

with ``Omega_A`` integrated over the *whole* sphere, exactly the denominator of autocal's
``Tsky`` (the ground seen below the horizon radiates too). Writing
``J(nu) = 2 k_B Omega_A / lambda^2 * 1e26`` (Jy per K) and equating the raw power,

    R = |g_ref|^2 V_Jy = |g_ref|^2 J T = |g_auto|^2 T
    =>  |g_auto|^2 = |g_ref|^2 J(nu),   |g_ref,K| = |g_ref| sqrt(J(nu)).

The comparison is ``|g_auto| / |g_ref,K|``, expected to be 1. Sanity check (README of the
data folder: "raw/|g|^2 ~ 6900 Jy ~ 255 K at 150 MHz for antenna 23"): the Fagnoni beam
gives ``Omega_A = 0.0411 sr`` at 150 MHz, ``J = 28.42 Jy/K``; the median of
``R / |g_ref|^2`` for antenna 23 (ee, 36 integrations, 11 channels around 150 MHz) is
7030 Jy = 247 K (nn: 6530 Jy = 230 K). The README's 255 K corresponds to
``Omega_A = 0.039 sr``, hera_sim's integral of its H1C beam model.
``Omega_A`` is computed from autocal's beam objects on a HEALPix grid
(:func:`beam_solid_angle`) and, for UVBeam files, cross-checked against pyuvdata's
``UVBeam.get_beam_area`` (:func:`uvbeam_solid_angle`). A reference with
``gain_scale = "K"`` (an autocal calh5) is compared without conversion.

The conversion assumes the V_Jy convention above for a single linear polarisation
(``V_xx = \oint A_xx I d\Omega``, HERA's pseudo-Stokes convention ``pI = (XX + YY) / 2``);
a flux scale defined with ``I/2`` per polarisation would change ``J`` by a factor 2.

Relative references (redcal/omnical)
------------------------------------
Redundant calibration leaves an overall amplitude (per polarisation, channel and time)
undetermined and fixes it near unity, so only the *shape* of ``|g|`` across frequency
can be compared: each of ``|g_auto|`` and ``|g_ref|`` is divided by its mean over the
channels valid in both, and the ratio of the normalised amplitudes is compared with 1.
(The degeneracy is common to all antennas, so an array-wide bandpass slope is not
constrained by such a reference; antenna-to-antenna differences are.)

Procedure
---------
1. Reference times: those overlapping the solution's JD span (within half a reference
   integration); if none overlap, the single nearest time (logged, recorded).
2. Reference drift (:func:`fractional_end_change`, per antenna and polarisation, on the
   reference channels inside the solution's band): the fractional change of
   ``|g_ref|^2`` between the means of the first and last :data:`DRIFT_END_FRACTION` of
   the selected integrations (median over channels) and its rms over time, set against
   the raw auto's own change over the same span when the caller supplies it
   (``auto_drift``; :func:`auto_trend` computes it from the raw autos with the same
   statistic). The reference is *unstable* (``reference_stable: false``) when

   * ``|reference change| > REFERENCE_DRIFT_FACTOR |auto change| + REFERENCE_DRIFT_ALLOWANCE``
     (3x and 5 %: an antenna's gain cannot change by much more than its raw power did,
     and the sky changes the raw power by a few per cent over half an hour), or
   * (absolute mode) ``R / (|g_ref|^2 J) - Tsky``, the receiver temperature the
     reference implies, has a negative median over channels at the first or the last
     end of the span (needs ``auto_power_ends`` and ``tsky_ends``).

   A clause whose inputs are missing is skipped and listed as such; with no testable
   clause ``reference_stable`` is ``null``. Relative references are not tested (their
   overall amplitude per time is a calibration degeneracy).
3. Relative mode only: each reference integration is divided by its mean over the
   compared band (that degenerate amplitude must not count as scatter).
4. Optional smoothing of each reference integration along frequency with a Gaussian
   kernel of FWHM ``smooth_mhz`` MHz (normalised over unflagged channels; flagged
   channels stay flagged).
5. Time average ``|g_ref| = sqrt(mean_t |g_ref(t)|^2)`` (like autocal's time-averaged
   ``G``), flagged samples excluded. Its per-channel uncertainty is the *scatter over
   time*, ``std_t(|g_ref(t)|)`` (``ddof=1``), the error a single-time reference would
   have -- not ``std / sqrt(N_t)``: the reference's variation over a span in which the
   gain should be constant is a calibration error that does not average down (unknown,
   NaN, with one time: the ratio's uncertainty is then the autos' alone).
6. Linear interpolation onto the solution's channels, only inside the reference's range
   and only between unflagged reference channels.
7. Conversion (absolute) or normalisation (relative), ratio
   ``r = |g_auto| / |g_ref|``, its uncertainty
   ``sigma_r = r sqrt((sigma_auto/|g_auto|)^2 + (sigma_ref/|g_ref|)^2)`` with the auto's
   ``solution.sigma_abs_g`` (the total error when the solution carries one), the
   agreement ``(r - 1) / sigma_r`` and the delay spectrum of ``r``.
8. The broadband offset ``mean(r) - 1`` over the compared channels and its error
   (:func:`block_bootstrap_error`): a circular block bootstrap over channels (blocks of
   :data:`BOOTSTRAP_BLOCK_MHZ`, :data:`BOOTSTRAP_RESAMPLES` resamples, seeded),
   bias-corrected for the block length (Richardson extrapolation from blocks of ``L``
   and ``L/2``) and for the subtracted sample mean, never below the independent-channel
   error ``sqrt(sum sigma_r^2) / N``; added in quadrature, the errors common to all
   channels that no resampling of channels can see: the reference's band-averaged
   scatter over time and the auto's systematic error (``sigma_abs_g^2 -
   sigma_abs_g_stat^2``, taken as fully correlated across channels).
9. Systematics budget (absolute mode, per antenna and polarisation): the ratio's shift
   if ``Omega_A`` came from hera_sim's H1C beam integrals (``omega_source``; the ratio
   scales as ``Omega_A^-1/2``), under the other pseudo-Stokes convention
   (``pol_convention``) and over alternative sky models (``sky_model``).

Pseudo-Stokes convention
------------------------
pyuvdata's ``UVCal.pol_convention`` (``POLCONV`` in calfits, ``Header/pol_convention``
in calh5) is ``"avg"`` (``I = (XX + YY) / 2``, a calibrated XX auto reads ``I``) or
``"sum"`` (``I = XX + YY``, XX reads ``I / 2``). For the same raw auto, 'sum' gains give
half the Jy, so ``|g_sum|^2 = 2 |g_avg|^2`` and ``|g_ref,K| = |g_ref| sqrt(J / 2)``: the
ratio ``|g_auto| / |g_ref,K|`` is ``sqrt(2)`` *larger* under 'sum' than under 'avg'. The
convention the file states is applied; a file that states none is taken as 'avg'
(HERA's pseudo-Stokes convention, recorded as "assumed") and the 'sum' alternative is
reported in the budget.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from autocal.errors import AutocalError

if TYPE_CHECKING:
    from autocal.fit.lsq import Solution
    from autocal.io.calsol import ReferenceGains

logger = logging.getLogger(__name__)

#: Boltzmann constant, J/K.
K_B = 1.380649e-23
#: Speed of light, m/s.
C_LIGHT = 299792458.0
#: One jansky in W m^-2 Hz^-1.
JANSKY = 1e-26
#: Delay beyond which the largest delay-spectrum amplitude is reported (ns).
DELAY_REPORT_NS = 200.0
#: Default HEALPix resolution for beams that are not HEALPix files.
DEFAULT_NSIDE = 128
#: Output file names written by :func:`write_comparison`.
OUTPUT_NAMES = {"json": "compare.json", "png": "compare.png", "h5": "compare.h5"}
#: Fraction of the integrations averaged at each end of the span to measure a drift.
DRIFT_END_FRACTION = 0.1
#: Stability rule: the reference is unstable when its fractional change of ``|g|^2``
#: exceeds ``REFERENCE_DRIFT_FACTOR * |auto change| + REFERENCE_DRIFT_ALLOWANCE``.
REFERENCE_DRIFT_FACTOR = 3.0
#: See :data:`REFERENCE_DRIFT_FACTOR` (a fraction: 0.05 = 5 %).
REFERENCE_DRIFT_ALLOWANCE = 0.05
#: Block length (MHz) of the block bootstrap of the mean ratio over channels.
BOOTSTRAP_BLOCK_MHZ = 5.0
#: Number of bootstrap resamples.
BOOTSTRAP_RESAMPLES = 1000
#: Seed of the bootstrap's random generator (results are reproducible).
BOOTSTRAP_SEED = 2458116
#: The block length is capped so that the band holds at least this many blocks.
BOOTSTRAP_MIN_BLOCKS = 4
#: hera_sim's H1C beam integrals (``freqs`` in GHz, ``omega_p`` in sr), data-folder path.
HERA_SIM_BEAM_INTEGRALS = "hera/instrument/HERA_H1C_BEAM_INTEGRALS.npz"
#: Pseudo-Stokes convention assumed when the reference file states none (HERA's).
DEFAULT_POL_CONVENTION = "avg"


class CompareError(AutocalError):
    """The solution and the reference cannot be compared as asked."""


# ---------------------------------------------------------------------------------------
# units
# ---------------------------------------------------------------------------------------
def jy_per_kelvin(freqs: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Return ``J = 2 k_B Omega_A / lambda^2 * 1e26``: Jy of an auto per K of antenna temperature.

    Parameters
    ----------
    freqs
        Hz.
    omega
        Beam solid angle ``Omega_A`` (sr) of the peak-normalised power beam, same shape.

    Returns
    -------
    numpy.ndarray
        Jy per K.
    """
    lam = C_LIGHT / np.asarray(freqs, dtype=np.float64)
    return 2.0 * K_B * np.asarray(omega, dtype=np.float64) / lam**2 / JANSKY


def _beam_pol(pol: str) -> str:
    pol = pol.lower()
    alias = {"xx": "ee", "yy": "nn"}
    if pol in alias:
        logger.info("using the %s beam for polarisation %s (x feed east)", alias[pol], pol)
    return alias.get(pol, pol)


def resolve_beam(beam: Any, pol: str = "ee") -> Any:
    """Resolve a beam for solid-angle integrals.

    ``"hera"`` and UVBeam file paths give a
    :class:`~autocal.sky.beams.HealpixFileBeam` at the file's own resolution (no harmonic
    upsampling, whose ringing would bias the peak); other specifications go through
    :func:`autocal.sky.beams.get_beam`.
    """
    from autocal.io.datasets import HERA_BEAM_FILE, data_file
    from autocal.sky.beams import Beam, HealpixFileBeam, get_beam

    pol = _beam_pol(pol)
    if isinstance(beam, Beam):
        return beam
    spec = str(beam).strip()
    if spec.lower() == "hera":
        return HealpixFileBeam(data_file(HERA_BEAM_FILE, "HERA Fagnoni beam"), pol, 0)
    path = Path(spec).expanduser()
    if path.suffix.lower() in {".beamfits", ".fits", ".h5", ".uvbeam"}:
        return HealpixFileBeam(path, pol, 0)
    return get_beam(spec, pol)


def beam_from_config(config: dict[str, Any] | None) -> str:
    """Return the beam specification a solution's configuration records, else ``"hera"``.

    Looks for ``beam`` at the top level and in the ``provenance``/``calibration``
    sections: a name or path string, or a beam description (``{"file": ...}``,
    ``{"beam": "gaussian_dipole" | "airy"}``).
    """
    from autocal.io.calsol import config_sources

    for source in config_sources(config):
        value = source.get("beam")
        if isinstance(value, str) and value.strip():
            return value.strip()
        if isinstance(value, dict):
            if value.get("file"):
                return str(value["file"])
            kind = {"gaussian_dipole": "dipole", "airy": "airy"}.get(str(value.get("beam")))
            if kind:
                return kind
    logger.warning("the solution records no usable beam; using the HERA beam for Omega_A")
    return "hera"


def beam_solid_angle(
    beam: Any, freqs: np.ndarray, *, pol: str = "ee", nside: int | None = None
) -> np.ndarray:
    """Return ``Omega_A(nu)``, the peak-normalised beam integrated over the whole sphere.

    The beam is evaluated at the centres of a RING HEALPix grid (plus the zenith, for the
    peak) and summed times the pixel area.

    Parameters
    ----------
    beam
        A :class:`~autocal.sky.beams.Beam` or a specification for :func:`resolve_beam`.
    freqs
        Hz.
    pol
        ``"ee"`` or ``"nn"``.
    nside
        HEALPix resolution (default: a HEALPix file beam's own, else 128).

    Returns
    -------
    numpy.ndarray
        ``(Nfreq,)`` steradians.
    """
    import healpy as hp

    from autocal.sky.beams import HealpixFileBeam

    b = resolve_beam(beam, pol)
    freqs = np.atleast_1d(np.asarray(freqs, dtype=np.float64))
    if nside is None:
        nside = b.data.nside if isinstance(b, HealpixFileBeam) else DEFAULT_NSIDE
    npix = hp.nside2npix(nside)
    theta, phi = hp.pix2ang(nside, np.arange(npix))
    az = np.mod(np.pi / 2 - phi, 2 * np.pi)  # pixel phi: azimuth east through north
    za = np.append(theta, 0.0)
    az = np.append(az, 0.0)
    evaluate = b.on(az, za)
    out = np.empty(freqs.size)
    chunk = max(1, int(4e6 // npix))
    for start in range(0, freqs.size, chunk):
        power = np.asarray(evaluate(freqs[start : start + chunk]), dtype=np.float64)
        peak = power.max(axis=1)
        if np.any(~(peak > 0)):
            raise CompareError(f"the beam {b.name} is not positive anywhere at some frequency")
        out[start : start + chunk] = power[:, :-1].sum(axis=1) * hp.nside2pixarea(nside) / peak
    return out


def uvbeam_solid_angle(path: str | Path, freqs: np.ndarray, pol: str = "ee") -> np.ndarray:
    """``Omega_A`` from pyuvdata's ``UVBeam.get_beam_area`` (peak-normalised), cubic in frequency.

    Parameters
    ----------
    path
        A power-beam file pyuvdata reads (e.g. the HERA beamfits).
    freqs
        Hz, inside the file's frequency range.
    pol
        ``"ee"`` or ``"nn"``.

    Returns
    -------
    numpy.ndarray
        ``(Nfreq,)`` steradians.
    """
    import warnings

    from pyuvdata import UVBeam
    from scipy.interpolate import CubicSpline

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        uvb = UVBeam.from_file(str(path))
        if uvb.data_normalization != "peak":
            uvb.peak_normalize()
        area = np.real(uvb.get_beam_area(_beam_pol(pol)))
    native = np.asarray(uvb.freq_array, dtype=np.float64).ravel()
    freqs = np.asarray(freqs, dtype=np.float64)
    if freqs.min() < native.min() - 1 or freqs.max() > native.max() + 1:
        raise CompareError(
            f"frequencies {freqs.min() / 1e6:.3f}-{freqs.max() / 1e6:.3f} MHz are outside "
            f"the beam file's {native.min() / 1e6:.3f}-{native.max() / 1e6:.3f} MHz"
        )
    return CubicSpline(native, area)(freqs)


# ---------------------------------------------------------------------------------------
# reference preparation
# ---------------------------------------------------------------------------------------
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


def fractional_end_change(
    values: np.ndarray, *, end_fraction: float = DRIFT_END_FRACTION
) -> dict[str, Any]:
    """Measure how a positive quantity moves over a span (a drift), robustly.

    The integrations with at least one finite channel are the valid ones; the first and
    the last ``k = max(1, round(end_fraction * N_valid))`` of them are averaged per
    channel (NaN-aware). The same statistic serves the reference's ``|g_ref|^2`` and the
    raw auto's power (:func:`auto_trend`), so the two are comparable.

    Parameters
    ----------
    values
        ``(Ntime, Nfreq)`` in time order, NaN where flagged.
    end_fraction
        Fraction of the valid integrations averaged at each end (0 < f <= 0.5).

    Returns
    -------
    dict
        ``change``: median over channels of ``last / first - 1`` (NaN when fewer than
        two valid integrations); ``rms``: median over channels of the rms over time of
        ``values / mean_t - 1``; ``first``, ``last``: ``(Nfreq,)`` end means; ``series``:
        ``(Ntime,)`` median over channels of ``values / mean_t``; ``n_end``, ``n_valid``;
        ``end_rows``: the integration indices averaged at the first and the last end.
    """
    if not 0 < end_fraction <= 0.5:
        raise CompareError(f"end_fraction must be in (0, 0.5], got {end_fraction}")
    x = np.asarray(values, dtype=np.float64)
    ntime, nfreq = x.shape
    nan_f = np.full(nfreq, np.nan)
    out: dict[str, Any] = {
        "change": float("nan"),
        "rms": float("nan"),
        "first": nan_f,
        "last": nan_f.copy(),
        "series": np.full(ntime, np.nan),
        "n_end": 0,
        "n_valid": 0,
        "end_rows": None,
    }
    good = np.isfinite(x) & (x > 0)
    x = np.where(good, x, np.nan)
    rows = np.flatnonzero(good.any(axis=1))
    out["n_valid"] = int(rows.size)
    if rows.size == 0:
        return out
    with np.errstate(invalid="ignore", divide="ignore"):
        count = good.sum(axis=0)
        mean = np.where(count > 0, np.where(good, x, 0.0).sum(axis=0) / count, np.nan)
        norm = x / mean
        series = np.full(ntime, np.nan)
        for t in rows:
            series[t] = np.nanmedian(norm[t])
        out["series"] = series
        dev = np.where(good, (norm - 1.0) ** 2, 0.0).sum(axis=0) / count
        rms = np.sqrt(dev[count > 0])
        out["rms"] = float(np.median(rms)) if rows.size >= 2 and rms.size else float("nan")
        if rows.size < 2:
            return out
        k = max(1, round(end_fraction * rows.size))
        k = min(k, rows.size // 2)
        first_rows, last_rows = rows[:k], rows[-k:]

        def end_mean(sel: np.ndarray) -> np.ndarray:
            n = good[sel].sum(axis=0)
            return np.where(n > 0, np.where(good[sel], x[sel], 0.0).sum(axis=0) / n, np.nan)

        first, last = end_mean(first_rows), end_mean(last_rows)
        change = last / first - 1.0
    ok = np.isfinite(change)
    out.update(
        first=first,
        last=last,
        n_end=k,
        end_rows=[first_rows.tolist(), last_rows.tolist()],
        change=float(np.median(change[ok])) if ok.any() else float("nan"),
    )
    return out


def auto_trend(
    power: np.ndarray,
    jds: np.ndarray,
    antennas: Any,
    pols: Any,
    *,
    flags: np.ndarray | None = None,
    tsky: np.ndarray | None = None,
    end_fraction: float = DRIFT_END_FRACTION,
) -> dict[str, Any]:
    """Return the raw autos' drift, end powers and time series as :func:`compare` arguments.

    Parameters
    ----------
    power
        ``(Nant, Npol, Ntime, Nfreq)`` raw auto-correlation power on the solution's
        channels (the fitted integrations of the same span).
    jds
        ``(Ntime,)`` Julian dates.
    antennas, pols
        The axes' antenna numbers and polarisation names.
    flags
        Like ``power``, ``True`` = flagged (optional).
    tsky
        ``(Npol, Ntime, Nfreq)`` or ``(Ntime, Nfreq)`` model Tsky in kelvin (optional;
        needed for the negative-Trxr clause of the stability rule).
    end_fraction
        See :func:`fractional_end_change`.

    Returns
    -------
    dict
        ``auto_drift`` ``{(ant, pol): change}``, ``auto_power_ends``
        ``{(ant, pol): (2, Nfreq)}``, ``tsky_ends`` ``{(ant, pol): (2, Nfreq)}`` (averaged
        over the same end integrations as the power) or ``None``, and ``auto_series``
        ``{(ant, pol): (jds, median over channels of power / mean_t)}``: pass it on as
        ``compare(solution, reference, **auto_trend(...))``.
    """
    p = np.asarray(power, dtype=np.float64)
    if p.ndim != 4:
        raise CompareError(f"power must be (Nant, Npol, Ntime, Nfreq), got shape {p.shape}")
    if flags is not None:
        p = np.where(np.broadcast_to(flags, p.shape), np.nan, p)
    jds = np.asarray(jds, dtype=np.float64)
    ants = [int(a) for a in np.atleast_1d(antennas)]
    pol_names = [str(q).lower() for q in (pols if not isinstance(pols, str) else [pols])]
    if p.shape[:3] != (len(ants), len(pol_names), jds.size):
        raise CompareError(
            f"power has shape {p.shape}, the axes need ({len(ants)}, {len(pol_names)}, "
            f"{jds.size}, Nfreq)"
        )
    sky = None
    if tsky is not None:
        sky = np.asarray(tsky, dtype=np.float64)
        if sky.ndim == 2:
            sky = np.broadcast_to(sky, (len(pol_names), *sky.shape))
    drift: dict[tuple[int, str], float] = {}
    ends: dict[tuple[int, str], np.ndarray] = {}
    sky_ends: dict[tuple[int, str], np.ndarray] = {}
    series: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] = {}
    for ia, ant in enumerate(ants):
        for ip, pol in enumerate(pol_names):
            stats = fractional_end_change(p[ia, ip], end_fraction=end_fraction)
            key = (ant, pol)
            drift[key] = stats["change"]
            ends[key] = np.stack([stats["first"], stats["last"]])
            series[key] = (jds.copy(), stats["series"])
            if sky is not None and stats["end_rows"] is not None:
                first_rows, last_rows = stats["end_rows"]
                sky_ends[key] = np.stack(
                    [sky[ip, first_rows].mean(axis=0), sky[ip, last_rows].mean(axis=0)]
                )
    return {
        "auto_drift": drift,
        "auto_power_ends": ends,
        "tsky_ends": sky_ends if sky is not None else None,
        "auto_series": series,
    }


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


def hera_sim_omega(freqs: np.ndarray, path: str | Path | None = None) -> np.ndarray:
    """hera_sim's H1C beam solid angle ``omega_p`` interpolated onto ``freqs``.

    Parameters
    ----------
    freqs
        Hz.
    path
        The ``HERA_H1C_BEAM_INTEGRALS.npz`` file (default: :data:`HERA_SIM_BEAM_INTEGRALS`
        in the data folder). Its ``freqs`` are in GHz (MHz or Hz are recognised by size),
        ``omega_p`` in sr, one curve for both feeds.

    Returns
    -------
    numpy.ndarray
        sr, NaN outside the table's frequency range.
    """
    from autocal.io.datasets import data_file

    if path is None:
        path = data_file(HERA_SIM_BEAM_INTEGRALS, "hera_sim H1C beam integrals")
    with np.load(path) as table:
        if "freqs" not in table or "omega_p" not in table:
            raise CompareError(f"{path} has keys {table.files}; 'freqs' and 'omega_p' needed")
        nu = np.asarray(table["freqs"], dtype=np.float64)
        om = np.asarray(table["omega_p"], dtype=np.float64)
    scale = 1e9 if nu.max() < 10 else (1e6 if nu.max() < 1e4 else 1.0)
    nu = nu * scale
    freqs = np.asarray(freqs, dtype=np.float64)
    inside = (freqs >= nu.min()) & (freqs <= nu.max())
    return np.where(inside, np.interp(freqs, nu, om), np.nan)


def reference_pol_convention(reference: ReferenceGains) -> tuple[str | None, str]:
    """Return the pseudo-Stokes convention (pyuvdata ``pol_convention``) a reference states.

    ``reference.meta["pol_convention"]`` when the reader recorded it, else each file in
    ``reference.meta["files"]`` is opened with pyuvdata (metadata only).

    Parameters
    ----------
    reference
        The reference gains.

    Returns
    -------
    convention, note
        ``"sum"``, ``"avg"`` or ``None`` (not stated or not readable), and how it was
        found.
    """
    if "pol_convention" in reference.meta:
        value = reference.meta["pol_convention"]
        return (str(value) if value else None), "recorded by the reference reader"
    files = [Path(f) for f in reference.meta.get("files", [])]
    readable = [f for f in files if f.is_file()]
    if not readable:
        return None, "no reference file to read"
    import warnings

    from pyuvdata import UVCal

    found: list[str | None] = []
    for path in readable:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                uvc = UVCal.from_file(str(path), read_data=False, run_check=False)
        except Exception as err:  # a metadata read must never block the comparison
            logger.warning("cannot read pol_convention from %s: %s", path.name, err)
            return None, f"pyuvdata could not read {path.name}"
        found.append(getattr(uvc, "pol_convention", None))
    stated = {v for v in found if v}
    if len(stated) > 1:
        logger.warning("the reference files state different pol_conventions %s", stated)
    if not stated:
        return None, f"not stated in {len(found)} file(s) (pyuvdata UVCal.pol_convention)"
    return str(found[0] or sorted(stated)[0]), "stated in the file (pyuvdata UVCal.pol_convention)"


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


# ---------------------------------------------------------------------------------------
# the comparison
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Comparison:
    """The result of :func:`compare`.

    Arrays are ``(Nant, Npol, Nfreq)`` on the solution's channels unless noted.

    Attributes
    ----------
    mode
        ``"absolute"`` or ``"relative"``.
    quantity
        What ``auto`` and ``reference`` hold (``|g|`` in ``sqrt(raw/K)``, or ``|g|``
        divided by its mean over frequency).
    antennas, pols, freqs
        Axes.
    auto, sigma_auto
        autocal's ``|g|`` (or normalised ``|g|``) and 1-sigma error.
    reference, sigma_reference
        The reference, time-averaged, smoothed, interpolated, converted to kelvin units
        (absolute) or normalised (relative); ``sigma_reference`` is its scatter over the
        selected times (the error of a single-time reference), NaN where unknown.
    ratio, sigma_ratio
        ``auto / reference`` and its 1-sigma error.
    valid
        Channels compared (both sides finite and unflagged).
    jy_per_k, omega
        ``(Npol, Nfreq)`` conversion (Jy per K) and beam solid angle (sr), or ``None``.
    delays, delay_amplitude
        ``(Ndelay,)`` seconds and ``(Nant, Npol, Ndelay)`` normalised delay spectrum of
        ``ratio - mean`` (fractions of the mean), or ``None`` for non-uniform channels.
    summary
        JSON-serialisable statistics and provenance.
    reference_jds, reference_series
        ``(Ntime_sel,)`` the reference JDs used and ``(Nant, Npol, Ntime_sel)`` the median
        over the compared band of ``|g_ref(t)|^2 / mean_t`` (the reference's drift), or
        ``None``.
    auto_series
        ``{(ant, pol): (jds, power / mean_t)}`` of the raw autos when the caller gave
        them (see :func:`auto_trend`), else ``None``.
    """

    mode: str
    quantity: str
    antennas: np.ndarray
    pols: tuple[str, ...]
    freqs: np.ndarray
    auto: np.ndarray
    sigma_auto: np.ndarray
    reference: np.ndarray
    sigma_reference: np.ndarray
    ratio: np.ndarray
    sigma_ratio: np.ndarray
    valid: np.ndarray
    jy_per_k: np.ndarray | None
    omega: np.ndarray | None
    delays: np.ndarray | None
    delay_amplitude: np.ndarray | None
    summary: dict[str, Any] = field(default_factory=dict)
    reference_jds: np.ndarray | None = None
    reference_series: np.ndarray | None = None
    auto_series: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] | None = None

    def __repr__(self) -> str:
        """Return one line; arrays as type and shape (:func:`~autocal.core.reprs.compact_repr`)."""
        from autocal.core.reprs import compact_repr

        return compact_repr(self)


def _match_axes(
    solution: Solution,
    reference: ReferenceGains,
    antennas: list[int] | None,
    pols: list[str] | None,
) -> tuple[list[int], list[str]]:
    sol_ants = [int(a) for a in solution.antennas]
    ref_ants = [int(a) for a in reference.antennas]
    if antennas is None:
        ants = [a for a in sol_ants if a in ref_ants]
        if not ants:
            raise CompareError(
                f"the solution's antennas {sol_ants} are not in the reference; it has "
                f"antennas {ref_ants}"
            )
    else:
        ants = [int(a) for a in antennas]
        missing = [a for a in ants if a not in sol_ants]
        if missing:
            raise CompareError(f"antenna(s) {missing} are not in the solution; it has {sol_ants}")
        missing = [a for a in ants if a not in ref_ants]
        if missing:
            raise CompareError(
                f"antenna(s) {missing} are not in the reference gains; available in the "
                f"reference: {ref_ants} (solution: {sol_ants})"
            )
    sol_pols = [str(p).lower() for p in solution.pols]
    ref_pols = [str(p).lower() for p in reference.pols]
    if pols is None:
        use = [p for p in sol_pols if p in ref_pols]
        if not use:
            raise CompareError(
                f"the solution's polarisations {sol_pols} are not in the reference; it has "
                f"{ref_pols}"
            )
    else:
        use = [str(p).lower() for p in pols]
        missing_p = [p for p in use if p not in sol_pols]
        if missing_p:
            raise CompareError(
                f"polarisation(s) {missing_p} are not in the solution; it has {sol_pols}"
            )
        missing_p = [p for p in use if p not in ref_pols]
        if missing_p:
            raise CompareError(
                f"polarisation(s) {missing_p} are not in the reference gains; available in "
                f"the reference: {ref_pols} (solution: {sol_pols})"
            )
    return ants, use


def _stats(
    ratio: np.ndarray,
    sigma: np.ndarray,
    valid: np.ndarray,
    nvalid_auto: int,
    nfreq: int,
) -> dict[str, Any]:
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


def _delay(
    ratio: np.ndarray, valid: np.ndarray, freqs: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None]:
    from autocal.compare.delay import DelayError, delay_spectrum

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


def _lookup(value: Any, ant: int, pol: str, ia: int, ip: int, per_pol_ndim: int) -> Any:
    """Pick an optional per-antenna/pol input.

    ``value`` is a mapping keyed by ``(ant, pol)`` or ``pol``, a scalar, or an array
    indexed like the solution's antennas (when its dimensionality exceeds
    ``per_pol_ndim + 1``) and polarisations.
    """
    if value is None:
        return None
    if isinstance(value, dict):
        for key in ((ant, pol), (int(ant), pol), pol):
            if key in value:
                return value[key]
        return None
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        return float(arr)
    if arr.ndim == per_pol_ndim + 2:
        return arr[ia, ip]
    if arr.ndim == per_pol_ndim + 1:
        return arr[ip]
    return arr


def _finite_or_none(value: Any) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None


def _stability(
    mode: str,
    drift: dict[str, Any],
    auto_change: float | None,
    trxr: dict[str, Any] | None,
    trxr_skip: str,
) -> dict[str, Any]:
    """Apply the reference stability rule (module notes) to one antenna/polarisation."""
    tested: list[str] = []
    failed: list[str] = []
    skipped: dict[str, str] = {}
    ref_change = _finite_or_none(drift["change"])
    limit = None
    if mode != "absolute":
        skipped["drift"] = "relative reference: its overall amplitude per time is degenerate"
        skipped["negative_trxr"] = skipped["drift"]
    else:
        if ref_change is None:
            skipped["drift"] = "the reference drift is not measurable (fewer than 2 times)"
        elif auto_change is None or not np.isfinite(auto_change):
            skipped["drift"] = "the raw auto's change over the span was not given (auto_drift)"
        else:
            limit = REFERENCE_DRIFT_FACTOR * abs(auto_change) + REFERENCE_DRIFT_ALLOWANCE
            tested.append("drift")
            if abs(ref_change) > limit:
                failed.append("drift")
        if trxr is None:
            skipped["negative_trxr"] = trxr_skip
        else:
            tested.append("negative_trxr")
            if any(v is not None and v < 0 for v in (trxr["first"], trxr["last"])):
                failed.append("negative_trxr")
    stable = None if not tested else not failed
    return {
        "stable": stable,
        "tested": tested,
        "failed": failed,
        "skipped": skipped,
        "drift_limit": limit,
        "implied_trxr_K": trxr,
    }


def _offset(
    ratio: np.ndarray,
    sigma: np.ndarray,
    valid: np.ndarray,
    freqs: np.ndarray,
    ref_common_rel: float,
    auto_sys_rel: np.ndarray | None,
    sigma_no_sys: np.ndarray | None = None,
) -> dict[str, Any]:
    """Broadband offset ``mean(r) - 1`` and its error (module notes, step 8).

    ``sigma_no_sys`` is the per-channel ratio error with the auto's statistical error
    only (for the ``*_without_auto_systematic`` entries).
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


def _sky_model_budget(
    alternatives: dict[str, Solution] | None,
    ant: int,
    pol: str,
    freqs: np.ndarray,
    ref_c: np.ndarray,
    ratio: np.ndarray,
    valid: np.ndarray,
) -> dict[str, Any] | None:
    """Ratio means under alternative sky models (absolute mode) for one antenna/pol."""
    if not alternatives:
        return None
    out: dict[str, Any] = {}
    shifts = [0.0]
    for name, alt in alternatives.items():
        entry: dict[str, Any] = {}
        ants = [int(a) for a in alt.antennas]
        alt_pols = [str(p).lower() for p in alt.pols]
        alt_f = np.asarray(alt.freqs, dtype=np.float64)
        if ant not in ants or pol not in alt_pols:
            entry["reason"] = f"antenna {ant} {pol} is not in this solution"
        elif alt_f.shape != freqs.shape or not np.allclose(alt_f, freqs, rtol=0, atol=1.0):
            entry["reason"] = "its channels differ from the compared solution's"
        else:
            ia, ip = ants.index(ant), alt_pols.index(pol)
            with np.errstate(invalid="ignore", divide="ignore"):
                g = np.asarray(alt.abs_g)[ia, ip]
                ok = valid & ~np.asarray(alt.flags)[ia, ip] & np.isfinite(g) & (g > 0)
                r_alt = g / ref_c
            if not ok.any():
                entry["reason"] = "no channel valid in both"
            else:
                base = float(np.mean(ratio[ok]))
                mean = float(np.mean(r_alt[ok]))
                shift = mean / base - 1.0
                shifts.append(shift)
                entry.update(ratio_mean=mean, shift=shift, n_channels=int(ok.sum()))
        out[name] = entry
    base_mean = float(np.mean(ratio[valid])) if valid.any() else float("nan")
    return {
        "alternatives": out,
        "spread_fraction": float(max(shifts) - min(shifts)),
        "spread": float(base_mean * (max(shifts) - min(shifts))),
        "note": "max - min of the mean ratio over this solution and the alternatives",
    }


def compare(
    solution: Solution,
    reference: ReferenceGains,
    *,
    antennas: list[int] | None = None,
    pols: list[str] | None = None,
    smooth_mhz: float | None = None,
    mode: str | None = None,
    beam: Any = None,
    nside: int | None = None,
    omega: np.ndarray | None = None,
    auto_drift: dict[tuple[int, str], float] | np.ndarray | float | None = None,
    auto_power_ends: dict[tuple[int, str], np.ndarray] | np.ndarray | None = None,
    tsky_ends: dict[Any, np.ndarray] | np.ndarray | None = None,
    auto_series: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] | None = None,
    alternatives: dict[str, Solution] | None = None,
    beam_integrals: str | Path | None = None,
) -> Comparison:
    """Compare a solution's ``|g|`` with reference gains (see the module notes).

    Parameters
    ----------
    solution
        An :class:`autocal.fit.lsq.Solution`.
    reference
        :class:`autocal.io.calsol.ReferenceGains`.
    antennas, pols
        What to compare (default: everything the two have in common).
    smooth_mhz
        FWHM (MHz) of the Gaussian kernel smoothing the reference along frequency.
    mode
        ``"absolute"`` or ``"relative"`` (default: from ``reference.absolute``).
    beam
        Beam for ``Omega_A`` (absolute Jy-referenced gains): ``"hera"`` (Fagnoni
        beamfits), a file, a name for :func:`autocal.sky.beams.get_beam` or a ``Beam``.
        Default: the beam recorded in the solution's configuration (the one its Tsky
        used), else ``"hera"``.
    nside
        HEALPix resolution of the ``Omega_A`` integral (default: see
        :func:`beam_solid_angle`).
    omega
        Precomputed ``Omega_A`` in sr, ``(Npol, Nfreq)`` or ``(Nfreq,)`` on the
        solution's channels (skips the beam integral).
    auto_drift
        The raw auto's fractional change over the span (:func:`fractional_end_change`
        of the power): ``{(ant, pol): change}``, a scalar for all, or an array indexed
        like the solution's ``(antennas, pols)``. Without it the drift clause of the
        stability rule is skipped and ``auto_drift`` is reported as ``null``.
    auto_power_ends
        Raw auto power averaged over the first and the last end of the span on the
        solution's channels: ``{(ant, pol): (2, Nfreq)}`` or ``(Nant, Npol, 2, Nfreq)``
        indexed like the solution.
    tsky_ends
        Model Tsky (K) at the same ends: ``{(ant, pol) or pol: (2, Nfreq)}``,
        ``(Npol, 2, Nfreq)`` or ``(2, Nfreq)``. With ``auto_power_ends`` it enables the
        negative-Trxr clause of the stability rule (absolute mode).
    auto_series
        ``{(ant, pol): (jds, power / mean_t)}`` for the figure.
    alternatives
        ``{name: Solution}``: the same data fitted with other sky models (same channels);
        the ratio's spread over them enters the systematics budget.
    beam_integrals
        hera_sim's ``HERA_H1C_BEAM_INTEGRALS.npz`` (default: the data folder's) for the
        ``omega_source`` entry of the budget.

    Returns
    -------
    Comparison
        Arrays and summary.

    Raises
    ------
    CompareError
        For antennas/polarisations missing on either side (the message lists what is
        available), no frequency overlap, no common valid channels, or an unknown
        gain scale.

    Notes
    -----
    :func:`auto_trend` turns raw autos (and Tsky) into ``auto_drift``,
    ``auto_power_ends``, ``tsky_ends`` and ``auto_series``.
    """
    ants, use_pols = _match_axes(solution, reference, antennas, pols)
    mode = mode or ("absolute" if reference.absolute else "relative")
    if mode not in ("absolute", "relative"):
        raise CompareError(f"mode must be 'absolute' or 'relative', got {mode!r}")
    freqs = np.asarray(solution.freqs, dtype=np.float64)
    ref_freqs = np.asarray(reference.freqs, dtype=np.float64)
    lo, hi = float(ref_freqs.min()), float(ref_freqs.max())
    in_range = (freqs >= lo - 1.0) & (freqs <= hi + 1.0)
    if not in_range.any():
        raise CompareError(
            f"no frequency overlap: the solution covers {freqs.min() / 1e6:.4f}-"
            f"{freqs.max() / 1e6:.4f} MHz, the reference {lo / 1e6:.4f}-{hi / 1e6:.4f} MHz"
        )
    if not in_range.all():
        logger.warning(
            "%d of %d solution channels lie outside the reference's %.3f-%.3f MHz and are "
            "not compared",
            int((~in_range).sum()),
            freqs.size,
            lo / 1e6,
            hi / 1e6,
        )

    ia_sol = [int(np.flatnonzero(solution.antennas == a)[0]) for a in ants]
    ip_sol = [list(solution.pols).index(p) for p in use_pols]
    ia_ref = [int(np.flatnonzero(reference.antennas == a)[0]) for a in ants]
    ip_ref = [list(reference.pols).index(p) for p in use_pols]
    idx_sol = np.ix_(ia_sol, ip_sol)
    stat_all = getattr(solution, "sigma_abs_g_stat", None)
    with np.errstate(invalid="ignore", divide="ignore"):
        auto = np.asarray(solution.abs_g)[idx_sol]
        sigma_auto = np.asarray(solution.sigma_abs_g)[idx_sol]
        sigma_stat = None if stat_all is None else np.asarray(stat_all)[idx_sol]
        # the part of the auto's (total) error beyond the statistical one, relative
        auto_sys_rel = (
            None
            if sigma_stat is None
            else np.sqrt(np.clip(sigma_auto**2 - sigma_stat**2, 0.0, None)) / auto
        )
    auto_ok = (
        ~np.asarray(solution.flags)[idx_sol]
        & np.isfinite(auto)
        & (auto > 0)
        & np.isfinite(sigma_auto)
    )

    # reference times, drift, time average with its scatter ------------------------------
    tsel, time_info = select_reference_times(reference.jds, solution.jds)
    amp = reference.abs_g[np.ix_(ia_ref, ip_ref, tsel, np.arange(ref_freqs.size))]
    band = (ref_freqs >= freqs.min() - 1.0) & (ref_freqs <= freqs.max() + 1.0)
    drifts = [
        [fractional_end_change(amp[ia, ip][:, band] ** 2) for ip in range(len(use_pols))]
        for ia in range(len(ants))
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

    # conversion -------------------------------------------------------------------------
    jpk = om = kfac = None
    pol_conv: dict[str, Any] | None = None
    conversion: dict[str, Any] = {"applied": False}
    if mode == "absolute":
        if not reference.gain_scale:
            logger.warning(
                "the reference states no gain scale; absolute gains are taken to be "
                "Jy-referenced (HERA abscal)"
            )
        scale = (reference.gain_scale or "Jy").strip()
        if scale.lower() in ("k", "kelvin"):
            conversion = {"applied": False, "reason": "reference gain_scale is K"}
            kfac = np.ones((len(use_pols), freqs.size))
        elif scale.lower() == "jy":
            if beam is None and omega is None:
                beam = beam_from_config(solution.config)
            om, conversion = _omega(beam, use_pols, freqs, nside, omega)
            jpk = jy_per_kelvin(freqs[None, :], om)
            stated, note = reference_pol_convention(reference)
            if stated not in (None, "sum", "avg"):
                logger.warning("unknown pol_convention %r; assuming 'avg'", stated)
                note = f"unknown value {stated!r}; {DEFAULT_POL_CONVENTION!r} assumed"
                stated = None
            used = stated or DEFAULT_POL_CONVENTION
            pol_conv = {
                "stated": stated,
                "used": used,
                "source": "file" if stated else "assumed",
                "note": note,
            }
            conversion["pol_convention"] = used
            conversion["pol_convention_source"] = pol_conv["source"]
            if used == "sum":
                conversion["formula"] = (
                    "|g_ref,K| = |g_ref,Jy| sqrt(2 k_B Omega_A / lambda^2 * 1e26 / 2) ('sum')"
                )
            kfac = jpk * (0.5 if used == "sum" else 1.0)
            factor = np.sqrt(kfac)[None, :, :]
            ref_i = ref_i * factor
            sig_i = sig_i * factor
        else:
            raise CompareError(
                f"reference gain_scale {scale!r} is not understood: absolute gains must be "
                "Jy- or K-referenced (use mode='relative' to compare shapes)"
            )

    valid = auto_ok & np.isfinite(ref_i) & (ref_i > 0)
    if not valid.any():
        raise CompareError(
            "no channel is valid in both the solution and the reference (check flags and "
            "the frequency overlap)"
        )
    if mode == "relative":
        quantity = "|g| / mean over valid channels"
        nvalid = valid.sum(axis=-1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            a_mean = np.where(valid, auto, 0.0).sum(axis=-1, keepdims=True) / nvalid
            r_mean = np.where(valid, ref_i, 0.0).sum(axis=-1, keepdims=True) / nvalid
            auto_c, sig_auto_c = auto / a_mean, sigma_auto / a_mean
            ref_c, sig_ref_c = ref_i / r_mean, sig_i / r_mean
        auto_sys_rel = None  # a channel-common fractional error cancels in the shapes
    else:
        quantity = "|g| = sqrt(G) in sqrt(raw/K)"
        auto_c, sig_auto_c, ref_c, sig_ref_c = auto, sigma_auto, ref_i, sig_i
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(valid, auto_c / ref_c, np.nan)
        rel_ref = np.where(np.isfinite(sig_ref_c), sig_ref_c / ref_c, 0.0)
        sigma_ratio = np.where(
            valid, np.abs(ratio) * np.sqrt((sig_auto_c / auto_c) ** 2 + rel_ref**2), np.nan
        )
        sigma_ratio_stat = (
            None
            if sigma_stat is None
            else np.where(
                valid, np.abs(ratio) * np.sqrt((sigma_stat / auto) ** 2 + rel_ref**2), np.nan
            )
        )
    delays, damp = _delay(ratio, valid, freqs)

    # hera_sim's beam integral for the budget --------------------------------------------
    om_hs = None
    om_hs_reason = None
    if om is not None:
        try:
            om_hs = hera_sim_omega(freqs, beam_integrals)
        except Exception as err:  # the budget must never block the comparison
            om_hs_reason = f"hera_sim beam integrals unavailable: {err}"
            logger.warning("%s", om_hs_reason)
    elif mode == "absolute":
        om_hs_reason = "no Jy->K conversion (reference in K)"
    else:
        om_hs_reason = "relative mode"

    per: list[dict[str, Any]] = []
    for ia, ant in enumerate(ants):
        for ip, pol in enumerate(use_pols):
            row_valid = valid[ia, ip]
            stats = _stats(
                ratio[ia, ip],
                sigma_ratio[ia, ip],
                row_valid,
                int(auto_ok[ia, ip].sum()),
                freqs.size,
            )
            stats["n_outside_reference_range"] = int((~in_range).sum())
            stats["reference_sigma_available"] = bool(
                np.isfinite(sig_ref_c[ia, ip][row_valid]).any()
            )
            with np.errstate(invalid="ignore", divide="ignore"):
                rel_auto = (sig_auto_c / auto_c)[ia, ip][row_valid]
                rel_stat = None if sigma_stat is None else (sigma_stat / auto)[ia, ip][row_valid]
            stats["sigma_auto_rel_median"] = float(np.median(rel_auto)) if rel_auto.size else None
            stats["sigma_auto_stat_rel_median"] = (
                float(np.nanmedian(rel_stat)) if rel_stat is not None and rel_stat.size else None
            )
            stats["sigma_reference_rel_median"] = (
                float(np.nanmedian(rel_ref[ia, ip][row_valid]))
                if stats["reference_sigma_available"]
                else None
            )
            # offset with frequency-correlated errors
            stats.update(
                _offset(
                    ratio[ia, ip],
                    sigma_ratio[ia, ip],
                    row_valid,
                    freqs,
                    float(ref_common_rel[ia, ip]),
                    None if auto_sys_rel is None else auto_sys_rel[ia, ip],
                    None if sigma_ratio_stat is None else sigma_ratio_stat[ia, ip],
                )
            )
            # drift and stability
            d = drifts[ia][ip]
            change = _lookup(auto_drift, ant, pol, ia_sol[ia], ip_sol[ip], 0)
            change = _finite_or_none(change)
            trxr, trxr_skip = _implied_trxr(
                mode,
                kfac,
                d,
                ref_freqs[band],
                freqs,
                auto_ok[ia, ip],
                ip,
                _lookup(auto_power_ends, ant, pol, ia_sol[ia], ip_sol[ip], 2),
                _lookup(tsky_ends, ant, pol, ia_sol[ia], ip_sol[ip], 2),
            )
            stability = _stability(mode, d, change, trxr, trxr_skip)
            stats.update(
                reference_drift=_finite_or_none(d["change"]),
                reference_drift_rms=_finite_or_none(d["rms"]),
                reference_drift_integrations={"end": d["n_end"], "valid": d["n_valid"]},
                auto_drift=change,
                reference_stable=stability.pop("stable"),
                reference_stability=stability,
            )
            if damp is not None and delays is not None:
                beyond = delays * 1e9 > DELAY_REPORT_NS
                row = damp[ia, ip]
                if beyond.any() and np.isfinite(row[beyond]).any():
                    k = int(np.nanargmax(np.where(beyond, row, np.nan)))
                    stats["delay_max_beyond_ns"] = DELAY_REPORT_NS
                    stats["delay_max_amplitude"] = float(row[k])
                    stats["delay_of_max_ns"] = float(delays[k] * 1e9)
            stats["systematics"] = _budget_row(
                mode,
                ratio[ia, ip],
                row_valid,
                None if om is None else om[ip],
                om_hs,
                om_hs_reason,
                pol_conv,
                _sky_model_budget(
                    alternatives, ant, pol, freqs, ref_c[ia, ip], ratio[ia, ip], row_valid
                )
                if mode == "absolute"
                else None,
            )
            per.append({"antenna": ant, "pol": pol, **stats})

    summary = {
        "mode": mode,
        "quantity": quantity,
        "expected_ratio": 1.0,
        "antennas": ants,
        "pols": use_pols,
        "solution": {
            "nfreq": int(freqs.size),
            "freq_range_Hz": [float(freqs.min()), float(freqs.max())],
            "ntime": len(solution.jds),
            "model": solution.model.describe(),
            "config": solution.config,
            "sigma_abs_g": "total (statistical + data-driven)"
            if getattr(solution, "total", None) is not None
            else "statistical",
        },
        "reference": reference.describe(),
        "time_match": time_info,
        "smoothing": (
            {"kernel": "gaussian", "fwhm_MHz": float(smooth_mhz), "applied_to": "each time"}
            if smooth_mhz
            else {"kernel": None}
        ),
        "interpolation": "linear in frequency inside the reference range; flagged gaps not bridged",
        "conversion": conversion,
        "reference_sigma": (
            "std over the selected reference times of |g_ref| per channel (ddof=1): the "
            "scatter of a single-time reference, not divided by sqrt(N_t)"
            + (
                "; each time normalised by its band mean first (relative)"
                if mode == "relative"
                else ""
            )
        ),
        "offset_method": (
            f"offset = mean ratio - 1 over the compared channels; error = circular block "
            f"bootstrap over channels ({BOOTSTRAP_RESAMPLES} resamples, blocks of "
            f"{BOOTSTRAP_BLOCK_MHZ:g} MHz, seed {BOOTSTRAP_SEED}, bias-corrected by "
            "Richardson extrapolation from blocks L and L/2 and for the subtracted mean; "
            "at least the independent-channel error sqrt(sum sigma_r^2)/N), in quadrature "
            "with the channel-common errors: the reference's band-averaged scatter over "
            "time and the auto's systematic |g| error sqrt(total^2 - stat^2) taken as "
            "fully correlated across channels"
        ),
        "reference_stability_rule": (
            f"unstable if |reference drift| > {REFERENCE_DRIFT_FACTOR:g} |auto drift| + "
            f"{REFERENCE_DRIFT_ALLOWANCE:g} (drift = median over channels of the fractional "
            f"change between the means of the first and last {DRIFT_END_FRACTION:g} of the "
            "integrations; |g_ref|^2 vs raw auto power), or (absolute) if R / (|g_ref|^2 J) "
            "- Tsky has a negative median over channels at either end; clauses without "
            "inputs are skipped; null when none could be tested"
        ),
        "systematics": _budget_summary(mode, use_pols, freqs, om, om_hs, om_hs_reason, pol_conv),
        "per_antenna_pol": per,
    }
    logger.info(
        "compared %d antenna(s) x %d pol(s) (%s): median ratio %s",
        len(ants),
        len(use_pols),
        mode,
        f"{np.nanmedian(ratio):.4g}",
    )
    series = None
    if auto_series:
        series = {}
        for ia, ant in enumerate(ants):
            for ip, pol in enumerate(use_pols):
                item = _lookup(auto_series, ant, pol, ia_sol[ia], ip_sol[ip], 0)
                if item is not None:
                    series[(ant, pol)] = (np.asarray(item[0]), np.asarray(item[1]))
    return Comparison(
        mode=mode,
        quantity=quantity,
        antennas=np.asarray(ants, dtype=np.int64),
        pols=tuple(use_pols),
        freqs=freqs,
        auto=np.where(auto_ok, auto_c, np.nan),
        sigma_auto=np.where(auto_ok, sig_auto_c, np.nan),
        reference=ref_c,
        sigma_reference=sig_ref_c,
        ratio=ratio,
        sigma_ratio=sigma_ratio,
        valid=valid,
        jy_per_k=jpk,
        omega=om,
        delays=delays,
        delay_amplitude=damp,
        summary=summary,
        reference_jds=np.asarray(reference.jds)[tsel],
        reference_series=np.array([[d["series"] for d in row] for row in drifts]),
        auto_series=series or None,
    )


def _implied_trxr(
    mode: str,
    kfac: np.ndarray | None,
    drift: dict[str, Any],
    band_freqs: np.ndarray,
    freqs: np.ndarray,
    ok: np.ndarray,
    ip: int,
    power_ends: Any,
    tsky_ends: Any,
) -> tuple[dict[str, Any] | None, str]:
    """``R / (|g_ref|^2 J) - Tsky`` (median over channels) at the span's two ends."""
    if mode != "absolute" or kfac is None:
        return None, "not an absolute comparison"
    if power_ends is None or tsky_ends is None:
        return None, "auto_power_ends and tsky_ends were not given"
    if drift["n_end"] == 0:
        return None, "the reference has fewer than 2 valid times"
    power = np.broadcast_to(np.asarray(power_ends, dtype=np.float64), (2, freqs.size))
    sky = np.broadcast_to(np.asarray(tsky_ends, dtype=np.float64), (2, freqs.size))
    ends = interpolate_frequency(band_freqs, np.stack([drift["first"], drift["last"]]), freqs)
    with np.errstate(invalid="ignore", divide="ignore"):
        trxr = power / (ends * kfac[ip][None, :]) - sky
    out: dict[str, Any] = {}
    for i, name in enumerate(("first", "last")):
        good = ok & np.isfinite(trxr[i])
        out[name] = float(np.median(trxr[i][good])) if good.any() else None
    if out["first"] is None and out["last"] is None:
        return None, "no channel with both end powers and reference gains"
    return out, ""


def _budget_row(
    mode: str,
    ratio: np.ndarray,
    valid: np.ndarray,
    om: np.ndarray | None,
    om_hs: np.ndarray | None,
    om_hs_reason: str | None,
    pol_conv: dict[str, Any] | None,
    sky: dict[str, Any] | None,
) -> dict[str, Any] | None:
    """Return the systematics budget of one antenna/polarisation (absolute mode)."""
    if mode != "absolute":
        return None
    r = ratio[valid]
    base = float(np.mean(r)) if r.size else float("nan")
    omega_entry: dict[str, Any]
    if om is not None and om_hs is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.sqrt(om / om_hs)  # ratio ~ Omega_A^-1/2
        ok = valid & np.isfinite(scale)
        if ok.any():
            alt = float(np.mean(ratio[ok] * scale[ok]))
            same = float(np.mean(ratio[ok]))
            omega_entry = {
                "alternative": "hera_sim H1C beam integrals (omega_p)",
                "ratio_mean": alt,
                "shift": alt / same - 1.0,
                "omega_ratio_hera_sim_over_autocal_mean": float(np.mean(om_hs[ok] / om[ok])),
                "n_channels": int(ok.sum()),
            }
        else:
            omega_entry = {"reason": "the hera_sim table does not cover the compared channels"}
    else:
        omega_entry = {"reason": om_hs_reason or "not applicable"}
    pol_entry: dict[str, Any]
    if pol_conv is not None:
        other = "sum" if pol_conv["used"] == "avg" else "avg"
        factor = np.sqrt(2.0) if other == "sum" else 1.0 / np.sqrt(2.0)
        pol_entry = {
            **pol_conv,
            "alternative": other,
            "ratio_scale": float(factor),
            "ratio_mean": base * float(factor),
            "shift": float(factor) - 1.0,
        }
    else:
        pol_entry = {"reason": "no Jy->K conversion (reference in K)"}
    return {"omega_source": omega_entry, "pol_convention": pol_entry, "sky_model": sky}


def _budget_summary(
    mode: str,
    pols: list[str],
    freqs: np.ndarray,
    om: np.ndarray | None,
    om_hs: np.ndarray | None,
    om_hs_reason: str | None,
    pol_conv: dict[str, Any] | None,
) -> dict[str, Any] | None:
    """Polarisation-level facts of the systematics budget (absolute mode)."""
    if mode != "absolute":
        return None
    ref_f = 150e6 if freqs.min() <= 150e6 <= freqs.max() else float(np.median(freqs))
    k = int(np.argmin(np.abs(freqs - ref_f)))
    per_pol: dict[str, Any] = {}
    for ip, pol in enumerate(pols):
        entry: dict[str, Any] = {"at_freq_Hz": float(freqs[k])}
        if om is not None:
            entry["omega_autocal_sr"] = float(om[ip, k])
        if om is not None and om_hs is not None and np.isfinite(om_hs[k]):
            entry["omega_hera_sim_sr"] = float(om_hs[k])
            entry["omega_ratio_hera_sim_over_autocal"] = float(om_hs[k] / om[ip, k])
            entry["ratio_scale_with_hera_sim_omega"] = float(np.sqrt(om[ip, k] / om_hs[k]))
        per_pol[pol] = entry
    return {
        "per_pol": per_pol,
        "omega_source_note": (
            "|g_ref,K| = |g_ref| sqrt(J), J ~ Omega_A, so the ratio |g_auto|/|g_ref,K| scales "
            "as Omega_A^-1/2: with hera_sim's Omega the ratio is multiplied by "
            "sqrt(Omega_autocal / Omega_hera_sim)"
            + ("" if om_hs is not None else f" (unavailable: {om_hs_reason})")
        ),
        "pol_convention": pol_conv,
        "pol_convention_note": (
            "pyuvdata: 'avg' I = (XX+YY)/2 (calibrated XX ~ I), 'sum' I = XX+YY (XX ~ I/2); "
            "'sum' gains give half the Jy for the same raw auto, |g_sum| = sqrt(2) |g_avg|, "
            "so the ratio is sqrt(2) larger under 'sum' than under 'avg'"
        ),
        "sky_model_note": "per antenna/pol in per_antenna_pol[*].systematics.sky_model "
        "(null when no alternative solutions were given)",
    }


def _omega(
    beam: Any, pols: list[str], freqs: np.ndarray, nside: int | None, omega: np.ndarray | None
) -> tuple[np.ndarray, dict[str, Any]]:
    """``Omega_A`` (Npol, Nfreq) and a description with the UVBeam cross-check."""
    from autocal.sky.beams import HealpixFileBeam

    info: dict[str, Any] = {
        "applied": True,
        "formula": "|g_ref,K| = |g_ref,Jy| sqrt(2 k_B Omega_A / lambda^2 * 1e26)",
    }
    if omega is not None:
        om = np.broadcast_to(np.asarray(omega, dtype=np.float64), (len(pols), freqs.size)).copy()
        info["omega_source"] = "given"
    else:
        rows = []
        checks = []
        for pol in pols:
            b = resolve_beam(beam, pol)
            row = beam_solid_angle(b, freqs, pol=pol, nside=nside)
            rows.append(row)
            info.setdefault("beam", b.describe())
            if isinstance(b, HealpixFileBeam):
                try:
                    alt = uvbeam_solid_angle(b.path, freqs, pol)
                    checks.append(float(np.max(np.abs(row / alt - 1.0))))
                except Exception as err:  # the cross-check must never block the comparison
                    logger.warning("UVBeam cross-check of Omega_A failed: %s", err)
        om = np.array(rows)
        info["omega_source"] = "autocal beam on a HEALPix grid (whole sphere, peak-normalised)"
        if checks:
            info["uvbeam_get_beam_area_max_rel_diff"] = max(checks)
    ref_f = 150e6 if freqs.min() <= 150e6 <= freqs.max() else float(np.median(freqs))
    k = int(np.argmin(np.abs(freqs - ref_f)))
    info["at_freq_Hz"] = float(freqs[k])
    info["omega_sr"] = {p: float(om[i, k]) for i, p in enumerate(pols)}
    info["jy_per_K"] = {p: float(jy_per_kelvin(freqs[k], om[i, k])) for i, p in enumerate(pols)}
    return om, info


# ---------------------------------------------------------------------------------------
# outputs
# ---------------------------------------------------------------------------------------
def _clean(value: Any) -> Any:
    """Make a structure strict-JSON safe (NaN/inf -> None, numpy -> Python)."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def plot_comparison(comparison: Comparison, path: str | Path, title: str | None = None) -> Path:
    """Plot the compared gains, the ratio with its 2-sigma band, its delay spectrum and drift.

    The last panel shows the reference's ``|g_ref|^2(t) / mean`` (median over the band)
    and, when given, the raw auto's ``power / mean`` against time, with the offset, the
    stability verdict and the systematics budget as text.

    Parameters
    ----------
    comparison
        The comparison.
    path
        Output image (PNG).
    title
        Figure title.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    from autocal.plots import band, figure, save_figure

    c = comparison
    fmhz = c.freqs / 1e6
    fig, axes = figure(4, 1, (9, 13))
    for ia, ant in enumerate(c.antennas):
        for ip, pol in enumerate(c.pols):
            label = f"ant {ant} {pol}"
            mask = c.valid[ia, ip]
            auto = np.where(mask, c.auto[ia, ip], np.nan)
            ref = np.where(mask, c.reference[ia, ip], np.nan)
            (line,) = axes[0].plot(fmhz, auto, lw=1, label=f"{label} autos")
            axes[0].plot(fmhz, ref, lw=1, ls="--", color=line.get_color(), label=f"{label} ref")
            sig = np.where(mask, c.sigma_ratio[ia, ip], np.nan)
            band(axes[1], fmhz, c.ratio[ia, ip], sig, label)
            if c.delay_amplitude is not None and c.delays is not None:
                # tau = 0 of the mean-subtracted ratio is ~0 by construction: not shown
                axes[2].semilogy(
                    c.delays[1:] * 1e9, c.delay_amplitude[ia, ip, 1:], lw=1, label=label
                )
    axes[0].set(
        xlabel="frequency [MHz]",
        ylabel="|g| [sqrt(raw/K)]" if c.mode == "absolute" else "|g| / mean",
        title="autos (solid) vs reference converted (dashed)"
        if c.mode == "absolute"
        else "normalised shapes: autos (solid), reference (dashed)",
    )
    axes[1].axhline(1.0, color="k", lw=0.8)
    good = c.ratio[c.valid & np.isfinite(c.ratio)]
    if good.size:
        # robust limits (single RFI channels with huge error bars must not squash the plot)
        lo, hi = np.percentile(good, [1, 99])
        lo, hi = min(lo, 1.0), max(hi, 1.0)
        pad = 0.15 * (hi - lo) + 0.02
        axes[1].set_ylim(lo - pad, hi + pad)
    axes[1].set(
        xlabel="frequency [MHz]", ylabel="|g_auto| / |g_ref|", title="ratio with 2-sigma band"
    )
    axes[2].set(
        xlabel="delay [ns]",
        ylabel="|FT(ratio - mean)| / |FT(mean)|",
        title="delay spectrum of the ratio",
    )
    _plot_drift(axes[3], c)
    if c.antennas.size * len(c.pols) <= 12:
        for i, ax in enumerate(axes):
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, ncol=2, loc="lower right" if i == 3 else "best")
    ref_files = c.summary.get("reference", {}).get("files", [])
    name = Path(ref_files[0]).name if ref_files else "reference"
    fig.suptitle(title or f"{c.mode} comparison with {name}", fontsize=10)
    return save_figure(fig, path)


def _fmt(value: Any, spec: str = ".3f") -> str:
    return "n/a" if value is None or not np.isfinite(value) else format(value, spec)


def _budget_text(row: dict[str, Any]) -> str:
    """One line per antenna/pol: offset, drift verdict and systematics."""
    parts = [
        f"ant {row['antenna']} {row['pol']}: offset {_fmt(row.get('offset'), '+.3f')} "
        f"+- {_fmt(row.get('offset_error'))} ({_fmt(row.get('offset_sigma'), '+.1f')} sigma)",
        f"ref drift {_fmt(row.get('reference_drift'), '+.1%')} vs auto "
        f"{_fmt(row.get('auto_drift'), '+.1%')}: "
        + {True: "stable", False: "UNSTABLE", None: "untested"}[row.get("reference_stable")],
    ]
    sysm = row.get("systematics") or {}
    om = (sysm.get("omega_source") or {}).get("shift")
    pc = sysm.get("pol_convention") or {}
    sky = sysm.get("sky_model") or {}
    if om is not None:
        parts.append(f"Omega(hera_sim) {om:+.1%}")
    if pc.get("shift") is not None:
        parts.append(f"pol '{pc['alternative']}' {pc['shift']:+.1%} ({pc['source']} {pc['used']})")
    if sky.get("spread_fraction") is not None:
        parts.append(f"sky spread {sky['spread_fraction']:.1%}")
    return "; ".join(parts)


def _plot_drift(ax: Any, c: Comparison) -> None:
    """Plot the reference's |g|^2(t)/mean and the raw auto's power/mean against time."""
    t0 = None
    if c.reference_jds is not None and c.reference_series is not None:
        t0 = float(c.reference_jds[0])
        minutes = (c.reference_jds - t0) * 1440.0
        for ia, ant in enumerate(c.antennas):
            for ip, pol in enumerate(c.pols):
                (line,) = ax.plot(
                    minutes,
                    c.reference_series[ia, ip],
                    lw=1,
                    marker=".",
                    label=f"ant {ant} {pol} ref",
                )
                if c.auto_series and (int(ant), pol) in c.auto_series:
                    jds, values = c.auto_series[(int(ant), pol)]
                    ax.plot(
                        (np.asarray(jds) - t0) * 1440.0,
                        values,
                        lw=1,
                        ls=":",
                        color=line.get_color(),
                        label=f"ant {ant} {pol} raw auto",
                    )
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set(
        xlabel="minutes since the first reference time",
        ylabel="value / time mean (median over band)",
        title="drift: reference |g_ref|^2 (solid) and raw auto power (dotted)",
    )
    lines = [_budget_text(row) for row in c.summary.get("per_antenna_pol", [])][:6]
    if lines:
        lo, hi = ax.get_ylim()  # headroom for the text above the curves
        ax.set_ylim(lo, hi + (hi - lo) * 0.1 * (len(lines) + 1))
        ax.text(
            0.01,
            0.98,
            "\n".join(lines),
            transform=ax.transAxes,
            fontsize=6.5,
            va="top",
            ha="left",
            bbox={"facecolor": "white", "alpha": 0.8, "lw": 0},
        )


def write_comparison(
    comparison: Comparison, out_dir: str | Path, *, overwrite: bool = False
) -> dict[str, Path]:
    """Write the JSON summary, the PNG plot and the arrays (HDF5) into ``out_dir``.

    Parameters
    ----------
    comparison
        The comparison.
    out_dir
        Output folder (created if missing).
    overwrite
        Replace existing output files.

    Returns
    -------
    dict
        ``{"json": path, "png": path, "h5": path}``.

    Raises
    ------
    FileExistsError
        If an output file exists and ``overwrite`` is false.
    """
    import h5py

    from autocal import __version__
    from autocal.core.files import atomic_path

    out_dir = Path(out_dir)
    paths = {k: out_dir / v for k, v in OUTPUT_NAMES.items()}
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{', '.join(existing)} exist(s); pass overwrite to replace")
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = _clean({"autocal_version": __version__, **comparison.summary})
    with atomic_path(paths["json"]) as tmp:
        tmp.write_text(json.dumps(summary, indent=2, sort_keys=False) + "\n")
    c = comparison
    with atomic_path(paths["h5"]) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs["format"] = "autocal-compare-1"
        h5.attrs["mode"] = c.mode
        h5.attrs["quantity"] = c.quantity
        h5.attrs["summary"] = json.dumps(summary)
        h5["antennas"] = c.antennas
        h5.create_dataset("pols", data=np.array(c.pols, dtype=object), dtype=h5py.string_dtype())
        h5["freqs"] = c.freqs
        for name in (
            "auto",
            "sigma_auto",
            "reference",
            "sigma_reference",
            "ratio",
            "sigma_ratio",
            "valid",
        ):
            h5[name] = getattr(c, name)
        for name in (
            "jy_per_k",
            "omega",
            "delays",
            "delay_amplitude",
            "reference_jds",
            "reference_series",
        ):
            value = getattr(c, name)
            if value is not None:
                h5[name] = value
        if c.auto_series:
            group = h5.create_group("auto_series")
            for (ant, pol), (jds, values) in c.auto_series.items():
                sub = group.create_group(f"{ant}_{pol}")
                sub["jds"] = np.asarray(jds, dtype=np.float64)
                sub["power_over_mean"] = np.asarray(values, dtype=np.float64)
    plot_comparison(c, paths["png"])
    logger.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return paths
