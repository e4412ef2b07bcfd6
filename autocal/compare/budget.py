"""The systematics budget of an absolute comparison (step 9 of the procedure).

Per antenna and polarisation (:func:`budget_row`): the shift of the mean ratio if
``Omega_A`` came from hera_sim's H1C beam integrals (the ratio scales as
``Omega_A^-1/2``; :func:`hera_sim_budget_omega`), under the other pseudo-Stokes
convention, and over alternative sky models (:func:`sky_model_budget`); per polarisation
(:func:`budget_summary`): the solid angles behind those shifts. See
:mod:`autocal.compare.comparison`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from autocal.compare.beam_area import hera_sim_omega, report_channel

if TYPE_CHECKING:
    from autocal.fit.solution import Solution

logger = logging.getLogger(__name__)


def hera_sim_budget_omega(
    mode: str, om: np.ndarray | None, freqs: np.ndarray, beam_integrals: str | Path | None
) -> tuple[np.ndarray | None, str | None]:
    """Return hera_sim's ``Omega_A`` on ``freqs`` for the budget, or ``None`` and why not.

    Parameters
    ----------
    mode
        ``"absolute"`` or ``"relative"``.
    om
        autocal's ``Omega_A`` of the Jy->K conversion, or ``None`` when there was none.
    freqs
        ``(Nfreq,)`` Hz.
    beam_integrals
        hera_sim's ``HERA_H1C_BEAM_INTEGRALS.npz`` (default: the data folder's).

    Returns
    -------
    omega, reason
        ``(Nfreq,)`` sr (NaN outside the table) and ``None``, or ``None`` and the reason.
    """
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
    return om_hs, om_hs_reason


def sky_model_budget(
    alternatives: dict[str, Solution] | None,
    ant: int,
    pol: str,
    freqs: np.ndarray,
    ref_c: np.ndarray,
    ratio: np.ndarray,
    valid: np.ndarray,
) -> dict[str, Any] | None:
    """Return the ratio means under alternative sky models for one antenna/pol (absolute).

    Parameters
    ----------
    alternatives
        ``{name: Solution}`` fitted with other sky models, or ``None``.
    ant, pol
        The antenna and polarisation.
    freqs
        ``(Nfreq,)`` the compared solution's channels (Hz).
    ref_c
        ``(Nfreq,)`` the reference in kelvin units.
    ratio
        ``(Nfreq,)`` the compared solution's ratio.
    valid
        ``(Nfreq,)`` its compared channels.

    Returns
    -------
    dict or None
        Each alternative's mean ratio and shift (or why it was skipped) and the spread
        of the mean ratio; ``None`` without alternatives.
    """
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


def budget_row(
    mode: str,
    ratio: np.ndarray,
    valid: np.ndarray,
    om: np.ndarray | None,
    om_hs: np.ndarray | None,
    om_hs_reason: str | None,
    pol_conv: dict[str, Any] | None,
    sky: dict[str, Any] | None,
) -> dict[str, Any] | None:
    """Return the systematics budget of one antenna/polarisation (absolute mode).

    Parameters
    ----------
    mode
        ``"absolute"`` or ``"relative"`` (relative: no budget).
    ratio, valid
        ``(Nfreq,)`` the ratio and the compared channels.
    om
        ``(Nfreq,)`` autocal's ``Omega_A`` for this polarisation, or ``None``.
    om_hs, om_hs_reason
        From :func:`hera_sim_budget_omega`.
    pol_conv
        The pol convention stated and used, or ``None`` without a Jy->K conversion.
    sky
        :func:`sky_model_budget`'s entry.

    Returns
    -------
    dict or None
        ``omega_source``, ``pol_convention`` and ``sky_model`` entries.
    """
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


def budget_summary(
    mode: str,
    pols: list[str],
    freqs: np.ndarray,
    om: np.ndarray | None,
    om_hs: np.ndarray | None,
    om_hs_reason: str | None,
    pol_conv: dict[str, Any] | None,
) -> dict[str, Any] | None:
    """Return the polarisation-level facts of the systematics budget (absolute mode).

    Parameters
    ----------
    mode
        ``"absolute"`` or ``"relative"`` (relative: no budget).
    pols
        Compared polarisations.
    freqs
        ``(Nfreq,)`` Hz.
    om
        ``(Npol, Nfreq)`` autocal's ``Omega_A``, or ``None``.
    om_hs, om_hs_reason
        From :func:`hera_sim_budget_omega`.
    pol_conv
        The pol convention stated and used, or ``None``.

    Returns
    -------
    dict or None
        Solid angles per polarisation at one frequency and notes on each budget entry.
    """
    if mode != "absolute":
        return None
    k = report_channel(freqs)
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
