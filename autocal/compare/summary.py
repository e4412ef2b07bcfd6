"""The JSON summary of a comparison: per antenna/polarisation statistics and the method.

:func:`antenna_pol_summary` gathers one antenna/polarisation's ratio statistics, broadband
offset, reference drift and stability verdict, delay-spectrum peak and systematics budget;
:func:`comparison_summary` adds the provenance and a description of each method.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from autocal.compare.axes import MatchedAxes
from autocal.compare.budget import budget_row, budget_summary, sky_model_budget
from autocal.compare.conversion import KelvinConversion
from autocal.compare.drift import DRIFT_END_FRACTION
from autocal.compare.ratio import AutoGains, GainRatio
from autocal.compare.ratio_stats import (
    BOOTSTRAP_BLOCK_MHZ,
    BOOTSTRAP_RESAMPLES,
    BOOTSTRAP_SEED,
    broadband_offset,
    delay_peak,
    ratio_statistics,
)
from autocal.compare.reference import PreparedReference
from autocal.compare.stability import (
    REFERENCE_DRIFT_ALLOWANCE,
    REFERENCE_DRIFT_FACTOR,
    finite_or_none,
    implied_trxr,
    stability_verdict,
)

if TYPE_CHECKING:
    from autocal.fit.solution import Solution
    from autocal.io.calsol_read import ReferenceGains

#: How the reference is put onto the solution's channels.
INTERPOLATION_NOTE = "linear in frequency inside the reference range; flagged gaps not bridged"
#: How the broadband offset and its error are computed.
OFFSET_METHOD_NOTE = (
    f"offset = mean ratio - 1 over the compared channels; error = circular block "
    f"bootstrap over channels ({BOOTSTRAP_RESAMPLES} resamples, blocks of "
    f"{BOOTSTRAP_BLOCK_MHZ:g} MHz, seed {BOOTSTRAP_SEED}, bias-corrected by "
    "Richardson extrapolation from blocks L and L/2 and for the subtracted mean; "
    "at least the independent-channel error sqrt(sum sigma_r^2)/N), in quadrature "
    "with the channel-common errors: the reference's band-averaged scatter over "
    "time and the auto's systematic |g| error sqrt(total^2 - stat^2) taken as "
    "fully correlated across channels"
)
#: The reference stability rule (:mod:`autocal.compare.stability`).
STABILITY_RULE_NOTE = (
    f"unstable if |reference drift| > {REFERENCE_DRIFT_FACTOR:g} |auto drift| + "
    f"{REFERENCE_DRIFT_ALLOWANCE:g} (drift = median over channels of the fractional "
    f"change between the means of the first and last {DRIFT_END_FRACTION:g} of the "
    "integrations; |g_ref|^2 vs raw auto power), or (absolute) if R / (|g_ref|^2 J) "
    "- Tsky has a negative median over channels at either end; clauses without "
    "inputs are skipped; null when none could be tested"
)


@dataclass(frozen=True, eq=False)
class ComparisonParts:
    """The intermediate results of :func:`~autocal.compare.comparison.compare`.

    Attributes
    ----------
    mode
        ``"absolute"`` or ``"relative"``.
    axes
        The matched axes.
    auto
        autocal's ``|g|`` on them.
    reference
        The reference averaged and interpolated (before conversion).
    conversion
        The Jy->K conversion.
    ratio
        The compared quantities and their ratio.
    delays, delay_amplitude
        The ratio's delay spectra (:func:`~autocal.compare.ratio_stats.ratio_delay_spectra`).
    omega_hera_sim, omega_hera_sim_reason
        hera_sim's ``Omega_A`` for the budget, or ``None`` and why.
    """

    mode: str
    axes: MatchedAxes
    auto: AutoGains
    reference: PreparedReference
    conversion: KelvinConversion
    ratio: GainRatio
    delays: np.ndarray | None
    delay_amplitude: np.ndarray | None
    omega_hera_sim: np.ndarray | None
    omega_hera_sim_reason: str | None


def pick_input(value: Any, ant: int, pol: str, ia: int, ip: int, per_pol_ndim: int) -> Any:
    """Pick an optional per-antenna/pol input.

    ``value`` is a mapping keyed by ``(ant, pol)`` or ``pol``, a scalar, or an array
    indexed like the solution's antennas (when its dimensionality exceeds
    ``per_pol_ndim + 1``) and polarisations.

    Parameters
    ----------
    value
        The input, or ``None``.
    ant, pol
        Antenna number and polarisation name (mapping keys).
    ia, ip
        Their indices into the solution's axes (array inputs).
    per_pol_ndim
        Dimensionality of one antenna/pol's entry (0 for a scalar, 2 for ``(2, Nfreq)``).

    Returns
    -------
    object
        The entry, or ``None`` when ``value`` is ``None`` or a mapping without it.
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


def antenna_pol_summary(
    parts: ComparisonParts,
    ia: int,
    ip: int,
    *,
    auto_drift: Any,
    auto_power_ends: Any,
    tsky_ends: Any,
    alternatives: dict[str, Solution] | None,
) -> dict[str, Any]:
    """Return one antenna/polarisation's entry of ``per_antenna_pol``.

    Parameters
    ----------
    parts
        The comparison's intermediate results.
    ia, ip
        Indices into the compared antennas and polarisations.
    auto_drift, auto_power_ends, tsky_ends, alternatives
        See :func:`~autocal.compare.comparison.compare`.

    Returns
    -------
    dict
        ``antenna``, ``pol``, the ratio statistics, the offset, the drift and stability
        verdict, the delay peak and the systematics budget.
    """
    ant, pol = parts.axes.antennas[ia], parts.axes.pols[ip]
    stats = _channel_statistics(parts, ia, ip)
    stats.update(_drift_statistics(parts, ia, ip, auto_drift, auto_power_ends, tsky_ends))
    damp = parts.delay_amplitude
    stats.update(delay_peak(parts.delays, None if damp is None else damp[ia, ip]))
    stats["systematics"] = _systematics(parts, ia, ip, alternatives)
    return {"antenna": ant, "pol": pol, **stats}


def _channel_statistics(parts: ComparisonParts, ia: int, ip: int) -> dict[str, Any]:
    """Ratio statistics, error medians and the broadband offset of one antenna/pol."""
    g, auto, freqs = parts.ratio, parts.auto, parts.axes.freqs
    row_valid = g.valid[ia, ip]
    stats = ratio_statistics(
        g.ratio[ia, ip],
        g.sigma[ia, ip],
        row_valid,
        int(auto.ok[ia, ip].sum()),
        freqs.size,
    )
    stats["n_outside_reference_range"] = int((~parts.axes.in_range).sum())
    stats["reference_sigma_available"] = bool(
        np.isfinite(g.sigma_reference[ia, ip][row_valid]).any()
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        rel_auto = (g.sigma_auto / g.auto)[ia, ip][row_valid]
        rel_stat = (
            None if auto.sigma_stat is None else (auto.sigma_stat / auto.abs_g)[ia, ip][row_valid]
        )
    stats["sigma_auto_rel_median"] = float(np.median(rel_auto)) if rel_auto.size else None
    stats["sigma_auto_stat_rel_median"] = (
        float(np.nanmedian(rel_stat)) if rel_stat is not None and rel_stat.size else None
    )
    stats["sigma_reference_rel_median"] = (
        float(np.nanmedian(g.rel_reference[ia, ip][row_valid]))
        if stats["reference_sigma_available"]
        else None
    )
    # offset with frequency-correlated errors
    stats.update(
        broadband_offset(
            g.ratio[ia, ip],
            g.sigma[ia, ip],
            row_valid,
            freqs,
            float(parts.reference.common_rel[ia, ip]),
            None if g.auto_sys_rel is None else g.auto_sys_rel[ia, ip],
            None if g.sigma_stat is None else g.sigma_stat[ia, ip],
        )
    )
    return stats


def _drift_statistics(
    parts: ComparisonParts,
    ia: int,
    ip: int,
    auto_drift: Any,
    auto_power_ends: Any,
    tsky_ends: Any,
) -> dict[str, Any]:
    """Return the reference's drift against the raw auto's and the stability verdict."""
    axes = parts.axes
    ant, pol = axes.antennas[ia], axes.pols[ip]
    isa, isp = axes.sol_antennas[ia], axes.sol_pols[ip]
    d = parts.reference.drifts[ia][ip]
    change = pick_input(auto_drift, ant, pol, isa, isp, 0)
    change = finite_or_none(change)
    trxr, trxr_skip = implied_trxr(
        parts.mode,
        parts.conversion.kfac,
        d,
        axes.ref_freqs[parts.reference.band],
        axes.freqs,
        parts.auto.ok[ia, ip],
        ip,
        pick_input(auto_power_ends, ant, pol, isa, isp, 2),
        pick_input(tsky_ends, ant, pol, isa, isp, 2),
    )
    stability = stability_verdict(parts.mode, d, change, trxr, trxr_skip)
    return {
        "reference_drift": finite_or_none(d["change"]),
        "reference_drift_rms": finite_or_none(d["rms"]),
        "reference_drift_integrations": {"end": d["n_end"], "valid": d["n_valid"]},
        "auto_drift": change,
        "reference_stable": stability.pop("stable"),
        "reference_stability": stability,
    }


def _systematics(
    parts: ComparisonParts, ia: int, ip: int, alternatives: dict[str, Solution] | None
) -> dict[str, Any] | None:
    """Return the systematics budget of one antenna/pol (absolute mode, else ``None``)."""
    g, mode, om = parts.ratio, parts.mode, parts.conversion.omega
    ant, pol = parts.axes.antennas[ia], parts.axes.pols[ip]
    row_valid = g.valid[ia, ip]
    return budget_row(
        mode,
        g.ratio[ia, ip],
        row_valid,
        None if om is None else om[ip],
        parts.omega_hera_sim,
        parts.omega_hera_sim_reason,
        parts.conversion.pol_convention,
        sky_model_budget(
            alternatives,
            ant,
            pol,
            parts.axes.freqs,
            g.reference[ia, ip],
            g.ratio[ia, ip],
            row_valid,
        )
        if mode == "absolute"
        else None,
    )


def comparison_summary(
    parts: ComparisonParts,
    solution: Solution,
    reference: ReferenceGains,
    smooth_mhz: float | None,
    per: list[dict[str, Any]],
) -> dict[str, Any]:
    """Return the JSON-ready summary of a comparison.

    Parameters
    ----------
    parts
        The comparison's intermediate results.
    solution, reference
        The compared solution and reference (for their descriptions).
    smooth_mhz
        The smoothing FWHM (MHz), or ``None``/0.
    per
        The :func:`antenna_pol_summary` entries.

    Returns
    -------
    dict
        Mode, axes, provenance of both sides, the time match, each method's description,
        the systematics budget and ``per_antenna_pol``.
    """
    mode, freqs = parts.mode, parts.axes.freqs
    conv = parts.conversion
    return {
        "mode": mode,
        "quantity": parts.ratio.quantity,
        "expected_ratio": 1.0,
        "antennas": parts.axes.antennas,
        "pols": parts.axes.pols,
        "solution": _solution_entry(solution, freqs),
        "reference": reference.describe(),
        "time_match": parts.reference.time_info,
        "smoothing": (
            {"kernel": "gaussian", "fwhm_MHz": float(smooth_mhz), "applied_to": "each time"}
            if smooth_mhz
            else {"kernel": None}
        ),
        "interpolation": INTERPOLATION_NOTE,
        "conversion": conv.info,
        "reference_sigma": (
            "std over the selected reference times of |g_ref| per channel (ddof=1): the "
            "scatter of a single-time reference, not divided by sqrt(N_t)"
            + (
                "; each time normalised by its band mean first (relative)"
                if mode == "relative"
                else ""
            )
        ),
        "offset_method": OFFSET_METHOD_NOTE,
        "reference_stability_rule": STABILITY_RULE_NOTE,
        "systematics": budget_summary(
            mode,
            parts.axes.pols,
            freqs,
            conv.omega,
            parts.omega_hera_sim,
            parts.omega_hera_sim_reason,
            conv.pol_convention,
        ),
        "per_antenna_pol": per,
    }


def _solution_entry(solution: Solution, freqs: np.ndarray) -> dict[str, Any]:
    """Return the compared solution's channels, times, model, configuration and error kind."""
    return {
        "nfreq": int(freqs.size),
        "freq_range_Hz": [float(freqs.min()), float(freqs.max())],
        "ntime": len(solution.jds),
        "model": solution.model.describe(),
        "config": solution.config,
        "sigma_abs_g": "total (statistical + data-driven)"
        if getattr(solution, "total", None) is not None
        else "statistical",
    }
