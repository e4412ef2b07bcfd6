"""What one search for missing effects holds fixed, and what it changes as it goes.

:class:`SearchSettings` are the statistic's settings of a search, :class:`SearchContext`
what all its steps share (templates, candidates, receiver prior, the products' errors),
and :class:`SearchState` what the steps change: the data (a per-antenna gain is divided
out once accepted), the weights, the accepted effects, the current model and the
:class:`~autocal.diagnosis.report.Diagnosis` they fill.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.bandpass import BandpassFit
from autocal.diagnosis.effects import Effect, SkyTemplates
from autocal.diagnosis.extended_fit import ExtendedFit
from autocal.diagnosis.report import Diagnosis, residual_snapshot


@dataclass(frozen=True)
class SearchSettings:
    """The statistic's settings of one search (:func:`autocal.diagnosis.stepwise.diagnose`).

    Attributes
    ----------
    bic_threshold
        Delta BIC an effect must exceed.
    alpha
        Largest chi^2_k survival probability of Delta chi^2 accepted.
    max_steps
        Most effects added.
    smooth_order
        Legendre order of the smooth bandpass of ``cable_reflection``.
    """

    bic_threshold: float
    alpha: float
    max_steps: int
    smooth_order: int


@dataclass(frozen=True, eq=False)
class SearchContext:
    """What every step of one search shares.

    Attributes
    ----------
    tpl
        Model Tsky and templates.
    candidates
        The candidate effects, in the catalogue's order.
    settings
        The statistic's settings.
    prior_kw
        The receiver prior's keywords of every fit
        (:func:`~autocal.diagnosis.extended_fit.fit_extended`: ``trxr_prior``,
        ``trxr_prior_sigma`` and, with a prior, ``gain_ref``, the data's own gain
        (:func:`~autocal.diagnosis.normal_equations.prior_gain_reference`), so that the
        chi^2 of every fit compare).
    sigma_g, sigma_t
        Total 1-sigma of ``G`` and ``Trxr`` of the ordinary calibration
        (:func:`autocal.diagnosis.impact.product_sigmas`).
    base_fit
        The starting model, detached from its data.
    large
        The observation is large: each step screens its candidates
        (:class:`autocal.diagnosis.screening.StepScreen`).
    progress
        Called with ``(fraction, message)`` before every model fit.
    """

    tpl: SkyTemplates
    candidates: tuple[Effect, ...]
    settings: SearchSettings
    prior_kw: dict[str, Any]
    sigma_g: np.ndarray
    sigma_t: np.ndarray
    base_fit: ExtendedFit
    large: bool
    progress: Callable[[float, str], None]


@dataclass(eq=False)
class SearchState:
    """What the steps of one search change.

    Attributes
    ----------
    obs
        The data (with every accepted per-antenna gain divided out).
    weights
        The radiometer weights of the current model.
    current
        The fit of the accepted effects.
    bandpass
        The bandpass domain's fit of the current model: the smooth bandpass, or the
        smooth bandpass with the accepted ripple.
    diag
        The diagnosis being filled.
    active
        The accepted effects (fitted jointly).
    cable
        The accepted ``cable_reflection`` ripple, or ``None``.
    feed_accepted
        The per-antenna gain entries accepted (held in :attr:`obs`).
    restarts
        Times the model was refitted from a candidate's better minimum.
    feed_departures
        ``(Nant, Npol, Ntime)`` the accepted per-antenna gains' departures from the shared
        series, divided out of :attr:`obs` (``None`` until one is accepted): the final
        products' change includes them.
    """

    obs: Observation
    weights: np.ndarray
    current: ExtendedFit
    bandpass: BandpassFit
    diag: Diagnosis
    active: list[Effect] = field(default_factory=list)
    cable: BandpassFit | None = None
    feed_accepted: set[str] = field(default_factory=set)
    restarts: int = 0
    feed_departures: np.ndarray | None = None

    def fail(self, key: str, reason: str) -> None:
        """Record why a candidate was not taken (the diagnosis's ``failed_candidates``)."""
        self.diag.config["failed_candidates"][key] = reason

    def snapshot(self, label: str) -> None:
        """Keep the current model's residuals of the antenna-pols the plots show."""
        self.diag.residual_snapshots.append((label, residual_snapshot(self.current)))
