"""Find the physical effect missing from the forward model (DESIGN.md section 5).

Workflow: fit the current model (per-channel ``G``, ``n`` plus the global parameters of
the accepted effects, :mod:`autocal.diagnosis.effects`;
:func:`autocal.diagnosis.extended_fit.fit_extended`), measure the gap
(:func:`autocal.diagnosis.gap.gap_metrics`), fit every candidate effect on top
(:mod:`autocal.diagnosis.candidate_fits`), rank them by

    Delta BIC = Delta chi^2 - k ln N

(``chi^2`` radiometer-weighted, ``k`` the candidate's free parameters, ``N`` the number of
data used; :mod:`autocal.diagnosis.trials`), and accept the best
(:mod:`autocal.diagnosis.acceptance`) only if ``Delta BIC > threshold`` (default 10, "very
strong") *and* its ``Delta chi^2`` is significant (chi^2_k survival < ``alpha``). Repeat
until nothing is accepted. ``cable_reflection`` is absorbed by the per-channel gain, so it
is ranked in the bandpass domain (:mod:`autocal.diagnosis.bandpass`).

The data's model is never exactly autocal's (another simulator, a real sky), so the
statistic is a quasi-likelihood one (``Delta chi^2`` over the step's overdispersion), and
a candidate is named only when its own signature explains the residual: the two halves of
the band agree on its parameters (:func:`autocal.diagnosis.consistency.band_consistency`,
with a significant partner fitted alongside when two chromatic effects are missing at
once), its own parameters are significant, a per-integration gain series is not a smooth
function of time (:func:`autocal.diagnosis.jitter.jitter_is_significant`), and its values
are plausible. Fits start from the current model's values, and a model stuck in a local
minimum is refitted from a candidate's better one. An effect that barely moves the
products (:func:`autocal.diagnosis.impact.is_negligible`) is kept in the model and reported
"detected, negligible"; what no entry explains is described
(:func:`autocal.diagnosis.gap.describe_unexplained`), not named; and when another entry
passing the same tests explains the residual about as well as the best (within
:data:`autocal.diagnosis.rivals.DECISIVE_MARGIN`, or within twice the noise of the lead,
:func:`autocal.diagnosis.rivals.lead_sigma`) and blames the other domain (receiver
against forward model), the search stops there and reports the step as
indistinguishable, naming neither (a rival of the same domain is listed with the best as
a close alternative). ``antenna_gain_jitter``
(every antenna-pol its own series) is fitted feed by feed against the common
``gain_jitter``, and ``antenna_gain_drift`` likewise (:mod:`autocal.diagnosis.feeds`).

Scale: a whole HERA file (350 antennas, 206 M samples) is diagnosed in ~6 GB
(:mod:`autocal.diagnosis.extended_fit`). Above :data:`autocal.diagnosis.chunks.LARGE_SAMPLES`
the weights are float32, fits start from the current model's parameters and each step
scores all candidates in one pass before fitting only those that could win in full
(:mod:`autocal.diagnosis.screening`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.acceptance import (
    AcceptedStep,
    accept,
    final_impacts,
    params_dict,
    retest_accepted,
    supersede,
)
from autocal.diagnosis.bandpass import (
    REFLECTION_DELAYS_NS,
    auto_smooth_order,
    fit_cable_reflection,
)
from autocal.diagnosis.candidate_fits import MAX_RESTARTS, escape_local_minimum, try_candidates
from autocal.diagnosis.catalogue import catalogue
from autocal.diagnosis.chunks import antenna_chunks, is_large
from autocal.diagnosis.consistency import BandCheck, check_trial, consistent_with_partner
from autocal.diagnosis.effects import Effect, SkyTemplates
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.extended_fit import ExtendedFit, fit_extended, radiometer_weights
from autocal.diagnosis.gap import ABSORBED_SHARE, describe_unexplained, gap_metrics
from autocal.diagnosis.impact import (
    DATA_STRUCTURE_EFFECTS,
    forward_model_accuracy,
    product_impact,
    product_sigmas,
    signal_rms,
)
from autocal.diagnosis.normal_equations import (
    MIN_IDENTIFIABLE,
    blas_single_thread,
    prior_gain_reference,
)
from autocal.diagnosis.outliers import (
    NOISE_MAX_SIGMA,
    OUTLIER_WINDOW,
    find_outliers,
    noise_outlier_limit,
    tail_scale,
)
from autocal.diagnosis.report import Diagnosis, residual_snapshot
from autocal.diagnosis.rivals import (
    DECISIVE_MARGIN,
    LEAD_SIGMAS,
    domain,
    find_rivals,
    indistinguishable_record,
)
from autocal.diagnosis.screening import StepScreen
from autocal.diagnosis.search_state import SearchContext, SearchSettings, SearchState
from autocal.diagnosis.trials import ALPHA, BIC_THRESHOLD, ModelTrial, Trial
from autocal.fit.model import unwrap_lsts

logger = logging.getLogger(__name__)

#: Most outlier-flagging rounds, each followed by a new search (see :func:`diagnose`).
OUTLIER_ROUNDS = 3


@blas_single_thread
def diagnose(
    obs: Observation,
    tpl: SkyTemplates,
    *,
    candidates: list[Effect] | None = None,
    trxr_prior: np.ndarray | float | None = None,
    trxr_prior_sigma: np.ndarray | float = 1.0,
    bic_threshold: float = BIC_THRESHOLD,
    alpha: float = ALPHA,
    max_steps: int = 5,
    smooth_order: int | None = None,
    flag_rfi: bool = True,
    outlier_threshold: float = 6.0,
    progress: Callable[[float, str], None] | None = None,
) -> Diagnosis:
    """Find, one by one, the effects missing from the forward model.

    Parameters
    ----------
    obs
        Observation (radiometer weights need its channel width, integration time,
        nsamples).
    tpl
        Model Tsky and templates (:func:`autocal.diagnosis.effects.sky_templates`) on the
        observation's LSTs and frequencies.
    candidates
        Candidate effects (default :func:`autocal.diagnosis.catalogue.catalogue`).
    trxr_prior, trxr_prior_sigma
        Known receiver temperature (K) and its 1-sigma; makes time-constant Tsky effects
        identifiable. ``None``: no prior (those effects are reported not identifiable).
    bic_threshold
        Delta BIC an effect must exceed.
    alpha
        Largest chi^2_k survival probability of Delta chi^2 accepted.
    max_steps
        Most effects added.
    smooth_order
        Legendre order of the smooth bandpass for ``cable_reflection`` (default
        :func:`autocal.diagnosis.bandpass.auto_smooth_order`).
    flag_rfi
        Flag narrow-band and impulsive outliers
        (:func:`autocal.diagnosis.outliers.find_outliers`) in the residuals of each search's
        final model and search again without them, at most :data:`OUTLIER_ROUNDS` times; a
        round that finds no more than clean noise gives
        (:func:`~autocal.diagnosis.outliers.noise_outlier_limit`, none beyond
        :data:`~autocal.diagnosis.outliers.NOISE_MAX_SIGMA`) ends the rounds without
        flagging them (all recorded in ``config["outlier_flagging"]``).
    outlier_threshold
        Sigmas of clean residuals' tails (after the outlier filter's high-pass) beyond which
        a sample is an outlier.
    progress
        Called with ``(fraction, message)`` before every model fit (fraction in [0, 1],
        non-decreasing). It may raise to abandon the search (the service's cancellation);
        the exception propagates and nothing is returned.

    Returns
    -------
    Diagnosis
        Steps, accepted effects and gaps.
    """
    searches = 1 + (OUTLIER_ROUNDS if flag_rfi else 0)
    search = 0

    def report(fraction: float, message: str) -> None:
        if progress is not None:
            progress(min(1.0, (search + fraction) / searches), f"search {search + 1}: {message}")

    settings = SearchSettings(
        bic_threshold=bic_threshold,
        alpha=alpha,
        max_steps=max_steps,
        smooth_order=(
            auto_smooth_order(obs.freqs, REFLECTION_DELAYS_NS[0])
            if smooth_order is None
            else smooth_order
        ),
    )

    def search_once(obs: Observation) -> Diagnosis:
        return _search_once(obs, tpl, candidates, settings, (trxr_prior, trxr_prior_sigma), report)

    nflag0 = int(obs.flags.sum())
    diag = search_once(obs)
    rounds = 0
    noise_like: dict[str, float] | None = None
    # outliers are judged on the residuals of the *final* model, so that structure an
    # effect explains is never mistaken for RFI; then the search is repeated without them.
    # The flags accumulate over the rounds. Recomputed from the data's own flags on each
    # round's model instead (find_outliers(base_flags=...)), JD 2458116 ended with 1.5 %
    # flagged instead of 2.1 %, chi2/dof 6629 at the start of the last search and an absurd
    # noise drift accepted: a round's bad model can unflag RFI
    while flag_rfi and rounds < OUTLIER_ROUNDS and diag.final_fit is not None:
        search += 1
        found = find_outliers(obs, diag.final_fit, threshold=outlier_threshold)
        flags = found.flags
        if np.array_equal(flags, obs.flags):
            break
        # no more outliers than clean noise gives at the threshold, none far beyond it:
        # nothing the fits need to be repeated without (a clean HERA file: ~2 of 206 M
        # samples, and a whole search)
        new = int(flags.sum()) - int(obs.flags.sum())
        limit = noise_outlier_limit(int(obs.flags.size - obs.flags.sum()), outlier_threshold)
        if new <= limit and found.peak_sigma <= NOISE_MAX_SIGMA:
            noise_like = {"samples": new, "limit": limit, "peak_sigma": found.peak_sigma}
            logger.info(
                "%d outlier sample(s), no more than clean noise gives at %.1f sigma (%d): "
                "not searching again",
                new,
                outlier_threshold,
                limit,
            )
            break
        obs = dataclasses.replace(obs, flags=flags)
        rounds += 1
        logger.info(
            "flagged %d outlier samples (%.2f %% of the data); searching again",
            int(obs.flags.sum()) - nflag0,
            100 * (obs.flags.sum() - nflag0) / obs.flags.size,
        )
        diag = search_once(obs)
    diag.config["outlier_flagging"] = {
        "enabled": flag_rfi,
        "threshold_sigma": outlier_threshold,
        "threshold_robust_sigma": (
            outlier_threshold * tail_scale(OUTLIER_WINDOW) if flag_rfi else None
        ),
        "rounds": rounds,
        "samples_flagged": int(obs.flags.sum()) - nflag0,
        "fraction_flagged": float(obs.flags.mean()),
        "channels_fully_flagged": int(obs.flags.all(axis=2).sum()),
        # a last round's outliers left unflagged: no more than clean noise gives
        "noise_like": noise_like,
    }
    return diag


def _search_once(
    obs: Observation,
    tpl: SkyTemplates,
    candidates: list[Effect] | None,
    settings: SearchSettings,
    prior: tuple[np.ndarray | float | None, np.ndarray | float],
    progress: Callable[[float, str], None],
) -> Diagnosis:
    """One search for effects (:func:`diagnose` without the outlier flagging).

    ``prior``: the receiver prior ``(trxr, sigma)`` (``trxr`` ``None`` for none).
    """
    _check_radiometer_inputs(obs)
    cands = _candidate_list(obs, tpl, candidates)
    diag = Diagnosis(config=_search_config(settings, prior, cands))
    ctx, state = _start(obs, tpl, cands, settings, prior, diag, progress)
    for step in range(settings.max_steps):
        if not _search_step(ctx, state, step):
            break
    _finish(ctx, state)
    return diag


def _check_radiometer_inputs(obs: Observation) -> None:
    """Refuse data without the channel width and integration time of radiometer weights."""
    width = obs.channel_width[None, None, None, :]
    tint = obs.integration_time[None, None, :, None]
    for sl in antenna_chunks(obs.shape):
        if not np.all((width * (tint * obs.nsamples[sl]))[~obs.flags[sl]] > 0):
            raise DiagnoseError(
                "diagnose needs radiometer weights: channel width, integration time"
            )


def _candidate_list(
    obs: Observation, tpl: SkyTemplates, candidates: list[Effect] | None
) -> list[Effect]:
    """Return the candidates given, or the catalogue's for these data and templates."""
    if candidates is not None:
        return list(candidates)
    return catalogue(
        include_beam_width=tpl.beam_dwidth is not None,
        ntime=obs.ntime,
        include_timing=tpl.lst_derivative is not None,
        include_tilt=tpl.frame_tilt is not None,
        span_h=float(np.ptp(unwrap_lsts(obs.lsts))),
        nfeeds=obs.nant * len(obs.pols),
    )


def _search_config(
    settings: SearchSettings,
    prior: tuple[np.ndarray | float | None, np.ndarray | float],
    cands: list[Effect],
) -> dict[str, Any]:
    """Return the diagnosis's ``config``: the statistic, its settings and the candidates."""
    trxr_prior, trxr_prior_sigma = prior
    return {
        "statistic": "Delta BIC = Delta chi2 / c - k ln N (radiometer-weighted chi2; "
        "c = max(1, smallest chi2/dof among the step's candidate models), the "
        "overdispersion of a quasi-likelihood, so unmodelled excess scatter does not "
        "pass for evidence; "
        "cable_reflection: chi2 of fitted G(nu) vs smooth bandpass, N = Nfreq)",
        "bic_threshold": settings.bic_threshold,
        "alpha": settings.alpha,
        "decisive_margin": DECISIVE_MARGIN,
        "lead_sigmas": LEAD_SIGMAS,
        "trxr_prior_K": None if trxr_prior is None else _describe_values(trxr_prior),
        "trxr_prior_sigma_K": None if trxr_prior is None else _describe_values(trxr_prior_sigma),
        "smooth_bandpass_order": settings.smooth_order,
        "min_identifiable": MIN_IDENTIFIABLE,
        "candidates": [c.describe() for c in cands],
    }


def _describe_values(values: np.ndarray | float) -> Any:
    """Return a prior's value for the report: the number, or a per-channel array's range."""
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 0 or np.all(arr == arr.flat[0]):
        return float(arr.flat[0])
    ok = arr[np.isfinite(arr)]
    return {
        "median": float(np.median(ok)) if ok.size else None,
        "min": float(ok.min()) if ok.size else None,
        "max": float(ok.max()) if ok.size else None,
    }


def _start(
    obs: Observation,
    tpl: SkyTemplates,
    cands: list[Effect],
    settings: SearchSettings,
    prior: tuple[np.ndarray | float | None, np.ndarray | float],
    diag: Diagnosis,
    progress: Callable[[float, str], None],
) -> tuple[SearchContext, SearchState]:
    """Fit the starting model; return what the search shares and its starting state.

    The weights come from the model: two passes of the model without effects.
    """
    trxr_prior, trxr_prior_sigma = prior
    prior_kw: dict[str, Any] = {"trxr_prior": trxr_prior, "trxr_prior_sigma": trxr_prior_sigma}
    progress(0.0, "fitting the starting model")
    w = radiometer_weights(obs, obs.data)
    current = fit_extended(obs, tpl, [], weights=w, **prior_kw)
    w = radiometer_weights(obs, current)
    if trxr_prior is not None:
        # one set of prior weights for every fit of the search, the starting model's
        # included, whatever effects a fit holds: their chi2 compare. From the data's own
        # gain, <D> / (<Tsky> + Trxr0), not a fit's (prior_gain_reference)
        ref = prior_gain_reference(obs, tpl, w, trxr_prior)
        prior_kw["gain_ref"] = np.where(np.isfinite(ref), ref, np.abs(current.G))
    current = fit_extended(obs, tpl, [], weights=w, **prior_kw)
    base_fit = current.detached()  # its G and Trxr only: no reference to these weights
    sigma_g, sigma_t = product_sigmas(
        obs, tpl, None if trxr_prior is None else (trxr_prior, trxr_prior_sigma)
    )
    diag.config["failed_candidates"] = {}
    bp_null, _ = fit_cable_reflection(
        obs.freqs, current.G, current.sigma_G, smooth_order=settings.smooth_order
    )
    diag.initial_gap = gap_metrics(current, obs, tpl, bp_null)
    diag.residual_snapshots.append(("initial model", residual_snapshot(current)))
    ctx = SearchContext(
        tpl=tpl,
        candidates=tuple(cands),
        settings=settings,
        prior_kw=prior_kw,
        sigma_g=sigma_g,
        sigma_t=sigma_t,
        base_fit=base_fit,
        # a large observation: each step fits in full only the candidates whose score
        # says they could win (StepScreen)
        large=is_large(obs.shape),
        progress=progress,
    )
    return ctx, SearchState(obs=obs, weights=w, current=current, bandpass=bp_null, diag=diag)


def _search_step(ctx: SearchContext, state: SearchState, step: int) -> bool:
    """Try every candidate and accept the best; return whether one was accepted."""
    trials = _fit_candidates(ctx, state, step)
    if not trials:
        return False
    report = {}
    for trial in trials:
        report.setdefault(trial.effect.name, float(trial.statistic))
    best, check = _best_consistent(ctx, state, trials, step)
    diag = state.diag
    if best is None:
        first = trials[0]
        diag.config["last_rejected"] = {
            "name": first.effect.name,
            "statistic": float(first.statistic),
            "p_value": first.p_value(),
            "reason": "significant, but refused by the band's halves (they disagree on "
            "its parameters, or its whole-band value lies outside what they combine to), "
            "as was every other significant candidate (failed_candidates)",
            "candidates": report,
        }
        return False
    pval = best.p_value()
    name = best.effect.name
    logger.info("step %d: best %s (Delta BIC %.1f, p %.2g)", step + 1, name, best.statistic, pval)
    if not best.passes(ctx.settings.bic_threshold, ctx.settings.alpha):
        diag.config["last_rejected"] = {
            "name": name,
            "statistic": best.statistic,
            "p_value": pval,
            "candidates": report,
        }
        return False
    sigmas: dict[str, float] = {}  # the leads' sigmas find_rivals computed
    rivals = find_rivals(ctx, state, best, trials, sigmas)
    if any(domain(r.effect) != domain(best.effect) for r in rivals):
        assert isinstance(best, ModelTrial)  # find_rivals returns none otherwise
        diag.indistinguishable = indistinguishable_record(ctx, state, step, best, rivals, sigmas)
        return False
    accepted = accept(ctx, state, best, step)
    _record_step(diag, best, pval, accepted, check, report)
    if rivals:
        diag.steps[-1]["close_alternatives"] = {r.effect.name: float(r.statistic) for r in rivals}
    if accepted.extra.get("negligible"):
        diag.negligible.append(name)
        logger.info("step %d: %s detected, negligible for the products", step + 1, name)
    else:
        diag.effects.append(name)
    supersede(diag, state.feed_accepted)
    return True


def _fit_candidates(ctx: SearchContext, state: SearchState, step: int) -> list[Trial]:
    """Fit the step's candidates, from a better minimum if one shows; rank them.

    A candidate's fit may reveal that the current model sits in a local minimum
    (:func:`autocal.diagnosis.candidate_fits.escape_local_minimum`): the model is then
    refitted from there (at most :data:`autocal.diagnosis.candidate_fits.MAX_RESTARTS`
    times a search) and the candidates fitted again.
    """
    while True:
        plan = (
            StepScreen(
                state.obs,
                ctx.tpl,
                state.active,
                state.current,
                ctx.candidates,
                state.weights,
                ctx.prior_kw,
                state.diag,
            )
            if ctx.large
            else None
        )
        trials, lowest = try_candidates(ctx, state, step, plan)
        escaped = (
            escape_local_minimum(
                state.obs,
                ctx.tpl,
                state.active,
                state.current,
                lowest,
                state.weights,
                ctx.prior_kw,
                ctx.settings.bic_threshold,
            )
            if state.restarts < MAX_RESTARTS and lowest is not None
            else None
        )
        if escaped is None:
            break
        assert lowest is not None
        _restart(ctx, state, step, lowest, escaped)
    if plan is not None:
        state.diag.config.setdefault("screening", []).append({"step": step + 1, **plan.report()})
    return _rank(trials, state.current.ndata)


def _restart(
    ctx: SearchContext, state: SearchState, step: int, lowest: ExtendedFit, escaped: ExtendedFit
) -> None:
    """Refit the current model from the better minimum a candidate's fit showed."""
    current = state.current
    state.restarts += 1
    state.diag.config.setdefault("restarts", []).append(
        {
            "step": step + 1,
            "chi2_before": float(current.chi2),
            "chi2_after": float(escaped.chi2),
            "from_model": [e.name for e in lowest.effects],
        }
    )
    logger.info(
        "step %d: the model was at a local minimum (%s reaches a chi2 lower by %.1f "
        "with parameters the model can take itself); refitted from there",
        step + 1,
        "+".join(e.name for e in lowest.effects),
        current.chi2 - escaped.chi2,
    )
    state.weights = radiometer_weights(state.obs, escaped)
    state.current = fit_extended(
        state.obs,
        ctx.tpl,
        state.active,
        weights=state.weights,
        start=escaped.params,
        **ctx.prior_kw,
    )


def _rank(trials: list[Trial], ndata: int) -> list[Trial]:
    """Return the trials with their Delta BIC, best first.

    One overdispersion for every time-domain candidate of a step (as in QAIC, from the
    best-fitting model), so that tiny differences of chi2/dof between candidates are not
    multiplied by a huge Delta chi2.
    """
    if not trials:
        return trials
    own = [r.overdispersion for r in trials if r.effect.kind != "bandpass"]
    chat_t = max(1.0, min(own)) if own else 1.0
    ranked = [
        r
        if r.effect.kind == "bandpass"
        else dataclasses.replace(
            r, statistic=r.delta_chi2 / chat_t - r.k * math.log(ndata), overdispersion=chat_t
        )
        for r in trials
    ]
    # best variant of each effect name first, then best overall
    ranked.sort(key=lambda r: -r.statistic)
    return ranked


def _best_consistent(
    ctx: SearchContext, state: SearchState, trials: list[Trial], step: int
) -> tuple[Trial | None, BandCheck | None]:
    """Return the best trial whose parameters the two halves of the band agree on.

    An effect of the catalogue is the same at every frequency, a template absorbing
    structure of another origin (a beam-shape error, say) is not. Trials are taken in
    order while significant; the first consistent one (or one without a verdict, or a
    bandpass or per-antenna one, which have none) is returned with its check. ``None``
    when every significant trial is inconsistent; the first trial if none is significant.
    """
    settings = ctx.settings
    best: Trial | None = trials[0]
    for trial in trials:
        if not trial.passes(settings.bic_threshold, settings.alpha):
            break
        best = trial
        if not isinstance(trial, ModelTrial):
            break  # a bandpass or per-antenna trial: no band split
        check = check_trial(ctx, state, trial)
        if check is not None and not check.consistent:
            check = consistent_with_partner(
                state.obs,
                ctx.tpl,
                state.active,
                trial,
                trials,
                state.weights,
                ctx.prior_kw,
                settings.bic_threshold,
                settings.alpha,
                check,
            )
        if check is None or check.consistent:
            return trial, check
        state.fail(
            trial.effect.label,
            f"Delta BIC {trial.statistic:.3g}, but {check.refusal} ({check.message}): its "
            "template absorbs structure of another origin",
        )
        logger.info("step %d: %s inconsistent across the band", step + 1, trial.effect.name)
        best = None
    return best, None


def _record_step(
    diag: Diagnosis,
    trial: Trial,
    pval: float,
    accepted: AcceptedStep,
    check: BandCheck | None,
    report: dict[str, float],
) -> None:
    """Append the accepted step to the diagnosis's steps."""
    eff = trial.effect
    params = accepted.parameters
    extra = dict(accepted.extra)
    if check is not None:
        extra["band_consistency"] = check.to_dict()
    if eff.order:
        if eff.basis not in ("integration", "feed_integration"):
            params["order"] = {"value": float(eff.order), "sigma": 0.0}
        extra["time_basis"] = eff.basis
    diag.steps.append(
        {
            "name": eff.name,
            "parameters": params,
            "statistic": float(trial.statistic),
            "delta": float(trial.delta_chi2),
            "k": int(trial.k),
            "p_value": pval,
            "gap_before": accepted.gap_before,
            "gap_after": accepted.gap_after,
            "overdispersion": float(trial.overdispersion),
            "candidates": report,
            **extra,
        }
    )


def _finish(ctx: SearchContext, state: SearchState) -> None:
    """Re-test the final model; its gap, remainder, products' change and parameters."""
    # final backward pass (also run after every accepted step); the kept effects' impact
    # on the products is judged in the final model
    withouts = retest_accepted(ctx, state, "the final model")
    final_impacts(ctx, state, withouts)
    diag, current = state.diag, state.current
    diag.final_gap = gap_metrics(current, state.obs, ctx.tpl, state.bandpass)
    diag.final_fit = current
    diag.unexplained = describe_unexplained(current, state.obs, diag.final_gap)
    _absorb_into_remainder(diag)
    floor = forward_model_accuracy(ctx.tpl.meta.get("tsky", {}).get("beam"))
    diag.config["forward_model_accuracy"] = floor
    _below_model_accuracy(diag, radiometer_total(state.obs), floor)
    diag.product_change = product_impact(
        ctx.base_fit,
        current,
        ctx.sigma_g,
        ctx.sigma_t,
        after_feed_factors=state.feed_departures,
    )
    diag.product_change["note"] = (
        "G and Trxr of the starting model against the diagnosed model (time-domain effects, "
        "each antenna-pol's own gain series included; a cable reflection is a bandpass "
        "feature, its G is unchanged); changes in units of the total 1-sigma of the "
        "ordinary calibration"
    )
    # every accepted effect's parameters from the final joint fit (a step's parameters
    # are those of the model at that step, before later effects were added)
    for st in diag.steps:
        if "dropped_in_backward_pass" in st:
            continue
        if st["name"] == "cable_reflection" or st["name"] not in current.params:
            final = dict(st["parameters"])
        else:
            eff = next(e for e in state.active if e.name == st["name"])
            final = params_dict(eff, current) if eff.fixed is None else dict(st["parameters"])
            if "order" in st["parameters"]:
                final["order"] = st["parameters"]["order"]
        diag.final_parameters[st["name"]] = final


def _absorb_into_remainder(diag: Diagnosis) -> None:
    """Move the negligible effects that follow the unexplained remainder out of "detected".

    With a remainder no catalogue entry explains, a template correlated with it passes the
    test without the effect being there; one negligible for the products whose Delta chi^2
    is below :data:`~autocal.diagnosis.gap.ABSORBED_SHARE` of the remainder's excess chi^2
    goes to :attr:`~autocal.diagnosis.report.Diagnosis.absorbed` (with its share under
    ``unexplained["absorbed"]``).
    """
    if diag.unexplained is None or not diag.negligible:
        return
    excess = float(diag.final_gap["chi2"]) - float(diag.final_gap["dof"])
    if not excess > 0:
        return
    absorbed = []
    for st in diag.steps:
        name = st["name"]
        if name in diag.negligible and name not in diag.absorbed:
            share = float(st["delta"]) / excess
            if share < ABSORBED_SHARE:
                diag.negligible.remove(name)
                diag.absorbed.append(name)
                st["absorbed_by_unexplained"] = share
                absorbed.append({"name": name, "delta_chi2": float(st["delta"]), "share": share})
    if absorbed:
        diag.unexplained["absorbed"] = absorbed


def radiometer_total(obs: Observation) -> float:
    """Return the sum of ``dnu dt N`` over the usable samples (:func:`signal_rms`)."""
    total = 0.0
    width = obs.channel_width[None, None, None, :]
    tint = obs.integration_time[None, None, :, None]
    for sl in antenna_chunks(obs.shape):
        usable = np.isfinite(obs.data[sl]) & ~obs.flags[sl]
        bt = np.broadcast_to(width * (tint * obs.nsamples[sl]), usable.shape)
        total += float(bt[usable].sum())
    return total


def _below_model_accuracy(diag: Diagnosis, radiometer: float, floor: float) -> None:
    """Move the effects whose signal is below the forward model's accuracy.

    An effect seen through the data's structure (:data:`DATA_STRUCTURE_EFFECTS`) whose Delta
    chi^2 corresponds to a signal below ``floor`` of the data (:func:`signal_rms`; the model
    beam's :func:`~autocal.diagnosis.impact.forward_model_accuracy`) fits what autocal's own
    Tsky gets wrong as well as any instrument or other model error could: it goes to
    :attr:`~autocal.diagnosis.report.Diagnosis.below_model_accuracy` (its size under the
    step's ``signal_rms``), neither named nor "detected", whatever it would change in the
    products (its step keeps that change, ``product_impact``). Named, a noise drift of 9e-5
    of the data blamed the receiver for a clean half hour through the HERA beam file, and a
    beam width of 3.6e-5 stood for a sky left in J2000 over half an hour, in realisations
    of the independent suite that its own seed did not show.
    """
    for st in diag.steps:
        name = st["name"]
        if name not in DATA_STRUCTURE_EFFECTS:
            continue
        if name in diag.negligible:
            listed = diag.negligible
        elif name in diag.effects:
            listed = diag.effects  # not attributed, whatever it would change in the products
        else:
            continue
        if st.get("dropped_in_backward_pass") or st.get("superseded_by"):
            continue  # not the step whose effect the final model keeps
        size = signal_rms(float(st["delta"]), radiometer)
        st["signal_rms"] = size
        if size < floor:
            listed.remove(name)
            diag.below_model_accuracy.append(name)
            st["below_model_accuracy"] = True
