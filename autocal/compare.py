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
2. Time average ``|g_ref| = sqrt(mean_t |g_ref(t)|^2)`` (like autocal's time-averaged
   ``G``), flagged samples excluded; its uncertainty is the standard error of the mean,
   ``std_t(|g_ref|) / sqrt(N_t)`` (unavailable with one time: the combined uncertainty
   is then the autos' alone).
3. Optional smoothing of the reference along frequency with a Gaussian kernel of FWHM
   ``smooth_mhz`` MHz (normalised over unflagged channels; flagged channels stay flagged;
   the uncertainty is propagated as for independent channels).
4. Linear interpolation onto the solution's channels, only inside the reference's range
   and only between unflagged reference channels.
5. Conversion (absolute) or normalisation (relative), ratio
   ``r = |g_auto| / |g_ref|``, its uncertainty
   ``sigma_r = r sqrt((sigma_auto/|g_auto|)^2 + (sigma_ref/|g_ref|)^2)``, the agreement
   ``(r - 1) / sigma_r`` and the delay spectrum of ``r``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from autocal.fit import Solution
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


class CompareError(ValueError):
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
    :class:`~autocal.beams.HealpixFileBeam` at the file's own resolution (no harmonic
    upsampling, whose ringing would bias the peak); other specifications go through
    :func:`autocal.beams.get_beam`.
    """
    from autocal.beams import Beam, HealpixFileBeam, get_beam
    from autocal.io.datasets import HERA_BEAM_FILE, data_file

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
        A :class:`~autocal.beams.Beam` or a specification for :func:`resolve_beam`.
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

    from autocal.beams import HealpixFileBeam

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
        ``"nearest"``, counts, JD ranges, offset in days for ``"nearest"``).
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
    }
    if inside.size:
        info.update(match="overlap", ntimes=int(inside.size))
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
    info.update(match="nearest", ntimes=1, offset_days=offset)
    return np.array([best]), info


def time_average(amp: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average ``|g|`` over the time axis (-2) ignoring NaN.

    Returns ``sqrt(mean |g|^2)``, the standard error ``std(|g|, ddof=1) / sqrt(N)``
    (NaN where fewer than two samples) and the sample counts.
    """
    finite = np.isfinite(amp)
    count = finite.sum(axis=-2)
    filled = np.where(finite, amp, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_sq = (filled**2).sum(axis=-2) / count
        mean = filled.sum(axis=-2) / count
        var = (np.where(finite, (amp - mean[..., None, :]) ** 2, 0.0)).sum(axis=-2) / (count - 1)
        sigma = np.where(count >= 2, np.sqrt(var / count), np.nan)
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
        (absolute) or normalised (relative); ``sigma_reference`` is NaN where unknown.
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
    from autocal.delay import DelayError, delay_spectrum

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
) -> Comparison:
    """Compare a solution's ``|g|`` with reference gains (see the module notes).

    Parameters
    ----------
    solution
        An :class:`autocal.fit.Solution`.
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
        beamfits), a file, a name for :func:`autocal.beams.get_beam` or a ``Beam``.
        Default: the beam recorded in the solution's configuration (the one its Tsky
        used), else ``"hera"``.
    nside
        HEALPix resolution of the ``Omega_A`` integral (default: see
        :func:`beam_solid_angle`).
    omega
        Precomputed ``Omega_A`` in sr, ``(Npol, Nfreq)`` or ``(Nfreq,)`` on the
        solution's channels (skips the beam integral).

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
    with np.errstate(invalid="ignore", divide="ignore"):
        auto = np.asarray(solution.abs_g)[idx_sol]
        sigma_auto = np.asarray(solution.sigma_abs_g)[idx_sol]
    auto_ok = (
        ~np.asarray(solution.flags)[idx_sol]
        & np.isfinite(auto)
        & (auto > 0)
        & np.isfinite(sigma_auto)
    )

    tsel, time_info = select_reference_times(reference.jds, solution.jds)
    amp = reference.abs_g[np.ix_(ia_ref, ip_ref, tsel, np.arange(ref_freqs.size))]
    ref_avg, ref_sig, _ = time_average(amp)
    if smooth_mhz:
        ref_avg, ref_sig = smooth_frequency(ref_freqs, ref_avg, ref_sig, float(smooth_mhz))
    ref_i = interpolate_frequency(ref_freqs, ref_avg, freqs)
    sig_i = interpolate_frequency(ref_freqs, np.where(np.isfinite(ref_avg), ref_sig, np.nan), freqs)
    sig_i = np.where(np.isfinite(ref_i), sig_i, np.nan)

    jpk = om = None
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
        elif scale.lower() == "jy":
            if beam is None and omega is None:
                beam = beam_from_config(solution.config)
            om, conversion = _omega(beam, use_pols, freqs, nside, omega)
            jpk = jy_per_kelvin(freqs[None, :], om)
            factor = np.sqrt(jpk)[None, :, :]
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
    else:
        quantity = "|g| = sqrt(G) in sqrt(raw/K)"
        auto_c, sig_auto_c, ref_c, sig_ref_c = auto, sigma_auto, ref_i, sig_i
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(valid, auto_c / ref_c, np.nan)
        rel_ref = np.where(np.isfinite(sig_ref_c), sig_ref_c / ref_c, 0.0)
        sigma_ratio = np.where(
            valid, np.abs(ratio) * np.sqrt((sig_auto_c / auto_c) ** 2 + rel_ref**2), np.nan
        )
    delays, damp = _delay(ratio, valid, freqs)

    per: list[dict[str, Any]] = []
    for ia, ant in enumerate(ants):
        for ip, pol in enumerate(use_pols):
            stats = _stats(
                ratio[ia, ip],
                sigma_ratio[ia, ip],
                valid[ia, ip],
                int(auto_ok[ia, ip].sum()),
                freqs.size,
            )
            stats["n_outside_reference_range"] = int((~in_range).sum())
            stats["reference_sigma_available"] = bool(
                np.isfinite(sig_ref_c[ia, ip][valid[ia, ip]]).any()
            )
            if damp is not None and delays is not None:
                beyond = delays * 1e9 > DELAY_REPORT_NS
                row = damp[ia, ip]
                if beyond.any() and np.isfinite(row[beyond]).any():
                    k = int(np.nanargmax(np.where(beyond, row, np.nan)))
                    stats["delay_max_beyond_ns"] = DELAY_REPORT_NS
                    stats["delay_max_amplitude"] = float(row[k])
                    stats["delay_of_max_ns"] = float(delays[k] * 1e9)
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
        },
        "reference": reference.describe(),
        "time_match": time_info,
        "smoothing": (
            {"kernel": "gaussian", "fwhm_MHz": float(smooth_mhz)}
            if smooth_mhz
            else {"kernel": None}
        ),
        "interpolation": "linear in frequency inside the reference range; flagged gaps not bridged",
        "conversion": conversion,
        "per_antenna_pol": per,
    }
    logger.info(
        "compared %d antenna(s) x %d pol(s) (%s): median ratio %s",
        len(ants),
        len(use_pols),
        mode,
        f"{np.nanmedian(ratio):.4g}",
    )
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
    )


def _omega(
    beam: Any, pols: list[str], freqs: np.ndarray, nside: int | None, omega: np.ndarray | None
) -> tuple[np.ndarray, dict[str, Any]]:
    """``Omega_A`` (Npol, Nfreq) and a description with the UVBeam cross-check."""
    from autocal.beams import HealpixFileBeam

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
    """Plot the compared gains, the ratio with its 2-sigma band, and its delay spectrum.

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
    from autocal.plots import _figure, band, save_figure

    c = comparison
    fmhz = c.freqs / 1e6
    fig, axes = _figure(3, 1, (9, 10))
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
    if c.antennas.size * len(c.pols) <= 12:
        for ax in axes:
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, ncol=2)
    ref_files = c.summary.get("reference", {}).get("files", [])
    name = Path(ref_files[0]).name if ref_files else "reference"
    fig.suptitle(title or f"{c.mode} comparison with {name}", fontsize=10)
    return save_figure(fig, path)


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
    from autocal.io.tskyfile import atomic_path

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
        for name in ("jy_per_k", "omega", "delays", "delay_amplitude"):
            value = getattr(c, name)
            if value is not None:
                h5[name] = value
    plot_comparison(c, paths["png"])
    logger.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return paths
