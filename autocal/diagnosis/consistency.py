"""Does a candidate's own signature explain the residual? Its parameters and the band's halves.

A candidate is named only when its own signature explains the residual: its own parameters
are significant (:func:`wald_statistic`), and the two halves of the band agree on them
(:func:`band_consistency`), with a significant partner fitted alongside when two chromatic
effects are missing at once (:func:`consistent_with_partner`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from autocal.core.observation import Observation
from autocal.diagnosis.effects import Effect, SkyTemplates
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.extended_fit import ExtendedFit, fit_extended
from autocal.diagnosis.normal_equations import MIN_IDENTIFIABLE
from autocal.diagnosis.search_state import SearchContext, SearchState
from autocal.diagnosis.trials import ModelTrial, Trial

logger = logging.getLogger(__name__)


#: A candidate is refused on its own parameters only when their Wald statistic is below
#: this fraction of its Delta chi2 (:func:`wald_statistic`): for a model linear in them
#: the two are equal, so a large shortfall is the other parameters moving along a nearly
#: degenerate valley of a model that is not linear in them.
WALD_SHORTFALL = 0.5


def wald_statistic(fit: ExtendedFit, eff: Effect) -> float | None:
    """Return the Wald statistic ``v^T C^-1 v`` of an effect's free parameters in a fit.

    ``v`` the effect's values, ``C`` the full covariance block of them
    (:attr:`.ExtendedFit.covariances`, correlations between them included: a diurnal
    sine and cosine, a drift's Legendre terms), inverted as a correlation matrix (a
    pseudo-inverse where it is singular). For a model linear in the effect's parameters
    it equals the fit's Delta chi2; a Delta chi2 far above it means the improvement came
    from the other parameters moving (the model is not linear in them), not from this
    effect. Falls back on the diagonal, ``sum (v / sigma)^2``, when the block is missing or
    not finite. ``None`` for a fixed effect.
    """
    if eff.fixed is not None or not eff.nfree or eff.name not in fit.params:
        return None
    values = np.asarray(fit.params[eff.name], float)
    sigmas = np.asarray(fit.sigmas[eff.name], float)
    ok = np.isfinite(values) & np.isfinite(sigmas) & (sigmas > 0)
    cov = fit.covariances.get(eff.name)
    if cov is not None and cov.shape == (values.size, values.size) and ok.all():
        diag = np.diag(cov)  # a rounding-negative variance falls back on the sigmas
        if np.all(np.isfinite(cov)) and np.all(diag > 0):
            scale = np.sqrt(diag)
            z = values / scale
            corr = cov / np.outer(scale, scale)
            return float(z @ np.linalg.pinv(corr, rcond=1e-12, hermitian=True) @ z)
    return float(np.sum((values[ok] / sigmas[ok]) ** 2))


#: Significance (chi-square survival probability) below which the two half-band fits of
#: an effect disagree (:func:`band_consistency`) ...
CONSISTENCY_ALPHA = 1e-3
#: ... provided they also differ by more than this fraction of the whole band's value.
CONSISTENCY_RELATIVE = 0.3


@dataclass(frozen=True)
class BandCheck:
    """The verdict of :func:`band_consistency` on one candidate.

    Attributes
    ----------
    consistent
        Whether the two halves of the band agree on the candidate's parameters.
    values
        ``lower``, ``upper`` and ``whole``: the parameters fitted in each half and in the
        whole band (``None`` for more than eight parameters).
    chi2, k, p_value
        Chi-square of the halves' difference (over its variance and the halves'
        overdispersion), its degrees of freedom and survival probability.
    relative_difference
        Norm of the halves' difference over that of the whole band's values, for the
        parameters of each unit apart (the largest).
    message
        One line on the comparison.
    partner
        The candidate fitted alongside, if any.
    whole_departure
        How far the whole band's values lie from the halves' combination (their
        inverse-covariance weighted mean), over the whole band's values, unit by unit (the
        largest; :func:`_whole_against_halves`); ``None`` when not computed.
    refused_by
        ``None`` when consistent, else the rule that refused: ``"halves"`` (the two halves
        disagree) or ``"whole"`` (the whole band lies outside what they combine to).
    """

    consistent: bool
    values: dict[str, list[float]] | None
    chi2: float
    k: int
    p_value: float
    relative_difference: float
    message: str
    partner: str | None = None
    whole_departure: float | None = None
    refused_by: str | None = None

    @property
    def refusal(self) -> str:
        """Return why the candidate was refused, in words (empty when consistent)."""
        if self.refused_by == "whole":
            return "the whole band's value lies outside what the two halves of the band combine to"
        return "the two halves of the band disagree on its parameters" if self.refused_by else ""

    def to_dict(self) -> dict[str, Any]:
        """Return the verdict as a diagnosis step's ``band_consistency`` entry."""
        return {
            "consistent": self.consistent,
            "values": self.values,
            "chi2": self.chi2,
            "k": self.k,
            "p_value": self.p_value,
            "relative_difference": self.relative_difference,
            "message": self.message,
            "partner": self.partner,
            "whole_departure": self.whole_departure,
            "refused_by": self.refused_by,
        }


def _band_half(
    obs: Observation,
    tpl: SkyTemplates,
    w: np.ndarray,
    prior_kw: dict[str, Any],
    channels: slice,
) -> tuple[Observation, SkyTemplates, np.ndarray, dict[str, Any]]:
    """Restrict the observation, templates, weights and receiver prior to ``channels``."""
    f = obs.freqs[channels]
    sub = obs.select(freq_range=(float(f[0]), float(f[-1])))
    sub_tpl = tpl.subset(channels=channels)
    sub_prior = {}
    for key, value in prior_kw.items():
        arr = None if value is None else np.asarray(value, float)
        sub_prior[key] = (
            arr[..., channels]
            if arr is not None and arr.ndim and arr.shape[-1] == obs.nfreq
            else value
        )
    return sub, sub_tpl, w[..., channels], sub_prior


def band_consistency(
    obs: Observation,
    tpl: SkyTemplates,
    active: list[Effect],
    eff: Effect,
    fit: ExtendedFit,
    w: np.ndarray,
    prior_kw: dict[str, Any],
    partner: Effect | None = None,
) -> BandCheck | None:
    """Fit a candidate in the lower and the upper half of the band and compare.

    Every effect of the catalogue has the same parameters at every frequency (an
    achromatic drift, one sky scale or index, one beam-width factor, one timing offset).
    A template that fits because it absorbs structure of another origin, e.g. a spectral
    index of -0.5 taking up part of a beam-shape error, generally gets different values
    from the two halves. They disagree when the difference is significant (chi-square of
    the difference over the summed variances, scaled by the halves' overdispersion,
    survival probability below :data:`CONSISTENCY_ALPHA`) and larger than
    :data:`CONSISTENCY_RELATIVE` of the whole band's value, for the parameters of each unit
    apart (a real effect measured with
    tiny errors may differ slightly between halves when the sky model is slightly wrong).

    A real effect next to another missing chromatic one (a noise drift while the sky's
    spectral index is also wrong) is biased differently in the two halves too; fitted
    with that ``partner`` alongside (``fit`` then the joint fit), both agree again.

    Parameters
    ----------
    obs, tpl, w, prior_kw
        The observation, its templates, weights and receiver prior.
    active
        The effects already in the model (refitted in each half).
    eff
        The candidate (free parameters; a fixed effect is not tested).
    fit
        Its fit on the whole band (with ``partner``, if any).
    partner
        Another candidate fitted alongside; its free parameters must agree as well.

    Returns
    -------
    BandCheck or None
        The verdict; ``None`` (no verdict) when the candidate has no free parameters, is a
        per-integration series (``gain_jitter``, judged by
        :func:`autocal.diagnosis.jitter.jitter_is_significant`: split by band, its
        hundreds of factors follow whatever chromatic structure the model still lacks), or
        a half cannot be fitted.
    """
    if eff.fixed is not None or not eff.nfree or obs.nfreq < 8 or eff.basis == "integration":
        return None
    model = [*active, eff] + ([partner] if partner is not None else [])
    mid = obs.nfreq // 2
    halves = []
    for channels in (slice(0, mid), slice(mid, obs.nfreq)):
        try:
            sub, sub_tpl, sub_w, sub_prior = _band_half(obs, tpl, w, prior_kw, channels)
            half = fit_extended(sub, sub_tpl, model, weights=sub_w, start=fit.params, **sub_prior)
        except (DiagnoseError, np.linalg.LinAlgError, ValueError) as exc:
            logger.debug("band consistency of %s: no verdict (%s)", eff.name, exc)
            return None
        if half.identifiable.get(eff.name, 0.0) < MIN_IDENTIFIABLE:
            return None
        # its parameters are all the comparison needs: without the half's copy of the
        # data, one half-band copy at a time is alive (run.HALF_BAND_BYTES_PER_SAMPLE)
        halves.append(half.detached())
        del sub, sub_w
    out = _compare_halves(eff, halves, fit)
    if out is None:
        return None
    out = dataclasses.replace(out, partner=None if partner is None else partner.name)
    if partner is not None and partner.fixed is None and partner.nfree:
        other = _compare_halves(partner, halves, fit)
        if other is not None and not other.consistent:
            message = f"{out.message}; with {partner.name}: {other.message}"
            out = dataclasses.replace(out, consistent=False, message=message)
        elif partner is not None:
            out = dataclasses.replace(out, message=f"{out.message} (fitted with {partner.name})")
    return out


def check_trial(ctx: SearchContext, state: SearchState, trial: ModelTrial) -> BandCheck | None:
    """Return :func:`band_consistency` of a step's trial on the search's current model."""
    return band_consistency(
        state.obs,
        ctx.tpl,
        state.active,
        trial.effect,
        trial.free_fit,
        state.weights,
        ctx.prior_kw,
    )


def _compare_halves(
    eff: Effect, halves: list[ExtendedFit], whole_fit: ExtendedFit
) -> BandCheck | None:
    """Compare one effect's parameters in the two half-band fits (:func:`band_consistency`)."""
    lo, hi = (np.asarray(h.params[eff.name], float) for h in halves)
    slo, shi = (np.asarray(h.sigmas[eff.name], float) for h in halves)
    whole = np.asarray(whole_fit.params[eff.name], float)
    var = slo**2 + shi**2
    ok = np.isfinite(lo) & np.isfinite(hi) & np.isfinite(var) & (var > 0)
    if not ok.any():
        return None
    chat = max(1.0, *(h.reduced_chi2 for h in halves))
    chi2 = float(np.sum((lo - hi)[ok] ** 2 / var[ok]) / chat)
    k = int(ok.sum())
    pval = float(stats.chi2.sf(chi2, k))
    rel = _relative_difference(eff, lo - hi, whole, ok)
    consistent = bool(pval >= CONSISTENCY_ALPHA or rel <= CONSISTENCY_RELATIVE)
    show = (
        f"{eff.params[0]} = {lo[0]:.4g} +- {slo[0]:.2g} (lower half), {hi[0]:.4g} +- "
        f"{shi[0]:.2g} (upper)"
        if lo.size <= 2
        else f"{k} values differ by {100 * rel:.0f} % rms of the whole band's"
    )
    message = f"{show}; chi2 {chi2:.3g} for {k}, p {pval:.2g}"
    refused_by = None if consistent else "halves"
    combined, departure, outside = _whole_against_halves(eff, halves, whole, ok, chat)
    if outside:
        refused_by = refused_by or "whole"
        consistent = False
        message += (
            f"; the whole band's {_show(whole[ok])} lies outside what the halves combine "
            f"to, {_show(combined[ok])} (by {100 * departure:.0f} % of the whole band's "
            "value): the template fits the difference between the halves, not an effect "
            "they share"
        )
    return BandCheck(
        consistent=consistent,
        values={
            "lower": lo.tolist(),
            "upper": hi.tolist(),
            "whole": whole.tolist(),
            "combined": combined.tolist(),
        }
        if lo.size <= 8
        else None,
        chi2=chi2,
        k=k,
        p_value=pval,
        relative_difference=rel,
        message=message,
        whole_departure=departure,
        refused_by=refused_by,
    )


def _show(values: np.ndarray) -> str:
    """Return values as ``a`` or ``(a, b, ...)`` with 4 significant digits."""
    parts = [f"{v:.4g}" for v in values]
    return parts[0] if len(parts) == 1 else f"({', '.join(parts)})"


def _whole_against_halves(
    eff: Effect, halves: list[ExtendedFit], whole: np.ndarray, ok: np.ndarray, chat: float
) -> tuple[np.ndarray, float | None, bool]:
    """Compare the whole band's values with what the two halves' fits combine to.

    The halves are disjoint data, so for an effect they share the whole band's fit is,
    to first order, the halves' values combined by their information,
    ``(C_lo^-1 + C_hi^-1)^-1 (C_lo^-1 lo + C_hi^-1 hi)`` (each half's covariance block of
    the effect's parameters): for one parameter a weighted mean, between the two. A template
    that fits the difference between the halves (a chromatic structure the model lacks,
    across the band) instead gets a whole-band value far from it, even outside both (a sky
    offset of +23.5 K from halves of -4.1 and -4.2 K, left by a beam width fitted as a
    stretch when the beam's FWHM was wrong). Outside when the departure is significant
    (chi-square over the combination's covariance and ``chat``, its rank degrees of
    freedom, survival probability below :data:`CONSISTENCY_ALPHA`: conservative, the two
    estimates share their data) and
    larger than :data:`CONSISTENCY_RELATIVE` of the whole band's values, unit by unit
    (:func:`_relative_difference`).

    Returns
    -------
    tuple
        The combination, the relative departure (``None`` when it cannot be computed:
        covariances not finite) and whether the whole lies outside.
    """
    covs = [_covariance(eff, h) for h in halves]
    idx = np.flatnonzero(ok)
    combined = np.full(whole.shape, np.nan)
    try:
        infos = [np.linalg.pinv(c[np.ix_(idx, idx)], hermitian=True) for c in covs]
        info = infos[0] + infos[1]  # the combination's information (inverse covariance)
        values = [np.asarray(h.params[eff.name], float)[idx] for h in halves]
        combined[idx] = np.linalg.pinv(info, hermitian=True) @ (
            infos[0] @ values[0] + infos[1] @ values[1]
        )
        rank = int(np.linalg.matrix_rank(info, hermitian=True)) if idx.size else 0
    except (np.linalg.LinAlgError, ValueError):
        return combined, None, False
    diff = np.where(ok, whole - combined, 0.0)
    if not np.all(np.isfinite(diff)) or not np.all(np.isfinite(info)):
        return combined, None, False
    departure = _relative_difference(eff, diff, whole, ok)
    chi2 = float(diff[idx] @ info @ diff[idx]) / chat
    pval = float(stats.chi2.sf(chi2, max(rank, 1)))
    return combined, departure, bool(pval < CONSISTENCY_ALPHA and departure > CONSISTENCY_RELATIVE)


def _covariance(eff: Effect, fit: ExtendedFit) -> np.ndarray:
    """Return the covariance block of an effect's parameters in a fit (else its sigmas')."""
    sig = np.asarray(fit.sigmas[eff.name], float)
    cov = fit.covariances.get(eff.name)
    if cov is not None and cov.shape == (sig.size, sig.size) and np.all(np.isfinite(cov)):
        return np.asarray(cov, float)
    return np.diag(sig**2)


def _relative_difference(eff: Effect, diff: np.ndarray, whole: np.ndarray, ok: np.ndarray) -> float:
    """Return the halves' difference over the whole band's values, unit by unit (largest).

    Parameters of one unit are compared as a vector (the norm of their difference over the
    norm of their whole-band values, e.g. a gain drift's Legendre coefficients); parameters
    of different units are not mixed (``timing_offset``'s seconds and arcminutes: a tilt
    the halves disagree on is not hidden behind a large clock offset).
    """
    if len(eff.units) != diff.size:
        raise ValueError(f"{eff.name}: {len(eff.units)} units for {diff.size} parameters")
    units = np.array(eff.units)
    worst = 0.0
    for unit in dict.fromkeys(units[ok].tolist()):
        group = ok & (units == unit)
        size = max(float(np.linalg.norm(whole[group])), 1e-300)
        ratio = float(np.linalg.norm(diff[group])) / size
        if not np.isfinite(ratio):  # no whole-band value to compare with: no escape
            return np.inf
        worst = max(worst, ratio)
    return worst


#: Most partners tried for a candidate whose parameters the band's halves disagree on.
CONSISTENCY_PARTNERS = 3


def consistent_with_partner(
    obs: Observation,
    tpl: SkyTemplates,
    active: list[Effect],
    trial: ModelTrial,
    trials: list[Trial],
    w: np.ndarray,
    prior_kw: dict[str, Any],
    bic_threshold: float,
    alpha: float,
    check: BandCheck,
) -> BandCheck:
    """Re-test an inconsistent candidate with another significant candidate alongside.

    Two effects missing at once bias each other's half-band fits (a noise drift and a
    spectral index error are both chromatic); fitted together, both agree across the band.
    The next :data:`CONSISTENCY_PARTNERS` significant candidates of other names among the
    step's ranked ``trials`` are tried; the first joint fit in which both are consistent is
    returned (with ``partner``), else the original ``check``.
    """
    eff = trial.effect
    tried = 0
    for other in trials:
        if other is trial or other.effect.name == eff.name or not isinstance(other, ModelTrial):
            continue  # a bandpass or per-antenna candidate is no partner
        if not other.passes(bic_threshold, alpha):
            break
        if tried >= CONSISTENCY_PARTNERS:
            break
        tried += 1
        partner = other.adopted
        try:
            joint = fit_extended(
                obs,
                tpl,
                [*active, eff, partner],
                weights=w,
                start={**other.fit.params, **trial.free_fit.params},
                **prior_kw,
            )
        except (DiagnoseError, np.linalg.LinAlgError):
            continue
        again = band_consistency(obs, tpl, active, eff, joint, w, prior_kw, partner=partner)
        if again is not None and again.consistent:
            return again
    return check
