"""Screening a large search's candidates by their score before fitting them.

Above :data:`autocal.diagnosis.chunks.LARGE_SAMPLES` each step of the search scores all
time-domain candidates in one pass over the data from the current model
(:func:`screen_candidates`) and fits in full only those that could win (:class:`StepScreen`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.effects import Effect, SkyTemplates
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.extended_fit import ExtendedFit
from autocal.diagnosis.normal_equations import (
    MIN_IDENTIFIABLE,
    FitProblem,
    blas_single_thread,
    identifiable_fractions,
    scaled_pinv,
)
from autocal.diagnosis.report import Diagnosis
from autocal.diagnosis.trials import BIC_THRESHOLD, Trial

logger = logging.getLogger(__name__)


#: A step of a large search fits in full at least this many time-domain candidates (those
#: with the best scores, :class:`StepScreen`) ...
SCREEN_FITS = 2
#: ... and then every one whose score-based Delta BIC comes within this much of the best
#: fitted candidate's Delta BIC, or within :data:`SCREEN_FRACTION` of it if that is more.
SCREEN_MARGIN = BIC_THRESHOLD
#: See :data:`SCREEN_MARGIN`. The score misses the full fit's Delta chi^2 by < 1 % for the
#: candidates near the data's effect and overestimates it by up to 25 % for strong ones far
#: from it (``beam_width`` against a gain drift; the test of :func:`screen_candidates`).
SCREEN_FRACTION = 0.25


@dataclass(frozen=True)
class Screening:
    """A candidate's score from the current model (:func:`screen_candidates`).

    Attributes
    ----------
    delta_chi2
        ``Delta chi^2`` one Gauss-Newton step from the current model predicts for the
        model with the candidate (its parameters from zero, the accepted effects' from
        their fitted values): the score (Lagrange-multiplier) statistic.
    identifiable
        Fraction of the candidate's Fisher information left after the ``(G, n)`` projection (as
        :attr:`~autocal.diagnosis.extended_fit.ExtendedFit.identifiable`, at the current model).
    """

    delta_chi2: float
    identifiable: float


@blas_single_thread
def screen_candidates(
    obs: Observation,
    tpl: SkyTemplates,
    active: list[Effect],
    current: ExtendedFit,
    candidates: list[Effect],
    *,
    weights: np.ndarray,
    trxr_prior: np.ndarray | float | None = None,
    trxr_prior_sigma: np.ndarray | float = 1.0,
    gain_ref: np.ndarray | None = None,
) -> list[Screening]:
    """Score every candidate against the current model in one pass over the data.

    The projected normal equations of the accepted effects and of all candidates together
    are summed in one stream of the antennas at the current model (the accepted effects
    at their fitted values, the candidates at zero); for each candidate the accepted
    effects' and its own rows give the ``Delta chi^2`` of one Gauss-Newton step,
    ``grad^T H^-1 grad``: the score statistic, exact for an effect linear in its
    parameters when ``(G, n)`` are held, and the first step of the candidate's own fit.
    The ``J^T W J`` blocks between two candidates are not computed (never used).

    Parameters
    ----------
    obs, tpl, weights, trxr_prior, trxr_prior_sigma
        As for :func:`~autocal.diagnosis.extended_fit.fit_extended` (the weights of ``current``).
    active
        The accepted effects.
    current
        The fit of ``active`` with these weights.
    candidates
        Time-domain candidates (not among ``active``).

    Returns
    -------
    list[Screening]
        One per candidate, in order.
    """
    effects = tuple(e for e in [*active, *candidates] if e.kind != "bandpass")
    prob = FitProblem(obs, tpl, effects, weights, trxr_prior, trxr_prior_sigma, gain_ref, None)
    nact = len(active)
    groups = [0 if i < nact else i for i, (_, sl) in enumerate(prob.blocks) if sl.stop > sl.start]
    p = np.zeros(prob.nfree)
    for eff, sl in prob.blocks[:nact]:
        if sl.stop > sl.start:
            p[sl] = current.params[eff.name]
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        st = prob.evaluate(p)
        h, grad, raw = prob.normal_equations(p, st, groups=groups)
    act_idx = np.concatenate(
        [np.arange(sl.start, sl.stop) for _, sl in prob.blocks[:nact]] + [np.zeros(0, int)]
    ).astype(int)
    out = []
    for eff, sl in prob.blocks[nact:]:
        idx = np.concatenate([act_idx, np.arange(sl.start, sl.stop)])
        frac = identifiable_fractions([(eff, sl)], h, raw).get(eff.name, 0.0)
        if (
            sl.stop == sl.start
            or frac < MIN_IDENTIFIABLE
            or not np.all(np.isfinite(h[idx][:, idx]))
        ):
            out.append(Screening(0.0, frac))
            continue
        hs = h[np.ix_(idx, idx)]
        gs = grad[idx]
        dchi = float(gs @ scaled_pinv(hs, raw[idx]) @ gs)
        out.append(Screening(max(dchi, 0.0), frac))
    return out


class StepScreen:
    """Which candidates one step of a large search fits in full.

    All time-domain candidates are scored at once from the current model
    (:func:`screen_candidates`); they are tried best score first, each fitted in full,
    until :data:`SCREEN_FITS` have passed the checks and the next one's score-based Delta
    BIC is out of reach of the best fitted one (:data:`SCREEN_MARGIN`,
    :data:`SCREEN_FRACTION`). Candidates the projection leaves unidentifiable are not
    fitted (a full fit would be refused for the same reason). The bandpass candidate
    (``cable_reflection``) is always tried.
    """

    def __init__(
        self,
        obs: Observation,
        tpl: SkyTemplates,
        active: list[Effect],
        current: ExtendedFit,
        cands: list[Effect],
        weights: np.ndarray,
        prior_kw: dict[str, Any],
        diag: Diagnosis,
    ) -> None:
        names = {a.name for a in active}
        jitter = any(a.kind == "gain" and a.basis == "integration" for a in active)
        scored = [
            c
            for c in cands
            if c.kind not in ("bandpass", "feed_gain")
            and c.name not in names
            and not (c.kind == "gain" and jitter)
        ]
        self.diag, self.lnn = diag, math.log(max(current.ndata, 2))
        self.scores: dict[int, Screening] = {}
        try:
            scores = screen_candidates(
                obs, tpl, active, current, scored, weights=weights, **prior_kw
            )
        except (DiagnoseError, np.linalg.LinAlgError) as exc:
            logger.warning("candidate screening failed (%s): every candidate is fitted", exc)
            scores = []
        self.scores = {id(c): s for c, s in zip(scored, scores, strict=False)}
        self.approx = {id(c): self._approx(c) for c in scored if id(c) in self.scores}
        ranked = sorted(
            (c for c in scored if id(c) in self.scores),
            key=lambda c: (
                -self.approx[id(c)]
                if self.scores[id(c)].identifiable >= MIN_IDENTIFIABLE
                else math.inf
            ),
        )
        rest = [c for c in cands if c.kind != "bandpass" and id(c) not in self.scores]
        self.order = [c for c in cands if c.kind == "bandpass"] + ranked + rest
        self.skipped: dict[str, float] = {}
        self.fitted: list[str] = []

    def _approx(self, eff: Effect, chat: float = 1.0) -> float:
        """Return the candidate's Delta BIC from its score (overdispersion ``chat``)."""
        return self.scores[id(eff)].delta_chi2 / chat - eff.nfree * self.lnn

    def skip(self, eff: Effect, trials: list[Trial]) -> bool:
        """Return whether to skip the candidate given the step's trials so far."""
        score = self.scores.get(id(eff))
        if score is None:
            return False
        label = eff.label
        if score.identifiable < MIN_IDENTIFIABLE:
            self.diag.identifiability.setdefault(eff.name, score.identifiable)
            return True
        fitted = [r for r in trials if r.effect.kind != "bandpass"]
        if len(fitted) >= SCREEN_FITS:
            chat = max(1.0, min(r.overdispersion for r in fitted))
            best = max(r.delta_chi2 / chat - r.k * self.lnn for r in fitted)
            approx = self._approx(eff, chat)
            if approx < best - max(SCREEN_MARGIN, SCREEN_FRACTION * abs(best)):
                self.skipped[label] = approx
                self.diag.identifiability.setdefault(eff.name, score.identifiable)
                return True
        self.fitted.append(label)
        return False

    def report(self) -> dict[str, Any]:
        """Return what the step fitted and the score-based Delta BIC of what it did not."""
        return {"fitted": list(self.fitted), "screened_out": dict(self.skipped)}
