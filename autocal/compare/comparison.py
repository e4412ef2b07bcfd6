r"""Compare gains from auto-correlations with gains from cross-correlation calibration.

:func:`compare` runs the procedure below in named steps, each in its own module
(:mod:`~autocal.compare.axes`, :mod:`~autocal.compare.reference`,
:mod:`~autocal.compare.conversion`, :mod:`~autocal.compare.ratio`,
:mod:`~autocal.compare.ratio_stats`, :mod:`~autocal.compare.stability`,
:mod:`~autocal.compare.budget`, :mod:`~autocal.compare.summary`) and returns a
:class:`Comparison`; :mod:`~autocal.compare.report` writes it.

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
``J(nu) = 2 k_B Omega_A / lambda^2 * 1e26`` (Jy per K) and equating the raw power::

    R = |g_ref|^2 V_Jy = |g_ref|^2 J T = |g_auto|^2 T
    =>  |g_auto|^2 = |g_ref|^2 J(nu),   |g_ref,K| = |g_ref| sqrt(J(nu)).

The comparison is ``|g_auto| / |g_ref,K|``, expected to be 1. Sanity check (README of the
data folder: ``raw/|g|^2 ~ 6900 Jy ~ 255 K at 150 MHz for antenna 23``): the Fagnoni beam
gives ``Omega_A = 0.0411 sr`` at 150 MHz, ``J = 28.42 Jy/K``; the median of
``R / |g_ref|^2`` for antenna 23 (ee, 36 integrations, 11 channels around 150 MHz) is
7030 Jy = 247 K (nn: 6530 Jy = 230 K). The README's 255 K corresponds to
``Omega_A = 0.039 sr``, hera_sim's integral of its H1C beam model.
``Omega_A`` is computed from autocal's beam objects on a HEALPix grid
(:func:`~autocal.compare.beam_area.beam_solid_angle`) and, for UVBeam files,
cross-checked against pyuvdata's ``UVBeam.get_beam_area``
(:func:`~autocal.compare.beam_area.uvbeam_solid_angle`). A reference with
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
2. Reference drift (:func:`~autocal.compare.drift.fractional_end_change`, per antenna
   and polarisation, on the reference channels inside the solution's band): the
   fractional change of ``|g_ref|^2`` between the means of the first and last
   :data:`~autocal.compare.drift.DRIFT_END_FRACTION` of the selected integrations
   (median over channels) and its rms over time, set against the raw auto's own change
   over the same span when the caller supplies it (``auto_drift``;
   :func:`~autocal.compare.drift.auto_trend` computes it from the raw autos with the
   same statistic). The reference is *unstable* (``reference_stable: false``) when

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
   (:func:`~autocal.compare.ratio_stats.block_bootstrap_error`): a circular block
   bootstrap over channels (blocks of :data:`~autocal.compare.ratio_stats.BOOTSTRAP_BLOCK_MHZ`,
   :data:`~autocal.compare.ratio_stats.BOOTSTRAP_RESAMPLES` resamples, seeded),
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

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from autocal.compare.axes import MatchedAxes, index_axes, match_axes
from autocal.compare.budget import hera_sim_budget_omega
from autocal.compare.conversion import convert_reference
from autocal.compare.errors import CompareError
from autocal.compare.ratio import auto_gains, gain_ratio
from autocal.compare.ratio_stats import ratio_delay_spectra
from autocal.compare.reference import prepare_reference
from autocal.compare.summary import (
    ComparisonParts,
    antenna_pol_summary,
    comparison_summary,
    pick_input,
)
from autocal.core.reprs import compact_repr

if TYPE_CHECKING:
    from autocal.fit.solution import Solution
    from autocal.io.calsol_read import ReferenceGains

logger = logging.getLogger(__name__)


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
        them (see :func:`~autocal.compare.drift.auto_trend`), else ``None``.
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
        return compact_repr(self)


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
        An :class:`autocal.fit.solution.Solution`.
    reference
        :class:`autocal.io.calsol_read.ReferenceGains`.
    antennas, pols
        What to compare (default: everything the two have in common).
    smooth_mhz
        FWHM (MHz) of the Gaussian kernel smoothing the reference along frequency.
    mode
        ``"absolute"`` or ``"relative"`` (default: from ``reference.absolute``).
    beam
        Beam for ``Omega_A`` (absolute Jy-referenced gains): ``"hera"`` (Fagnoni
        beamfits), a file, a name for :func:`autocal.sky.beam_names.get_beam` or a ``Beam``.
        Default: the beam recorded in the solution's configuration (the one its Tsky
        used), else ``"hera"``.
    nside
        HEALPix resolution of the ``Omega_A`` integral (default: see
        :func:`~autocal.compare.beam_area.beam_solid_angle`).
    omega
        Precomputed ``Omega_A`` in sr, ``(Npol, Nfreq)`` or ``(Nfreq,)`` on the
        solution's channels (skips the beam integral).
    auto_drift
        The raw auto's fractional change over the span
        (:func:`~autocal.compare.drift.fractional_end_change`
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
    :func:`~autocal.compare.drift.auto_trend` turns raw autos (and Tsky) into ``auto_drift``,
    ``auto_power_ends``, ``tsky_ends`` and ``auto_series``.
    """
    ants, use_pols = match_axes(solution, reference, antennas, pols)
    mode = mode or ("absolute" if reference.absolute else "relative")
    if mode not in ("absolute", "relative"):
        raise CompareError(f"mode must be 'absolute' or 'relative', got {mode!r}")
    axes = index_axes(solution, reference, ants, use_pols)
    auto = auto_gains(solution, axes)
    ref = prepare_reference(reference, axes, solution.jds, mode, smooth_mhz)
    conversion = convert_reference(
        mode, reference, solution.config, beam, use_pols, axes.freqs, nside, omega
    )
    g = gain_ratio(mode, auto, conversion.apply(ref.amplitude), conversion.apply(ref.sigma))
    delays, damp = ratio_delay_spectra(g.ratio, g.valid, axes.freqs)
    om_hs, om_hs_reason = hera_sim_budget_omega(mode, conversion.omega, axes.freqs, beam_integrals)
    parts = ComparisonParts(
        mode=mode,
        axes=axes,
        auto=auto,
        reference=ref,
        conversion=conversion,
        ratio=g,
        delays=delays,
        delay_amplitude=damp,
        omega_hera_sim=om_hs,
        omega_hera_sim_reason=om_hs_reason,
    )
    per = [
        antenna_pol_summary(
            parts,
            ia,
            ip,
            auto_drift=auto_drift,
            auto_power_ends=auto_power_ends,
            tsky_ends=tsky_ends,
            alternatives=alternatives,
        )
        for ia in range(len(ants))
        for ip in range(len(use_pols))
    ]
    summary = comparison_summary(parts, solution, reference, smooth_mhz, per)
    logger.info(
        "compared %d antenna(s) x %d pol(s) (%s): median ratio %s",
        len(ants),
        len(use_pols),
        mode,
        f"{np.nanmedian(g.ratio):.4g}",
    )
    return Comparison(
        mode=mode,
        quantity=g.quantity,
        antennas=np.asarray(ants, dtype=np.int64),
        pols=tuple(use_pols),
        freqs=axes.freqs,
        auto=np.where(auto.ok, g.auto, np.nan),
        sigma_auto=np.where(auto.ok, g.sigma_auto, np.nan),
        reference=g.reference,
        sigma_reference=g.sigma_reference,
        ratio=g.ratio,
        sigma_ratio=g.sigma,
        valid=g.valid,
        jy_per_k=conversion.jy_per_k,
        omega=conversion.omega,
        delays=delays,
        delay_amplitude=damp,
        summary=summary,
        reference_jds=np.asarray(reference.jds)[ref.times],
        reference_series=np.array([[d["series"] for d in row] for row in ref.drifts]),
        auto_series=_auto_series(auto_series, axes),
    )


def _auto_series(
    auto_series: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] | None, axes: MatchedAxes
) -> dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] | None:
    """Return the raw autos' time series of the compared antennas/pols (for the figure)."""
    series = None
    if auto_series:
        series = {}
        for ia, ant in enumerate(axes.antennas):
            for ip, pol in enumerate(axes.pols):
                item = pick_input(
                    auto_series, ant, pol, axes.sol_antennas[ia], axes.sol_pols[ip], 0
                )
                if item is not None:
                    series[(ant, pol)] = (np.asarray(item[0]), np.asarray(item[1]))
    return series or None
