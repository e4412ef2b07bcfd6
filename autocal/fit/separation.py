"""How well a span separates gain from receiver noise, per channel and per antenna-pol.

Over a short span the sky changes by a few per cent of the system temperature (or less),
so ``G`` and ``n`` separate weakly. The diagnostics here come from the normal sums alone:
the sky's contrast (:func:`sky_contrast`), how far an unmodelled gain drift would move the
fitted ``G`` (:func:`drift_sensitivity`) and the profile ``G(Trxr)``, what ``G`` is if the
receiver temperature is known (:func:`profile_gain`). :func:`separation_summary` reports
them, with a solution's error budget, per antenna and polarisation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from autocal.fit.blocks import base_index
from autocal.fit.centring import centre_rhs, sky_mean, uncentre
from autocal.fit.finite import finite_trailing
from autocal.fit.model import FitModel
from autocal.fit.sums import NormalSums

#: separate weakly: a 1 % gain drift over the span would move ``G`` by more than 10 %.
WEAK_SENSITIVITY = 10.0
#: Assumed receiver temperatures (K) of the ``G(Trxr)`` profile, extended to cover the
#: fitted ``Trxr`` when it lies outside.
PROFILE_TRXR = np.arange(0.0, 501.0, 50.0)
#: A description of the method, recorded in the products.


def nanmedian_last(x: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN (NaN where all are NaN), without warnings."""
    srt = np.sort(x, axis=-1)  # NaN last
    n = np.sum(np.isfinite(x), axis=-1)
    lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[..., None], axis=-1)[..., 0]
    return np.where(n > 0, (lo + hi) / 2, np.nan)


def sky_contrast(sums: NormalSums, model: FitModel, theta: np.ndarray) -> np.ndarray:
    """Weighted rms of Tsky over ``mean(Tsky) + Trxr`` from the fitted model's sums."""
    nb = model.nbasis
    sw = sums.ata[..., nb, nb]  # sum w P_0^2
    swt = sums.ata[..., 0, nb]  # sum w T
    swt2 = sums.ata[..., 0, 0]  # sum w T^2
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = swt / sw
        var = np.maximum(swt2 / sw - mean**2, 0.0)
        tsys = mean + theta[..., 1] / theta[..., 0]
        return np.sqrt(var) / np.abs(tsys)


def drift_sensitivity(
    ext_sums: NormalSums, model: FitModel, theta: np.ndarray, vg: np.ndarray
) -> np.ndarray:
    """``(dG/G)/delta`` of the fitted model for a gain change of the next order's shape.

    The unmodelled gain ``G (1 + delta P_{p+1}(s) / 2)`` (and ``n`` in proportion, a gain
    that multiplies the whole system temperature) adds ``delta/2 (G, n)`` to the next
    order's coefficients; least squares maps that onto the fitted parameters by
    ``A^-1 B`` (``A`` the fitted model's normal matrix, ``B`` its cross terms with the
    next order's columns).
    """
    nb = model.nbasis
    idx = base_index(model)
    new = np.array([nb, 2 * nb + 1])
    a = ext_sums.ata[..., idx[:, None], idx[None, :]]
    b = ext_sums.ata[..., idx[:, None], new[None, :]]
    ok = finite_trailing(theta)
    rhs = b @ np.where(ok[..., None], theta, 0.0)[..., None] / 2.0  # (..., m, 1)
    eye = np.eye(a.shape[-1])
    # solved in the sky-centred frame, as the fit is (a short span's A is ill-conditioned)
    c = sky_mean(a)
    from autocal.fit.centring_kernel import centre_many  # numba: the same values as centre

    a, rhs = centre_many(a, c), centre_rhs(rhs[..., 0], c)[..., None]
    if a.shape[-1] == 2:  # the constant model: Cramer's rule, not a LAPACK call per channel
        return _drift_sensitivity_2x2(a, rhs[..., 0], ok, c, vg, theta)
    good = ok & (np.linalg.det(np.where(ok[..., None, None], a, eye)) != 0)
    with np.errstate(all="ignore"):
        dx = uncentre(np.linalg.solve(np.where(good[..., None, None], a, eye), rhs)[..., 0], c)
        return np.where(good, (dx @ vg) / theta[..., 0], np.nan)


def _drift_sensitivity_2x2(
    a: np.ndarray,
    rhs: np.ndarray,
    ok: np.ndarray,
    c: np.ndarray,
    vg: np.ndarray,
    theta: np.ndarray,
) -> np.ndarray:
    """:func:`drift_sensitivity`'s solve for ``(G, n)`` systems in closed form.

    On a HERA file's million channels batched ``numpy.linalg.det`` and ``solve`` spend
    ~1 s in per-matrix overhead; the same solution (to rounding: tested against them in
    ``tests/fit/test_separation.py``) by Cramer's rule costs a few array operations.
    """
    with np.errstate(all="ignore"):
        det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
        good = ok & np.isfinite(det) & (det != 0)
        x0 = (rhs[..., 0] * a[..., 1, 1] - a[..., 0, 1] * rhs[..., 1]) / det
        x1 = (a[..., 0, 0] * rhs[..., 1] - a[..., 1, 0] * rhs[..., 0]) / det
        dx = uncentre(np.stack([x0, x1], axis=-1), c)
        return np.where(good, (dx @ vg) / theta[..., 0], np.nan)


def profile_grid(theta: np.ndarray) -> np.ndarray:
    """:data:`PROFILE_TRXR`, extended in 50 K steps to cover the fitted ``Trxr``."""
    with np.errstate(all="ignore"):
        trxr = theta[..., 1] / theta[..., 0]
    trxr = trxr[np.isfinite(trxr)]
    lo, hi = float(PROFILE_TRXR[0]), float(PROFILE_TRXR[-1])
    if trxr.size:
        lo = min(lo, 50.0 * np.floor(np.percentile(trxr, 5) / 50.0))
        hi = max(hi, 50.0 * np.ceil(np.percentile(trxr, 95) / 50.0))
    return np.arange(lo, hi + 1.0, 50.0)


def profile_gain(sums: NormalSums, model: FitModel, vg: np.ndarray, trxr: np.ndarray) -> np.ndarray:
    """Time-averaged ``G`` fitted with ``n(t) = G(t) Trxr`` for each assumed ``Trxr``.

    The model ``R = G(t) (Tsky + Trxr)`` is linear in the gain coefficients alone; its
    normal equations follow from the fitted model's sums.

    Parameters
    ----------
    sums
        The fitted model's normal sums.
    model
        The fitted model.
    vg
        Time-average vector of the gain coefficients (length ``nparam``).
    trxr
        ``(Ngrid,)`` assumed receiver temperatures, K.

    Returns
    -------
    numpy.ndarray
        ``(Nant, Npol, Ngrid, Nfreq)``; NaN where the reduced system is singular.
    """
    nb = model.nbasis
    g, n = slice(0, nb), slice(nb, 2 * nb)
    agg, agn, ann = sums.ata[..., g, g], sums.ata[..., g, n], sums.ata[..., n, n]
    ag, an = sums.aty[..., g], sums.aty[..., n]
    out = np.empty((*sums.count.shape[:2], len(trxr), sums.count.shape[2]))
    eye = np.eye(nb)
    for i, t in enumerate(np.asarray(trxr, np.float64)):
        a = agg + t * (agn + np.swapaxes(agn, -1, -2)) + t * t * ann
        rhs = ag + t * an
        if nb == 1:
            with np.errstate(all="ignore"):
                coef = rhs / a[..., 0]
        else:
            ok = np.linalg.det(a) > 0
            coef = np.linalg.solve(np.where(ok[..., None, None], a, eye), rhs[..., None])[..., 0]
            coef = np.where(ok[..., None], coef, np.nan)
        out[:, :, i] = np.where(sums.count > nb, coef @ vg[:nb], np.nan)
    return out


def _medians(x: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """``(Nant, Npol)`` medians over the channels of ``x`` that are in ``sel`` and finite."""
    if x.shape[-1] == 0:  # no channel at all
        return np.full(x.shape[:-1], np.nan)
    with np.errstate(invalid="ignore"):
        return nanmedian_last(np.where(sel & np.isfinite(x), x, np.nan))


def _number(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def separation_summary(solution: Any) -> list[dict[str, Any]]:
    """Per antenna and polarisation: how well ``G`` and ``n`` separate, and the error budget.

    Parameters
    ----------
    solution
        An :class:`autocal.fit.solution.Solution` with a total uncertainty.

    Returns
    -------
    list of dict
        One entry per antenna-pol (medians over the solved channels): ``sky_contrast``,
        ``corr_G_n``, ``drift_sensitivity``, ``separation`` (``"weak"`` or ``"adequate"``),
        ``G``, ``sigma_G_frac`` and ``sigma_G_stat_frac`` (total and statistical 1-sigma
        over ``G``), ``jackknife_factor``, ``drift_weight``, ``G_halves``, ``G_if_trxr_K``
        (the profile: ``{Trxr: G}``) and ``message``, a sentence for people. Empty without
        a total uncertainty.
    """
    total = solution.total
    if total is None:
        return []
    out = []
    ok = ~solution.flags
    weak = total.separation()
    gain, trxr = solution.G, solution.Trxr  # properties: computed once, not per antenna
    with np.errstate(all="ignore"):
        frac_tot = solution.sigma_G / gain
        frac_stat = solution.sigma_G_stat / gain
    columns = {
        "G": gain,
        "Trxr_K": trxr,
        "sky_contrast": total.sky_contrast,
        "corr_G_n": total.corr_G_n,
        "drift_sensitivity": total.drift_sensitivity,
        "sigma_G_frac": frac_tot,
        "sigma_G_stat_frac": frac_stat,
        "jackknife_factor": total.jackknife_factor,
        "drift_weight": total.drift_weight,
    }
    # medians of all antenna-pols at once (one sort per quantity, not one median per
    # antenna-pol: 15,000 numpy calls for a HERA file)
    medians = {key: _medians(arr, ok) for key, arr in columns.items()}
    halves = [_medians(total.G_halves[h], ok) for h in range(2)]
    profile = [_medians(total.profile_G[:, :, i], ok) for i in range(len(total.profile_trxr))]
    channels = ok.sum(axis=-1)
    for ia, ant in enumerate(np.asarray(solution.antennas).tolist()):
        for ip, pol in enumerate(solution.pols):
            value = {key: _number(med[ia, ip]) for key, med in medians.items()}
            entry = {
                "antenna": int(ant),
                "pol": pol,
                "channels": int(channels[ia, ip]),
                **{key: value[key] for key in list(columns)[:5]},
                "separation": "weak" if weak[ia, ip] else "adequate",
                **{key: value[key] for key in list(columns)[5:]},
                "G_halves": [_number(h[ia, ip]) for h in halves],
                "G_if_trxr_K": {
                    f"{t:g}": _number(profile[i][ia, ip]) for i, t in enumerate(total.profile_trxr)
                },
            }
            entry["message"] = _message(entry)
            out.append(entry)
    return out


def _message(e: dict[str, Any]) -> str:
    """One sentence on an antenna-pol's separation and error budget."""
    head = f"ant {e['antenna']} {e['pol']}: "
    if e["G"] is None:
        return head + "no solved channel"
    sens = e["drift_sensitivity"]
    text = head + (
        f"G = {e['G']:.4g} +- {100 * (e['sigma_G_frac'] or np.nan):.3g} % total "
        f"({100 * (e['sigma_G_stat_frac'] or np.nan):.2g} % statistical)"
    )
    if e["separation"] == "weak":
        trxr = e["Trxr_K"] if e["Trxr_K"] is not None else 150.0
        near = sorted(e["G_if_trxr_K"], key=lambda k: abs(float(k) - trxr))[:3]
        near = sorted(near, key=float)
        prof = ", ".join(
            f"{e['G_if_trxr_K'][k]:.4g} if Trxr = {k} K"
            for k in near
            if e["G_if_trxr_K"][k] is not None
        )
        text += (
            f"; weak separation: the sky varies by {100 * (e['sky_contrast'] or np.nan):.2g} % "
            f"of Tsys, so a 1 % gain drift over the span moves G by "
            f"{abs(sens or np.nan):.3g} %; G = {prof}"
        )
    return text
