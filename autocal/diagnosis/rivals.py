"""When the data cannot tell the step's best candidate from another catalogue entry.

Over a short span many entries reduce to the same few smooth modes: half an hour of a
drift scan, a receiver-noise drift, a clock offset and a sky-model error all add a nearly
linear trend in time. :func:`find_rivals` returns the entries that pass the same tests and
explain the residual within :data:`DECISIVE_MARGIN` of the best (``Delta BIC``, i.e.
``2 ln`` of the Bayes factor between the two), or within :data:`LEAD_SIGMAS` times the
noise of the best's lead over them (:func:`lead_sigma`: a fixed margin is a coin toss when
two large fits of one residual differ by less than their difference scatters). The first
question a diagnosis answers is
whether the receiver or the forward model of the sky is at fault (:func:`domain`): when a
rival is of the other domain, naming the best would blame one at the toss of a coin, so the
search stops and reports the step as indistinguishable
(:attr:`autocal.diagnosis.report.Diagnosis.indistinguishable`), with what each entry would
change in the products. A rival of the same domain (a missing CMB against a sky-scale
error) leaves the conclusion standing: the best is named and its close alternatives are
listed with it.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from autocal.diagnosis.consistency import check_trial
from autocal.diagnosis.effects import Effect
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.extended_fit import ExtendedFit
from autocal.diagnosis.impact import product_impact
from autocal.diagnosis.search_state import SearchContext, SearchState
from autocal.diagnosis.trials import ModelTrial, Trial

logger = logging.getLogger(__name__)

#: ``Delta BIC`` by which the best candidate must beat every other passing entry to be
#: named: 6, "strong" evidence (a Bayes factor of 20; Kass & Raftery 1995, JASA 90, 773).
#: On the independent simulator's suite the correct entries win by >= 9.1 and the two
#: wrong ones that passed on clean data by 3.0 and 4.0 (docs/results/diagnose_independent).
DECISIVE_MARGIN = 6.0

#: How many standard deviations of its own noise the best's lead over an entry must be to
#: be decisive (:func:`lead_sigma`): 2, Vuong's (1989, Econometrica 57, 307) test of two
#: non-nested models at ~5 %. A lead of ``Delta BIC`` 7.9 between two entries that
#: explained the same residual of a clean HERA-beam half hour (noise drift against a
#: clock offset, each ~270) was 0.6 of its sigma: the data had not decided. The price:
#: when the best is exactly right, its lead is about ``|m_a - m_b|^2`` and its sigma
#: ``2 |m_a - m_b|``, so it decides only from a lead of about 16 (a true ground
#: temperature leading a gain drift by 24.9, 1.4 sigma, was left undecided in one
#: held-out realisation of the independent suite).
LEAD_SIGMAS = 2.0

#: Pairs of entries one of which is the other at fixed parameter values: ``missing_cmb``
#: is ``sky_offset`` at ``T_offset = -+2.725 K`` (both ``f_above`` times a constant). The
#: two state the same residual, one more sharply; whichever wins is named, the other is
#: not its rival (the fixed hypothesis, one parameter fewer, wins by ``ln N`` when the
#: offset is the CMB's: 9.1 on a 24-hour single-feed case, < 6 on shorter ones).
NESTED = frozenset({frozenset({"missing_cmb", "sky_offset"})})

#: Entry kinds of the receiver (gains, noise, the bandpass); the others (``tsky``: sky,
#: ground, beam, timing) are the forward model's.
RECEIVER_KINDS = frozenset({"gain", "feed_gain", "noise", "bandpass"})


def domain(effect: Effect) -> str:
    """Return ``"receiver"`` or ``"forward model"`` (sky, ground, beam, timing)."""
    return "receiver" if effect.kind in RECEIVER_KINDS else "forward model"


def find_rivals(
    ctx: SearchContext,
    state: SearchState,
    best: Trial,
    trials: list[Trial],
    sigmas: dict[str, float] | None = None,
) -> list[ModelTrial]:
    """Return the other entries the data cannot tell from ``best``, best first.

    Parameters
    ----------
    ctx, state
        The search's context and state.
    best
        The step's winner (it passed the test and the band-consistency check).
    trials
        The step's trials, ranked (best statistic first). Candidates the step screened
        out (:class:`~autocal.diagnosis.screening.StepScreen`, large observations) were
        not fitted and cannot be rivals.
    sigmas
        Filled with the :func:`lead_sigma` of every entry it was computed for, by name
        (for :func:`indistinguishable_record`), when given.

    Returns
    -------
    list of ModelTrial
        Time-domain entries other than ``best`` (and not nested with it, :data:`NESTED`)
        that pass the same test, whose two band halves agree on their parameters, and
        whose ``Delta BIC`` is within :data:`DECISIVE_MARGIN` of ``best``'s or within
        :data:`LEAD_SIGMAS` :func:`lead_sigma` of it. Empty when
        ``best`` is a bandpass or per-antenna trial (ranked on other data: a reflection in
        the bandpass, one antenna against the others).
    """
    if not isinstance(best, ModelTrial):
        return []
    settings = ctx.settings
    out: list[ModelTrial] = []
    for trial in trials[trials.index(best) + 1 :]:
        lead = best.statistic - trial.statistic
        bound = _lead_sigma_bound(best, trial)
        if bound is not None and lead > DECISIVE_MARGIN + LEAD_SIGMAS * bound:
            continue  # decisive whatever the two models' difference (the ranking's order)
        if not isinstance(trial, ModelTrial) or trial.effect.name == best.effect.name:
            continue
        if any(t.effect.name == trial.effect.name for t in out):
            continue  # another variant (order, basis) of an entry already a rival: its best
        if frozenset({trial.effect.name, best.effect.name}) in NESTED:
            continue
        if not trial.passes(settings.bic_threshold, settings.alpha):
            continue
        if lead > DECISIVE_MARGIN:
            sigma = _sigma_or_bound(ctx, best, trial)
            if sigmas is not None:
                sigmas[trial.effect.name] = sigma
            if lead > LEAD_SIGMAS * sigma:  # a NaN sigma decides nothing: a rival
                continue
        check = check_trial(ctx, state, trial)
        if check is not None and not check.consistent:
            continue
        out.append(trial)
    return out


def _lead_sigma_bound(best: Trial, trial: Trial) -> float | None:
    """Return a bound of :func:`lead_sigma` from the two statistics alone, or ``None``.

    For fits whose model spaces contain the current model (free parameters, the model
    linear in them), each fit's change of the model has the size ``sqrt(Delta chi^2)``
    (whitened), and the two changes cannot differ by more than the sum of their sizes: a
    bound, up to the model's curvature. A fixed hypothesis (``missing_cmb`` at -+1, no free
    parameter) moves the model by more than its ``Delta chi^2`` says, so there is no
    bound (``None``: its sigma is computed).
    """
    for t in (best, trial):
        if t.k == 0 or getattr(t, "fixed_hypothesis", False):
            return None
    c = max(best.overdispersion, 1.0)
    size = math.sqrt(max(best.delta_chi2, 0.0)) + math.sqrt(max(trial.delta_chi2, 0.0))
    return 2.0 * size / math.sqrt(c)


def _sigma_or_bound(ctx: SearchContext, best: ModelTrial, trial: ModelTrial) -> float:
    """Return :func:`lead_sigma`, or the bound when a fit no longer holds its data.

    A fit detached from its data (:meth:`ExtendedFit.detached`) cannot give its model;
    the bound (or infinity without one) then leaves the two undecided, the safe side.
    """
    try:
        return lead_sigma(ctx, best, trial)
    except DiagnoseError:
        bound = _lead_sigma_bound(best, trial)
        logger.warning(
            "the lead of %s over %s: a fit without its data, its sigma bounded",
            best.effect.name,
            trial.effect.name,
        )
        return math.inf if bound is None else bound


def lead_sigma(ctx: SearchContext, best: ModelTrial, trial: ModelTrial) -> float:
    """Return the standard deviation, over the noise, of ``best``'s lead over ``trial``.

    The two statistics are the same residual fitted by two models. With whitened data
    ``r`` and the two fitted models ``m_a``, ``m_b``, the difference of their chi^2 is
    ``|r - m_b|^2 - |r - m_a|^2``, whose variance over Gaussian noise is
    ``4 |m_a - m_b|^2`` (Vuong 1989's variance of a log-likelihood ratio, summed over the
    data and the receiver prior's rows); in the units of ``Delta BIC`` (``Delta chi^2 / c``)
    its sigma is ``2 |m_a - m_b| / sqrt(c)``: small for two entries that reduce to nearly
    the same change of the model, large for two that explain the same residual by
    different changes (when ``a`` is exactly right its lead is about ``|m_a - m_b|^2``, so
    the lead over its sigma is ``|m_a - m_b| / 2``: 2 sigma needs a lead of about 16).

    Parameters
    ----------
    ctx
        The search's context (the receiver prior's rows).
    best, trial
        Two time-domain trials of one step (same data and weights).

    Returns
    -------
    float
        The sigma of ``best.statistic - trial.statistic``.
    """
    a, b = best.fit, trial.fit
    total = 0.0
    for (sl, ma), (_, mb) in zip(a.model_chunks(), b.model_chunks(), strict=True):
        w = _weights_of_both(a, b, sl)
        with np.errstate(invalid="ignore", over="ignore"):
            total += float(np.sum(np.where(w > 0, w * (ma - mb) ** 2, 0.0)))
    total += _prior_rows(ctx, a, b)
    c = max(best.overdispersion, 1.0)
    return 2.0 * math.sqrt(total / c)


def _weights_of_both(a: ExtendedFit, b: ExtendedFit, sl: slice) -> np.ndarray:
    """Weights of antennas ``sl`` where both fits have a channel solution."""
    assert a.source is not None and b.source is not None
    w = a.source.weights_chunk(sl)
    return np.where(b.source.chan_ok[sl][:, :, None, :], w, 0.0)


def _prior_rows(ctx: SearchContext, a: ExtendedFit, b: ExtendedFit) -> float:
    """``sum (prior residual of a - that of b)^2`` over the receiver prior's rows.

    A row is ``(n - Trxr0 G) / (G_ref sigma)`` per channel with a finite prior and
    ``sigma > 0`` (:class:`~autocal.diagnosis.normal_equations.FitProblem`), so the
    difference is ``((n_a - n_b) - Trxr0 (G_a - G_b)) / (G_ref sigma)``. A search always
    gives ``gain_ref`` (the data's own gain,
    :func:`~autocal.diagnosis.normal_equations.prior_gain_reference`, which
    :class:`FitProblem` also derives when none is given); without it, ``a``'s gain stands
    in.
    """
    kw = ctx.prior_kw
    if kw.get("trxr_prior") is None:
        return 0.0
    shape = a.G.shape
    t0 = np.broadcast_to(np.asarray(kw["trxr_prior"], float), shape)
    sig = np.broadcast_to(np.asarray(kw.get("trxr_prior_sigma", 1.0), float), shape)
    gain_ref = kw.get("gain_ref")
    ref = np.abs(np.broadcast_to(np.asarray(a.G if gain_ref is None else gain_ref, float), shape))
    usable = np.isfinite(t0) & np.isfinite(sig) & (sig > 0) & (ref > 0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        row = ((a.n - b.n) - t0 * (a.G - b.G)) / (ref * sig)
    return float(np.sum(np.where(usable & np.isfinite(row), row * row, 0.0)))


def indistinguishable_record(
    ctx: SearchContext,
    state: SearchState,
    step: int,
    best: ModelTrial,
    rivals: list[ModelTrial],
    sigmas: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Describe a step whose best candidate the data cannot tell from rivals of another domain.

    Returns
    -------
    dict
        ``step`` (1-based), ``candidates`` (``{name: Delta BIC}``, best first),
        ``margin`` (:data:`DECISIVE_MARGIN`), ``lead_sigma`` (``{rival: sigma of the best's
        lead over it}``, :func:`lead_sigma`), ``lead_sigmas`` (:data:`LEAD_SIGMAS`),
        ``product_impact`` (``{name: what the
        products would change by with that entry}``,
        :func:`~autocal.diagnosis.impact.product_impact`) and ``message``.
    """
    entries = [best, *rivals]
    impacts = {
        t.effect.name: product_impact(state.current, t.fit, ctx.sigma_g, ctx.sigma_t)
        for t in entries
    }

    def moved(name: str, q: str) -> float:
        return float(impacts[name].get(q, {}).get("median_change_over_sigma") or 0.0)

    known = sigmas or {}
    noise = {
        r.effect.name: known[r.effect.name]
        if r.effect.name in known
        else _sigma_or_bound(ctx, best, r)
        for r in rivals
    }
    listed = ", ".join(
        f"{t.effect.name} (Delta BIC {t.statistic:.1f}"
        + (f", the lead's sigma {noise[t.effect.name]:.2g}" if t is not best else "")
        + f"; G {moved(t.effect.name, 'G'):.2g}, Trxr {moved(t.effect.name, 'Trxr'):.2g} sigma)"
        for t in entries
    )
    leads = ", ".join(
        f"{(best.statistic - r.statistic) / noise[r.effect.name]:.2g}"
        if noise[r.effect.name] > 0
        else "-"
        for r in rivals
    )
    message = (
        f"step {step + 1}: indistinguishable: a residual the model lacks, which {listed} "
        f"explain about equally (the best leads by less than Delta BIC {DECISIVE_MARGIN:g}, "
        f"a Bayes factor of 20, or by less than {LEAD_SIGMAS:g} sigma of its own noise: "
        f"{leads} sigma); the data cannot say whether the receiver or the forward model "
        "is at fault, so none is named (the products' median-channel change with each in "
        "total sigma). A longer span, other LSTs or more antennas would tell them apart."
    )
    logger.info("%s", message)
    return {
        "step": step + 1,
        "candidates": {t.effect.name: float(t.statistic) for t in entries},
        "delta_chi2": {t.effect.name: float(t.delta_chi2) for t in entries},
        "margin": DECISIVE_MARGIN,
        "lead_sigma": {name: float(v) if math.isfinite(v) else None for name, v in noise.items()},
        "lead_sigmas": LEAD_SIGMAS,
        "product_impact": impacts,
        "message": message,
    }
