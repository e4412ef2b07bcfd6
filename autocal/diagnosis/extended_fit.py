"""The extended fit: per-channel ``(G, n)`` plus the global parameters of some effects.

The model is that of :mod:`autocal.diagnosis.effects`; :func:`fit_extended` solves it by a
variable-projection Gauss-Newton (:mod:`autocal.diagnosis.normal_equations`), streaming the
antennas through its sums a chunk at a time (:func:`autocal.diagnosis.chunks.antenna_chunks`).
A fit's model and residuals are computed from its inputs when needed, never stored
(:class:`ModelSource`), so a whole HERA file (350 antennas, 206 M samples) is diagnosed in
~6 GB. :func:`radiometer_weights` gives the inverse variances every fit of a search shares.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.chunks import antenna_chunks, usable_weights, weights_dtype
from autocal.diagnosis.effects import Effect, SkyTemplates
from autocal.diagnosis.errors import DiagnoseError
from autocal.diagnosis.normal_equations import (
    MIN_IDENTIFIABLE,
    FitProblem,
    FitState,
    blas_single_thread,
    identifiable_fractions,
    scaled_pinv,
)


@dataclass(frozen=True, eq=False)
class ModelSource:
    """What the model and residuals of a fit are computed from, a chunk at a time.

    ``a1`` ``(P, T, F)`` is the model Tsky times the gain factor, ``a2`` ``(T,)`` the noise
    factor times the gain factor: ``model = G a1 + n a2``. ``g``, ``nn`` ``(A, P, F)`` are
    zero in channels without a solution. The observation and weights are references (not
    copies) to the arrays the fit was given.
    """

    obs: Observation
    weights: np.ndarray
    chan_ok: np.ndarray
    a1: np.ndarray
    a2: np.ndarray
    g: np.ndarray
    nn: np.ndarray
    chunks: list[slice]

    def weights_chunk(self, sl: slice) -> np.ndarray:
        """Weights the fit used for antennas ``sl``, ``(a, P, T, F)`` float64."""
        return usable_weights(self.weights[sl], self.chan_ok[sl])

    def model_chunk(self, sl: slice) -> np.ndarray:
        """Model autos of antennas ``sl``, ``(a, P, T, F)``."""
        return (
            self.g[sl][:, :, None, :] * self.a1[None]
            + self.nn[sl][:, :, None, :] * self.a2[None, None, :, None]
        )

    def residual_chunk(self, sl: slice) -> np.ndarray:
        """Normalised residuals of antennas ``sl`` (NaN where the weight is zero)."""
        w = self.weights_chunk(sl)
        with np.errstate(invalid="ignore"):
            return np.where(w > 0, (self.obs.data[sl] - self.model_chunk(sl)) * np.sqrt(w), np.nan)


@dataclass(frozen=True, eq=False)
class ExtendedFit:
    """Result of :func:`fit_extended`.

    Attributes
    ----------
    effects
        The effects included.
    params
        ``{effect name: values}`` (fixed values included).
    sigmas
        ``{effect name: 1-sigma}`` (0 for fixed values).
    G, n, sigma_G
        ``(Nant, Npol, Nfreq)`` per-channel gain, noise and gain error.
    chi2
        Weighted chi-square (with the prior term).
    ndata
        Number of data used (with prior pseudo-observations).
    nparam
        Per-channel plus free global parameters.
    identifiable
        ``{effect name: fraction of Fisher information left after the (G, n) projection}``
        (0 below :data:`~autocal.diagnosis.normal_equations.IDENTIFIABLE_RESOLUTION`:
        degenerate with ``(G, n)``).
    iterations
        Gauss-Newton iterations used.
    covariances
        ``{effect name: (k, k) covariance block of its free parameters}`` (the full block,
        off-diagonal terms included; empty ``(0, 0)`` for a fixed effect, infinite when
        the effect is not identifiable).
    gain_factor, noise_factor
        ``(Ntime,)`` the achromatic factors of ``G`` and ``n`` over time
        (``G(t) = G gain_factor(t)``, ``n(t) = n noise_factor(t)``; ones without drift or
        jitter).
    source
        What :attr:`model` and :attr:`residuals` are computed from (``None`` once
        :meth:`detached`). They are not stored: a whole HERA file's would be 1.6 GB each,
        and a search keeps a fit of every candidate. :meth:`model_chunks` and
        :meth:`residual_chunks` give them a chunk of antennas at a time.
    """

    effects: tuple[Effect, ...]
    params: dict[str, np.ndarray]
    sigmas: dict[str, np.ndarray]
    G: np.ndarray
    n: np.ndarray
    sigma_G: np.ndarray  # noqa: N815
    chi2: float
    ndata: int
    nparam: int
    identifiable: dict[str, float]
    iterations: int
    covariances: dict[str, np.ndarray] = field(default_factory=dict)
    gain_factor: np.ndarray | None = None
    noise_factor: np.ndarray | None = None
    source: ModelSource | None = field(default=None, repr=False)

    @property
    def dof(self) -> int:
        """Degrees of freedom ``ndata - nparam``."""
        return self.ndata - self.nparam

    @property
    def reduced_chi2(self) -> float:
        """``chi^2 / dof``."""
        return self.chi2 / max(self.dof, 1)

    @property
    def Trxr(self) -> np.ndarray:
        """``n / G``."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.n / self.G

    def _source(self) -> ModelSource:
        if self.source is None:
            raise DiagnoseError("this fit was detached from its data: no model or residuals")
        return self.source

    def model_chunks(self) -> Iterator[tuple[slice, np.ndarray]]:
        """Yield ``(antenna slice, (a, Npol, Ntime, Nfreq) model autos)``."""
        src = self._source()
        for sl in src.chunks:
            yield sl, src.model_chunk(sl)

    def residual_chunks(self) -> Iterator[tuple[slice, np.ndarray]]:
        """Yield ``(antenna slice, normalised residuals (R - model) sqrt(w))``, NaN unused."""
        src = self._source()
        for sl in src.chunks:
            yield sl, src.residual_chunk(sl)

    @property
    def model(self) -> np.ndarray:
        """``(Nant, Npol, Ntime, Nfreq)`` model autos (computed on every access)."""
        return np.concatenate([m for _, m in self.model_chunks()])

    @property
    def residuals(self) -> np.ndarray:
        """Normalised residuals ``(R - model) sqrt(w)`` (computed on every access)."""
        return np.concatenate([r for _, r in self.residual_chunks()])

    def residuals_of(self, antenna: int, pol: int) -> np.ndarray:
        """``(Ntime, Nfreq)`` normalised residuals of one antenna (index) and pol (index)."""
        return self._source().residual_chunk(slice(antenna, antenna + 1))[0, pol]

    def residuals_of_first(self, nant: int) -> np.ndarray:
        """Return the normalised residuals of the first antennas: ``(a, Npol, Ntime, Nfreq)``.

        ``a = min(nant, Nant)`` (at least 1).
        """
        return self._source().residual_chunk(slice(0, max(nant, 1)))

    def detached(self) -> ExtendedFit:
        """Return the fit without its :attr:`source` (no reference to data or weights)."""
        return dataclasses.replace(self, source=None)


def radiometer_weights(
    obs: Observation, reference: np.ndarray | ExtendedFit, *, dtype: Any = None
) -> np.ndarray:
    """Inverse variances ``dnu dt N / reference^2`` (zero where flagged or non-finite).

    Parameters
    ----------
    obs
        The observation.
    reference
        ``(Nant, Npol, Ntime, Nfreq)`` reference autos, or a fit whose model is the
        reference (computed a chunk of antennas at a time).
    dtype
        Of the result (default :func:`~autocal.diagnosis.chunks.weights_dtype`).
    """
    out = np.empty(obs.shape, weights_dtype(obs.shape) if dtype is None else dtype)
    width = obs.channel_width[None, None, None, :]
    tint = obs.integration_time[None, None, :, None]
    if isinstance(reference, ExtendedFit):
        pieces: Iterator[tuple[slice, np.ndarray]] = reference.model_chunks()
    else:
        pieces = ((sl, reference[sl]) for sl in antenna_chunks(obs.shape))
    for sl, ref in pieces:
        bt = width * (tint * obs.nsamples[sl])
        usable = np.isfinite(obs.data[sl]) & ~obs.flags[sl]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            w = bt / ref**2
        out[sl] = np.where(usable & np.isfinite(w) & (w > 0), w, 0.0)
    return out


def residual_pieces(fit: Any) -> Iterator[tuple[slice, np.ndarray]]:
    """Yield ``(antenna slice, residuals)`` of a fit chunk by chunk.

    Anything else with a ``residuals`` array gives it whole.
    """
    if hasattr(fit, "residual_chunks"):
        yield from fit.residual_chunks()
    else:
        res = np.asarray(fit.residuals)
        yield slice(0, res.shape[0]), res


@blas_single_thread
def fit_extended(
    obs: Observation,
    tpl: SkyTemplates,
    effects: tuple[Effect, ...] | list[Effect] = (),
    *,
    weights: np.ndarray,
    trxr_prior: np.ndarray | float | None = None,
    trxr_prior_sigma: np.ndarray | float = 1.0,
    gain_ref: np.ndarray | None = None,
    max_iter: int = 30,
    tol: float = 1e-4,
    start: dict[str, np.ndarray] | None = None,
    chunk_antennas: int | None = None,
) -> ExtendedFit:
    """Fit per-channel ``(G, n)`` and the global parameters of ``effects``.

    Antennas are streamed through the fit in chunks
    (:func:`~autocal.diagnosis.chunks.antenna_chunks`): each channel's ``(G, n)`` is solved
    within its chunk and the global normal equations and chi^2 are summed over chunks, so
    memory holds the observation, the weights and a chunk's working arrays; the result does
    not depend on the chunking (up to rounding).

    Parameters
    ----------
    obs
        The observation ``(Nant, Npol, Ntime, Nfreq)``.
    tpl
        Model Tsky and its templates on the observation's grid.
    effects
        Effects added to the model (``bandpass`` effects are ignored here).
    weights
        ``(Nant, Npol, Ntime, Nfreq)`` inverse variances (hold them fixed to compare fits);
        float32 or float64, referenced by the fit's :attr:`ExtendedFit.source`.
    trxr_prior, trxr_prior_sigma
        Receiver prior in kelvin and its 1-sigma, each a scalar or an array broadcastable
        to ``(Nant, Npol, Nfreq)`` (:meth:`autocal.fit.priors.TrxrPrior.at`); ``None`` for no
        prior. Channels whose prior is not finite get no prior term.
    gain_ref
        ``(Nant, Npol, Nfreq)`` gain used to scale the prior's sigma (default: the data's
        own, :func:`~autocal.diagnosis.normal_equations.prior_gain_reference`, and a fit
        without the prior's where that has none).
    max_iter, tol
        Gauss-Newton limits (``tol`` in units of the parameter sigma).
    start
        ``{effect name: values}`` to start Gauss-Newton from (default zero: no effect);
        entries whose length does not match the effect's free parameters are ignored.
    chunk_antennas
        Antennas per chunk (default :data:`~autocal.diagnosis.chunks.CHUNK_SAMPLES`).

    Returns
    -------
    ExtendedFit
        The fit.
    """
    effects = tuple(e for e in effects if e.kind not in ("bandpass", "feed_gain"))
    prob = FitProblem(
        obs, tpl, effects, weights, trxr_prior, trxr_prior_sigma, gain_ref, chunk_antennas
    )
    p = _start_values(prob, start)
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        st = prob.evaluate(p)
        if not np.isfinite(st.chi2):
            raise DiagnoseError(
                "the baseline fit is not finite: check the data for unflagged zeros, "
                "infinities or absurd values"
            )
        minimum = _gauss_newton(prob, p, st, max_iter, tol)
    return _result(obs, prob, minimum)


def _start_values(prob: FitProblem, start: dict[str, np.ndarray] | None) -> np.ndarray:
    """Return the free parameters to start from: ``start``'s where they fit, else zero."""
    p = np.zeros(prob.nfree)
    for eff, sl in prob.blocks:
        init = None if start is None else start.get(eff.name)
        if init is not None and sl.stop > sl.start and np.size(init) == sl.stop - sl.start:
            p[sl] = np.where(np.isfinite(init), init, 0.0)
    return p


@dataclass(frozen=True, eq=False)
class _Minimum:
    """Where :func:`_gauss_newton` stopped: parameters, evaluation, covariance."""

    p: np.ndarray
    state: FitState
    cov: np.ndarray
    identifiable: dict[str, float]
    iterations: int


def _gauss_newton(
    prob: FitProblem, p: np.ndarray, st: FitState, max_iter: int, tol: float
) -> _Minimum:
    """Damped Gauss-Newton from ``p`` (evaluated in ``st``) on the projected problem."""
    blocks, nfree = prob.blocks, prob.nfree
    ident: dict[str, float] = {}
    it = 0
    cov = np.zeros((nfree, nfree))
    for it in range(1, max_iter + 1):
        if nfree == 0:
            break
        h, grad, raw = prob.normal_equations(p, st)
        if not (np.all(np.isfinite(h)) and np.all(np.isfinite(grad))):
            raise DiagnoseError("non-finite normal equations for the global parameters")
        if it == 1:
            ident = identifiable_fractions(blocks, h, raw)
            if any(ident.get(e.name, 1.0) < MIN_IDENTIFIABLE for e, _ in blocks):
                cov = np.full((nfree, nfree), np.inf)
                break
        cov = scaled_pinv(h, raw)
        step = cov @ grad
        sig = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
        # damped Gauss-Newton: halve the step until chi^2 does not increase
        lam, trial = 1.0, None
        for _ in range(12):
            cand = prob.evaluate(p + lam * step)
            if np.isfinite(cand.chi2) and cand.chi2 <= st.chi2 * (1 + 1e-12) + 1e-9:
                trial = cand
                break
            lam *= 0.5
        if trial is None:
            break  # no decrease along the Gauss-Newton direction: at the minimum
        p = p + lam * step
        st = trial
        if np.all(np.abs(lam * step) < tol * sig):
            break
    return _Minimum(p, st, cov, ident, it)


def _result(obs: Observation, prob: FitProblem, minimum: _Minimum) -> ExtendedFit:
    """Return the fit at ``minimum``: parameters, sigmas, channel solutions and counts."""
    blocks, nfree = prob.blocks, prob.nfree
    p, st, cov = minimum.p, minimum.state, minimum.cov
    chi2 = st.chi2
    g, nn = np.where(st.good, st.g, np.nan), np.where(st.good, st.nn, np.nan)
    nchan = int(st.good.sum())
    ndata = prob.used + (nchan if prob.prior else 0)
    params: dict[str, np.ndarray] = {}
    sigmas: dict[str, np.ndarray] = {}
    covariances: dict[str, np.ndarray] = {}
    sig_all = np.sqrt(np.abs(np.diag(cov))) if nfree else np.zeros(0)
    for eff, sl in blocks:
        params[eff.name] = prob.values(eff, sl, p).copy()
        sigmas[eff.name] = (
            np.zeros(len(eff.params)) if eff.fixed is not None else sig_all[sl].copy()
        )
        covariances[eff.name] = np.zeros((0, 0)) if eff.fixed is not None else cov[sl, sl].copy()
    source = ModelSource(
        obs=obs,
        weights=prob.weights,
        chan_ok=prob.chan_ok,
        a1=st.a1,
        a2=st.a2,
        g=st.g,
        nn=st.nn,
        chunks=prob.chunks,
    )
    return ExtendedFit(
        effects=prob.effects,
        params=params,
        sigmas=sigmas,
        G=g,
        n=nn,
        sigma_G=np.where(st.good, np.sqrt(np.abs(st.inv[0])), np.nan),
        chi2=chi2,
        ndata=ndata,
        nparam=2 * nchan + nfree,
        identifiable=minimum.identifiable,
        iterations=minimum.iterations,
        covariances=covariances,
        gain_factor=np.asarray(st.gfac, float).copy(),
        noise_factor=np.asarray(st.nfac, float).copy(),
        source=source,
    )
