"""A candidate's trial in one step of the search, and the statistic that ranks it.

Every candidate not yet in the model is fitted on top of it and recorded as a
:class:`Trial`: its ``Delta chi^2``, free parameters ``k`` and overdispersion ``c``, from
which

    Delta BIC = Delta chi^2 / c - k ln N

ranks the candidates of a step. An effect is accepted only if ``Delta BIC``
exceeds a threshold (default :data:`BIC_THRESHOLD`, "very strong") *and* its
``Delta chi^2`` is significant (chi^2_k survival below ``alpha``, default :data:`ALPHA`).
A trial of a time-domain candidate holds its fitted model (:class:`ModelTrial`), one of
``cable_reflection`` the bandpass fit (:class:`BandpassTrial`), one of a per-antenna gain
the antenna-pols' fits (:class:`FeedTrial`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from scipy import stats

from autocal.diagnosis.bandpass import BandpassFit
from autocal.diagnosis.effects import Effect
from autocal.diagnosis.extended_fit import ExtendedFit
from autocal.diagnosis.feeds import FeedGainFit

#: Default Delta BIC an effect must exceed to be accepted.
BIC_THRESHOLD = 10.0
#: Default significance (chi^2_k survival of Delta chi^2) an effect must reach.
ALPHA = 1e-4


@dataclass(frozen=True, eq=False, kw_only=True)
class Trial:
    """One candidate fitted on top of the current model.

    Attributes
    ----------
    effect
        The candidate, as listed.
    delta_chi2
        ``chi^2`` of the current model less that of the model with the candidate (for
        ``cable_reflection``, of the bandpass fits without and with the ripple).
    k
        Free parameters the candidate adds.
    overdispersion
        ``c`` of the statistic. As fitted, the model's own ``chi^2/dof``; once the step's
        trials are ranked, the step's common overdispersion (``cable_reflection``: always
        its own ``max(1, chi^2/dof)``).
    statistic
        ``Delta BIC = Delta chi^2 / c - k ln N`` (NaN until the step's trials are ranked;
        ``cable_reflection``'s is computed when fitted, with ``N = Nfreq``).
    """

    effect: Effect
    delta_chi2: float
    k: int
    overdispersion: float
    statistic: float = math.nan

    def p_value(self) -> float:
        """Return the chi^2_k survival probability of ``Delta chi^2 / c``."""
        return float(stats.chi2.sf(self.delta_chi2 / self.overdispersion, max(self.k, 1)))

    def passes(self, bic_threshold: float, alpha: float) -> bool:
        """Return whether ``Delta BIC > bic_threshold`` and the p-value is below ``alpha``."""
        return self.statistic > bic_threshold and self.p_value() < alpha


@dataclass(frozen=True, eq=False, kw_only=True)
class ModelTrial(Trial):
    """A time-domain candidate: the model with it, fitted.

    Attributes
    ----------
    fit
        The model the statistic compares: the current effects and :attr:`adopted`.
    free_fit
        The candidate's own fit, its parameters free (the same as :attr:`fit` unless the
        candidate is a fixed hypothesis).
    adopted
        What joins the model when the candidate is accepted: the candidate, or the fixed
        hypothesis it was tested as (``missing_cmb`` with its factor +-1, no free parameter).
    """

    fit: ExtendedFit
    free_fit: ExtendedFit
    adopted: Effect

    @property
    def fixed_hypothesis(self) -> bool:
        """Whether the candidate was tested as a fixed hypothesis (:attr:`adopted`)."""
        return self.adopted is not self.effect


@dataclass(frozen=True, eq=False, kw_only=True)
class BandpassTrial(Trial):
    """``cable_reflection``: the bandpass fit with the ripple (:attr:`ripple`)."""

    ripple: BandpassFit


@dataclass(frozen=True, eq=False, kw_only=True)
class FeedTrial(Trial):
    """A per-antenna gain (``antenna_gain_jitter``, ``antenna_gain_drift``): :attr:`feed`."""

    feed: FeedGainFit
