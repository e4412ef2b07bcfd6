"""Drift of a positive quantity over a span: the reference's gains and the raw autos.

:func:`fractional_end_change` measures the fractional change between the means of the
first and the last :data:`DRIFT_END_FRACTION` of the integrations (median over channels);
:func:`auto_trend` applies it to the raw auto-correlation power so that the reference's
drift (``|g_ref|^2``) can be set against the autos' own (the stability rule of
:mod:`autocal.compare.stability`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from autocal.compare.errors import CompareError

#: Fraction of the integrations averaged at each end of the span to measure a drift.
DRIFT_END_FRACTION = 0.1


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
    """Return the raw autos' drift, end powers and time series as ``compare`` arguments.

    The result is passed on to :func:`~autocal.compare.comparison.compare`.

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
