"""Every antenna-pol its own gain series: ``antenna_gain_jitter`` and ``antenna_gain_drift``.

``antenna_gain_jitter`` (every antenna-pol its own per-integration series) is fitted feed by
feed against the common ``gain_jitter``, and ``antenna_gain_drift`` (every antenna-pol its
own Legendre drift) on top of the current model (:func:`fit_feed_gains`), the other
accepted effects held at their joint estimates.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.dispersion import (
    ROBUST_SAMPLES,
    pooled_overdispersion,
    squared_residual_sample,
)
from autocal.diagnosis.effects import Effect, SkyTemplates
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.extended_fit import ExtendedFit, fit_extended
from autocal.diagnosis.normal_equations import MIN_IDENTIFIABLE

#: Most antenna-pols for which ``antenna_gain_jitter`` is tried (one fit each).
FEED_JITTER_MAX_FEEDS = 64


@dataclass(frozen=True)
class FeedGainFit:
    """Every antenna-pol's own gain series (:func:`fit_feed_gains`).

    Attributes
    ----------
    factors, sigmas
        ``(Nant, Npol, Ntime)`` gain factors (time mean 1 per antenna-pol) and 1-sigma.
    chi2
        Sum of the antenna-pols' chi-square (with their prior terms).
    delta_chi2
        The common-series model's chi-square less :attr:`chi2`.
    k
        Extra parameters: ``(Nfeeds - 1) (Ntime - 1)`` for a jitter replacing the common
        series, ``Nfeeds x order`` for a drift.
    ndata, nparam
        Data (with prior rows) and parameters of the per-antenna-pol model.
    values
        ``(Nant, Npol, k)`` each antenna-pol's fitted parameters.
    bulk_overdispersion
        The overdispersion of the bulk of the antenna-pols' residuals pooled (median
        squared normalised residual over that of chi-square with one degree of freedom,
        :func:`~autocal.diagnosis.dispersion.pooled_overdispersion`): the yardstick of
        their departures' test, which a few outliers do not inflate as they inflate
        :attr:`reduced_chi2`. ``nan`` until computed.
    """

    factors: np.ndarray
    sigmas: np.ndarray
    chi2: float
    delta_chi2: float
    k: int
    ndata: int
    nparam: int
    values: np.ndarray | None = None
    bulk_overdispersion: float = float("nan")

    @property
    def reduced_chi2(self) -> float:
        """``chi^2 / dof``."""
        return self.chi2 / max(self.ndata - self.nparam, 1)


def fit_feed_gains(
    obs: Observation,
    tpl: SkyTemplates,
    active: list[Effect],
    current: ExtendedFit,
    w: np.ndarray,
    prior_kw: dict[str, Any],
    eff: Effect,
) -> FeedGainFit | None:
    """Fit each antenna-pol's own gain series, the other effects held at their values.

    ``antenna_gain_jitter`` (``eff.basis == "feed_integration"``): the model with one
    common series (``gain_jitter`` in ``active``, fitted in ``current``) is nested in this
    one, each antenna-pol getting its own series started from the common one.
    ``antenna_gain_drift`` (``"feed_legendre"``): each antenna-pol its own Legendre drift
    of order ``eff.order`` on top of the current model. Every other accepted effect is
    fixed at its joint estimate, so the antenna-pols are independent and fitted one by
    one; an antenna-pol without usable data follows the shared series. ``None`` when there
    is nothing to test.

    Raises
    ------
    DiagnoseError
        When an antenna-pol cannot be fitted or its own parameters are not identifiable
        (parameters without any data take no part).
    """
    model = _feed_model(obs, active, current, eff)
    if model is None:
        return None
    basis = model.own.time_basis(obs.lsts)
    shape = (obs.nant, len(obs.pols), obs.nfreq)
    prior = {
        key: value
        if value is None or np.ndim(value) == 0
        else np.broadcast_to(np.asarray(value, float), shape)
        for key, value in prior_kw.items()
    }
    factors = np.ones((obs.nant, len(obs.pols), obs.ntime))
    sigmas = np.zeros_like(factors)
    values = np.zeros((obs.nant, len(obs.pols), basis.shape[0]))
    chi2, ndata, nparam, skipped = 0.0, 0, 0, 0
    squares: list[np.ndarray] = []
    for ia, ant in enumerate(obs.antennas):
        for ip, pol in enumerate(obs.pols):
            sub = obs.select(antennas=[int(ant)], pols=[pol])
            usable = (~sub.flags & np.isfinite(sub.data)).sum(axis=2) >= 3
            if not usable.any():
                # no data: it follows the shared series and adds no parameter
                factors[ia, ip] = (
                    current.gain_factor / np.mean(current.gain_factor) if model.replaced else 1.0
                )
                skipped += 1
                continue
            fit = _fit_feed(sub, tpl, (ia, ip), f"antenna {ant} {pol}", model, w, prior)
            own = model.own.name
            values[ia, ip] = fit.params[own]
            factor = 1.0 + fit.params[own] @ basis
            factors[ia, ip] = factor / np.mean(factor)
            # 1-sigma of the factor at each integration (diagonal: the reference of a
            # series, or a drift's centre, has none)
            sigmas[ia, ip] = np.sqrt(fit.sigmas[own] ** 2 @ basis**2)
            chi2 += fit.chi2
            ndata += fit.ndata
            nparam += fit.nparam
            # pooled over antenna-pols: ~ROBUST_SAMPLES in all
            per_feed = ROBUST_SAMPLES // (obs.nant * len(obs.pols))
            squares.append(squared_residual_sample(fit, per_feed))
    nfeeds = obs.nant * len(obs.pols)
    return FeedGainFit(
        factors=factors,
        sigmas=sigmas,
        chi2=chi2,
        delta_chi2=float(current.chi2 - chi2),
        k=(nfeeds - skipped) * model.k_per_feed - model.k_shared,
        ndata=ndata,
        nparam=nparam,
        values=values,
        bulk_overdispersion=pooled_overdispersion(squares, chi2 / max(ndata - nparam, 1)),
    )


@dataclass(frozen=True)
class _FeedModel:
    """The model every antenna-pol is fitted with (:func:`fit_feed_gains`).

    Attributes
    ----------
    own
        The antenna-pol's own gain effect (the common series, or a Legendre drift).
    held
        The other accepted effects, fixed at their joint estimates.
    start
        Where the antenna-pol's fit starts (the common series, if any).
    replaced
        The common series the antenna-pols' own ones replace, or ``None``.
    k_per_feed, k_shared
        Parameters each antenna-pol adds, and those of the replaced common series.
    """

    own: Effect
    held: tuple[Effect, ...]
    start: dict[str, np.ndarray]
    replaced: Effect | None
    k_per_feed: int
    k_shared: int


def _feed_model(
    obs: Observation, active: list[Effect], current: ExtendedFit, eff: Effect
) -> _FeedModel | None:
    """Return the model of every antenna-pol, or ``None`` when there is nothing to test."""
    jitter = next((a for a in active if a.basis == "integration"), None)
    if eff.basis == "feed_integration":
        if jitter is None:
            return None
        own = jitter
        start = {jitter.name: current.params[jitter.name]}
        replaced: Effect | None = jitter
        k_per_feed, k_shared = obs.ntime - 1, obs.ntime - 1
    else:
        own = Effect(eff.name, "gain", eff.params, eff.units, eff.order, basis="legendre")
        start, replaced = {}, None
        k_per_feed, k_shared = eff.order, 0
    held = tuple(
        a if a.fixed is not None else dataclasses.replace(a, fixed=tuple(current.params[a.name]))
        for a in active
        if a is not replaced
    )
    return _FeedModel(own, held, start, replaced, k_per_feed, k_shared)


def _fit_feed(
    sub: Observation,
    tpl: SkyTemplates,
    index: tuple[int, int],
    label: str,
    model: _FeedModel,
    w: np.ndarray,
    prior: dict[str, Any],
) -> ExtendedFit:
    """Fit one antenna-pol (``sub``, at ``index`` (antenna, pol) of the observation)."""
    ia, ip = index
    sub_tpl = tpl.subset(pols=slice(ip, ip + 1))
    sub_prior = {
        key: value if value is None or np.ndim(value) == 0 else value[ia : ia + 1, ip : ip + 1]
        for key, value in prior.items()
    }
    try:
        fit = fit_extended(
            sub,
            sub_tpl,
            [model.own, *model.held],
            weights=w[ia : ia + 1, ip : ip + 1],
            start=model.start,
            **sub_prior,
        )
    except (DiagnoseError, np.linalg.LinAlgError) as exc:
        raise DiagnoseError(f"{label} could not be fitted: {exc}") from exc
    if fit.identifiable.get(model.own.name, 1.0) < MIN_IDENTIFIABLE:
        raise DiagnoseError(
            f"{label}: its own parameters are not identifiable from these data "
            "(degenerate with G and n)"
        )
    return fit
