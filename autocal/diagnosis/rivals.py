"""When the data cannot tell the step's best candidate from another catalogue entry.

Over a short span many entries reduce to the same few smooth modes: half an hour of a
drift scan, a receiver-noise drift, a clock offset and a sky-model error all add a nearly
linear trend in time. :func:`find_rivals` returns the entries that pass the same tests and
explain the residual within :data:`DECISIVE_MARGIN` of the best (``Delta BIC``, i.e.
``2 ln`` of the Bayes factor between the two). The first question a diagnosis answers is
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
from typing import Any

from autocal.diagnosis.consistency import check_trial
from autocal.diagnosis.effects import Effect
from autocal.diagnosis.impact import product_impact
from autocal.diagnosis.search_state import SearchContext, SearchState
from autocal.diagnosis.trials import ModelTrial, Trial

logger = logging.getLogger(__name__)

#: ``Delta BIC`` by which the best candidate must beat every other passing entry to be
#: named: 6, "strong" evidence (a Bayes factor of 20; Kass & Raftery 1995, JASA 90, 773).
#: On the independent simulator's suite the correct entries win by >= 9.1 and the two
#: wrong ones that passed on clean data by 3.0 and 4.0 (docs/results/diagnose_independent).
DECISIVE_MARGIN = 6.0

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
    ctx: SearchContext, state: SearchState, best: Trial, trials: list[Trial]
) -> list[ModelTrial]:
    """Return the other entries the data cannot tell from ``best``, best first.

    Parameters
    ----------
    ctx, state
        The search's context and state.
    best
        The step's winner (it passed the test and the band-consistency check).
    trials
        The step's trials, ranked (best statistic first).

    Returns
    -------
    list of ModelTrial
        Time-domain entries other than ``best`` (and not nested with it, :data:`NESTED`)
        that pass the same test, whose two band halves agree on their parameters, and
        whose ``Delta BIC`` is within :data:`DECISIVE_MARGIN` of ``best``'s. Empty when
        ``best`` is a bandpass or per-antenna trial (ranked on other data: a reflection in
        the bandpass, one antenna against the others).
    """
    if not isinstance(best, ModelTrial):
        return []
    settings = ctx.settings
    floor = best.statistic - DECISIVE_MARGIN
    out: list[ModelTrial] = []
    for trial in trials[trials.index(best) + 1 :]:
        if trial.statistic < floor:
            break
        if not isinstance(trial, ModelTrial) or trial.effect.name == best.effect.name:
            continue
        if any(t.effect.name == trial.effect.name for t in out):
            continue  # another variant (order, basis) of an entry already a rival: its best
        if frozenset({trial.effect.name, best.effect.name}) in NESTED:
            continue
        if not trial.passes(settings.bic_threshold, settings.alpha):
            continue
        check = check_trial(ctx, state, trial)
        if check is not None and not check.consistent:
            continue
        out.append(trial)
    return out


def indistinguishable_record(
    ctx: SearchContext, state: SearchState, step: int, best: ModelTrial, rivals: list[ModelTrial]
) -> dict[str, Any]:
    """Describe a step whose best candidate the data cannot tell from rivals of another domain.

    Returns
    -------
    dict
        ``step`` (1-based), ``candidates`` (``{name: Delta BIC}``, best first),
        ``margin`` (:data:`DECISIVE_MARGIN`), ``product_impact`` (``{name: what the
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

    listed = ", ".join(
        f"{t.effect.name} (Delta BIC {t.statistic:.1f}; G {moved(t.effect.name, 'G'):.2g}, "
        f"Trxr {moved(t.effect.name, 'Trxr'):.2g} sigma)"
        for t in entries
    )
    message = (
        f"step {step + 1}: indistinguishable: a residual the model lacks, which {listed} "
        f"explain about equally (within Delta BIC {DECISIVE_MARGIN:g} of the best, a Bayes "
        "factor below 20); the data cannot say whether the receiver or the forward model "
        "is at fault, so none is named (the products' median-channel change with each in "
        "total sigma). A longer span, other LSTs or more antennas would tell them apart."
    )
    logger.info("%s", message)
    return {
        "step": step + 1,
        "candidates": {t.effect.name: float(t.statistic) for t in entries},
        "delta_chi2": {t.effect.name: float(t.delta_chi2) for t in entries},
        "margin": DECISIVE_MARGIN,
        "product_impact": impacts,
        "message": message,
    }
