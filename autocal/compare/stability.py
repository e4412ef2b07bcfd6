"""Is the reference stable over the span? The rule of step 2 of the comparison procedure.

The reference is *unstable* when its drift exceeds what the raw auto's own change allows,
``|reference change| > REFERENCE_DRIFT_FACTOR |auto change| + REFERENCE_DRIFT_ALLOWANCE``,
or (absolute mode) when the receiver temperature it implies, ``R / (|g_ref|^2 J) - Tsky``
(:func:`implied_trxr`), has a negative median at either end of the span
(:func:`stability_verdict`; see :mod:`autocal.compare.comparison`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from autocal.compare.reference import interpolate_frequency

#: Stability rule: the reference is unstable when its fractional change of ``|g|^2``
#: exceeds ``REFERENCE_DRIFT_FACTOR * |auto change| + REFERENCE_DRIFT_ALLOWANCE``.
REFERENCE_DRIFT_FACTOR = 3.0
#: See :data:`REFERENCE_DRIFT_FACTOR` (a fraction: 0.05 = 5 %).
REFERENCE_DRIFT_ALLOWANCE = 0.05


def finite_or_none(value: Any) -> float | None:
    """Return ``value`` as a float, ``None`` when it is ``None`` or not finite."""
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None


def stability_verdict(
    mode: str,
    drift: dict[str, Any],
    auto_change: float | None,
    trxr: dict[str, Any] | None,
    trxr_skip: str,
) -> dict[str, Any]:
    """Apply the reference stability rule (module notes) to one antenna/polarisation.

    Parameters
    ----------
    mode
        ``"absolute"`` or ``"relative"`` (relative references are not tested).
    drift
        The reference's :func:`~autocal.compare.drift.fractional_end_change`.
    auto_change
        The raw auto's fractional change over the span, or ``None``.
    trxr
        :func:`implied_trxr`'s medians at the two ends, or ``None``.
    trxr_skip
        Why ``trxr`` is ``None``.

    Returns
    -------
    dict
        ``stable`` (``None`` when no clause could be tested), the clauses ``tested``,
        ``failed`` and ``skipped`` (with reasons), ``drift_limit`` and ``implied_trxr_K``.
    """
    tested: list[str] = []
    failed: list[str] = []
    skipped: dict[str, str] = {}
    ref_change = finite_or_none(drift["change"])
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


def implied_trxr(
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
    """Return ``R / (|g_ref|^2 J) - Tsky`` (median over channels) at the span's two ends.

    Parameters
    ----------
    mode
        ``"absolute"`` or ``"relative"``.
    kfac
        ``(Npol, Nfreq)`` Jy per K of the conversion (with the pol convention), or ``None``.
    drift
        The reference's :func:`~autocal.compare.drift.fractional_end_change` of
        ``|g_ref|^2`` on ``band_freqs`` (its ``first`` and ``last`` end means are used).
    band_freqs
        The reference channels of ``drift`` (Hz).
    freqs
        The solution's channels (Hz).
    ok
        ``(Nfreq,)`` the solution's valid channels.
    ip
        Polarisation index into ``kfac``.
    power_ends, tsky_ends
        Raw auto power and model Tsky (K) at the two ends, ``(2, Nfreq)``, or ``None``.

    Returns
    -------
    trxr, reason
        ``{"first": K or None, "last": K or None}`` and ``""``, or ``None`` and why the
        clause cannot be tested.
    """
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
