"""One step of the search: every candidate fitted on top of the current model, and checked.

:func:`try_candidates` fits every candidate not yet in the model and returns the
:class:`~autocal.diagnosis.trials.Trial` of each that passes its own checks: its values are
plausible (:data:`PLAUSIBLE_LIMITS`, :data:`TIMING_MAX_S`), a per-integration gain series is
not a smooth function of time (:func:`autocal.diagnosis.jitter.jitter_is_significant`), its
own parameters are significant (:func:`autocal.diagnosis.consistency.wald_statistic`);
``missing_cmb`` is tested as the fixed hypothesis it is. What is refused, and why, goes to
the diagnosis's ``failed_candidates``. Fits start from the current model's values, and a
model stuck in a local minimum is refitted from a candidate's better one
(:func:`escape_local_minimum`).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.bandpass import (
    SIDE_LOBE_ELEMENTS,
    BandpassFit,
    fit_cable_reflection,
    ripple_halves,
)
from autocal.diagnosis.consistency import (
    CONSISTENCY_ALPHA,
    CONSISTENCY_RELATIVE,
    WALD_SHORTFALL,
    wald_statistic,
)
from autocal.diagnosis.dispersion import robust_overdispersion
from autocal.diagnosis.effects import (
    LST_STEP_H,
    SIDEREAL_RATE,
    TILT_STEP_ARCMIN,
    Effect,
    SkyTemplates,
)
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.extended_fit import ExtendedFit, fit_extended
from autocal.diagnosis.feeds import FEED_JITTER_MAX_FEEDS, fit_feed_gains
from autocal.diagnosis.jitter import (
    JITTER_SMOOTH_ORDER,
    feed_departures_rough,
    jitter_is_significant,
    sky_time_shapes,
)
from autocal.diagnosis.normal_equations import MIN_IDENTIFIABLE
from autocal.diagnosis.screening import StepScreen
from autocal.diagnosis.search_state import SearchContext, SearchState
from autocal.diagnosis.trials import BandpassTrial, FeedTrial, ModelTrial, Trial

logger = logging.getLogger(__name__)

#: Largest ``|parameter|`` of an effect taken as that effect (fractions; K for ``sky_offset`` and
#: ``ground_temperature``): a fit beyond it means the template absorbs other structure (e.g.
#: a diurnal drift of amplitude 100 over half an hour, nearly collinear with a constant).
#: ``sky_spectral_index``: the diffuse sky's index at 90-190 MHz is measured between about
#: -2.5 and -2.6 (EDGES, Mozdzen et al. 2017), varying by ~0.1 over the sky, so a sky
#: model whose index is wrong by more than 0.3 is a template absorbing a beam or horizon
#: error.
PLAUSIBLE_LIMITS = {
    "gain_drift": 0.5,
    "noise_drift": 0.5,
    "beam_width": 0.3,
    "sky_scale": 0.5,
    "sky_spectral_index": 0.3,
    "sky_offset": 100.0,
    "ground_temperature": 300.0,
}
#: Largest ``timing_offset`` (seconds) taken as one: its template is Tsky's first
#: derivative in time, a central difference over +-2 min of LST
#: (:data:`autocal.diagnosis.effects.LST_STEP_H`), so a shift beyond that step extrapolates the
#: difference; J2000 instead of the frame of date for data of the 2010s-2020s is ~1 min
#: in right ascension. (It was 240 s until a real night, JD 2458116, fitted -227 +- 8 s
#: next to a per-antenna jitter: the template trading off against the jitter series.)
TIMING_MAX_S = LST_STEP_H * 3600.0 / SIDEREAL_RATE
#: Largest frame tilt (arcmin) of ``timing_offset`` taken as one: the tilt templates are
#: central differences over :data:`autocal.diagnosis.effects.TILT_STEP_ARCMIN`.
TILT_MAX_ARCMIN = TILT_STEP_ARCMIN
#: Most times one search re-fits its model from a candidate's better minimum
#: (:func:`escape_local_minimum`).
MAX_RESTARTS = 2


def try_candidates(
    ctx: SearchContext, state: SearchState, step: int, plan: StepScreen | None
) -> tuple[list[Trial], ExtendedFit | None]:
    """Fit every candidate not yet in the model (those ``plan`` lets through, if any).

    Returns
    -------
    list[Trial], ExtendedFit or None
        The trials of the candidates that passed their checks, and the lowest-chi2 model
        fitted (refused candidates included: see :func:`escape_local_minimum`).
    """
    trials: list[Trial] = []
    lowest: ExtendedFit | None = None
    for icand, eff in enumerate(ctx.candidates if plan is None else plan.order):
        ctx.progress(
            (step + icand / len(ctx.candidates)) / ctx.settings.max_steps,
            f"step {step + 1}: trying {eff.name} ({eff.basis}, order {eff.order})",
        )
        if any(a.name == eff.name for a in state.active) or (
            eff.kind == "bandpass" and state.cable is not None
        ):
            continue
        if plan is not None and plan.skip(eff, trials):
            continue
        trial: Trial | None
        if eff.kind == "bandpass":
            trial = try_cable_reflection(ctx, state, eff)
        elif eff.kind == "feed_gain":
            trial = try_feed_gains(ctx, state, eff)
        else:
            trial, fit = try_model_effect(ctx, state, eff, step)
            if fit is not None and (lowest is None or fit.chi2 < lowest.chi2):
                lowest = fit
        if trial is not None:
            trials.append(trial)
    return trials, lowest


#: A half of the band whose ripple's Wald statistic has a survival probability above this
#: shows none of it (:func:`reflection_refusal`).
ABSENT_P = 0.05


def reflection_refusal(
    freqs: np.ndarray, gain: np.ndarray, sigma_gain: np.ndarray, rip: BandpassFit
) -> str | None:
    """Why the best ripple ``rip`` of ``G(nu)`` is not a reflection, or ``None``.

    Its delay lies outside the range searched (``rip.at_edge``: structure shorter or longer
    than a reflection's); it is a side lobe of shorter structure that fits better, within
    :data:`~autocal.diagnosis.bandpass.SIDE_LOBE_ELEMENTS` resolution elements of it
    (``rip.shorter_tau_ns``); or it is carried by one part of the band
    (:func:`~autocal.diagnosis.bandpass.ripple_halves`): the two halves disagree on it by
    the model effects' thresholds (chi-square survival below :data:`CONSISTENCY_ALPHA`, in
    units of the ripple fit's overdispersion, and a difference over
    :data:`CONSISTENCY_RELATIVE` of the amplitude, both less what noise adds), or one half
    carries it (survival below :data:`CONSISTENCY_ALPHA` against zero) and the other shows
    none of it (above :data:`ABSENT_P`).
    """
    if not np.isfinite(rip.tau_ns):
        return None  # no delay scanned (too narrow a band): nothing to refuse
    if rip.at_edge:
        lo, hi = rip.delay_range_ns
        where = (
            "below the range: structure shorter than a reflection's delay (what the smooth "
            "bandpass leaves of a bump or a step)"
            if rip.tau_ns < lo
            else "at its upper end: structure beyond the delays searched"
        )
        return (
            f"best delay {rip.tau_ns:.0f} ns of the {lo:.0f}-{hi:.0f} ns searched, {where}, "
            "not a reflection"
        )
    resolution = 1e9 / abs(freqs[-1] - freqs[0])
    if rip.tau_ns - rip.shorter_tau_ns < SIDE_LOBE_ELEMENTS * resolution:
        return (
            f"best delay {rip.tau_ns:.0f} ns, a side lobe of shorter bandpass structure that "
            f"fits better at {rip.shorter_tau_ns:.0f} ns (within {SIDE_LOBE_ELEMENTS:g} "
            "resolution elements), not a reflection"
        )
    halves = ripple_halves(freqs, gain, sigma_gain, rip)
    # one half carries the ripple, the other shows none of it. A half merely too weak to
    # show a faint reflection (where the bandpass is low) fails this too: 20 of 245 faint
    # reflections over the threshold (scripts/reflection_limits.py). Requiring the weak half
    # to be inconsistent with the whole band's ripple as well let 6 of the 324 localised
    # features of tests/diagnosis/test_bandpass.py through (tried on 2026-11-29): their
    # poor fit inflates the overdispersion the test divides by
    one_sided = (
        min(halves.p_lower, halves.p_upper) < CONSISTENCY_ALPHA
        and max(halves.p_lower, halves.p_upper) > ABSENT_P
    )
    differ = (
        halves.p_value < CONSISTENCY_ALPHA and halves.relative_difference > CONSISTENCY_RELATIVE
    )
    if one_sided or differ:
        row = int(np.argmax([f["a"] if np.isfinite(f["a"]) else -1.0 for f in rip.per_feed]))
        a_lo, a_hi = np.hypot(*halves.lower[row]), np.hypot(*halves.upper[row])
        amplitudes = f"a = {a_lo:.2g} and {a_hi:.2g} on its strongest antenna-pol"
        verdict = (
            f"only one of the two halves of the band carries the ripple at {rip.tau_ns:.0f} ns "
            f"({amplitudes}; p {halves.p_lower:.2g} and {halves.p_upper:.2g} against none)"
            if one_sided
            else f"the two halves of the band disagree on the ripple at {rip.tau_ns:.0f} ns "
            f"({amplitudes}; chi2 {halves.chi2:.1f} for {halves.dof}, p {halves.p_value:.2g})"
        )
        return f"{verdict}: structure in one part of the band, not a reflection"
    return None


def try_cable_reflection(
    ctx: SearchContext, state: SearchState, eff: Effect
) -> BandpassTrial | None:
    """Fit a ripple on the current model's ``G(nu)``; ``None`` when it is refused.

    A ripple significant enough to be named is refused (:func:`reflection_refusal`) when
    its best delay lies outside the range searched, it is a side lobe of shorter structure
    that fits better, or the halves of the band disagree on it or only one carries it.
    """
    current = state.current
    null, rip = fit_cable_reflection(
        state.obs.freqs, current.G, current.sigma_G, smooth_order=ctx.settings.smooth_order
    )
    dchi = null.chi2 - rip.chi2
    k = rip.nparam - null.nparam
    chat = max(1.0, rip.reduced_chi2)
    stat = dchi / chat - k * math.log(max(null.nfreq, 2))
    # a ripple that would not pass anyway is rejected as any candidate is, not refused
    refusal = (
        reflection_refusal(state.obs.freqs, current.G, current.sigma_G, rip)
        if stat > ctx.settings.bic_threshold
        else None
    )
    if refusal is not None:
        state.fail("cable_reflection", refusal)
        return None
    return BandpassTrial(
        effect=eff, delta_chi2=dchi, k=k, overdispersion=chat, statistic=stat, ripple=rip
    )


def try_feed_gains(ctx: SearchContext, state: SearchState, eff: Effect) -> FeedTrial | None:
    """Fit every antenna-pol's own gain series (``antenna_gain_jitter``, ``_drift``)."""
    obs, active = state.obs, state.active
    if eff.name in state.feed_accepted:
        return None  # held in the data already
    # a per-antenna jitter is tested once a common series is in the model
    # (nested: it replaces it); a per-antenna drift unless every antenna-pol
    # has its own series already (which holds any drift of its own)
    if eff.basis == "feed_integration":
        if not any(a.basis == "integration" for a in active):
            return None
    elif "antenna_gain_jitter" in state.feed_accepted:
        return None
    if obs.nant * len(obs.pols) > FEED_JITTER_MAX_FEEDS:
        why = (
            f"{obs.nant * len(obs.pols)} antenna-pols, more than the "
            f"{FEED_JITTER_MAX_FEEDS} it fits one by one (a fit each, every step); "
            "diagnose a selection of antennas (--antennas) to test it"
        )
        state.fail(eff.name, f"not tested: {why}")
        state.diag.not_tested[eff.name] = why
        return None
    try:
        feed = fit_feed_gains(obs, ctx.tpl, active, state.current, state.weights, ctx.prior_kw, eff)
    except DiagnoseError as exc:
        state.fail(eff.name, f"not tested: {exc}")
        return None
    rough = (
        feed_departures_rough(feed, state.current, obs, ctx.tpl)
        if feed is not None and eff.basis == "feed_integration"
        else None
    )
    if rough is not None and rough <= ctx.settings.bic_threshold:
        state.fail(
            eff.name,
            "the antenna-pols' departures from the common series are smooth "
            "functions of time (Legendre order "
            f"{JITTER_SMOOTH_ORDER} and the sky's time shapes) up to a remainder "
            f"that does not pay for its parameters (Delta BIC {rough:.3g}): a "
            "smooth per-antenna change, not jitter",
        )
        return None
    if feed is None:
        return None
    return FeedTrial(
        effect=eff,
        delta_chi2=feed.delta_chi2,
        k=feed.k,
        overdispersion=feed.reduced_chi2,
        feed=feed,
    )


def try_model_effect(
    ctx: SearchContext, state: SearchState, eff: Effect, step: int
) -> tuple[ModelTrial | None, ExtendedFit | None]:
    """Fit a time-domain candidate with the accepted effects and check it.

    Returns
    -------
    ModelTrial or None, ExtendedFit or None
        The trial if the candidate passed its checks, and its fit if there is one.
    """
    active, current = state.active, state.current
    if eff.kind == "gain" and any(a.kind == "gain" and a.basis == "integration" for a in active):
        return None, None  # nested: a per-integration gain already absorbs any gain drift
    try:
        # from the current model's values (a new effect starts at zero): a model
        # of several effects is not linear in them, and from zero Gauss-Newton
        # can stop in a local minimum
        trial = fit_extended(
            state.obs,
            ctx.tpl,
            [*active, eff],
            weights=state.weights,
            start=current.params,
            **ctx.prior_kw,
        )
    except (DiagnoseError, np.linalg.LinAlgError) as exc:
        logger.warning("candidate %s failed: %s", eff.label, exc)
        state.fail(eff.label, str(exc))
        return None, None
    if eff.name not in state.diag.identifiability:
        state.diag.identifiability[eff.name] = trial.identifiable.get(eff.name, 0.0)
    if trial.identifiable.get(eff.name, 0.0) < MIN_IDENTIFIABLE:
        return None, trial
    refusal = (
        _implausible(eff, trial)
        or _beyond_timing_range(eff, trial)
        or _smooth_jitter(ctx, state, eff, trial, step)
        or _own_parameters_insignificant(state, eff, trial, ctx.settings.bic_threshold)
    )
    if refusal is not None:
        state.fail(*refusal)
        return None, trial
    if eff.name == "missing_cmb":
        return _cmb_hypothesis(ctx, state, eff, trial), trial
    modelled = ModelTrial(
        effect=eff,
        delta_chi2=current.chi2 - trial.chi2,
        k=eff.nfree,
        overdispersion=trial.reduced_chi2,
        fit=trial,
        free_fit=trial,
        adopted=eff,
    )
    return modelled, trial


def _implausible(eff: Effect, trial: ExtendedFit) -> tuple[str, str] | None:
    """Refuse values beyond :data:`PLAUSIBLE_LIMITS`: ``(failed key, reason)`` or ``None``."""
    limit = PLAUSIBLE_LIMITS.get(eff.name)
    values = np.abs(np.asarray(trial.params.get(eff.name, []), float))
    if limit is not None and eff.fixed is None and np.any(values > limit):
        return eff.label, (
            f"best fit {np.round(trial.params[eff.name], 4).tolist()} beyond the "
            f"plausible range (|value| <= {limit:g}): the template absorbs other "
            "structure"
        )
    return None


def _beyond_timing_range(eff: Effect, trial: ExtendedFit) -> tuple[str, str] | None:
    """Refuse a timing offset beyond :data:`TIMING_MAX_S`, a tilt beyond :data:`TILT_MAX_ARCMIN`."""
    if eff.name != "timing_offset":
        return None
    values = trial.params[eff.name]
    if abs(values[0]) > TIMING_MAX_S:
        return "timing_offset", (
            f"best dt {values[0]:.0f} s is beyond the linear "
            f"template's range (+-{TIMING_MAX_S:.0f} s; a frame error of decades is "
            "~1 min): the template absorbs other time structure, not a timing error"
        )
    tilts = [abs(v) for v in values[1:]]
    if tilts and max(tilts) > TILT_MAX_ARCMIN:
        return "timing_offset", (
            f"best tilt {max(tilts):.0f} arcmin is beyond the templates' range "
            f"(+-{TILT_MAX_ARCMIN:.0f} arcmin, their central-difference step; J2000 against "
            "the date is ~6 arcmin in 2018): they absorb other structure, not a frame error"
        )
    return None


def _smooth_jitter(
    ctx: SearchContext, state: SearchState, eff: Effect, trial: ExtendedFit, step: int
) -> tuple[str, str] | None:
    """Refuse a per-integration gain series that is a smooth function of time or the sky.

    The test (:func:`autocal.diagnosis.jitter.jitter_is_significant`) is recorded in the
    diagnosis's ``jitter_tests`` whatever its verdict.
    """
    if eff.basis != "integration":
        return None
    eps = np.concatenate([[0.0], trial.params[eff.name]])
    sig = np.concatenate([[0.0], trial.sigmas[eff.name]])
    test = jitter_is_significant(
        eps,
        sig,
        state.obs.lsts,
        sky_time_shapes(ctx.tpl),
        ndata=trial.ndata,
        overdispersion=robust_overdispersion(trial),
    )
    state.diag.config.setdefault("jitter_tests", []).append({"step": step + 1, **test.to_dict()})
    if test.significant:
        return None
    return "gain_jitter", (
        "its per-integration series is a smooth function of time (Legendre "
        f"order {JITTER_SMOOTH_ORDER}) and of the sky's own time shape up to "
        f"a remainder that does not pay for its parameters (Delta BIC "
        f"{test.rough_delta_bic:.3g}; {100 * test.smooth_fraction:.0f} % "
        "of the power smooth): a smooth effect or a sky-model error, not jitter"
    )


def _own_parameters_insignificant(
    state: SearchState, eff: Effect, trial: ExtendedFit, bic_threshold: float
) -> tuple[str, str] | None:
    """Refuse a candidate that would pass on its Delta chi2 but not on its own parameters."""
    current = state.current
    wald = wald_statistic(trial, eff)
    penalty = eff.nfree * math.log(current.ndata)
    chat_own = max(1.0, trial.reduced_chi2)
    dchi_own = current.chi2 - trial.chi2
    if (
        wald is not None
        and dchi_own / chat_own - penalty > bic_threshold
        and wald / chat_own - penalty <= bic_threshold
        # equal to Delta chi2 for a model linear in the effect: only a large
        # shortfall is the other parameters moving
        and wald < WALD_SHORTFALL * dchi_own
    ):
        return eff.label, (
            f"its own parameters are consistent with zero (Wald chi2 {wald:.3g} for "
            f"{eff.nfree}) though the fit improves by Delta chi2 "
            f"{current.chi2 - trial.chi2:.3g}: the other parameters moved along a "
            "nearly degenerate valley, not evidence for this effect"
        )
    return None


def _cmb_hypothesis(
    ctx: SearchContext, state: SearchState, eff: Effect, trial: ExtendedFit
) -> ModelTrial | None:
    """Test ``missing_cmb`` as the discrete hypothesis it is, its factor fixed at +-1.

    It is nested in ``sky_offset`` (``T_offset = -+2.725 K``) and has no free parameter, so
    that it wins over ``sky_offset`` when it fits as well; but only if the data ask for a
    CMB-shaped offset at all: the free factor must pay for its parameter (else a small
    offset of any origin, e.g. a horizon treated differently, passes for a missing CMB).
    """
    current = state.current
    m = 1.0 if trial.params[eff.name][0] > 0 else -1.0
    free_stat = (current.chi2 - trial.chi2) / max(1.0, trial.reduced_chi2) - math.log(current.ndata)
    if free_stat <= ctx.settings.bic_threshold:
        state.fail(
            "missing_cmb",
            f"the free CMB factor {trial.params[eff.name][0]:.3g} +- "
            f"{trial.sigmas[eff.name][0]:.2g} does not pay for its parameter "
            f"(Delta BIC {free_stat:.3g})",
        )
        return None
    fixed_eff = Effect(**{**eff.__dict__, "fixed": (m,)})
    fixed_fit = fit_extended(
        state.obs,
        ctx.tpl,
        [*state.active, fixed_eff],
        weights=state.weights,
        start=trial.params,
        **ctx.prior_kw,
    )
    return ModelTrial(
        effect=eff,
        delta_chi2=current.chi2 - fixed_fit.chi2,
        k=0,
        overdispersion=fixed_fit.reduced_chi2,
        fit=fixed_fit,
        free_fit=trial,
        adopted=fixed_eff,
    )


def escape_local_minimum(
    obs: Observation,
    tpl: SkyTemplates,
    active: list[Effect],
    current: ExtendedFit,
    fit: ExtendedFit,
    w: np.ndarray,
    prior_kw: dict[str, Any],
    bic_threshold: float,
) -> ExtendedFit | None:
    """Re-fit the current model from a candidate fit's values of its parameters.

    The model with several effects is not linear in their parameters (a per-integration
    gain and a noise drift are nearly interchangeable over half an hour), so Gauss-Newton
    from zero can stop in a local minimum. A candidate fit that nests the current model
    then "explains" the difference between the two minima, whatever its own parameter
    says (a timing offset of -76 +- 130 s taking Delta chi2 1.5e5 from a per-integration
    gain and a noise drift stuck at chi2/dof 6.4 with the drift's sign wrong). Started from
    ``fit``'s values (the step's lowest-chi2 candidate model) of the accepted effects'
    parameters, the current model reaches the better minimum itself; it is returned when
    it lowers chi2 by more than ``bic_threshold`` (in units of its overdispersion), else
    ``None``. Every fit's prior weights come from one reference gain (the data's own,
    ``prior_kw["gain_ref"]``), so chi2 of fits started from different values compare.
    """
    start = {e.name: fit.params[e.name] for e in active if e.fixed is None and e.name in fit.params}
    if not start:
        return None
    try:
        refit = fit_extended(obs, tpl, active, weights=w, start=start, **prior_kw)
    except (DiagnoseError, np.linalg.LinAlgError):
        return None
    gain = (current.chi2 - refit.chi2) / max(1.0, refit.reduced_chi2)
    return refit if gain > bic_threshold else None
