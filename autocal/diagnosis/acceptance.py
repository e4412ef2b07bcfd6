"""Taking an accepted candidate into the model, and re-testing what was accepted before.

:func:`accept` adds the step's winner to the model (a time-domain effect is fitted jointly
with the others, a per-antenna gain is divided out of the data, a cable reflection joins
the bandpass model), re-weights, and returns what the step's record needs
(:class:`AcceptedStep`). :func:`retest_accepted` drops effects the others now explain
(backward elimination); :func:`supersede` marks common entries contained in an accepted
per-antenna one.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from autocal.diagnosis.effects import Effect
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.extended_fit import ExtendedFit, fit_extended, radiometer_weights
from autocal.diagnosis.gap import gap_metrics
from autocal.diagnosis.impact import is_negligible, product_impact
from autocal.diagnosis.report import Diagnosis
from autocal.diagnosis.search_state import SearchContext, SearchState
from autocal.diagnosis.trials import BandpassTrial, FeedTrial, ModelTrial, Trial

logger = logging.getLogger(__name__)

#: Common entries that a per-antenna entry contains (the antenna-pols sharing one series
#: or drift is a special case): named once the per-antenna one is accepted, they stay in
#: the fitted model (the part the antenna-pols share) but are reported as superseded.
SUPERSEDES = {
    "antenna_gain_jitter": ("gain_jitter", ("integration",)),
    "antenna_gain_drift": ("gain_drift", ("legendre",)),
}


@dataclass(frozen=True)
class AcceptedStep:
    """What accepting a candidate gives its step's record (:attr:`.Diagnosis.steps`).

    Attributes
    ----------
    parameters
        ``{parameter: {value, sigma}}``.
    gap_before, gap_after
        Gap metrics of the model before and after the step.
    extra
        The kind's own entries (``product_impact``, ``negligible``, ``per_feed``,
        ``series``...).
    """

    parameters: dict[str, dict[str, Any]]
    gap_before: dict[str, Any]
    gap_after: dict[str, Any]
    extra: dict[str, Any]


def accept(ctx: SearchContext, state: SearchState, trial: Trial, step: int) -> AcceptedStep:
    """Take the step's winner into the model; re-weight with the new model."""
    gap_before = gap_metrics(state.current, state.obs, ctx.tpl, state.bandpass)
    if isinstance(trial, BandpassTrial):
        return _accept_cable_reflection(state, trial, gap_before)
    if isinstance(trial, FeedTrial):
        return _accept_feed_gains(ctx, state, trial, gap_before)
    if isinstance(trial, ModelTrial):
        return _accept_model_effect(ctx, state, trial, gap_before, step)
    raise TypeError(f"unknown trial {type(trial).__name__}")


def _accept_cable_reflection(
    state: SearchState, trial: BandpassTrial, gap_before: dict[str, Any]
) -> AcceptedStep:
    """Add the ripple to the bandpass model (``G`` is unchanged: it absorbs the ripple)."""
    rip = trial.ripple
    state.cable = rip
    params = {
        "a": {"value": rip.a, "sigma": rip.sigma_a},
        "tau_ns": {"value": rip.tau_ns, "sigma": rip.sigma_tau_ns},
        "phi": {"value": rip.phi, "sigma": rip.sigma_phi},
    }
    feeds = [(a, p) for a in state.obs.antennas for p in state.obs.pols]
    extra: dict[str, Any] = {
        "per_feed": [
            {"antenna": int(a), "pol": str(p), **vals}
            for (a, p), vals in zip(feeds, rip.per_feed, strict=True)
        ],
        "smooth_bandpass_order": rip.smooth_order,
        "masked_channels": rip.masked_channels,
    }
    gap_after = dict(gap_before)
    gap_after["bandpass_reduced_chi2"] = rip.reduced_chi2
    state.bandpass = rip
    state.snapshot(f"after {trial.effect.name}")
    return AcceptedStep(params, gap_before, gap_after, extra)


def _accept_feed_gains(
    ctx: SearchContext, state: SearchState, trial: FeedTrial, gap_before: dict[str, Any]
) -> AcceptedStep:
    """Divide every antenna-pol's own departure from the shared series out of the data.

    Its departure from what the antenna-pols share (the common jitter series, or their mean
    drift) is held at its estimate from here on; the shared part stays with the model,
    free, so that later candidates are fitted jointly with it (held whole, a jitter series
    would keep whatever trend it absorbed, e.g. most of a noise drift).
    """
    eff, feed, current = trial.effect, trial.feed, state.current
    state.feed_accepted.add(eff.name)
    jitter = eff.basis == "feed_integration"
    if jitter:
        shared = current.gain_factor / np.mean(current.gain_factor)
    else:
        shared = feed.factors.mean(axis=(0, 1))
    departures = feed.factors / shared
    obs = dataclasses.replace(state.obs, data=state.obs.data / departures[..., None])
    state.obs = obs
    state.feed_departures = (
        departures if state.feed_departures is None else state.feed_departures * departures
    )
    new = fit_extended(
        obs, ctx.tpl, state.active, weights=state.weights, start=current.params, **ctx.prior_kw
    )
    impact = product_impact(current, new, ctx.sigma_g, ctx.sigma_t)
    diff = feed.factors - (shared if jitter else 1.0)
    impact["G_time"] = {
        "rms_relative_change": float(np.sqrt(np.mean(diff**2))),
        "max_abs_relative_change": float(np.max(np.abs(diff))),
    }
    extra: dict[str, Any] = {
        "product_impact": impact,
        "negligible": is_negligible(impact, trial.delta_chi2 / current.ndata),
    }
    gap_after = gap_metrics(new, obs, ctx.tpl, state.bandpass)
    _reweight(ctx, state, new)
    state.snapshot(f"after {eff.name}")
    rms = np.std(feed.factors, axis=-1)
    swing = np.ptp(feed.factors, axis=-1)
    params = {
        "rms": {"value": float(np.median(rms)), "sigma": float(np.median(feed.sigmas))},
        "max_rms": {"value": float(np.max(rms)), "sigma": float(np.max(feed.sigmas))},
    }
    if not jitter:
        params["max_change"] = {"value": float(np.max(swing)), "sigma": 0.0}
    extra["per_feed"] = []
    for ia, a in enumerate(obs.antennas):
        for ip, p in enumerate(obs.pols):
            row = {"antenna": int(a), "pol": str(p), "rms": float(rms[ia, ip])}
            if not jitter and feed.values is not None:
                own = zip(eff.params, feed.values[ia, ip], strict=True)
                row.update({name: float(v) for name, v in own})
            extra["per_feed"].append(row)
    extra["series"] = {
        "lst_h": obs.lsts.tolist(),
        "gain_factor": feed.factors.tolist(),
        "shared_gain_factor": np.broadcast_to(shared, (obs.ntime,)).tolist(),
    }
    return AcceptedStep(params, gap_before, gap_after, extra)


def _accept_model_effect(
    ctx: SearchContext,
    state: SearchState,
    trial: ModelTrial,
    gap_before: dict[str, Any],
    step: int,
) -> AcceptedStep:
    """Fit the effect jointly with the accepted ones; re-test those against the refit."""
    eff, current = trial.effect, state.current
    params = params_dict(eff, trial.free_fit)
    if trial.fixed_hypothesis:
        params["cmb_factor"]["adopted"] = float(trial.adopted.fixed[0])
    state.active.append(trial.adopted)
    new = fit_extended(
        state.obs,
        ctx.tpl,
        state.active,
        weights=state.weights,
        start=trial.fit.params,
        **ctx.prior_kw,
    )
    impact = product_impact(current, new, ctx.sigma_g, ctx.sigma_t)
    gap_after = gap_metrics(new, state.obs, ctx.tpl, state.bandpass)
    extra: dict[str, Any] = {
        "product_impact": impact,
        # detected, but it moves G and Trxr by a small fraction of their total errors:
        # kept in the fitted model (else other entries would absorb what it explains)
        # and reported as negligible, not named among the effects
        "negligible": is_negligible(impact, trial.delta_chi2 / current.ndata),
    }
    # re-weight with the improved model for the next step
    _reweight(ctx, state, new)
    # the effects accepted before are re-tested against the refit: one that the
    # new effect explains away is dropped now, before the search goes on
    retest_accepted(ctx, state, f"step {step + 1}", keep=state.active[-1])
    state.snapshot(f"after {eff.name}")
    if not trial.fixed_hypothesis:
        params = params_dict(eff, state.current)
    if eff.basis == "integration":
        eps = np.concatenate([[0.0], state.current.params[eff.name]])
        extra["series"] = {
            "lst_h": state.obs.lsts.tolist(),
            "gain_factor": ((1 + eps) / np.mean(1 + eps)).tolist(),
            "sigma": np.concatenate([[0.0], state.current.sigmas[eff.name]]).tolist(),
        }
    return AcceptedStep(params, gap_before, gap_after, extra)


def _reweight(ctx: SearchContext, state: SearchState, new: ExtendedFit) -> None:
    """Weights from ``new``'s model, and the current model refitted with them from it."""
    state.weights = radiometer_weights(state.obs, new)
    state.current = fit_extended(
        state.obs,
        ctx.tpl,
        state.active,
        weights=state.weights,
        start=new.params,
        **ctx.prior_kw,
    )


def params_dict(eff: Effect, fit: ExtendedFit) -> dict[str, dict[str, float]]:
    """Return an effect's parameters in a fit as ``{parameter: {value, sigma}}``.

    A per-integration series is reported by its scatter (``rms``, ``max_abs``); the series
    itself goes to the step.
    """
    vals, sigs = fit.params[eff.name], fit.sigmas[eff.name]
    if eff.basis == "integration":
        # one factor per integration: report their scatter; the series goes to the step
        # factors relative to their mean (the reference integration has eps = 0)
        series = np.concatenate([[0.0], vals])
        rel = (1 + series) / np.mean(1 + series) - 1
        return {
            "rms": {"value": float(np.std(rel)), "sigma": float(np.sqrt(np.mean(sigs**2)))},
            "max_abs": {"value": float(np.max(np.abs(rel))), "sigma": float(np.max(sigs))},
        }
    return {
        p: {"value": float(v), "sigma": float(s)}
        for p, v, s in zip(eff.params, vals, sigs, strict=True)
    }


def retest_accepted(
    ctx: SearchContext, state: SearchState, when: str, keep: Effect | None = None
) -> dict[str, ExtendedFit]:
    """Drop accepted effects that the others now explain (backward elimination).

    An effect accepted early may be explained away by later ones (a per-integration gain
    soaking up part of a sky error, say): any whose removal from the current model no
    longer costs Delta BIC > ``bic_threshold`` is dropped, one at a time, the model refitted
    after each (``state.active`` and ``state.current`` updated). ``keep`` (the effect just
    accepted) is not re-tested.

    Returns
    -------
    dict
        ``{effect name: the model without it}`` for every effect kept, fitted at the last
        pass (what :func:`final_impacts` compares the final model with); empty with a
        single effect.
    """
    obs, tpl, w, prior_kw = state.obs, ctx.tpl, state.weights, ctx.prior_kw
    active, current = state.active, state.current
    changed = True
    withouts: dict[str, ExtendedFit] = {}
    while changed and len(active) > 1:
        changed = False
        withouts = {}
        chat_f = max(1.0, current.reduced_chi2)
        for eff in list(active):
            if eff is keep:
                continue
            rest = [a for a in active if a is not eff]
            try:
                without = fit_extended(obs, tpl, rest, weights=w, start=current.params, **prior_kw)
            except (DiagnoseError, np.linalg.LinAlgError):
                continue
            withouts[eff.name] = without.detached()
            stat = (without.chi2 - current.chi2) / chat_f - eff.nfree * math.log(current.ndata)
            if stat < ctx.settings.bic_threshold:
                logger.info("re-test at %s: %s dropped (Delta BIC %.1f)", when, eff.name, stat)
                active = rest
                _mark_dropped(state.diag, eff, float(stat), when)
                current = fit_extended(
                    obs, tpl, active, weights=w, start=without.params, **prior_kw
                )
                changed = True
                break
    state.active, state.current = active, current
    # after a drop that left a single effect, the last pass's fits are of an older model
    return {} if changed else withouts


def final_impacts(ctx: SearchContext, state: SearchState, withouts: dict[str, ExtendedFit]) -> None:
    """Judge every kept effect's impact on the products in the final joint model.

    A step's ``product_impact`` compares the model before and after it; effects accepted
    later change what it moves (a drift accepted next to a sky scale shares part of its
    effect on ``G`` with a timing offset accepted after it). The verdict that counts is the
    final model's, with and without the effect (``withouts``, the last re-test's fits):
    recorded as the step's ``final_product_impact``, and the effect moved between the
    named effects and the "detected, negligible" ones when its final verdict differs.
    """
    diag, current = state.diag, state.current
    for st in diag.steps:
        without = withouts.get(st["name"])
        if without is None or "dropped_in_backward_pass" in st or st.get("superseded_by"):
            continue
        impact = product_impact(without, current, ctx.sigma_g, ctx.sigma_t)
        negligible = is_negligible(impact, (without.chi2 - current.chi2) / current.ndata)
        st["final_product_impact"] = impact
        st["final_negligible"] = negligible
        if negligible == bool(st.get("negligible")):
            continue
        st["negligible"] = negligible
        source, target = (
            (diag.effects, diag.negligible) if negligible else (diag.negligible, diag.effects)
        )
        if st["name"] in source:
            source.remove(st["name"])
            target.append(st["name"])
        logger.info(
            "%s is %s in the final model",
            st["name"],
            "negligible" if negligible else "no longer negligible",
        )


def _mark_dropped(diag: Diagnosis, eff: Effect, stat: float, when: str) -> None:
    """Record that the re-test dropped an accepted effect."""
    for names in (diag.effects, diag.negligible):
        if eff.name in names:
            names.remove(eff.name)
    for st in diag.steps:
        if st["name"] == eff.name and "dropped_in_backward_pass" not in st:
            st["dropped_in_backward_pass"] = {"statistic": stat, "at": when}


def supersede(diag: Diagnosis, accepted: set[str]) -> None:
    """Report common entries contained in accepted per-antenna ones as superseded."""
    for feed_name in accepted:
        common, bases = SUPERSEDES[feed_name]
        for st in diag.steps:
            if (
                st["name"] == common
                and st.get("time_basis", "legendre") in bases
                and "dropped_in_backward_pass" not in st
            ):
                st["superseded_by"] = feed_name
                for names in (diag.effects, diag.negligible):
                    if common in names:
                        names.remove(common)
